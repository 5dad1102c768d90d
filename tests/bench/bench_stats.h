/* What the benchmarks share to sum up repeated timings: a comparison of
 * doubles for qsort and the median. Header only (static inline), so that
 * every benchmark stays one program; vlff_bench puts tests/bench on the
 * include path. */
#ifndef VLFF_BENCH_STATS_H
#define VLFF_BENCH_STATS_H

#include <stdlib.h>

static inline int bench_cmp_double(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return x < y ? -1 : x > y;
}

/* Sorts v (n values) in place; the middle one, the upper middle for even n. */
static inline double bench_median(double *v, int n) {
  qsort(v, (size_t)n, sizeof *v, bench_cmp_double);
  return v[n / 2];
}

#endif
