/*
 * The whole-map refresh's schedule (refresh.h).
 */
#include "refresh.h"

#include <math.h>
#include <string.h>

#include "stats.h"

void vlff_refresh_init(struct vlff_refresh *rf, double period) {
  memset(rf, 0, sizeof *rf);
  rf->period = rf->span = period;
  rf->share = VLFF_REFRESH_SHARE;
  rf->start = rf->top = rf->last_end = -1;
}

void vlff_refresh_pass(struct vlff_refresh *rf, double now) {
  if (rf->top >= 0) {
    rf->passes[rf->npass++ % VLFF_REFRESH_PASSES] = fmax(0, now - rf->top - rf->sliced);
    double tmp[VLFF_REFRESH_PASSES];
    int m = rf->npass < VLFF_REFRESH_PASSES ? rf->npass : VLFF_REFRESH_PASSES;
    memcpy(tmp, rf->passes, (size_t)m * sizeof tmp[0]);
    rf->pass = vlff_percentile(tmp, (size_t)m, 0.75);
  }
  rf->top = now;
  rf->sliced = 0;
}

double vlff_refresh_due(const struct vlff_refresh *rf, double now, double done) {
  if (rf->start < 0) return 1;
  double to = (now + rf->pass - rf->start) / rf->span;
  /* A round behind its plan (a long pass) catches up by slices of a
   * bounded size, not in one: a keyframe that comes during a slice waits
   * for it. The bound grows with the passes, so that a round of slow
   * passes still fits its period. */
  double most = fmax(VLFF_REFRESH_MAX_SLICE, 2 * rf->pass / rf->span);
  if (to > done + most) to = done + most;
  if (to >= 1) return 1;
  return to - done >= VLFF_REFRESH_MIN_SLICE ? to : -1;
}

void vlff_refresh_sliced(struct vlff_refresh *rf, double seconds) {
  rf->sliced += seconds;
  rf->cost += seconds;
}

double vlff_refresh_round_end(struct vlff_refresh *rf, double end, bool counted, bool whole) {
  double mean = -1;
  if (counted && rf->last_end >= 0) {
    rf->ring[rf->count % VLFF_REFRESH_WINDOW] = end - rf->last_end;
    rf->count++;
  }
  if (rf->count > 0) {
    int m = rf->count < VLFF_REFRESH_WINDOW ? rf->count : VLFF_REFRESH_WINDOW;
    double sum = 0;
    for (int i = 0; i < m; i++) sum += rf->ring[i];
    mean = sum / m;
  }
  rf->last_end = end;
  if (whole || rf->start < 0) {
    rf->start = end;
  } else {
    /* The next round starts at this one's deadline, on the grid; deadlines
     * already missed by more than half a period are given up, so a late
     * round (a checkpoint's long pass) is made up by one round shorter by at
     * most half a period, never by a burst of rounds. */
    double next = rf->start + rf->span;
    while (end - next > 0.5 * rf->span) next += rf->span;
    rf->start = next;
  }
  rf->span = whole ? rf->period : fmax(rf->period, rf->cost / rf->share);
  rf->cost = 0;
  return mean;
}
