/*
 * Adam (Kingma & Ba) with bias correction and decoupled-from-moments L2 weight
 * decay on MLP weights (added to the gradient, as torch.optim.Adam does).
 * The hash table is updated lazily: only entries that received a gradient
 * this step move, and their moments decay only then (as torch's SparseAdam):
 * a step touches a small part of a 2^19-entry level, and a dense pass over
 * 4 x 64 MB would cost more than the rest of the step.
 */
#include <math.h>

#include "field_internal.h"

VLFF_HOT
void vlff_adam_dense(const struct vlff_adam *a, long long t, float lr, float *p, const float *g, float *m,
                     float *v, size_t i0, size_t i1, int decay) {
  float b1 = a->beta1, b2 = a->beta2;
  float c1 = 1.0f / (1.0f - powf(b1, (float)t)), c2 = 1.0f / (1.0f - powf(b2, (float)t));
  float wd = decay ? a->wd : 0.0f, eps = a->eps;
  for (size_t i = i0; i < i1; i++) {
    float gi = g[i] + wd * p[i];
    float mi = b1 * m[i] + (1.0f - b1) * gi;
    float vi = b2 * v[i] + (1.0f - b2) * gi * gi;
    m[i] = mi;
    v[i] = vi;
    p[i] -= lr * (mi * c1) / (sqrtf(vi * c2) + eps);
  }
}

VLFF_HOT
size_t vlff_adam_sparse(const struct vlff_adam *a, long long t, float lr, float *p, const float *g, float *m,
                        float *v, uint64_t *bits, size_t n, int width) {
  float b1 = a->beta1, b2 = a->beta2;
  float c1 = 1.0f / (1.0f - powf(b1, (float)t)), c2 = 1.0f / (1.0f - powf(b2, (float)t));
  float eps = a->eps;
  size_t count = 0;
  for (size_t wi = 0; wi < (n + 63) / 64; wi++) {
    uint64_t word = bits[wi];
    if (!word) continue;
    bits[wi] = 0;
    while (word) {
      size_t e = wi * 64 + (size_t)__builtin_ctzll(word);
      word &= word - 1;
      count++;
      for (int f = 0; f < width; f++) {
        size_t i = e * width + f;
        float gi = g[i];
        float mi = b1 * m[i] + (1.0f - b1) * gi;
        float vi = b2 * v[i] + (1.0f - b2) * gi * gi;
        m[i] = mi;
        v[i] = vi;
        p[i] -= lr * (mi * c1) / (sqrtf(vi * c2) + eps);
      }
    }
  }
  return count;
}
