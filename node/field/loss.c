/*
 * Per-ray losses. The trainer scales each by its lambda and by the number of
 * rays (or of valid-depth rays) so the step's loss is a mean, as in the
 * reference. Feature loss: squared error / D (the paper), mean absolute
 * error (the reference code) or 1 - cosine similarity (what segmentation
 * reads: the argmax over prompts ignores a feature's norm); see
 * docs/field.md for the default.
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
float vlff_loss_feat(const float *restrict pred, const float *restrict target, int d, int mode, float scale,
                     float *restrict grad) {
  enum { P = 16 };
  float part[P] = {0}, inv = 1.0f / (float)d, g1 = scale * inv, g2 = 2.0f * scale * inv;
  int i = 0;
  if (mode == VLFF_FEAT_LOSS_COS) {
    /* l = 1 - p.t / (|p| |t|); dl/dp = (c p / |p|^2 - t / (|p| |t|)) */
    float pt[P] = {0}, pp[P] = {0}, tt[P] = {0};
    for (; i + P <= d; i += P)
      for (int j = 0; j < P; j++) {
        pt[j] += pred[i + j] * target[i + j];
        pp[j] += pred[i + j] * pred[i + j];
        tt[j] += target[i + j] * target[i + j];
      }
    for (; i < d; i++) pt[0] += pred[i] * target[i], pp[0] += pred[i] * pred[i], tt[0] += target[i] * target[i];
    float spt = 0, spp = 0, stt = 0;
    for (int j = 0; j < P; j++) spt += pt[j], spp += pp[j], stt += tt[j];
    if (!(spp > 1e-20f) || !(stt > 1e-20f)) {
      for (i = 0; i < d; i++) grad[i] = 0;
      return 0;
    }
    float np = sqrtf(spp), nt = sqrtf(stt), c = spt / (np * nt);
    float a = scale * c / spp, b = scale / (np * nt);
    for (i = 0; i < d; i++) grad[i] = a * pred[i] - b * target[i];
    return 1.0f - c;
  }
  if (mode == VLFF_FEAT_LOSS_L1) {
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
