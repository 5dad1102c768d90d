/* Heartbeat timing against the ideal grid. With absolute deadlines the i-th
 * heartbeat belongs to deadline anchor + k_i * period; its lateness is the
 * distance to that deadline (a late wake never shifts later ones). The
 * anchor is the least-late observation, so lateness >= 0 and the figure is
 * free of the receiver's own scheduling (kernel timestamps). */
#ifndef VLFF_TEST_HB_GRID_H
#define VLFF_TEST_HB_GRID_H

#include <math.h>
#include <stdlib.h>

struct hb_grid {
  int n;             /* heartbeats analysed */
  int missed;        /* deadlines in the span with no heartbeat */
  int duplicates;    /* two heartbeats on one deadline (must be 0) */
  double p50_ms, p99_ms, max_ms;
  double mean_period_ms;
};

static int hb_cmp(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return x < y ? -1 : x > y;
}

/* t: timestamps in seconds (ascending); anchor: the boot-up message's
 * timestamp, which starts the deadline grid; lat: scratch of n doubles.
 * The boot-up frame can itself be late, so the grid's phase is re-estimated:
 * the median residual first (most heartbeats are nearly on time), then the
 * least-late heartbeat within [-P/20, 19P/20) of it is taken as "on time".
 * Nothing is sent early and a deadline missed by a whole period is skipped,
 * so every heartbeat is 0..P late and the window attributes it uniquely
 * (up to 0.95 P; the node counts later ones in tx_late).
 * Lateness is thus measured against the best case seen, a slight
 * underestimate by the minimum wake latency. */
static inline struct hb_grid hb_grid_analyse(const double *t, int n, double period_s, double anchor, double *lat) {
  struct hb_grid g = {.n = n};
  if (n < 2) return g;
  for (int i = 0; i < n; i++) {
    double x = (t[i] - anchor) / period_s;
    lat[i] = (x - floor(x + 0.5)) * period_s;
  }
  qsort(lat, (size_t)n, sizeof lat[0], hb_cmp);
  double phase = anchor + lat[n / 2];
  double rmin = 1e9;
  for (int i = 0; i < n; i++) {
    double x = (t[i] - phase) / period_s;
    double r = (x - floor(x + 0.05)) * period_s;
    if (r < rmin) rmin = r;
  }
  phase += rmin;
  long prev = -1;
  for (int i = 0; i < n; i++) {
    long k = (long)floor((t[i] - phase) / period_s + 0.05);
    lat[i] = fmax(0.0, (t[i] - phase - (double)k * period_s) * 1e3);
    if (k == prev) g.duplicates++;
    else if (prev >= 0 && k > prev) g.missed += (int)(k - prev - 1);
    prev = k;
  }
  g.mean_period_ms = (t[n - 1] - t[0]) / (n - 1) * 1e3;
  qsort(lat, (size_t)n, sizeof lat[0], hb_cmp);
  /* Percentiles over every deadline: a skipped one counts as a full period
   * late (a lower bound), so skipping can never flatter the tail. */
  int all = n + g.missed;
  int i50 = all / 2, i99 = (int)((all - 1) * 0.99);
  g.p50_ms = i50 < n ? lat[i50] : period_s * 1e3;
  g.p99_ms = i99 < n ? lat[i99] : period_s * 1e3;
  g.max_ms = g.missed ? period_s * 1e3 : lat[n - 1];
  return g;
}

#endif
