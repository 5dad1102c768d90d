/*
 * The best of K scores and its margin over the second: the label a set of
 * per-prompt scores gives and how clearly it gives it (the evidence's
 * labels and census, the label image's region vote). Pure.
 */
#ifndef VLFF_BEST_H
#define VLFF_BEST_H

#include <math.h>

/* The index of the first largest of v[0..K) (K >= 1), and in *gap (may be
 * NULL) its lead over the second largest (0 for K = 1). */
static inline int vlff_best_of(const float *v, int K, float *gap) {
  int b = 0;
  float s = -INFINITY;
  for (int k = 1; k < K; k++)
    if (v[k] > v[b]) s = v[b], b = k;
    else if (v[k] > s) s = v[k];
  if (gap) *gap = K > 1 ? v[b] - s : 0.0f;
  return b;
}

#endif
