/*
 * Talking to the service manager (systemd's sd_notify) for the programs whose
 * units are Type=notify: vlff-node, vlff-camd, vlff-pose.
 *
 * vlff_service_ready() sends READY=1 and reads the watchdog period systemd
 * gives the process (WatchdogSec, passed as $WATCHDOG_USEC). The caller's own
 * loop asks vlff_service_watchdog_due() on every pass and, when it says so and
 * the caller judges itself healthy, sends vlff_service_watchdog(): the
 * watchdog is fed from the loop it guards, never from a timer of its own.
 * vlff_service_stopping() sends STOPPING=1 when shutdown begins.
 *
 * Outside systemd (no $NOTIFY_SOCKET) every call does nothing. Built without
 * libsystemd (VLFF_WITH_SYSTEMD off) they do nothing either and the watchdog
 * is never due; the install writes that build's units as Type=simple with no
 * watchdog to match. Single-threaded: one struct per program, used by the
 * thread that runs its main loop.
 */
#ifndef VLFF_SERVICE_H
#define VLFF_SERVICE_H

#include <stdbool.h>
#include <stdint.h>

struct vlff_service {
  uint64_t watchdog_ns; /* systemd's watchdog period, 0 when there is none */
  uint64_t checked_ns;  /* when vlff_service_watchdog_due last said yes */
};

/* READY=1, and the watchdog period into s (0 without one). */
void vlff_service_ready(struct vlff_service *s);
/* True once a quarter of the period has passed since it last said true (the
 * first call after ready says true at once); never true without a watchdog.
 * now_ns: vlff_now_ns(). */
bool vlff_service_watchdog_due(struct vlff_service *s, uint64_t now_ns);
/* WATCHDOG=1. */
void vlff_service_watchdog(void);
/* STOPPING=1. */
void vlff_service_stopping(void);

#endif
