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

float vlff_loss_feat(const float *pred, const float *target, int d, int l1, float scale, float *grad) {
  float l = 0.0f, inv = 1.0f / (float)d;
  if (l1) {
    for (int i = 0; i < d; i++) {
      float e = pred[i] - target[i];
      l += fabsf(e);
      grad[i] = scale * inv * (e > 0 ? 1.0f : e < 0 ? -1.0f : 0.0f);
    }
  } else {
    for (int i = 0; i < d; i++) {
      float e = pred[i] - target[i];
      l += e * e;
      grad[i] = scale * inv * 2.0f * e;
    }
  }
  return l * inv;
}
