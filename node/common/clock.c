/* See clock.h. */
#include "clock.h"

#include <time.h>

uint64_t vlff_now_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

double vlff_seconds(void) { return (double)vlff_now_ns() * 1e-9; }

uint64_t vlff_wall_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_REALTIME, &ts);
  return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

int64_t vlff_mono_minus_wall_ns(void) {
  uint64_t best = UINT64_MAX;
  int64_t off = 0;
  for (int i = 0; i < 8 && best > 20000; i++) {
    uint64_t m0 = vlff_now_ns(), r = vlff_wall_ns(), m1 = vlff_now_ns();
    if (m1 - m0 < best) best = m1 - m0, off = (int64_t)(m0 + (m1 - m0) / 2) - (int64_t)r;
  }
  return off;
}
