/*
 * The level is an atomic so it can change at run time (a CAN command or a
 * signal) without a lock on the logging path.
 */
#include "log.h"
#include "clock.h"

#include <pthread.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

static _Atomic int log_level = VLFF_LOG_INFO;
static _Atomic long long log_t0_ns;
/* A status line is on stderr without its newline. */
static atomic_bool status_shown;

void vlff_log_start(void) {
  long long zero = 0;
  atomic_compare_exchange_strong(&log_t0_ns, &zero, (long long)vlff_now_ns());
}

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

/* Per call site, keyed by the caller's counter: when it last logged and the count
 * then. A fixed table (a process has a few dozen such sites); a site that finds it
 * full falls back to every 1000th. */
#define WARN_SITES 128
#define WARN_FIRST 5
#define WARN_INTERVAL_NS 5000000000ll
static struct warn_site {
  const uint64_t *key;
  long long last_ns;
  uint64_t logged_n;
} warn_sites[WARN_SITES];
static pthread_mutex_t warn_lock = PTHREAD_MUTEX_INITIALIZER;

/* 0: do not log; 1: log as is; 2: log with *suppressed lines left out since *since_ns. */
static int warn_decide(const uint64_t *key, uint64_t n, uint64_t *suppressed, long long *since_ns) {
  long long now = (long long)vlff_now_ns();
  size_t h = ((uintptr_t)key >> 3) % WARN_SITES;
  int rc = -1;
  pthread_mutex_lock(&warn_lock);
  for (size_t i = 0; i < WARN_SITES; i++) {
    struct warn_site *w = &warn_sites[(h + i) % WARN_SITES];
    if (w->key && w->key != key) continue;
    /* A new site, or a counter started over (a new object at an old address). */
    if (!w->key || w->logged_n >= n) *w = (struct warn_site){key, 0, 0};
    if (n <= WARN_FIRST) {
      rc = 1;
    } else if (now - w->last_ns >= WARN_INTERVAL_NS) {
      *suppressed = n - 1 - w->logged_n;
      *since_ns = now - w->last_ns;
      rc = *suppressed ? 2 : 1;
    } else {
      rc = 0;
    }
    if (rc) w->last_ns = now, w->logged_n = n;
    break;
  }
  pthread_mutex_unlock(&warn_lock);
  if (rc < 0) rc = n <= WARN_FIRST || n % 1000 == 0;
  return rc;
}

void vlff_warn_limited(uint64_t *count, const char *tag, const char *fmt, ...) {
  uint64_t n = ++*count, suppressed = 0;
  long long since = 0;
  int how = warn_decide(count, n, &suppressed, &since);
  if (!how) return;
  va_list ap;
  va_start(ap, fmt);
  if (how == 1) {
    vlff_logv(VLFF_LOG_WARN, tag, fmt, ap);
  } else {
    char msg[900];
    vsnprintf(msg, sizeof msg, fmt, ap);
    vlff_log(VLFF_LOG_WARN, tag, "%s [%llu more like this in the last %.0f s not shown]", msg,
             (unsigned long long)suppressed, (double)since / 1e9);
  }
  va_end(ap);
}
