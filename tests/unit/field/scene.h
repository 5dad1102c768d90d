/*
 * A small analytic scene for the field's tests and benchmark: a room (the
 * inside of a box) with two coloured boxes in it, ray-cast exactly. Every
 * surface has a class; each class has a fixed random unit feature vector.
 * Header-only so tests and tests/bench share it.
 */
#ifndef VLFF_TEST_SCENE_H
#define VLFF_TEST_SCENE_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "field.h"

#define SCENE_CLASSES 5

struct scene_box {
  double lo[3], hi[3];
  int cls;
};

/* Room [-1.5,1.5]x[-1.5,1.5]x[0,2]: floor class 0, walls 1, ceiling 2; a
 * table-like box (3) and a cabinet (4). */
static const struct scene_box scene_room = {{-1.5, -1.5, 0.0}, {1.5, 1.5, 2.0}, 1};
static const struct scene_box scene_objs[2] = {
    {{-0.5, -0.3, 0.0}, {0.3, 0.4, 0.7}, 3},
    {{0.7, 0.6, 0.0}, {1.5, 1.5, 1.2}, 4},
};
static const float scene_colour[SCENE_CLASSES][3] = {
    {0.55f, 0.45f, 0.30f}, {0.85f, 0.85f, 0.80f}, {0.95f, 0.95f, 0.95f}, {0.80f, 0.20f, 0.15f}, {0.15f, 0.35f, 0.75f}};

static int scene_ray_box(const double *o, const double *d, const struct scene_box *b, double *tin, double *tout,
                         int *ain, int *aout) {
  double lo = -1e30, hi = 1e30;
  int al = 0, ah = 0;
  for (int a = 0; a < 3; a++) {
    if (fabs(d[a]) < 1e-12) {
      if (o[a] < b->lo[a] || o[a] > b->hi[a]) return 0;
      continue;
    }
    double t0 = (b->lo[a] - o[a]) / d[a], t1 = (b->hi[a] - o[a]) / d[a];
    if (t0 > t1) {
      double x = t0;
      t0 = t1;
      t1 = x;
    }
    if (t0 > lo) {
      lo = t0;
      al = a;
    }
    if (t1 < hi) {
      hi = t1;
      ah = a;
    }
  }
  if (hi < lo) return 0;
  *tin = lo;
  *tout = hi;
  *ain = al;
  *aout = ah;
  return 1;
}

/* Cast a ray: returns the hit t (along d) and the class and colour. */
static double scene_cast(const double *o, const double *d, int *cls, float *rgb) {
  double best = 1e30, ti, to;
  int ai, ao, c = -1, axis = 0;
  if (scene_ray_box(o, d, &scene_room, &ti, &to, &ai, &ao) && to > 0) {
    best = to;
    axis = ao;
    double z = o[2] + to * d[2];
    c = ao == 2 ? (z < 1.0 ? 0 : 2) : 1;
  }
  for (int k = 0; k < 2; k++)
    if (scene_ray_box(o, d, &scene_objs[k], &ti, &to, &ai, &ao) && ti > 1e-6 && ti < best) {
      best = ti;
      c = scene_objs[k].cls;
      axis = ai;
    }
  if (c < 0) {
    *cls = 0;
    rgb[0] = rgb[1] = rgb[2] = 0;
    return 0;
  }
  *cls = c;
  /* A checker of 25 cm gives texture for the colour head to learn. */
  double x[3] = {o[0] + best * d[0], o[1] + best * d[1], o[2] + best * d[2]};
  int chk = 0;
  for (int a = 0; a < 3; a++)
    if (a != axis) chk += (int)floor(x[a] * 4.0 + 100.0);
  float shade = (chk & 1) ? 0.8f : 1.0f;
  for (int ch = 0; ch < 3; ch++) rgb[ch] = scene_colour[c][ch] * shade;
  return best;
}

/* Class feature vectors: fixed pseudo-random unit vectors. */
static void scene_class_features(int d, float *out /* [SCENE_CLASSES][d] */) {
  uint64_t s = 12345;
  for (int c = 0; c < SCENE_CLASSES; c++) {
    double n = 0;
    for (int j = 0; j < d; j++) {
      s = s * 6364136223846793005ull + 1442695040888963407ull;
      float v = (float)((double)(s >> 11) / 9007199254740992.0 - 0.5);
      out[c * d + j] = v;
      n += v * v;
    }
    for (int j = 0; j < d; j++) out[c * d + j] /= (float)sqrt(n);
  }
}

/* Camera at eye looking at target (world z up), OpenCV axes. */
static void scene_look_at(const double *eye, const double *target, double *c2w) {
  double f[3] = {target[0] - eye[0], target[1] - eye[1], target[2] - eye[2]};
  double n = sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
  for (int a = 0; a < 3; a++) f[a] /= n;
  double up[3] = {0, 0, 1};
  double r[3] = {f[1] * up[2] - f[2] * up[1], f[2] * up[0] - f[0] * up[2], f[0] * up[1] - f[1] * up[0]};
  n = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
  for (int a = 0; a < 3; a++) r[a] /= n;
  double dn[3] = {f[1] * r[2] - f[2] * r[1], f[2] * r[0] - f[0] * r[2], f[0] * r[1] - f[1] * r[0]};
  for (int a = 0; a < 3; a++) {
    c2w[4 * a + 0] = r[a];
    c2w[4 * a + 1] = dn[a];
    c2w[4 * a + 2] = f[a];
    c2w[4 * a + 3] = eye[a];
  }
  c2w[12] = c2w[13] = c2w[14] = 0;
  c2w[15] = 1;
}

/* Storage for one rendered view. */
struct scene_view {
  struct vlff_view v;
  uint8_t *rgb;
  float *depth;
  uint16_t *feat;
  int *cls;
};

/* View k of n on a circle around the room centre, looking across it. */
static void scene_pose(int k, int n, double *c2w) {
  double a = 2 * M_PI * k / n;
  double eye[3] = {1.1 * cos(a), 1.1 * sin(a), 1.0 + 0.3 * sin(3 * a)};
  double tgt[3] = {-0.8 * cos(a + 0.4), -0.8 * sin(a + 0.4), 0.4};
  scene_look_at(eye, tgt, c2w);
}

static void scene_render(struct scene_view *sv, int w, int h, int d, const double *c2w) {
  memset(sv, 0, sizeof(*sv));
  sv->rgb = malloc((size_t)w * h * 3);
  sv->depth = malloc((size_t)w * h * sizeof(float));
  sv->feat = malloc((size_t)w * h * d * sizeof(uint16_t));
  sv->cls = malloc((size_t)w * h * sizeof(int));
  float *cf = malloc((size_t)SCENE_CLASSES * d * sizeof(float));
  scene_class_features(d, cf);
  struct vlff_view *v = &sv->v;
  v->width = w;
  v->height = h;
  v->fx = v->fy = 0.8 * w;
  v->cx = w / 2.0;
  v->cy = h / 2.0;
  memcpy(v->c2w, c2w, sizeof(v->c2w));
  for (int y = 0; y < h; y++)
    for (int x = 0; x < w; x++) {
      double dc[3] = {(x + 0.5 - v->cx) / v->fx, (y + 0.5 - v->cy) / v->fy, 1.0}, dw[3], o[3];
      for (int a = 0; a < 3; a++) {
        dw[a] = c2w[4 * a] * dc[0] + c2w[4 * a + 1] * dc[1] + c2w[4 * a + 2] * dc[2];
        o[a] = c2w[4 * a + 3];
      }
      int c;
      float rgb[3];
      double t = scene_cast(o, dw, &c, rgb);
      size_t i = (size_t)y * w + x;
      for (int ch = 0; ch < 3; ch++) sv->rgb[3 * i + ch] = (uint8_t)lrintf(rgb[ch] * 255.0f);
      sv->depth[i] = (float)t;
      sv->cls[i] = c;
      for (int j = 0; j < d; j++) sv->feat[i * d + j] = vlff_f32_to_f16(cf[c * d + j]);
    }
  free(cf);
  v->rgb = sv->rgb;
  v->depth = sv->depth;
  v->features = sv->feat;
  v->feat_width = w;
  v->feat_height = h;
  v->feature_dim = d;
}

static void scene_view_free(struct scene_view *sv) {
  free(sv->rgb);
  free(sv->depth);
  free(sv->feat);
  free(sv->cls);
}

#endif
