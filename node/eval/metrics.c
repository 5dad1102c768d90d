/*
 * Confusion matrices, protocol summaries, feature classification and the
 * multi-view fusion baseline. See metrics.h for the protocols' definitions.
 */
#include "metrics.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "field.h" /* float16 conversions */
#include "log.h"


int vlff_confusion_init(struct vlff_confusion *c, int k, char *err, size_t errlen) {
  memset(c, 0, sizeof *c);
  if (k < 1 || k > VLFF_METRICS_MAX_CLASSES) {
    vlff_errf(err, errlen, "metrics: class count %d outside 1..%d", k, VLFF_METRICS_MAX_CLASSES);
    return -1;
  }
  c->m = calloc((size_t)k * (k + 1), sizeof *c->m);
  if (!c->m) {
    vlff_errf(err, errlen, "metrics: out of memory");
    return -1;
  }
  c->k = k;
  return 0;
}

void vlff_confusion_free(struct vlff_confusion *c) {
  free(c->m);
  memset(c, 0, sizeof *c);
}

void vlff_confusion_reset(struct vlff_confusion *c) {
  memset(c->m, 0, (size_t)c->k * (c->k + 1) * sizeof *c->m);
  c->ignored = 0;
}

void vlff_confusion_add_one(struct vlff_confusion *c, int gt, int pred) {
  if (gt < 0 || gt >= c->k) {
    c->ignored++;
    return;
  }
  if (pred < 0 || pred >= c->k) pred = c->k;
  c->m[(size_t)gt * (c->k + 1) + pred]++;
}

void vlff_confusion_add(struct vlff_confusion *c, const uint8_t *gt, const int *pred, size_t n) {
  for (size_t i = 0; i < n; i++) vlff_confusion_add_one(c, gt[i], pred[i]);
}

int vlff_confusion_merge(struct vlff_confusion *c, const struct vlff_confusion *o) {
  if (c->k != o->k) return -1;
  for (size_t i = 0; i < (size_t)c->k * (c->k + 1); i++) c->m[i] += o->m[i];
  c->ignored += o->ignored;
  return 0;
}

void vlff_confusion_class(const struct vlff_confusion *c, int cls, struct vlff_class_score *out) {
  memset(out, 0, sizeof *out);
  if (cls < 0 || cls >= c->k) return;
  const size_t K1 = (size_t)c->k + 1;
  for (int j = 0; j <= c->k; j++) {
    uint64_t v = c->m[(size_t)cls * K1 + j];
    if (j == cls) out->tp = v;
    else out->fn += v;
  }
  for (int i = 0; i < c->k; i++)
    if (i != cls) out->fp += c->m[(size_t)i * K1 + cls];
  out->present = out->tp + out->fn > 0;
  uint64_t u = out->tp + out->fp + out->fn;
  out->iou = u ? (double)out->tp / u : 0;
  out->recall = out->tp + out->fn ? (double)out->tp / (out->tp + out->fn) : 0;
  out->precision = out->tp + out->fp ? (double)out->tp / (out->tp + out->fp) : 0;
}

void vlff_confusion_summary(const struct vlff_confusion *c, struct vlff_summary *out) {
  memset(out, 0, sizeof *out);
  uint64_t correct = 0;
  for (int i = 0; i < c->k; i++) {
    struct vlff_class_score s;
    vlff_confusion_class(c, i, &s);
    correct += s.tp;
    out->labelled += s.tp + s.fn;
    if (!s.present) continue;
    out->present++;
    out->miou += s.iou;
    out->macc += s.recall;
    out->mprec += s.precision;
  }
  if (out->present) {
    out->miou /= out->present;
    out->macc /= out->present;
    out->mprec /= out->present;
  }
  out->pixel_acc = out->labelled ? (double)correct / out->labelled : 0;
}

void vlff_normalize_rows(const float *in, float *out, int k, int d) {
  for (int i = 0; i < k; i++) {
    double s = 0;
    for (int j = 0; j < d; j++) s += (double)in[(size_t)i * d + j] * in[(size_t)i * d + j];
    double inv = s > 0 ? 1.0 / sqrt(s) : 0;
    for (int j = 0; j < d; j++) out[(size_t)i * d + j] = (float)(in[(size_t)i * d + j] * inv);
  }
}

static void classify_one(const float *f, int d, const float *emb, int k, int *label, float *score) {
  double nn = 0;
  for (int j = 0; j < d; j++) nn += (double)f[j] * f[j];
  if (!(nn > 0) || !isfinite(nn)) {
    *label = -1;
    if (score) *score = 0;
    return;
  }
  int best = -1;
  double bv = -INFINITY;
  for (int c = 0; c < k; c++) {
    double dot = 0;
    for (int j = 0; j < d; j++) dot += (double)f[j] * emb[(size_t)c * d + j];
    if (dot > bv) bv = dot, best = c;
  }
  *label = best;
  if (score) *score = (float)(bv / sqrt(nn));
}

void vlff_classify_f32(const float *feat, size_t n, int d, const float *emb_unit, int k,
                       int *label, float *score) {
  for (size_t i = 0; i < n; i++)
    classify_one(feat + i * d, d, emb_unit, k, &label[i], score ? &score[i] : NULL);
}

void vlff_classify_f16(const uint16_t *feat, size_t n, int d, const float *emb_unit, int k,
                       int *label, float *score) {
  float *tmp = malloc((size_t)d * sizeof(float));
  if (!tmp) {
    for (size_t i = 0; i < n; i++) label[i] = -1;
    return;
  }
  for (size_t i = 0; i < n; i++) {
    for (int j = 0; j < d; j++) tmp[j] = vlff_f16_to_f32(feat[i * d + j]);
    classify_one(tmp, d, emb_unit, k, &label[i], score ? &score[i] : NULL);
  }
  free(tmp);
}

/* The feature-map cell a point takes its feature from in view w, or -1
 * when the view does not see it (outside the image, behind the camera, or
 * not within tol of the measured depth there). */
static long fusion_cell(const struct vlff_fusion_view *w, const float *xyz, double tol) {
  const double *M = w->c2w;
  double p[3] = {xyz[0] - M[3], xyz[1] - M[7], xyz[2] - M[11]};
  /* world -> camera with R^T */
  double x = M[0] * p[0] + M[4] * p[1] + M[8] * p[2];
  double y = M[1] * p[0] + M[5] * p[1] + M[9] * p[2];
  double z = M[2] * p[0] + M[6] * p[1] + M[10] * p[2];
  if (z <= 1e-6) return -1;
  double u = w->fx * x / z + w->cx, vv = w->fy * y / z + w->cy;
  if (!(u >= 0 && vv >= 0 && u < w->width && vv < w->height)) return -1;
  int iu = (int)u, iv = (int)vv;
  float dz = w->depth[(size_t)iv * w->width + iu];
  if (!(dz > 0) || fabs(dz - z) > tol) return -1;
  int fi = (int)(u * w->feat_width / w->width), fj = (int)(vv * w->feat_height / w->height);
  if (fi >= w->feat_width) fi = w->feat_width - 1;
  if (fj >= w->feat_height) fj = w->feat_height - 1;
  return (long)fj * w->feat_width + fi;
}

static int fusion_view_ok(const struct vlff_fusion_view *w) {
  return w->width >= 1 && w->height >= 1 && w->feat_width >= 1 && w->feat_height >= 1 && w->depth &&
         w->fx > 0 && w->fy > 0;
}

int vlff_fusion_add(const float *xyz, size_t n, const struct vlff_fusion_view *view, int d, const float *emb_unit,
                    int k, double tol, double *acc, int *count, char *err, size_t errlen) {
  if (d < 1 || k < 1 || !(tol > 0) || !fusion_view_ok(view) || !view->features) {
    vlff_errf(err, errlen, "fusion: invalid view sizes, intrinsics or buffers (D=%d, K=%d, tol=%g)", d, k, tol);
    return -1;
  }
  /* cells are projected when a point first lands in them: a view sees a
   * part of the scene, and most of its cells may hold no labelled point */
  const size_t cells = (size_t)view->feat_width * view->feat_height;
  float *proj = malloc(cells * (size_t)k * sizeof(float) + (size_t)d * sizeof(float));
  uint8_t *done = calloc(cells, 1);
  if (!proj || !done) {
    free(proj), free(done);
    vlff_errf(err, errlen, "fusion: out of memory for a %dx%d feature map", view->feat_width, view->feat_height);
    return -1;
  }
  float *tmp = proj + cells * (size_t)k;
  for (size_t i = 0; i < n; i++) {
    long cell = fusion_cell(view, xyz + 3 * i, tol);
    if (cell < 0) continue;
    float *f = proj + (size_t)cell * k;
    if (!done[cell]) {
      const uint16_t *src = view->features + (size_t)cell * d;
      for (int j = 0; j < d; j++) tmp[j] = vlff_f16_to_f32(src[j]);
      for (int c = 0; c < k; c++) {
        double dot = 0;
        for (int j = 0; j < d; j++) dot += (double)tmp[j] * emb_unit[(size_t)c * d + j];
        f[c] = (float)dot;
      }
      done[cell] = 1;
    }
    double *o = acc + i * k;
    for (int c = 0; c < k; c++) o[c] += f[c];
    count[i]++;
  }
  free(proj), free(done);
  return 0;
}

void vlff_fusion_labels(const double *acc, const int *count, size_t n, int k, int *label) {
  for (size_t i = 0; i < n; i++) {
    int best = -1;
    double bv = -INFINITY;
    if (count[i] > 0)
      for (int c = 0; c < k; c++)
        if (isfinite(acc[i * k + c]) && acc[i * k + c] > bv) bv = acc[i * k + c], best = c;
    label[i] = best;
  }
}

int vlff_fusion(const float *xyz, size_t n, const struct vlff_fusion_view *views, int nviews, int d,
                double tol, float *out, int *count, char *err, size_t errlen) {
  if (d < 1 || nviews < 0 || !(tol > 0)) {
    vlff_errf(err, errlen, "fusion: bad arguments (D=%d, views=%d, tol=%g)", d, nviews, tol);
    return -1;
  }
  for (int v = 0; v < nviews; v++) {
    const struct vlff_fusion_view *w = &views[v];
    if (!fusion_view_ok(w) || !w->features) {
      vlff_errf(err, errlen, "fusion: view %d has invalid sizes, intrinsics or buffers", v);
      return -1;
    }
  }
  memset(out, 0, n * (size_t)d * sizeof(float));
  if (count) memset(count, 0, n * sizeof(int));
  for (int v = 0; v < nviews; v++) {
    const struct vlff_fusion_view *w = &views[v];
    for (size_t i = 0; i < n; i++) {
      long cell = fusion_cell(w, xyz + 3 * i, tol);
      if (cell < 0) continue;
      const uint16_t *f = w->features + (size_t)cell * d;
      float *o = out + i * d;
      for (int j = 0; j < d; j++) o[j] += vlff_f16_to_f32(f[j]);
      if (count) count[i]++;
    }
  }
  /* average (the argmax ignores the scale, but averaged features are what
   * OpenScene stores) */
  if (count)
    for (size_t i = 0; i < n; i++)
      if (count[i] > 1)
        for (int j = 0; j < d; j++) out[i * d + j] /= (float)count[i];
  return 0;
}

void vlff_downsample_labels(const uint8_t *label, int w, int h, uint8_t *out, int ow, int oh) {
  for (int j = 0; j < oh; j++)
    for (int i = 0; i < ow; i++) {
      int u = (int)((i + 0.5) * w / ow), v = (int)((j + 0.5) * h / oh);
      if (u >= w) u = w - 1;
      if (v >= h) v = h - 1;
      out[(size_t)j * ow + i] = label[(size_t)v * w + u];
    }
}
