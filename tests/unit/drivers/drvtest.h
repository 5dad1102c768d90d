/*
 * Small helpers shared by the driver tests, on the host and in the VM:
 * a monotonic clock, an EINTR-proof sleep, and the counters of vlff-camd's
 * stats line (" key=value" pairs) captured in a file.
 */
#ifndef VLFF_DRVTEST_H
#define VLFF_DRVTEST_H

#include <errno.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static inline uint64_t now_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

static inline void sleep_ms(int ms) {
  struct timespec ts = {ms / 1000, (long)(ms % 1000) * 1000000L};
  while (nanosleep(&ts, &ts) && errno == EINTR) {}
}

/* The value of `key` in the stats line saved at path; UINT64_MAX when the file
 * or the key is missing. */
static inline uint64_t stats_value(const char *path, const char *key) {
  FILE *f = fopen(path, "r");
  if (!f) return UINT64_MAX;
  char line[1024] = "";
  if (!fgets(line, sizeof line, f)) line[0] = 0;
  fclose(f);
  char pat[64];
  snprintf(pat, sizeof pat, " %s=", key);
  const char *p = strstr(line, pat);
  return p ? strtoull(p + strlen(pat), NULL, 10) : UINT64_MAX;
}

#endif
