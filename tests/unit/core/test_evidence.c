/* Per-voxel evidence: features land in the voxel where measured depth puts
 * them, average over views, combine with the field's cosines into labels,
 * follow new evidence and new prompts, and stay within their budget. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>
#include <unistd.h>
#include <cmocka.h>

#include "evidence.h"
#include "unit.h"

enum { W = 8, H = 8, FW = 4, FH = 4, D = 4 };

static const double origin[3] = {-2, -2, 0};
static const uint32_t dims[3] = {8, 8, 8}; /* 0.5 m voxels over [-2,2] x [-2,2] x [0,4] */

/* A camera at the origin looking along +z at a wall depth_m away; every
 * feature pixel carries feature f. */
struct wall {
  float depth[W * H];
  uint16_t feat[FW * FH * D];
  struct vlff_view v;
};

static void wall_make(struct wall *w, float depth_m, const float f[D]) {
  for (int i = 0; i < W * H; i++) w->depth[i] = depth_m;
  for (int i = 0; i < FW * FH; i++)
    for (int j = 0; j < D; j++) w->feat[i * D + j] = vlff_f32_to_f16(f[j]);
  memset(&w->v, 0, sizeof w->v);
  w->v.width = W, w->v.height = H, w->v.fx = w->v.fy = 40, w->v.cx = w->v.cy = 4;
  w->v.c2w[0] = w->v.c2w[5] = w->v.c2w[10] = w->v.c2w[15] = 1;
  w->v.depth = w->depth, w->v.features = w->feat;
  w->v.feat_width = FW, w->v.feat_height = FH, w->v.feature_dim = D;
}

static struct vlff_evidence *make(size_t bytes) {
  char err[256];
  struct vlff_evidence *e = vlff_evidence_create(origin, dims, 0.5, D, VLFF_MAX_PROMPTS, bytes, err, sizeof err);
  if (!e) fail_msg("%s", err);
  return e;
}

static void test_views_average_where_depth_ends(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20);
  struct wall a, b;
  wall_make(&a, 2.2f, (const float[D]){1, 0, 0, 0});
  wall_make(&b, 2.2f, (const float[D]){0, 1, 0, 0});
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_add(e, &b.v, err, sizeof err), 0);
  /* fx = 40 over 8 pixels: the wall spans +-0.22 m around the axis at
   * 2.2 m, all within the voxels around x, y = 0 at z in [2, 2.5). */
  float out[D];
  int n = vlff_evidence_get(e, vlff_evidence_voxel(e, (const double[3]){0.1, 0.1, 2.2}), out);
  assert_true(n >= 2);
  assert_float_equal(out[0], 0.5f, 2e-3);
  assert_float_equal(out[1], 0.5f, 2e-3);
  assert_float_equal(out[2], 0.0f, 1e-6);
  /* In front of the wall, behind it and outside the grid: nothing. */
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, (const double[3]){0.1, 0.1, 1.2}), out), 0);
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, (const double[3]){0.1, 0.1, 3.2}), out), 0);
  assert_int_equal(vlff_evidence_voxel(e, (const double[3]){0.1, 0.1, 9}), -1);
  assert_int_equal(vlff_evidence_voxels(e), 4); /* the four voxels at x, y in [-0.5, 0.5) */
  assert_int_equal(vlff_evidence_overflow(e), 0);
  vlff_evidence_reset(e);
  assert_int_equal(vlff_evidence_voxels(e), 0);
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, (const double[3]){0.1, 0.1, 2.2}), out), 0);
  vlff_evidence_destroy(e);
}

/* Features join the mean as directions: a view whose features are eight
 * times as long as another's (a model that is surer, or brighter light)
 * does not outweigh it, and the map's cosines read both alike. With the
 * plain mean the first view's prompt won (8/9 of the mean). Zero and
 * non-finite features add nothing. */
static void test_views_average_as_directions(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20);
  struct wall a, b, z;
  wall_make(&a, 2.2f, (const float[D]){8, 0, 0, 0});
  wall_make(&b, 2.2f, (const float[D]){0, 0.5f, 0, 0});
  wall_make(&z, 2.2f, (const float[D]){0, 0, 0, 0});
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_add(e, &b.v, err, sizeof err), 0);
  const double x[3] = {0.1, 0.1, 2.2};
  float out[D];
  const int n = vlff_evidence_get(e, vlff_evidence_voxel(e, x), out);
  assert_true(n >= 2);
  assert_float_equal(out[0], 0.5f, 2e-3);
  assert_float_equal(out[1], 0.5f, 2e-3);
  assert_int_equal(vlff_evidence_add(e, &z.v, err, sizeof err), 0);
  z.feat[0] = vlff_f32_to_f16(NAN);
  assert_int_equal(vlff_evidence_add(e, &z.v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, x), out), n);
  assert_float_equal(out[0], 0.5f, 2e-3);
  vlff_evidence_destroy(e);
}

/* A mean saved by a node that averaged features at their own length (a
 * checkpoint from before directions) joins the new samples at unit length:
 * kept 8 long, it held 8 / 9 of the mean after as many new samples as it
 * had. */
static void test_old_long_mean_joins_as_direction(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20), *g = make(1 << 20);
  struct wall a, b;
  wall_make(&a, 2.2f, (const float[D]){1, 0, 0, 0});
  wall_make(&b, 2.2f, (const float[D]){0, 1, 0, 0});
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  const size_t n = vlff_evidence_save_size(e), rec = 4 + 1 + 2 * D;
  uint8_t *buf = malloc(n);
  vlff_evidence_save(e, buf);
  /* the four voxels' records close the save: their means made 8 long */
  for (size_t r = 1; r <= 4; r++)
    for (int j = 0; j < D; j++) {
      uint16_t h;
      memcpy(&h, buf + n - r * rec + 5 + 2 * j, 2);
      h = vlff_f32_to_f16(8 * vlff_f16_to_f32(h));
      memcpy(buf + n - r * rec + 5 + 2 * j, &h, 2);
    }
  assert_int_equal(vlff_evidence_load(g, buf, n, err, sizeof err), 0);
  const long vi = vlff_evidence_voxel(g, (const double[3]){0.1, 0.1, 2.2});
  float out[D];
  assert_int_equal(vlff_evidence_get(g, vi, out), 4);
  assert_float_equal(out[0], 8.0f, 1e-3);
  assert_int_equal(vlff_evidence_add(g, &b.v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_get(g, vi, out), 8);
  assert_float_equal(out[0], 0.5f, 2e-3);
  assert_float_equal(out[1], 0.5f, 2e-3);
  free(buf);
  vlff_evidence_destroy(e);
  vlff_evidence_destroy(g);
}

/* A feature pixel whose footprint straddles two voxels is averaged into
 * both: with cx = 3, feature column 1 (depth columns 2 and 3) sees the wall
 * at x = -0.03 and +0.03 m, either side of the voxel face at x = 0. The
 * point under its centre lies on one side only, which left the other side's
 * pixels of that column without its feature. */
static void test_footprint_reaches_every_voxel(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20);
  struct wall a;
  wall_make(&a, 2.2f, (const float[D]){1, 0, 0, 0});
  a.v.cx = 3;
  for (int fj = 0; fj < FH; fj++) {
    uint16_t *px = a.feat + (fj * FW + 1) * D;
    px[0] = vlff_f32_to_f16(0), px[1] = vlff_f32_to_f16(1);
  }
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  float left[D], right[D];
  /* The voxels above y = 0 (feature rows 2 and 3): left of x = 0 columns 0
   * and 1, right of it columns 1, 2 and 3. */
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, (const double[3]){-0.05, 0.1, 2.2}), left), 4);
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, (const double[3]){0.05, 0.1, 2.2}), right), 6);
  assert_float_equal(left[1], 0.5f, 2e-3);
  assert_float_equal(right[1], 1.0f / 3, 2e-3);
  vlff_evidence_destroy(e);
}

static void test_labels_combine_field_and_evidence(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20);
  const float E[2 * D] = {1, 0, 0, 0, 0, 1, 0, 0};
  /* The field leans to prompt 0 at both points; the second lies outside
   * the grid, the third is a point the field does not score. */
  const float xyz[9] = {0.1f, 0.1f, 2.2f, 0.1f, 0.1f, 9.0f, 0.1f, 0.1f, 2.2f};
  const float fcos[6] = {0.6f, 0.5f, 0.6f, 0.5f, 0, 0};
  int lab[3];
  float score[3], margin[3];
  /* No evidence yet: the field's labels and cosines. */
  vlff_evidence_label(e, xyz, 3, fcos, NULL, 0, E, 2, 1, 1.0f, lab, score, margin);
  assert_int_equal(lab[0], 0);
  assert_float_equal(score[0], 0.6f, 1e-6);
  assert_int_equal(lab[2], -1);
  struct wall a, b;
  wall_make(&a, 2.2f, (const float[D]){1, 0, 0, 0});
  wall_make(&b, 2.2f, (const float[D]){0, 2, 0, 0});
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  vlff_evidence_label(e, xyz, 3, fcos, NULL, 0, E, 2, 1, 1.0f, lab, score, margin);
  assert_int_equal(lab[0], 0);
  assert_float_equal(score[0], (0.6f + 1.0f) / 2, 1e-3); /* evidence cosine 1 with prompt 0 */
  assert_float_equal(margin[0], (1.6f - 0.5f) / 2, 1e-3);
  /* Twice as many views of prompt 1's feature: the mean (1/3, 4/3) has
   * cosines 0.24 and 0.97, and the cached cosines follow the new evidence. */
  assert_int_equal(vlff_evidence_add(e, &b.v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_add(e, &b.v, err, sizeof err), 0);
  vlff_evidence_label(e, xyz, 3, fcos, NULL, 0, E, 2, 1, 1.0f, lab, score, margin);
  assert_int_equal(lab[0], 1);
  assert_int_equal(lab[1], 0); /* outside the grid: the field alone */
  assert_float_equal(score[1], 0.6f, 1e-6);
  /* The sums behind those labels (a region's vote reads them, regions.h):
   * each prompt's, scaled as the score; the best is the label, its sum
   * the score; all 0 for the point the field does not score. */
  float sums[3 * 2];
  int lab2[3];
  memset(sums, 0x7f, sizeof sums);
  vlff_evidence_label_scores(e, xyz, 3, fcos, NULL, 0, E, 2, 1, 1.0f, lab2, NULL, NULL, sums);
  for (int i = 0; i < 3; i++) assert_int_equal(lab2[i], lab[i]);
  assert_true(sums[1] > sums[0]);
  assert_float_equal(sums[1], score[0], 1e-6);
  assert_float_equal(sums[2], 0.6f, 1e-6); /* point 1: the field alone */
  assert_float_equal(sums[3], 0.5f, 1e-6);
  assert_true(sums[4] == 0 && sums[5] == 0);
  /* A small weight leaves the field's decision standing. */
  vlff_evidence_label(e, xyz, 1, fcos, NULL, 0, E, 2, 1, 0.1f, lab, NULL, NULL);
  assert_int_equal(lab[0], 0);
  /* New prompts (the order swapped, another stamp): cosines recomputed. */
  const float E2[2 * D] = {0, 1, 0, 0, 1, 0, 0, 0};
  const float fcos2[2] = {0.5f, 0.6f};
  vlff_evidence_label(e, xyz, 1, fcos2, NULL, 0, E2, 2, 2, 1.0f, lab, NULL, NULL);
  assert_int_equal(lab[0], 0);
  vlff_evidence_destroy(e);
}

/* The field counts in proportion to its exposure (training rays in the
 * point's cell) up to trust_rays, then fully; without evidence it decides
 * alone however little it was trained. */
static void test_field_trust_follows_exposure(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20);
  const float E[2 * D] = {1, 0, 0, 0, 0, 1, 0, 0};
  /* Two points in the wall's voxel, one outside the grid (no evidence). */
  const float xyz[9] = {0.1f, 0.1f, 2.2f, 0.1f, 0.1f, 2.2f, 0.1f, 0.1f, 9.0f};
  const float fcos[6] = {0.9f, 0.1f, 0.9f, 0.1f, 0.9f, 0.1f};
  struct wall a;
  wall_make(&a, 2.2f, (const float[D]){0.6f, 0.8f}); /* evidence cosines 0.6 and 0.8 */
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  int lab[3];
  float score[3], margin[3];
  /* Not fitted there yet (0 rays), and a tenth of the way (5 of 50). */
  const uint16_t young[3] = {0, 5, 0};
  vlff_evidence_label(e, xyz, 3, fcos, young, 50, E, 2, 1, 1.0f, lab, score, margin);
  assert_int_equal(lab[0], 1); /* the evidence alone */
  assert_float_equal(score[0], 0.8f, 1e-3);
  assert_float_equal(margin[0], 0.2f, 1e-3);
  assert_int_equal(lab[1], 1); /* 0.09 + 0.6 < 0.01 + 0.8 */
  assert_float_equal(score[1], (0.01f + 0.8f) / 1.1f, 1e-3);
  assert_int_equal(lab[2], 0); /* no evidence: the field */
  assert_float_equal(score[2], 0.9f, 1e-6);
  /* Half way (25) and beyond (50, 60000): 0.45 + 0.6 > 0.05 + 0.8, then
   * the usual sum. */
  const uint16_t older[3] = {25, 50, 60000};
  vlff_evidence_label(e, xyz, 3, fcos, older, 50, E, 2, 1, 1.0f, lab, score, NULL);
  assert_int_equal(lab[0], 0);
  assert_float_equal(score[0], (0.45f + 0.6f) / 1.5f, 1e-3);
  assert_int_equal(lab[1], 0);
  assert_float_equal(score[1], (0.9f + 0.6f) / 2, 1e-3);
  /* trust_rays 0, or no exposure given: the field counts fully. */
  vlff_evidence_label(e, xyz, 1, fcos, young, 0, E, 2, 1, 1.0f, lab, score, NULL);
  assert_int_equal(lab[0], 0);
  vlff_evidence_label(e, xyz, 1, fcos, NULL, 50, E, 2, 1, 1.0f, lab, score, NULL);
  assert_int_equal(lab[0], 0);
  assert_float_equal(score[0], (0.9f + 0.6f) / 2, 1e-3);
  vlff_evidence_destroy(e);
}

/* Prompt 1's object (cosines 0.6, 0.8 with E_LOST) 2.2 m before prompt 0's
 * wall at 3.2 m, seen once each. */
static const float E_LOST[2 * D] = {1, 0, 0, 0, 0, 1, 0, 0};
static void object_before_wall(struct vlff_evidence *e) {
  struct wall a, b;
  wall_make(&a, 2.2f, (const float[D]){0.6f, 0.8f});
  wall_make(&b, 3.2f, (const float[D]){0.8f, 0.6f});
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_add(e, &b.v, err, sizeof err), 0);
}

/* 16 points on each of object_before_wall's surfaces, four in each of four
 * voxels; the field says prompt 0 everywhere, sure enough that w = 1 keeps
 * its word (0.9 + 0.6 > 0.5 + 0.8 on the object), fitted (60 rays) or
 * young (10). */
enum { LOST_N = 32 };
struct lost_points {
  float xyz[LOST_N * 3], fcos[LOST_N * 2];
  uint16_t fitted[LOST_N], young[LOST_N];
};
static void lost_points(struct lost_points *p) {
  for (int i = 0; i < LOST_N; i++) {
    p->xyz[3 * i] = i & 1 ? 0.1f : -0.1f, p->xyz[3 * i + 1] = i & 2 ? 0.1f : -0.1f;
    p->xyz[3 * i + 2] = i < LOST_N / 2 ? 2.2f : 3.2f;
    p->fcos[2 * i] = 0.9f, p->fcos[2 * i + 1] = 0.5f;
    p->fitted[i] = 60, p->young[i] = 10;
  }
}

/* Lost classes: a census over the map finds the prompt the fitted field
 * gave away (it labels none of the points the evidence labels so), and
 * later labels read the evidence there; a class the field keeps, an
 * unfitted field, ratio 0, new prompts and a reset restore nothing. */
static void test_lost_class_read_from_evidence(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20);
  object_before_wall(e);
  struct lost_points p;
  lost_points(&p);
  enum { N = LOST_N };
  const float *E = E_LOST, *xyz = p.xyz;
  float *fcos = p.fcos; /* the field's word changes below */
  const uint16_t *fitted = p.fitted, *young = p.young;
  int lab[N];
  float margin[N];
  unsigned long long nf, ne;
  /* An unfitted field's labels count for nothing. */
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, N, fcos, young, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(vlff_evidence_census_end(e, 0.25), 0);
  assert_false(vlff_evidence_lost(e, 1, &nf, &ne));
  assert_true(nf == 0 && ne == 0);
  /* Evidence at fewer than 10 points is not a class to restore. */
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, 9, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(vlff_evidence_census_end(e, 0.25), 0);
  /* The census pass itself labels as before: prompt 1 is gone. */
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  for (int i = 0; i < N; i++) assert_int_equal(lab[i], 0);
  assert_int_equal(vlff_evidence_census_end(e, 0.25), 1);
  assert_true(vlff_evidence_lost(e, 1, &nf, &ne));
  assert_true(nf == 0 && ne == N / 2);
  assert_false(vlff_evidence_lost(e, 0, &nf, &ne));
  assert_true(nf == N && ne == N / 2);
  /* From now on the object reads the evidence, with the evidence's margin
   * (0.8 - 0.6, halved as every combined margin); the wall stays. */
  float score[N];
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, score, margin);
  for (int i = 0; i < N; i++) assert_int_equal(lab[i], i < N / 2 ? 1 : 0);
  assert_float_equal(margin[0], 0.1f, 1e-3);
  assert_float_equal(score[0], (0.5f + 0.8f) / 2, 1e-3); /* prompt 1's own sum */
  /* The sums a region votes with say the same: the restored prompt leads
   * the other by that margin. */
  float sums[2 * N];
  vlff_evidence_label_scores(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL, sums);
  assert_int_equal(lab[0], 1);
  assert_float_equal(sums[1] - sums[0], 0.1f, 1e-3);
  /* The next census counts what the field picks, not what was restored:
   * still lost. */
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(lab[0], 1);
  assert_int_equal(vlff_evidence_census_end(e, 0.25), 1);
  assert_true(vlff_evidence_lost(e, 1, &nf, &ne));
  assert_true(nf == 0 && ne == N / 2);
  /* Restored where the field is not fully fitted too (a = 0.8: 0.72 + 0.6
   * would beat 0.4 + 0.8). */
  vlff_evidence_label(e, xyz, 1, fcos, (const uint16_t[1]){40}, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(lab[0], 1);
  /* Other prompts (another stamp): nothing is restored for them. */
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 7, 1.0f, lab, NULL, NULL);
  assert_int_equal(lab[0], 0);
  /* A lost class is kept again only at twice the ratio: the field picking
   * 4 of the 16 leaves it lost, 8 of 16 does not; a class not lost before
   * is lost only under the ratio (4 of 16 is a quarter: not lost). */
  for (int i = 0; i < 4; i++) fcos[2 * i + 1] = 0.95f;
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(vlff_evidence_census_end(e, 0.25), 1);
  for (int i = 0; i < 8; i++) fcos[2 * i + 1] = 0.95f;
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(vlff_evidence_census_end(e, 0.25), 0);
  for (int i = 4; i < 8; i++) fcos[2 * i + 1] = 0.5f;
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(vlff_evidence_census_end(e, 0.25), 0);
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(lab[0], 1); /* the field's own word there */
  assert_int_equal(lab[4], 0);
  /* Ratio 0 marks nothing; a reset forgets what was lost. */
  for (int i = 0; i < 4; i++) fcos[2 * i + 1] = 0.5f;
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(vlff_evidence_census_end(e, 0), 0);
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(vlff_evidence_census_end(e, 0.25), 1);
  vlff_evidence_reset(e);
  assert_false(vlff_evidence_lost(e, 1, &nf, &ne));
  assert_true(nf == 0 && ne == 0);
  vlff_evidence_destroy(e);
}

/* The census's verdict saved, and set on an evidence of the same views (a
 * restarted node's, loaded from the map it saved): its first label call
 * reads the lost prompt from the evidence, without a census of its own,
 * for the same prompts only. A block no census writes is refused by
 * what is wrong in it. */
static void test_lost_classes_saved(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20), *r = make(1 << 20);
  object_before_wall(e);
  object_before_wall(r);
  struct lost_points p;
  lost_points(&p);
  enum { N = LOST_N };
  const float *E = E_LOST, *xyz = p.xyz, *fcos = p.fcos;
  const uint16_t *fitted = p.fitted;
  char err[256];
  int lab[N];
  uint8_t blk[VLFF_EVIDENCE_LOST_BYTES], bad[VLFF_EVIDENCE_LOST_BYTES];
  vlff_evidence_lost_save(e, blk); /* nothing lost yet: a block that restores nothing */
  assert_int_equal(vlff_evidence_lost_check(blk, 8, err, sizeof err), 0);
  vlff_evidence_census_begin(e);
  vlff_evidence_label(e, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(vlff_evidence_census_end(e, 0.25), 1);
  /* Before: the restarted evidence's first labels are the field's. */
  vlff_evidence_label(r, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  assert_int_equal(lab[0], 0);
  vlff_evidence_lost_save(e, blk);
  assert_int_equal(vlff_evidence_lost_check(blk, 8, err, sizeof err), 0);
  vlff_evidence_lost_set(r, blk);
  assert_true(vlff_evidence_lost(r, 1, NULL, NULL));
  assert_false(vlff_evidence_lost(r, 0, NULL, NULL));
  vlff_evidence_label(r, xyz, N, fcos, fitted, 50, E, 2, 1, 1.0f, lab, NULL, NULL);
  for (int i = 0; i < N; i++) assert_int_equal(lab[i], i < N / 2 ? 1 : 0);
  vlff_evidence_label(r, xyz, N, fcos, fitted, 50, E, 2, 7, 1.0f, lab, NULL, NULL); /* other prompts */
  assert_int_equal(lab[0], 0);
  /* Forged blocks. */
  memcpy(bad, blk, sizeof bad);
  bad[16 + 1] = 2;
  assert_int_equal(vlff_evidence_lost_check(bad, 8, err, sizeof err), -1);
  assert_non_null(strstr(err, "prompt 1 marked 2"));
  memcpy(bad, blk, sizeof bad);
  bad[16 + 5] = 1; /* past the census's 2 prompts */
  assert_int_equal(vlff_evidence_lost_check(bad, 8, err, sizeof err), -1);
  assert_non_null(strstr(err, "prompt 5 marked 1 (of 2 prompts)"));
  memcpy(bad, blk, sizeof bad);
  bad[12] = 3; /* the lost count */
  assert_int_equal(vlff_evidence_lost_check(bad, 8, err, sizeof err), -1);
  assert_non_null(strstr(err, "1 marked, the block says 3"));
  memcpy(bad, blk, sizeof bad);
  bad[8] = 9; /* prompts beyond what the evidence takes */
  assert_int_equal(vlff_evidence_lost_check(bad, 8, err, sizeof err), -1);
  assert_non_null(strstr(err, "9 prompts, expected 0 to 8"));
  vlff_evidence_destroy(e);
  vlff_evidence_destroy(r);
}

/* A budget full of what the view in hand saw leaves further voxels to the
 * field, counted; bad values in a view are skipped; a view of another D is
 * refused. */
static void test_budget_and_bad_values(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1); /* room for one voxel */
  struct wall a;
  wall_make(&a, 2.2f, (const float[D]){1, 0, 0, 0});
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(e), 1);
  assert_true(vlff_evidence_overflow(e) > 0);
  vlff_evidence_destroy(e);

  e = make(1 << 20);
  for (int i = 0; i < W * H; i++) a.depth[i] = i % 2 ? NAN : INFINITY;
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(e), 0);
  wall_make(&a, 2.2f, (const float[D]){NAN, 0, 0, 0});
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(e), 0);
  a.v.feature_dim = D + 1;
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), -1);
  assert_non_null(strstr(err, "D"));
  vlff_evidence_destroy(e);
}

/* One view of a wall filling voxel (i, j, k) of the grid alone: the camera
 * at that column's centre, the wall at that layer's middle. */
static void add_at(struct vlff_evidence *e, int i, int j, int k, const float f[D]) {
  struct wall a;
  wall_make(&a, 0.25f + 0.5f * (float)k, f);
  a.v.c2w[3] = origin[0] + 0.25 + 0.5 * i;
  a.v.c2w[7] = origin[1] + 0.25 + 0.5 * j;
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
}

static long voxel_at(const struct vlff_evidence *e, int i, int j, int k) {
  return vlff_evidence_voxel(e, (const double[3]){origin[0] + 0.25 + 0.5 * i, origin[1] + 0.25 + 0.5 * j,
                                                   origin[2] + 0.25 + 0.5 * k});
}

/* A full budget gives up the least-observed voxels that no recent view
 * touched (at equal counts the first in memory, here the oldest) and goes
 * on taking new ones: a voxel seen three times keeps its evidence, and so
 * do those the last views saw; the rest stay intact and save and load as
 * before. */
static void test_full_budget_gives_up_least_observed(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 14);
  const float well[D] = {0, 0, 1, 0}, stray[D] = {1, 0, 0, 0};
  for (int r = 0; r < 3; r++) add_at(e, 0, 0, 0, well);
  float out[D];
  assert_int_equal(vlff_evidence_get(e, voxel_at(e, 0, 0, 0), out), 48); /* 16 feature pixels a view */
  /* Strays, one view each, until the budget is full and one more. */
  int i = 1;
  size_t cap = 0;
  for (; vlff_evidence_evicted(e) == 0; i++) {
    assert_true(i < 8 * 8 * 8);
    cap = vlff_evidence_voxels(e);
    add_at(e, i % 8, i / 8 % 8, i / 64, stray);
  }
  assert_int_equal(cap, vlff_evidence_capacity(e));
  assert_true(cap >= 16);
  const long long gone = vlff_evidence_evicted(e);
  assert_int_equal(gone, cap / 8);
  assert_int_equal(vlff_evidence_overflow(e), 0);
  assert_int_equal(vlff_evidence_voxels(e), cap - (size_t)gone + 1);
  assert_int_equal(vlff_evidence_get(e, voxel_at(e, 0, 0, 0), out), 48);
  assert_float_equal(out[2], 1.0f, 1e-3);
  /* The oldest strays are gone, the rest and the last eight views' kept. */
  for (int t = 1; t < i; t++) {
    int got = vlff_evidence_get(e, voxel_at(e, t % 8, t / 8 % 8, t / 64), out);
    assert_int_equal(got, t <= gone ? 0 : 16);
    if (got) assert_float_equal(out[0], 1.0f, 1e-3);
  }
  /* A voxel given up starts over when seen again. */
  add_at(e, 1, 0, 0, well);
  assert_int_equal(vlff_evidence_get(e, voxel_at(e, 1, 0, 0), out), 16);
  assert_float_equal(out[2], 1.0f, 1e-3);
  /* Packed slots save and load as they hold. */
  struct vlff_evidence *g = make(1 << 14);
  size_t sz = vlff_evidence_save_size(e);
  uint8_t *buf = malloc(sz);
  vlff_evidence_save(e, buf);
  char err[256];
  assert_int_equal(vlff_evidence_load(g, buf, sz, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(g), vlff_evidence_voxels(e));
  float x[D];
  for (int t = 0; t < i; t++) {
    long vi = voxel_at(e, t % 8, t / 8 % 8, t / 64);
    assert_int_equal(vlff_evidence_get(e, vi, out), vlff_evidence_get(g, vi, x));
  }
  free(buf);
  vlff_evidence_destroy(g);
  vlff_evidence_destroy(e);
}

/* Label of the voxel (i, j, k)'s centre with field cosines fc for prompts E
 * (K = 2, stamp), evidence weight 1; its score in *score. */
static int label_at(struct vlff_evidence *e, int i, int j, int k, const float E[2 * D], uint64_t stamp,
                    const float fc[2], float *score) {
  const float xyz[3] = {(float)origin[0] + 0.25f + 0.5f * i, (float)origin[1] + 0.25f + 0.5f * j,
                        (float)origin[2] + 0.25f + 0.5f * k};
  int lab;
  vlff_evidence_label(e, xyz, 1, fc, NULL, 0, E, 2, stamp, 1.0f, &lab, score, NULL);
  return lab;
}

/* With a page file, what a full budget gives up is written there instead
 * of dropped: nothing is evicted; the map still reads the paged voxels
 * (their cosines kept in memory), follows new prompts there (read back from
 * the file), and a voxel seen again gets its evidence back and adds to it.
 * A checkpoint holds every voxel, paged or not; a load pages out what is
 * beyond its budget. A page file that cannot be made is said, naming it. */
static void test_full_budget_pages_out(void **state) {
  (void)state;
  char dir[] = "/tmp/vlff-test-evpage-XXXXXX", path[64];
  assert_non_null(mkdtemp(dir));
  snprintf(path, sizeof path, "%s/evidence.pages", dir);
  char err[256];
  struct vlff_evidence *e = make(1 << 14);
  assert_int_equal(vlff_evidence_page_to(e, path, 1 << 20, err, sizeof err), 0);
  const float well[D] = {0, 0, 1, 0}, stray[D] = {1, 0, 0, 0};
  const float E[2 * D] = {0, 0, 1, 0, 1, 0, 0, 0}, E2[2 * D] = {1, 0, 0, 0, 0, 0, 1, 0};
  const float fc[2] = {0.6f, 0.5f}; /* the field leans to prompt 0 */
  float score;
  for (int r = 0; r < 3; r++) add_at(e, 0, 0, 0, well);
  assert_int_equal(label_at(e, 0, 0, 0, E, 1, fc, &score), 0);
  int i = 1;
  for (; vlff_evidence_paged_out(e) == 0; i++) {
    assert_true(i < 8 * 8 * 8);
    add_at(e, i % 8, i / 8 % 8, i / 64, stray);
  }
  const size_t cap = vlff_evidence_capacity(e);
  const long long paged = vlff_evidence_paged_out(e);
  assert_int_equal(paged, cap / 8);
  assert_int_equal(vlff_evidence_paged(e), (size_t)paged);
  assert_int_equal(vlff_evidence_evicted(e), 0);
  assert_int_equal(vlff_evidence_page_errors(e), 0);
  assert_true(vlff_evidence_page_memory(e) > 0);
  float out[D];
  /* The oldest strays are paged: not in memory, but the map reads them. */
  assert_int_equal(vlff_evidence_get(e, voxel_at(e, 1, 0, 0), out), 0);
  assert_int_equal(label_at(e, 1, 0, 0, E, 1, fc, &score), 1);
  assert_float_equal(score, (0.5f + 1.0f) / 2, 1e-2);
  /* New prompts (swapped): the paged voxels' cosines follow. */
  assert_int_equal(label_at(e, 1, 0, 0, E2, 2, (const float[2]){0.5f, 0.6f}, &score), 0);
  assert_float_equal(score, (0.5f + 1.0f) / 2, 1e-2);
  /* Seen again: its evidence comes back and the new view adds to it. */
  add_at(e, 1, 0, 0, stray);
  assert_int_equal(vlff_evidence_get(e, voxel_at(e, 1, 0, 0), out), 32);
  assert_float_equal(out[0], 1.0f, 1e-3);
  assert_int_equal(vlff_evidence_paged_in(e), 1);
  /* A checkpoint holds every voxel: loaded with room for all, each as it was. */
  size_t sz = vlff_evidence_save_size(e);
  uint8_t *buf = malloc(sz);
  vlff_evidence_save(e, buf);
  struct vlff_evidence *g = make(1 << 20);
  assert_int_equal(vlff_evidence_load(g, buf, sz, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(g), vlff_evidence_voxels(e) + vlff_evidence_paged(e));
  for (int t = 1; t < i; t++) {
    int got = vlff_evidence_get(g, voxel_at(g, t % 8, t / 8 % 8, t / 64), out);
    assert_int_equal(got, t == 1 ? 32 : 16);
    assert_float_equal(out[0], 1.0f, 1e-3);
  }
  /* Loaded into a budget that holds a part: the rest is paged, none dropped. */
  char path2[80];
  snprintf(path2, sizeof path2, "%s/second.pages", dir);
  struct vlff_evidence *h = make(1 << 14);
  assert_int_equal(vlff_evidence_page_to(h, path2, 1 << 20, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_load(h, buf, sz, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_evicted(h), 0);
  assert_int_equal(vlff_evidence_voxels(h) + vlff_evidence_paged(h), vlff_evidence_voxels(g));
  assert_true(vlff_evidence_paged(h) > 0);
  for (int t = 1; t < i; t++) assert_int_equal(label_at(h, t % 8, t / 8 % 8, t / 64, E, 1, fc, &score), 1);
  /* A page file that cannot be made: said, naming it, and what the budget
   * gives up is dropped (counted) as without paging. */
  struct vlff_evidence *bad = make(1 << 14);
  assert_int_equal(vlff_evidence_page_to(bad, "/nonexistent-dir/evidence.pages", 1 << 20, err, sizeof err), 0);
  assert_string_equal(vlff_evidence_page_error(bad), "");
  for (int t = 1; vlff_evidence_evicted(bad) == 0; t++) {
    assert_true(t < 8 * 8 * 8);
    add_at(bad, t % 8, t / 8 % 8, t / 64, stray);
  }
  assert_int_equal(vlff_evidence_page_errors(bad), 1);
  assert_int_equal(vlff_evidence_paged(bad), 0);
  assert_non_null(strstr(vlff_evidence_page_error(bad), "/nonexistent-dir/evidence.pages: No such file"));
  vlff_evidence_destroy(bad);
  /* The file goes with the evidence. */
  assert_int_equal(access(path, F_OK), 0);
  free(buf);
  vlff_evidence_destroy(h);
  vlff_evidence_destroy(g);
  vlff_evidence_destroy(e);
  assert_int_equal(access(path, F_OK), -1);
  assert_int_equal(access(path2, F_OK), -1);
  assert_int_equal(rmdir(dir), 0);
}

/* Evidence is read between voxel centres as a grid is: trilinearly, over the
 * voxels that have some. Two voxels side by side, one of prompt 0's feature,
 * one of prompt 1's: a point 0.3 of the way from the first's centre reads
 * 0.7 of it, one 0.7 of the way the other way round; a point in an empty
 * voxel beside the second reads the second's (the nearest voxel alone gave
 * it none, the field's tie decided); one with no evidence within a voxel's
 * reach reads the field alone. */
static void test_labels_read_between_voxel_centres(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20);
  add_at(e, 3, 3, 2, (const float[D]){1, 0, 0, 0});
  add_at(e, 4, 3, 2, (const float[D]){0, 1, 0, 0});
  const float E[2 * D] = {1, 0, 0, 0, 0, 1, 0, 0};
  const float y = (float)origin[1] + 1.75f, z = (float)origin[2] + 1.25f; /* voxel centres: row 3, layer 2 */
  const float c3 = (float)origin[0] + 1.75f;                               /* voxel 3's centre in x */
  const float xyz[12] = {c3 + 0.15f, y, z, c3 + 0.35f, y, z, c3 + 0.8f, y, z, c3 + 2.0f, y, z};
  const float fcos[8] = {0.5f, 0.5f, 0.5f, 0.5f, 0.5f, 0.5f, 0.5f, 0.5f};
  int lab[4];
  float score[4], margin[4];
  vlff_evidence_label(e, xyz, 4, fcos, NULL, 0, E, 2, 1, 1.0f, lab, score, margin);
  assert_int_equal(lab[0], 0);
  assert_float_equal(score[0], (0.5f + 0.7f) / 2, 2e-3);
  assert_float_equal(margin[0], (0.7f - 0.3f) / 2, 2e-3);
  assert_int_equal(lab[1], 1);
  assert_float_equal(score[1], (0.5f + 0.7f) / 2, 2e-3);
  assert_int_equal(lab[2], 1); /* voxel 5, empty: 0.4 of voxel 4's reach */
  assert_float_equal(score[2], (0.5f + 1.0f) / 2, 2e-3);
  assert_int_equal(lab[3], 0); /* voxel 7: the field's tie, its first prompt */
  assert_float_equal(score[3], 0.5f, 1e-6);
  assert_float_equal(margin[3], 0.0f, 1e-6);
  vlff_evidence_destroy(e);
}

/* Saved evidence loads back as it was; a record that points outside the
 * grid or holds a NaN and a truncated file are refused, and one of another feature size is
 * not loaded (1: a config changed), each leaving the evidence as it was. */
static void test_save_load(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20), *g = make(1 << 20);
  struct wall a;
  wall_make(&a, 2.2f, (const float[D]){0.25f, -1, 0.5f, 0});
  char err[256];
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  size_t n = vlff_evidence_save_size(e);
  uint8_t *buf = malloc(n);
  vlff_evidence_save(e, buf);
  assert_int_equal(vlff_evidence_load(g, buf, n, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(g), 4);
  float x[D], y[D];
  long vi = vlff_evidence_voxel(e, (const double[3]){-0.1, 0.1, 2.2});
  assert_int_equal(vlff_evidence_get(e, vi, x), vlff_evidence_get(g, vi, y));
  assert_memory_equal(x, y, sizeof x);
  /* The last record's voxel index past the grid. */
  uint32_t bad = 8 * 8 * 8;
  memcpy(buf + n - (4 + 1 + 2 * D), &bad, 4);
  assert_int_equal(vlff_evidence_load(g, buf, n, err, sizeof err), -1);
  assert_non_null(strstr(err, "bad voxel record"));
  assert_int_equal(vlff_evidence_get(g, vi, y), 4); /* four feature pixels of one view */
  /* A NaN in the last record's mean (a float16 of all exponent bits). */
  vlff_evidence_save(e, buf);
  const uint16_t nan16 = 0x7e00;
  memcpy(buf + n - 2 * D, &nan16, 2);
  assert_int_equal(vlff_evidence_load(g, buf, n, err, sizeof err), -1);
  assert_non_null(strstr(err, "bad voxel record"));
  assert_int_equal(vlff_evidence_get(g, vi, y), 4);
  assert_int_equal(vlff_evidence_load(g, buf, n - 1, err, sizeof err), -1);
  char err2[256];
  struct vlff_evidence *other = vlff_evidence_create(origin, dims, 0.5, D + 1, VLFF_MAX_PROMPTS, 1 << 20, err2, sizeof err2);
  vlff_evidence_save(e, buf);
  assert_int_equal(vlff_evidence_load(other, buf, n, err, sizeof err), 1);
  assert_non_null(strstr(err, "another grid"));
  assert_int_equal(vlff_evidence_voxels(other), 0);
  vlff_evidence_destroy(other);
  free(buf);
  vlff_evidence_destroy(e);
  vlff_evidence_destroy(g);
}

/* The node's evidence for a growing box (field.grow) that starts as
 * make()'s grid, with a 1 MB budget (an index of at most 65536 voxels);
 * *cfg is its configuration. */
static struct vlff_evidence *make_growing(struct vlff_config *cfg) {
  vlff_config_defaults(cfg);
  cfg->field.feature_dim = D;
  cfg->field.grow = true;
  memcpy(cfg->field.scene_min, origin, sizeof origin);
  for (int a = 0; a < 3; a++) cfg->field.scene_max[a] = origin[a] + 4;
  cfg->publish.evidence_voxel_m = 0.5;
  cfg->publish.evidence_max_mb = 1;
  char err[256];
  struct vlff_evidence *e = vlff_evidence_for(&cfg->publish, &cfg->field, VLFF_MAX_PROMPTS, err, sizeof err);
  if (!e) fail_msg("%s", err);
  return e;
}

/* e saved (*buf, *len: the save) and loaded into a new evidence of cfg,
 * which starts in the first box. */
static struct vlff_evidence *reloaded(const struct vlff_config *cfg, const struct vlff_evidence *e, uint8_t **buf,
                                      size_t *len) {
  char err[256];
  *len = vlff_evidence_save_size(e);
  *buf = malloc(*len);
  assert_non_null(*buf);
  vlff_evidence_save(e, *buf);
  struct vlff_evidence *g = vlff_evidence_for(&cfg->publish, &cfg->field, VLFF_MAX_PROMPTS, err, sizeof err);
  assert_non_null(g);
  if (vlff_evidence_load(g, *buf, *len, err, sizeof err)) fail_msg("%s", err);
  return g;
}

/* A growing box's evidence (field.grow): the grid grows on its lattice and
 * every voxel's evidence stays where it is in the world; the new part takes
 * evidence; a save of the grown grid loads into a first-box evidence by
 * growing it; past the index's share of the budget, or for a fixed grid or
 * a bad box, growth is refused and nothing changes. */
static void test_grow(void **state) {
  (void)state;
  struct vlff_config cfg;
  struct vlff_evidence *e = make_growing(&cfg);
  char err[256];
  struct wall a;
  wall_make(&a, 2.2f, (const float[D]){0.25f, -1, 0.5f, 0});
  assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  const double p[3] = {-0.1, 0.1, 2.2}, q[3] = {-4.3, 0.1, 2.2};
  float x[D], y[D];
  int n = vlff_evidence_get(e, vlff_evidence_voxel(e, p), x);
  assert_int_equal(n, 4);
  assert_int_equal(vlff_evidence_voxel(e, q), -1); /* beyond the first box */

  const double lo[3] = {-4.6, -2, 0}, hi[3] = {1, 1, 7.9};
  assert_int_equal(vlff_evidence_grow(e, lo, hi, lo, hi, 1000, err, sizeof err), 1);
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, p), y), n);
  assert_memory_equal(x, y, sizeof x);
  assert_int_equal(vlff_evidence_voxels(e), 4);
  assert_int_equal(vlff_evidence_grow(e, lo, hi, lo, hi, 1000, err, sizeof err), 0); /* held */
  /* the new part takes evidence: the same wall seen from 4.2 m further -x */
  struct wall b;
  wall_make(&b, 2.2f, (const float[D]){0, 0, 0, 1});
  b.v.c2w[3] = -4.2;
  assert_int_equal(vlff_evidence_add(e, &b.v, err, sizeof err), 0);
  assert_true(vlff_evidence_voxel(e, q) >= 0);
  assert_true(vlff_evidence_get(e, vlff_evidence_voxel(e, q), y) > 0);

  /* past the index's quarter of the budget: refused, nothing changed */
  const double huge_lo[3] = {-100, -100, 0}, huge_hi[3] = {100, 100, 4}; /* holds part, below */
  assert_int_equal(vlff_evidence_grow(e, huge_lo, huge_hi, huge_lo, huge_hi, 1000, err, sizeof err), -1);
  assert_non_null(strstr(err, "publish.evidence_max_mb"));
  const double nan_hi[3] = {NAN, 0, 0};
  assert_int_equal(vlff_evidence_grow(e, lo, nan_hi, lo, nan_hi, 1000, err, sizeof err), -1);
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, p), y), n);
  assert_memory_equal(x, y, sizeof x);

  /* saved grown, loaded into a first-box evidence: it grows to the grid */
  size_t len;
  uint8_t *buf;
  struct vlff_evidence *g = reloaded(&cfg, e, &buf, &len);
  assert_int_equal(vlff_evidence_voxels(g), vlff_evidence_voxels(e));
  assert_int_equal(vlff_evidence_voxel(g, q), vlff_evidence_voxel(e, q));
  assert_int_equal(vlff_evidence_get(g, vlff_evidence_voxel(g, p), y), n);
  assert_memory_equal(x, y, sizeof x);
  /* a fixed grid does not grow, and does not take the grown save */
  struct vlff_evidence *fixed = make(1 << 20);
  assert_int_equal(vlff_evidence_grow(fixed, lo, hi, lo, hi, 1000, err, sizeof err), -1);
  assert_non_null(strstr(err, "fixed"));
  assert_int_equal(vlff_evidence_load(fixed, buf, len, err, sizeof err), 1);
  assert_non_null(strstr(err, "another grid"));
  free(buf);
  vlff_evidence_destroy(fixed);
  vlff_evidence_destroy(g);
  vlff_evidence_destroy(e);
}

/* Past the index's share of the budget, the grid is refitted to the voxels
 * that hold evidence and the box asked for: the empty margins of earlier
 * growths are dropped, each voxel's evidence stays where it is in the world,
 * a save of the refitted grid (which does not hold the first box) loads
 * into a first-box evidence; a refit that still does not fit is refused,
 * nothing changed. */
/* A wall 2.2 m ahead of the first box's camera added to e (a: its view);
 * x: the mean at p, on it, of the 4 samples there. */
static const double wall_p[3] = {-0.1, 0.1, 2.2};
static void first_wall(struct vlff_evidence *e, struct wall *a, float x[D]) {
  char err[256];
  wall_make(a, 2.2f, (const float[D]){0.25f, -1, 0.5f, 0});
  assert_int_equal(vlff_evidence_add(e, &a->v, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, wall_p), x), 4);
}

static void test_refit(void **state) {
  (void)state;
  struct vlff_config cfg;
  struct vlff_evidence *e = make_growing(&cfg); /* an index of at most 65536 voxels */
  char err[256];
  struct wall a;
  float x[D], y[D];
  first_wall(e, &a, x);
  const double *p = wall_p;
  const int n = 4;
  const double lo[3] = {-2, -2, 0}, hi[3] = {30, 14, 4}; /* 64 x 32 x 8 voxels */
  assert_int_equal(vlff_evidence_grow(e, lo, hi, lo, hi, 1000, err, sizeof err), 1);
  const double margin[3] = {25, 10, 1}, far[3] = {-99.5, 0.2, 2.2};
  assert_true(vlff_evidence_voxel(e, margin) >= 0);
  /* 100 m toward -x: holding all of the grid would take 260 x 32 x 8 */
  const double far_lo[3] = {-100, 0, 2}, far_hi[3] = {-99, 0.4, 2.4};
  assert_int_equal(vlff_evidence_grow(e, far_lo, far_hi, far_lo, far_hi, 1000, err, sizeof err), 1);
  assert_int_equal(vlff_evidence_voxel(e, margin), -1); /* held nothing: dropped */
  assert_true(vlff_evidence_voxel(e, far) >= 0);
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, p), y), n);
  assert_memory_equal(x, y, sizeof x);
  assert_int_equal(vlff_evidence_voxels(e), 4);
  /* even refitted, too large: refused, nothing changed */
  const double huge_lo[3] = {-100, -100, 0}, huge_hi[3] = {100, 100, 4}; /* holds part, below */
  assert_int_equal(vlff_evidence_grow(e, huge_lo, huge_hi, huge_lo, huge_hi, 1000, err, sizeof err), -1);
  assert_non_null(strstr(err, "publish.evidence_max_mb"));
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, p), y), n);
  assert_true(vlff_evidence_voxel(e, far) >= 0);
  /* that box wanted, a part of it needed: grown to the part, in one call */
  const double part_lo[3] = {5, 0, 2}, part_hi[3] = {8, 0.4, 2.4}, part[3] = {7.5, 0.2, 2.2};
  assert_int_equal(vlff_evidence_voxel(e, part), -1);
  assert_int_equal(vlff_evidence_grow(e, huge_lo, huge_hi, part_lo, part_hi, 1000, err, sizeof err), 1);
  assert_true(vlff_evidence_voxel(e, part) >= 0 && vlff_evidence_voxel(e, far) >= 0);
  assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, p), y), n);
  assert_int_equal(vlff_evidence_grow(e, huge_lo, huge_hi, part_lo, part_hi, 1000, err, sizeof err), 0); /* held */
  /* saved refitted, loaded into a first-box evidence */
  size_t len;
  uint8_t *buf;
  struct vlff_evidence *g = reloaded(&cfg, e, &buf, &len);
  assert_int_equal(vlff_evidence_voxel(g, far), vlff_evidence_voxel(e, far));
  assert_int_equal(vlff_evidence_voxel(g, margin), -1);
  assert_int_equal(vlff_evidence_get(g, vlff_evidence_voxel(g, p), y), n);
  assert_memory_equal(x, y, sizeof x);
  free(buf);
  vlff_evidence_destroy(g);
  vlff_evidence_destroy(e);
}

/* Beyond the caps (docs/field.md): a box that even a refit cannot hold
 * with the grid (the first wall 500 m behind) slides the grid instead; the
 * wall's evidence pages out, kept by its place in the world, is not in a
 * save of the slid grid, and comes back to its voxel when the grid slides
 * back: seen again, its samples join the ones it had. Without a page file
 * a slide gives evidence up, counted. */
static void test_slide(void **state) {
  (void)state;
  char dir[] = "/tmp/vlff-test-evslide-XXXXXX", path[64];
  assert_non_null(mkdtemp(dir));
  snprintf(path, sizeof path, "%s/evidence.pages", dir);
  for (int paging = 1; paging >= 0; paging--) {
    struct vlff_config cfg;
    struct vlff_evidence *e = make_growing(&cfg); /* an index of at most 65536 voxels of 0.5 m */
    char err[256];
    if (paging) assert_int_equal(vlff_evidence_page_to(e, path, 1 << 20, err, sizeof err), 0);
    struct wall a;
    float x[D], y[D];
    first_wall(e, &a, x);
    const double *p = wall_p;
    const int n = 4;
    const size_t held = vlff_evidence_voxels(e);
    /* 40 x 40 x 4 m, 500 m along x: 51200 voxels alone, far more with the wall */
    const double lo[3] = {500, -20, 0}, hi[3] = {540, 20, 4};
    const uint64_t gen0 = vlff_evidence_far_generation(e);
    assert_int_equal(vlff_evidence_grow(e, lo, hi, lo, hi, 1000, err, sizeof err), 1);
    assert_true(vlff_evidence_far_generation(e) != gen0); /* a checkpoint writes the far records again */
    assert_int_equal(vlff_evidence_voxel(e, p), -1); /* beyond the grid now */
    assert_true(vlff_evidence_voxel(e, (const double[3]){520, 0, 2}) >= 0);
    assert_int_equal(vlff_evidence_voxels(e), 0);
    if (!paging) {
      assert_int_equal(vlff_evidence_evicted(e), (long long)held); /* given up, counted */
      vlff_evidence_destroy(e);
      continue;
    }
    assert_int_equal(vlff_evidence_paged(e), held);
    /* a save holds the grid's evidence: none */
    size_t len;
    uint8_t *buf;
    struct vlff_evidence *g = reloaded(&cfg, e, &buf, &len);
    assert_int_equal(vlff_evidence_voxels(g) + vlff_evidence_paged(g), 0);
    free(buf);
    vlff_evidence_destroy(g);
    /* ... the far records beside it: a restarted evidence takes them into
     * its own page file, and the wall's evidence comes back with the grid */
    char fpath[96], gpages[96];
    snprintf(fpath, sizeof fpath, "%s/map.obs.evfar", dir);
    snprintf(gpages, sizeof gpages, "%s/evidence2.pages", dir);
    assert_int_equal(vlff_evidence_far_records(e), held);
    const uint64_t gen1 = vlff_evidence_far_generation(e);
    assert_int_equal(vlff_evidence_save_far(e, fpath, err, sizeof err), 0);
    assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0); /* the wall's view: beyond the grid */
    assert_int_equal(vlff_evidence_far_generation(e), gen1); /* nothing far changed: no rewrite owed */
    struct vlff_config c2;
    g = make_growing(&c2);
    long long dropped;
    assert_int_equal(vlff_evidence_load_far(g, fpath, &dropped, err, sizeof err), 0);
    assert_int_equal(dropped, (long long)held); /* no page file: given up, counted */
    assert_int_equal(vlff_evidence_evicted(g), (long long)held);
    vlff_evidence_destroy(g);
    g = make_growing(&c2);
    assert_int_equal(vlff_evidence_page_to(g, gpages, 1 << 20, err, sizeof err), 0);
    assert_int_equal(vlff_evidence_load_far(g, fpath, &dropped, err, sizeof err), 0);
    assert_int_equal(dropped, 0);
    assert_int_equal(vlff_evidence_far_records(g), 0); /* the first box holds the wall: back at once */
    assert_true(vlff_evidence_paged(g) >= 1);
    assert_int_equal(vlff_evidence_add(g, &a.v, err, sizeof err), 0);
    assert_int_equal(vlff_evidence_get(g, vlff_evidence_voxel(g, p), y), 2 * n);
    for (int j = 0; j < D; j++) assert_float_equal(x[j], y[j], 2e-3);
    vlff_evidence_destroy(g);
    /* a cut file, or one of another grid, refused with nothing taken */
    assert_int_equal(truncate(fpath, 70), 0);
    g = make_growing(&c2);
    assert_int_equal(vlff_evidence_load_far(g, fpath, &dropped, err, sizeof err), -1);
    assert_non_null(strstr(err, "truncated"));
    assert_int_equal(vlff_evidence_paged(g) + vlff_evidence_far_records(g), 0);
    vlff_evidence_destroy(g);
    g = make_growing(&c2); /* without a page file too: refused, not counted as given up */
    assert_int_equal(vlff_evidence_load_far(g, fpath, &dropped, err, sizeof err), -1);
    assert_non_null(strstr(err, "truncated"));
    assert_int_equal(vlff_evidence_evicted(g), 0);
    vlff_evidence_destroy(g);
    unlink(fpath);
    assert_int_equal(vlff_evidence_load_far(e, fpath, &dropped, err, sizeof err), 1); /* none */
    unlink(gpages);
    /* back at the first wall: the grid slides back, the wall's records with it */
    const double blo[3] = {-2, -2, 0}, bhi[3] = {2, 2, 4};
    assert_int_equal(vlff_evidence_grow(e, blo, bhi, blo, bhi, 1000, err, sizeof err), 1);
    assert_true(vlff_evidence_voxel(e, p) >= 0);
    assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
    assert_int_equal(vlff_evidence_get(e, vlff_evidence_voxel(e, p), y), 2 * n);
    for (int j = 0; j < D; j++) assert_float_equal(x[j], y[j], 2e-3);
    assert_true(vlff_evidence_paged_in(e) >= 1);
    g = reloaded(&cfg, e, &buf, &len);
    assert_int_equal(vlff_evidence_get(g, vlff_evidence_voxel(g, p), y), 2 * n);
    free(buf);
    vlff_evidence_destroy(g);
    vlff_evidence_destroy(e);
  }
  unlink(path);
  rmdir(dir);
}

/* Paged, then grown: a voxel of the first box whose evidence a full budget
 * paged out stays readable where it is in the world after the grid grows
 * (toward -x, so that every voxel index changes), and comes back into a
 * slot, its samples whole, when it is seen again. */
static void test_paged_then_grown(void **state) {
  (void)state;
  char dir[] = "/tmp/vlff-test-evgrow-XXXXXX", path[64];
  assert_non_null(mkdtemp(dir));
  snprintf(path, sizeof path, "%s/evidence.pages", dir);
  struct vlff_config cfg;
  struct vlff_evidence *e = make_growing(&cfg);
  char err[256];
  assert_int_equal(vlff_evidence_page_to(e, path, 1 << 20, err, sizeof err), 0);
  const float mark[D] = {0, 0, 1, 0}, stray[D] = {1, 0, 0, 0};
  const float E[2 * D] = {0, 0, 1, 0, 1, 0, 0, 0}, fc[2] = {0.5f, 0.6f}; /* the field leans to prompt 1 */
  float score, out[D];
  add_at(e, 1, 2, 3, mark); /* the first voxel in memory: the first given up */
  const double lo[3] = {-2, -2, 0}, hi[3] = {30, 14, 4}, lo2[3] = {-6, -2, 0};
  assert_int_equal(vlff_evidence_grow(e, lo, hi, lo, hi, 1000, err, sizeof err), 1);
  int t = 0;
  for (; vlff_evidence_paged_out(e) == 0; t++) {
    assert_true(t < 56 * 32 * 8);
    add_at(e, 8 + t % 56, t / 56 % 32, t / (56 * 32), stray);
  }
  assert_int_equal(vlff_evidence_get(e, voxel_at(e, 1, 2, 3), out), 0); /* paged */
  assert_int_equal(label_at(e, 1, 2, 3, E, 1, fc, &score), 0);
  const long before = voxel_at(e, 1, 2, 3);
  assert_int_equal(vlff_evidence_grow(e, lo2, hi, lo2, hi, 1000, err, sizeof err), 1);
  assert_true(voxel_at(e, 1, 2, 3) != before);
  assert_int_equal(vlff_evidence_paged(e), (size_t)vlff_evidence_paged_out(e));
  /* read where it was: the evidence's prompt, at the paged cosines' score */
  assert_int_equal(label_at(e, 1, 2, 3, E, 1, fc, &score), 0);
  assert_float_equal(score, (0.5f + 1.0f) / 2, 1e-2);
  /* a stray paged beside it reads as a stray */
  assert_int_equal(label_at(e, 8, 0, 0, E, 1, fc, &score), 1);
  /* seen again: back in a slot with its 16 samples and the new view's */
  add_at(e, 1, 2, 3, mark);
  assert_int_equal(vlff_evidence_get(e, voxel_at(e, 1, 2, 3), out), 32);
  assert_float_equal(out[2], 1.0f, 1e-3);
  assert_int_equal(vlff_evidence_paged_in(e), 1);
  assert_int_equal(vlff_evidence_evicted(e), 0);
  vlff_evidence_destroy(e);
  assert_int_equal(rmdir(dir), 0);
}

/* Saved evidence of more voxels than the budget holds (its budget lowered
 * since) keeps the most-observed, at equal counts the lowest voxel indices,
 * each as it was saved, and counts the rest as given up; a budget with room
 * loads it all. */
static void test_load_thins_to_budget(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20);
  enum { N = 60 };
  for (int t = 0; t < N; t++)
    for (int r = 0; r <= t % 3; r++) add_at(e, t % 8, t / 8 % 8, t / 64, (const float[D]){(float)t, 1, 0, 0});
  size_t n = vlff_evidence_save_size(e);
  uint8_t *buf = malloc(n);
  vlff_evidence_save(e, buf);
  char err[256];
  struct vlff_evidence *g = make(1 << 12);
  const size_t cap = vlff_evidence_capacity(g);
  assert_true(cap > N / 3 && cap < 2 * N / 3); /* all of the 48-sample voxels and some of the 32-sample ones */
  assert_int_equal(vlff_evidence_load(g, buf, n, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(g), cap);
  assert_int_equal(vlff_evidence_evicted(g), N - (long long)cap);
  int kept[3] = {0}, last_kept32 = -1, first_gone32 = N;
  for (int t = 0; t < N; t++) {
    float x[D], y[D];
    long vi = voxel_at(e, t % 8, t / 8 % 8, t / 64);
    int got = vlff_evidence_get(g, vi, y);
    assert_int_equal(vlff_evidence_get(e, vi, x), 16 * (t % 3 + 1));
    if (!got) {
      if (t % 3 == 1 && t < first_gone32) first_gone32 = t;
      continue;
    }
    assert_int_equal(got, 16 * (t % 3 + 1));
    assert_memory_equal(x, y, sizeof x);
    kept[t % 3]++;
    if (t % 3 == 1) last_kept32 = t;
  }
  assert_int_equal(kept[2], N / 3);
  assert_int_equal(kept[1], (int)cap - N / 3);
  assert_int_equal(kept[0], 0);
  assert_true(last_kept32 < first_gone32);
  /* The loaded budget is full, but no view has touched it since: a newly
   * seen voxel takes the place of the least-observed. */
  add_at(g, 7, 7, 0, (const float[D]){0, 0, 0, 1});
  float z[D];
  assert_int_equal(vlff_evidence_get(g, voxel_at(g, 7, 7, 0), z), 16);
  assert_int_equal(vlff_evidence_overflow(g), 0);
  /* Room for all: nothing given up. */
  struct vlff_evidence *big = make(1 << 20);
  assert_int_equal(vlff_evidence_load(big, buf, n, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(big), N);
  assert_int_equal(vlff_evidence_evicted(big), 0);
  vlff_evidence_destroy(big);
  free(buf);
  vlff_evidence_destroy(g);
  vlff_evidence_destroy(e);
}

/* The grid plan coarsens until the box fits the voxel budget. */
static void test_grid_plan(void **state) {
  (void)state;
  const double lo[3] = {-5, -4, -1.5}, hi[3] = {5, 4, 1.5};
  uint32_t d[3];
  assert_float_equal(vlff_map_grid_plan(lo, hi, 0.1, 1u << 20, d), 0.1, 1e-12);
  assert_int_equal(d[0], 100);
  assert_int_equal(d[1], 80);
  assert_int_equal(d[2], 30);
  double v = vlff_map_grid_plan(lo, hi, 0.1, 10000, d);
  assert_true(v > 0.1);
  assert_true((size_t)d[0] * d[1] * d[2] <= 10000);
}

/* A re-observation replaces what was seen before: a voxel averaged from
 * 60 views of one thing reads another after 20 views of it (a thing moved
 * there). A lifetime mean (each new sample 1/255 once the count was
 * full) still read mostly the old one: 0.25 of the new. */
static void test_recent_views_replace_old(void **state) {
  (void)state;
  struct vlff_evidence *e = make(1 << 20);
  struct wall a, b;
  wall_make(&a, 2.2f, (const float[D]){1, 0, 0, 0});
  wall_make(&b, 2.2f, (const float[D]){0, 1, 0, 0});
  char err[256];
  for (int i = 0; i < 60; i++) assert_int_equal(vlff_evidence_add(e, &a.v, err, sizeof err), 0);
  for (int i = 0; i < 20; i++) assert_int_equal(vlff_evidence_add(e, &b.v, err, sizeof err), 0);
  float out[D];
  assert_true(vlff_evidence_get(e, vlff_evidence_voxel(e, (const double[3]){0.1, 0.1, 2.2}), out) > 0);
  assert_true(out[1] > 0.6f);
  assert_true(out[0] < 0.4f);
  vlff_evidence_destroy(e);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_views_average_where_depth_ends),
    cmocka_unit_test(test_views_average_as_directions),
    cmocka_unit_test(test_old_long_mean_joins_as_direction),
    cmocka_unit_test(test_footprint_reaches_every_voxel),
    cmocka_unit_test(test_labels_combine_field_and_evidence),
    cmocka_unit_test(test_field_trust_follows_exposure), cmocka_unit_test(test_lost_class_read_from_evidence),
    cmocka_unit_test(test_lost_classes_saved),
    cmocka_unit_test(test_budget_and_bad_values), cmocka_unit_test(test_full_budget_gives_up_least_observed),
    cmocka_unit_test(test_full_budget_pages_out),
    cmocka_unit_test(test_labels_read_between_voxel_centres), cmocka_unit_test(test_save_load),
    cmocka_unit_test(test_grow), cmocka_unit_test(test_refit), cmocka_unit_test(test_slide),
    cmocka_unit_test(test_paged_then_grown),
    cmocka_unit_test(test_load_thins_to_budget),
    cmocka_unit_test(test_grid_plan), cmocka_unit_test(test_recent_views_replace_old))
