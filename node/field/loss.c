/*
 * Per-ray losses. The trainer scales each by its lambda and by the number of
 * rays (or of valid-depth rays) so the step's loss is a mean, as in the
 * reference. Feature loss: squared error / D (the paper) or mean absolute
 * error (the reference code); see docs/field.md for the default.
 */
#include <math.h>

#include "field_internal.h"

float vlff_loss_rgb(const float *pred, const float *target, float scale, float *grad) {
  float l = 0.0f;
  for (int c = 0; c < 3; c++) {
    float d = pred[c] - target[c];
    l += d * d;
    grad[c] = scale * 2.0f * d / 3.0f;
  }
  return l / 3.0f;
}

float vlff_loss_depth(float pred, float target, float scale, float *grad) {
  float d = pred - target;
  *grad = scale * (d > 0 ? 1.0f : d < 0 ? -1.0f : 0.0f);
  return fabsf(d);
}

/* Sixteen partial sums: a float sum in one chain cannot be vectorised
 * without reassociation, and this runs over D values for every ray. */
VLFF_HOT
float vlff_loss_feat(const float *restrict pred, const float *restrict target, int d, int l1, float scale,
                     float *restrict grad) {
  enum { P = 16 };
  float part[P] = {0}, inv = 1.0f / (float)d, g1 = scale * inv, g2 = 2.0f * scale * inv;
  int i = 0;
  if (l1) {
    for (; i + P <= d; i += P)
      for (int j = 0; j < P; j++) {
        float e = pred[i + j] - target[i + j];
        part[j] += fabsf(e);
        grad[i + j] = e > 0 ? g1 : e < 0 ? -g1 : 0.0f;
      }
    for (; i < d; i++) {
      float e = pred[i] - target[i];
      part[0] += fabsf(e);
      grad[i] = e > 0 ? g1 : e < 0 ? -g1 : 0.0f;
    }
  } else {
    for (; i + P <= d; i += P)
      for (int j = 0; j < P; j++) {
        float e = pred[i + j] - target[i + j];
        part[j] += e * e;
        grad[i + j] = g2 * e;
      }
    for (; i < d; i++) {
      float e = pred[i] - target[i];
      part[0] += e * e;
      grad[i] = g2 * e;
    }
  }
  float l = 0.0f;
  for (int j = 0; j < P; j++) l += part[j];
  return l * inv;
}
