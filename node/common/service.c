/* sd_notify for the Type=notify programs; the contract is in service.h. */
#include "service.h"

#ifdef VLFF_HAVE_SYSTEMD
#include <systemd/sd-daemon.h>
#endif

void vlff_service_ready(struct vlff_service *s) {
  s->watchdog_ns = 0;
  s->checked_ns = 0;
#ifdef VLFF_HAVE_SYSTEMD
  uint64_t usec = 0;
  if (sd_watchdog_enabled(0, &usec) > 0) s->watchdog_ns = usec * 1000;
  sd_notify(0, "READY=1");
#endif
}

bool vlff_service_watchdog_due(struct vlff_service *s, uint64_t now_ns) {
  if (!s->watchdog_ns) return false;
  /* Four chances per period: a pass that is late by less than three quarters
   * of it still keeps the service alive. */
  if (s->checked_ns && now_ns - s->checked_ns < s->watchdog_ns / 4) return false;
  s->checked_ns = now_ns;
  return true;
}

void vlff_service_watchdog(void) {
#ifdef VLFF_HAVE_SYSTEMD
  sd_notify(0, "WATCHDOG=1");
#endif
}

void vlff_service_stopping(void) {
#ifdef VLFF_HAVE_SYSTEMD
  sd_notify(0, "STOPPING=1");
#endif
}
