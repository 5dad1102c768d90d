/*
 * Percentiles of a sample: the one helper the node's statistics use (the
 * frame-to-map latency on --status and CAN). Pure, thread-safe.
 */
#ifndef VLFF_STATS_H
#define VLFF_STATS_H

#include <stddef.h>

/* Sorts v (n > 0 values, no NaN) ascending in place and returns its
 * q-quantile, q in [0, 1], by the floor rank: v[floor(q (n - 1))]. v stays
 * sorted, so further quantiles can be read from it directly. */
double vlff_percentile(double *v, size_t n, double q);

#endif
