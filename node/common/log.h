/*
 * vlff logging: levelled, tagged lines on stderr.
 *
 * Contract
 *  - One line per call, written with a single write(2) so lines from
 *    different threads and processes never interleave.
 *  - Interactive: "[   12.345678] W tag: message" with CLOCK_MONOTONIC
 *    seconds since vlff_log_start (or, without it, since the first line).
 *  - Under systemd (JOURNAL_STREAM set) lines start with the syslog
 *    priority "<N>" and carry no timestamp: journald adds its own.
 *  - Thread-safe; callable from any thread. Not async-signal-safe.
 *  - A live status line (vlff_log_status) is rewritten in place with '\r';
 *    a log line that comes while one is shown starts on a line of its own
 *    (a newline first), so it is neither glued to the status line nor
 *    overwritten by the next one.
 */
#ifndef VLFF_LOG_H
#define VLFF_LOG_H

#include <stdarg.h>
#include <stdint.h>
#include <stddef.h>

#include "config.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Starts the interactive stamps' clock now (a program calls it first thing, so that
 * stamps count from its start); without it they count from the first line logged. */
void vlff_log_start(void);
void vlff_log_set_level(enum vlff_log_level level);

void vlff_log(enum vlff_log_level level, const char *tag, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));
void vlff_logv(enum vlff_log_level level, const char *tag, const char *fmt, va_list ap);

/* Shows a one-line status (no newline of its own) in place of the last
 * one, with a single write(2). */
void vlff_log_status(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
/* Ends a shown status line with a newline (nothing if none is shown). */
void vlff_log_status_end(void);

/* Format an error message into a caller's buffer (err may be NULL): the
 * "-1 with err filled" convention every vlff module follows. */
void vlff_errf(char *err, size_t errlen, const char *fmt, ...) __attribute__((format(printf, 3, 4)));

/* A warning that can come with every frame, iteration or request, rate-limited
 * so the log stays readable: the first five events of a call site are logged,
 * then at most one line every 5 s, which says how many like it were not shown
 * since the last. *count is the caller's count of them (incremented here; it
 * also names the call site, so one counter per kind of line), its counters
 * tell the rest. The caller serialises calls with the same counter. Any
 * message that can repeat per frame, iteration or request goes through here. */
void vlff_warn_limited(uint64_t *count, const char *tag, const char *fmt, ...) __attribute__((format(printf, 3, 4)));

#define VLFF_ERROR(tag, ...) vlff_log(VLFF_LOG_ERROR, tag, __VA_ARGS__)
#define VLFF_WARN(tag, ...) vlff_log(VLFF_LOG_WARN, tag, __VA_ARGS__)
#define VLFF_INFO(tag, ...) vlff_log(VLFF_LOG_INFO, tag, __VA_ARGS__)
#define VLFF_DEBUG(tag, ...) vlff_log(VLFF_LOG_DEBUG, tag, __VA_ARGS__)

#ifdef __cplusplus
}
#endif

#endif
