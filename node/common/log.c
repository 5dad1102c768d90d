/*
 * The level is an atomic so it can change at run time (a CAN command or a
 * signal) without a lock on the logging path.
 */
#include "log.h"
#include "clock.h"

#include <stdatomic.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

static _Atomic int log_level = VLFF_LOG_INFO;
static _Atomic long long log_t0_ns;
/* A status line is on stderr without its newline. */
static atomic_bool status_shown;

void vlff_log_set_level(enum vlff_log_level level) { atomic_store(&log_level, (int)level); }

void vlff_logv(enum vlff_log_level level, const char *tag, const char *fmt, va_list ap) {
  if ((int)level > atomic_load(&log_level)) return;
  /* syslog priorities: err=3 warning=4 info=6 debug=7 */
  static const int prio[] = {3, 4, 6, 7};
  static const char letter[] = "EWID";
  char buf[1025], *line = buf + 1; /* buf[0]: room for the newline that ends a status line */
  const size_t cap = sizeof buf - 1;
  int n;
  if (getenv("JOURNAL_STREAM")) {
    n = snprintf(line, cap, "<%d>%s: ", prio[level], tag);
  } else {
    long long t = (long long)vlff_now_ns(), zero = 0;
    atomic_compare_exchange_strong(&log_t0_ns, &zero, t);
    long long rel = t - atomic_load(&log_t0_ns);
    n = snprintf(line, cap, "[%5lld.%06lld] %c %s: ", rel / 1000000000ll, (rel % 1000000000ll) / 1000,
                 letter[level], tag);
  }
  if (n < 0) return;
  int m = vsnprintf(line + n, cap - (size_t)n, fmt, ap);
  if (m < 0) return;
  size_t len = (size_t)n + (size_t)m;
  if (len > cap - 2) len = cap - 2;
  line[len++] = '\n';
  if (atomic_exchange(&status_shown, false)) line--, len++, line[0] = '\n';
  /* Best effort: a full or closed stderr must never stop the node. */
  ssize_t w = write(STDERR_FILENO, line, len);
  (void)w;
}

void vlff_log_status(const char *fmt, ...) {
  char line[512];
  line[0] = '\r';
  va_list ap;
  va_start(ap, fmt);
  int m = vsnprintf(line + 1, sizeof line - 1, fmt, ap);
  va_end(ap);
  if (m < 0) return;
  size_t len = 1 + ((size_t)m < sizeof line - 1 ? (size_t)m : sizeof line - 2);
  ssize_t w = write(STDERR_FILENO, line, len);
  (void)w;
  atomic_store(&status_shown, true);
}

void vlff_log_status_end(void) {
  if (!atomic_exchange(&status_shown, false)) return;
  ssize_t w = write(STDERR_FILENO, "\n", 1);
  (void)w;
}

void vlff_log(enum vlff_log_level level, const char *tag, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  vlff_logv(level, tag, fmt, ap);
  va_end(ap);
}

void vlff_errf(char *err, size_t errlen, const char *fmt, ...) {
  if (!err || !errlen) return;
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(err, errlen, fmt, ap);
  va_end(ap);
}

void vlff_warn_limited(uint64_t *count, const char *tag, const char *fmt, ...) {
  uint64_t n = ++*count;
  if (n > 5 && n % 1000 != 0) return;
  va_list ap;
  va_start(ap, fmt);
  vlff_logv(VLFF_LOG_WARN, tag, fmt, ap);
  va_end(ap);
}
