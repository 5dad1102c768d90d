/* The synthetic scene: determinism, geometry, labels, poses and features. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <cmocka.h>

#include "config.h"
#include "field.h"
#include "metrics.h"
#include "sim.h"
#include "unit.h"

static void small_cfg(struct vlff_config *c, int seed) {
  vlff_config_defaults(c);
  c->sim.seed = seed;
  c->sim.width = 160, c->sim.height = 120, c->field.feature_dim = 32;
}

static struct vlff_sim *make(const struct vlff_config *c) {
  char err[256] = "";
  struct vlff_sim *s = vlff_sim_create(&c->sim, &c->field, err, sizeof err);
  if (!s) fail_msg("%s", err);
  return s;
}

static void render(struct vlff_sim *s, long long i, struct vlff_sim_frame *f) {
  char err[256] = "";
  if (vlff_sim_render(s, i, VLFF_SIM_ALL, f, err, sizeof err) < 0) fail_msg("%s", err);
}

static void test_deterministic_per_seed(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c, 7);
  struct vlff_sim *a = make(&c), *b = make(&c);
  struct vlff_sim_frame *fa = vlff_sim_frame_new(a), *fb = vlff_sim_frame_new(b);
  render(a, 13, fa);
  render(b, 13, fb);
  size_t n = (size_t)fa->width * fa->height;
  assert_memory_equal(fa->rgb, fb->rgb, n * 3);
  assert_memory_equal(fa->depth, fb->depth, n * sizeof(float));
  assert_memory_equal(fa->label, fb->label, n);
  assert_memory_equal(fa->features, fb->features,
                      (size_t)fa->feat_width * fa->feat_height * fa->feature_dim * sizeof(uint16_t));
  /* rendering out of order gives the same frame */
  render(b, 2, fb);
  render(b, 13, fb);
  assert_memory_equal(fa->features, fb->features,
                      (size_t)fa->feat_width * fa->feat_height * fa->feature_dim * sizeof(uint16_t));
  /* another seed: another room */
  struct vlff_config c2;
  small_cfg(&c2, 8);
  struct vlff_sim *d = make(&c2);
  struct vlff_sim_frame *fd = vlff_sim_frame_new(d);
  render(d, 13, fd);
  assert_true(memcmp(fa->label, fd->label, n) != 0);
  vlff_sim_frame_free(fa), vlff_sim_frame_free(fb), vlff_sim_frame_free(fd);
  vlff_sim_destroy(a), vlff_sim_destroy(b), vlff_sim_destroy(d);
}

/* Back-projected depth lands on the surfaces the labels name: floor pixels
 * at floor height, wall pixels on a wall plane; measured depth stays within
 * the noise model, is 0 beyond the range limit, and holes are about as
 * frequent as configured. */
static void test_depth_matches_geometry(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c, 3);
  c.sim.depth_max_m = 3.0;
  struct vlff_sim *s = make(&c);
  struct vlff_sim_frame *f = vlff_sim_frame_new(s);
  double lo[3], hi[3];
  vlff_sim_bounds(s, lo, hi);
  long floor_px = 0, wall_px = 0, valid = 0, holes = 0, inrange = 0;
  for (int fi = 0; fi < 40; fi += 5) {
    render(s, fi, f);
    const double *M = f->c2w_true;
    for (int v = 0; v < f->height; v++)
      for (int u = 0; u < f->width; u++) {
        size_t k = (size_t)v * f->width + u;
        double z = f->depth_gt[k];
        assert_true(z > 0);
        double xc = (u + 0.5 - f->cx) / f->fx * z, yc = (v + 0.5 - f->cy) / f->fy * z;
        double w[3];
        for (int r = 0; r < 3; r++) w[r] = M[4 * r] * xc + M[4 * r + 1] * yc + M[4 * r + 2] * z + M[4 * r + 3];
        if (f->label[k] == 1) {
          assert_true(fabs(w[2] - lo[2]) < 1e-6);
          floor_px++;
        }
        if (f->label[k] == 0) {
          double dmin = fmin(fmin(fabs(w[0] - lo[0]), fabs(w[0] - hi[0])), fmin(fabs(w[1] - lo[1]), fabs(w[1] - hi[1])));
          assert_true(dmin < 1e-6);
          wall_px++;
        }
        double m = f->depth[k];
        if (z <= 3.0) {
          inrange++;
          if (m == 0) holes++;
          else assert_true(fabs(m - z) < 6 * c.sim.depth_noise_m * z * z + 1e-6);
        } else {
          assert_true(m == 0);
        }
        if (m > 0) {
          valid++;
          assert_int_equal(f->depth_mm[k], (uint16_t)(m * 1000.0 + 0.5));
        } else {
          assert_int_equal(f->depth_mm[k], 0);
        }
      }
  }
  assert_true(floor_px > 1000 && wall_px > 1000 && valid > 0);
  double hf = (double)holes / inrange;
  assert_true(hf > 0.3 * c.sim.depth_hole_frac && hf < 3.0 * c.sim.depth_hole_frac);
  vlff_sim_frame_free(f);
  vlff_sim_destroy(s);
}

static void test_labels_cover_classes(void **state) {
  (void)state;
  for (int seed = 1; seed <= 3; seed++) {
    struct vlff_config c;
    small_cfg(&c, seed);
    struct vlff_sim *s = make(&c);
    int counts[VLFF_SIM_CLASSES];
    vlff_sim_class_counts(s, counts);
    int placed = 0;
    for (int k = 0; k < VLFF_SIM_CLASSES; k++) placed += counts[k] > 0;
    assert_true(placed >= 19);
    struct vlff_sim_frame *f = vlff_sim_frame_new(s);
    int seen[256] = {0};
    for (int fi = 0; fi < c.sim.frames; fi += 6) {
      render(s, fi, f);
      for (int k = 0; k < f->width * f->height; k++) seen[f->label[k]] = 1;
    }
    int nseen = 0;
    for (int k = 0; k < VLFF_SIM_CLASSES; k++) nseen += seen[k];
    assert_true(nseen >= 17);
    for (int k = VLFF_SIM_CLASSES; k < 255; k++) assert_int_equal(seen[k], 0);
    vlff_sim_frame_free(f);
    vlff_sim_destroy(s);
  }
}

static void test_poses_opencv_and_speed(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c, 2);
  c.sim.trajectory = VLFF_TRAJ_ORBIT;
  c.sim.speed_mps = 0.5, c.sim.rate_hz = 5;
  struct vlff_sim *s = make(&c);
  double prev[16] = {0};
  for (int i = 0; i < 30; i++) {
    double m[16];
    vlff_sim_pose(s, i, m);
    for (int a = 0; a < 3; a++)
      for (int b = 0; b < 3; b++) {
        double d = 0;
        for (int k = 0; k < 3; k++) d += m[4 * k + a] * m[4 * k + b];
        assert_true(fabs(d - (a == b)) < 1e-9);
      }
    assert_true(m[12] == 0 && m[13] == 0 && m[14] == 0 && m[15] == 1);
    /* OpenCV camera: y (down) points down in the z-up world, z looks down a little */
    assert_true(m[9] < 0);
    assert_true(m[10] < 0);
    if (i) {
      double dx = m[3] - prev[3], dy = m[7] - prev[7], dz = m[11] - prev[11];
      double step = sqrt(dx * dx + dy * dy + dz * dz);
      assert_true(fabs(step - 0.5 / 5) < 0.01);
    }
    memcpy(prev, m, sizeof prev);
  }
  vlff_sim_destroy(s);
  /* corrupted poses are flagged and differ from the rendered pose */
  small_cfg(&c, 2);
  c.sim.bad_pose_frac = 0.5;
  s = make(&c);
  struct vlff_sim_frame *f = vlff_sim_frame_new(s);
  int bad = 0;
  for (int i = 0; i < 20; i++) {
    render(s, i, f);
    double d = fabs(f->c2w[3] - f->c2w_true[3]) + fabs(f->c2w[7] - f->c2w_true[7]);
    if (f->bad_pose) {
      bad++;
      assert_true(d > 0.1);
    } else {
      assert_true(d == 0);
    }
  }
  assert_true(bad >= 4 && bad <= 16);
  vlff_sim_frame_free(f);
  vlff_sim_destroy(s);
}

static double cosine(const float *a, const float *b, int d) {
  double ab = 0, aa = 0, bb = 0;
  for (int i = 0; i < d; i++) ab += a[i] * b[i], aa += a[i] * a[i], bb += b[i] * b[i];
  return ab / sqrt(aa * bb);
}

static void test_embeddings_structure(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c, 1);
  c.field.feature_dim = 512;
  struct vlff_sim *s = make(&c);
  const int D = 512;
  float t[VLFF_SIM_CLASSES][512], p[512], u1[512], u2[512];
  for (int k = 0; k < VLFF_SIM_CLASSES; k++) {
    vlff_sim_text_embedding(s, vlff_sim_class_name(k), t[k]);
    vlff_sim_prototype(s, k, p);
    double cp = cosine(t[k], p, D);
    assert_true(cp > 0.8 && cp < 0.99); /* close to, not equal to, the prototype */
  }
  /* look-alikes are closer than unrelated classes */
  int desk = vlff_sim_class_of("desk"), table = vlff_sim_class_of("table"), bed = vlff_sim_class_of("bed");
  int cur = vlff_sim_class_of("curtain"), sh = vlff_sim_class_of("Shower Curtain"), floor = vlff_sim_class_of("floor");
  assert_true(desk >= 0 && table >= 0 && sh >= 0);
  assert_true(cosine(t[desk], t[table], D) > cosine(t[desk], t[bed], D) + 0.1);
  assert_true(cosine(t[cur], t[sh], D) > cosine(t[cur], t[floor], D) + 0.1);
  /* any text has a deterministic embedding */
  vlff_sim_text_embedding(s, "a red mug", u1);
  vlff_sim_text_embedding(s, "a red mug", u2);
  assert_memory_equal(u1, u2, sizeof u1);
  vlff_sim_text_embedding(s, "a blue mug", u2);
  assert_true(cosine(u1, u2, D) < 0.5);
  assert_int_equal(vlff_sim_class_of("chairs"), -1);
  vlff_sim_destroy(s);
}

/* Per-frame features: informative (far above chance) but imperfect, and
 * worse with difficulty. */
static double raw_miou(double difficulty) {
  struct vlff_config c;
  small_cfg(&c, 4);
  c.sim.difficulty = difficulty;
  c.field.feature_dim = 64;
  struct vlff_sim *s = make(&c);
  struct vlff_sim_frame *f = vlff_sim_frame_new(s);
  int K = VLFF_SIM_CLASSES, D = 64, n = f->feat_width * f->feat_height;
  float emb[VLFF_SIM_CLASSES * 64], unit[VLFF_SIM_CLASSES * 64];
  for (int k = 0; k < K; k++) vlff_sim_text_embedding(s, vlff_sim_class_name(k), emb + k * D);
  vlff_normalize_rows(emb, unit, K, D);
  struct vlff_confusion cm;
  char err[128];
  assert_int_equal(vlff_confusion_init(&cm, K, err, sizeof err), 0);
  uint8_t *gl = malloc((size_t)n);
  int *pl = malloc((size_t)n * sizeof(int));
  for (int fi = 0; fi < 300; fi += 15) {
    render(s, fi, f);
    vlff_downsample_labels(f->label, f->width, f->height, gl, f->feat_width, f->feat_height);
    vlff_classify_f16(f->features, (size_t)n, D, unit, K, pl, NULL);
    vlff_confusion_add(&cm, gl, pl, (size_t)n);
  }
  struct vlff_summary sm;
  vlff_confusion_summary(&cm, &sm);
  free(gl), free(pl);
  vlff_confusion_free(&cm);
  vlff_sim_frame_free(f);
  vlff_sim_destroy(s);
  return sm.miou;
}

static void test_features_imperfect_but_informative(void **state) {
  (void)state;
  double easy = raw_miou(0.0), mid = raw_miou(0.5), hard = raw_miou(1.0);
  print_message("per-frame 2D mIoU: difficulty 0 %.3f, 0.5 %.3f, 1 %.3f\n", easy, mid, hard);
  assert_true(mid > 0.25 && mid < 0.8);
  assert_true(easy > mid + 0.05);
  assert_true(mid > hard + 0.05);
  assert_true(hard > 0.1); /* chance is 0.05 */
}

static void test_points(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c, 5);
  struct vlff_sim *s = make(&c);
  struct vlff_sim_points p;
  char err[128];
  assert_int_equal(vlff_sim_points(s, 60, 4, 0.05, &p, err, sizeof err), 0);
  double lo[3], hi[3];
  vlff_sim_bounds(s, lo, hi);
  assert_true(p.n > 2000);
  int cls[256] = {0};
  for (size_t i = 0; i < p.n; i++) {
    for (int k = 0; k < 3; k++) assert_true(p.xyz[3 * i + k] >= lo[k] - 1e-4 && p.xyz[3 * i + k] <= hi[k] + 1e-4);
    cls[p.label[i]]++;
  }
  for (int k = VLFF_SIM_CLASSES; k < 255; k++) assert_int_equal(cls[k], 0);
  assert_true(cls[0] > 0 && cls[1] > 0);
  /* each labelled point lies on a surface of its class: a short ray down
   * onto a floor point hits the floor */
  for (size_t i = 0; i < p.n; i++)
    if (p.label[i] == 1) {
      double o[3] = {p.xyz[3 * i], p.xyz[3 * i + 1], p.xyz[3 * i + 2] + 0.01}, d[3] = {0, 0, -1};
      int lab;
      double t = vlff_sim_raycast(s, o, d, &lab, NULL);
      assert_true(fabs(t - 0.01) < 1e-4);
      assert_int_equal(lab, 1);
      break;
    }
  /* every second pixel of 160x120, frames 0, 4, ..., 56 */
  assert_true(p.rays == 15 * 80 * 60);
  vlff_sim_points_free(&p);
  /* within a budget: the same while it holds them; a million frames take
   * views spread over the whole run; every 4th pixel of a view larger than
   * a sixteenth of it */
  const uint64_t budget = 80000;
  assert_int_equal(vlff_sim_points_budget(s, 60, 4, 0.05, budget, &p, err, sizeof err), 0);
  assert_true(p.rays == 15 * 80 * 60);
  vlff_sim_points_free(&p);
  assert_int_equal(vlff_sim_points_budget(s, 1000000, 5, 0.05, budget, &p, err, sizeof err), 0);
  assert_true(p.rays <= budget && p.rays > budget / 4);
  assert_true(p.n > 500);
  vlff_sim_points_free(&p);
  assert_int_equal(vlff_sim_points_budget(s, 60, 4, 0.05, 4 * 4800, &p, err, sizeof err), 0);
  assert_true(p.rays == 15 * 40 * 30); /* 160x120 at every 4th pixel, the same 15 views */
  vlff_sim_points_free(&p);
  assert_int_equal(vlff_sim_points_budget(s, 60, 4, 0.05, 8, &p, err, sizeof err), -1);
  assert_int_equal(vlff_sim_points(s, 0, 1, 0.05, &p, err, sizeof err), -1);
  assert_null(p.xyz);
  vlff_sim_destroy(s);
}

/* The flat: rooms over a 10 x 8 m box joined by doorways. The walk between
 * two consecutive frames never passes through a wall (it goes through the
 * doorways), it covers the whole flat and comes back where it started;
 * every class is furnished, with more chairs and small things than a room;
 * a box too small for 60 m^2 is refused. */
static void flat_cfg(struct vlff_config *c, int seed) {
  small_cfg(c, seed);
  c->sim.layout = VLFF_LAYOUT_FLAT;
  c->sim.frames = 200;
  double lo[3] = {-5, -4, -1.5}, hi[3] = {5, 4, 1.5};
  memcpy(c->field.scene_min, lo, sizeof lo);
  memcpy(c->field.scene_max, hi, sizeof hi);
}

static void test_flat_walk_through_doorways(void **state) {
  (void)state;
  for (int seed = 1; seed <= 3; seed++) {
    struct vlff_config c;
    flat_cfg(&c, seed);
    struct vlff_sim *s = make(&c);
    double lo[3], hi[3];
    vlff_sim_bounds(s, lo, hi);
    assert_true((hi[0] - lo[0]) * (hi[1] - lo[1]) >= 60);
    int counts[VLFF_SIM_CLASSES];
    vlff_sim_class_counts(s, counts);
    for (int k = 0; k < VLFF_SIM_CLASSES; k++)
      if (counts[k] == 0) fail_msg("seed %d: no %s in the flat", seed, vlff_sim_class_name(k));
    assert_true(counts[vlff_sim_class_of("chair")] >= 5 * 4); /* seat, back, legs: >= 4 prims a chair */
    assert_true(counts[vlff_sim_class_of("other furniture")] >= 8);
    double xmin = 1e9, xmax = -1e9, ymin = 1e9, ymax = -1e9, prev[16] = {0}, first[16] = {0};
    int crossings = 0;
    for (int i = 0; i <= c.sim.frames; i++) {
      double m[16];
      vlff_sim_pose(s, i, m);
      if (i == 0) memcpy(first, m, sizeof m);
      xmin = fmin(xmin, m[3]), xmax = fmax(xmax, m[3]), ymin = fmin(ymin, m[7]), ymax = fmax(ymax, m[7]);
      assert_true(m[3] > lo[0] && m[3] < hi[0] && m[7] > lo[1] && m[7] < hi[1]);
      if (i > 0) {
        double d[3] = {m[3] - prev[3], m[7] - prev[7], m[11] - prev[11]};
        double len = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        double o[3] = {prev[3], prev[7], prev[11]};
        double t = vlff_sim_raycast(s, o, d, NULL, NULL);
        if (t >= 0 && t < 1) crossings++;
        assert_true(len < 1.0);
      }
      memcpy(prev, m, sizeof m);
    }
    assert_int_equal(crossings, 0);
    assert_true(xmax - xmin > 4.5 && ymax - ymin > 3.5);
    /* one loop per sim.frames frames: frame `frames` is frame 0 again */
    assert_true(fabs(prev[3] - first[3]) < 1e-9 && fabs(prev[7] - first[7]) < 1e-9);
    vlff_sim_destroy(s);
  }
  struct vlff_config c;
  flat_cfg(&c, 1);
  c.field.scene_max[0] = 2;
  char err[256] = "";
  assert_null(vlff_sim_create(&c.sim, &c.field, err, sizeof err));
  assert_non_null(strstr(err, "60 m^2"));
}

/* sim.object_bias: geometry, labels and depth stay the same; features
 * change, and the change is shared by every view of an object, so the mean
 * feature of one object over many views moves away from its class. */
static void test_object_bias_view_consistent(void **state) {
  (void)state;
  struct vlff_config c0, c1;
  flat_cfg(&c0, 2);
  c1 = c0;
  c1.sim.object_bias = 1;
  struct vlff_sim *a = make(&c0), *b = make(&c1);
  struct vlff_sim_frame *fa = vlff_sim_frame_new(a), *fb = vlff_sim_frame_new(b);
  size_t n = (size_t)fa->width * fa->height, nf = (size_t)fa->feat_width * fa->feat_height * fa->feature_dim;
  int D = fa->feature_dim, K = VLFF_SIM_CLASSES;
  float *emb = malloc((size_t)K * D * sizeof(float)), *unit = malloc((size_t)K * D * sizeof(float));
  for (int k = 0; k < K; k++) vlff_sim_text_embedding(a, vlff_sim_class_name(k), emb + (size_t)k * D);
  vlff_normalize_rows(emb, unit, K, D);
  size_t np = (size_t)fa->feat_width * fa->feat_height;
  int *la = malloc(np * sizeof(int)), *lb = malloc(np * sizeof(int));
  long agree_a = 0, agree_b = 0, total = 0;
  for (int i = 0; i < 40; i += 4) {
    render(a, i, fa);
    render(b, i, fb);
    assert_memory_equal(fa->label, fb->label, n);
    assert_memory_equal(fa->depth, fb->depth, n * sizeof(float));
    assert_true(memcmp(fa->features, fb->features, nf * sizeof(uint16_t)) != 0);
    vlff_classify_f16(fa->features, np, D, unit, K, la, NULL);
    vlff_classify_f16(fb->features, np, D, unit, K, lb, NULL);
    for (int y = 0; y < fa->feat_height; y++)
      for (int x = 0; x < fa->feat_width; x++) {
        int g = fa->label[(size_t)(4 * y + 2) * fa->width + 4 * x + 2];
        if (g >= K) continue;
        total++;
        agree_a += la[(size_t)y * fa->feat_width + x] == g;
        agree_b += lb[(size_t)y * fa->feat_width + x] == g;
      }
  }
  print_message("pixel accuracy without / with object bias: %.3f / %.3f\n", (double)agree_a / total,
                (double)agree_b / total);
  assert_true(agree_b < agree_a);
  free(emb), free(unit), free(la), free(lb);
  vlff_sim_frame_free(fa), vlff_sim_frame_free(fb);
  vlff_sim_destroy(a), vlff_sim_destroy(b);
}

/* The building: sim.flats flats off a corridor over a 24.4 x 10 m box
 * (tests/bench/eval-building.yaml's), walked once per sim.frames frames. */
static void building_cfg(struct vlff_config *c, int seed, int frames) {
  small_cfg(c, seed);
  c->sim.layout = VLFF_LAYOUT_BUILDING;
  c->sim.flats = 3;
  c->sim.frames = frames;
  double lo[3] = {-12.2, -5, -1.5}, hi[3] = {12.2, 5, 1.5};
  memcpy(c->field.scene_min, lo, sizeof lo);
  memcpy(c->field.scene_max, hi, sizeof hi);
}

/* Floor (the rooms' insides) of at least 200 m^2; every flat has two or
 * more rooms; the corridor joins them. */
static void check_building_rooms(struct vlff_sim *s, int flats) {
  struct vlff_sim_room rooms[64];
  int n = vlff_sim_rooms(s, rooms, 64);
  assert_true(n > 0 && n <= 64);
  assert_int_equal(vlff_sim_flat_count(s), flats);
  double area = 0;
  int per[8] = {0}, corridor = 0;
  for (int i = 0; i < n; i++) {
    area += (rooms[i].hi[0] - rooms[i].lo[0]) * (rooms[i].hi[1] - rooms[i].lo[1]);
    if (rooms[i].flat < 0) corridor++;
    else per[rooms[i].flat]++;
  }
  print_message("building: %d rooms, %.1f m^2 of floor\n", n, area);
  assert_true(area >= 200);
  assert_int_equal(corridor, 1);
  for (int k = 0; k < flats; k++)
    if (per[k] < 2) fail_msg("flat %d has %d rooms", k + 1, per[k]);
}

/* The walk, sampled at every frame: its length, that it starts and ends in
 * flat 1 and enters every flat, and that no step between two frames passes
 * through anything (walls, doors, furniture): ray-cast along each step. */
static double check_building_walk(struct vlff_sim *s, int frames, int flats) {
  double prev[16] = {0}, first[16] = {0}, len = 0;
  int crossings = 0, inside[8] = {0};
  for (int i = 0; i <= frames; i++) {
    double m[16];
    vlff_sim_pose(s, i, m);
    if (i == 0) memcpy(first, m, sizeof m);
    int f = vlff_sim_flat_at(s, m[3], m[7]);
    if (f >= 0) inside[f]++;
    if (i > 0) {
      double d[3] = {m[3] - prev[3], m[7] - prev[7], m[11] - prev[11]}, o[3] = {prev[3], prev[7], prev[11]};
      len += sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
      int lab;
      double t = vlff_sim_raycast(s, o, d, &lab, NULL);
      if (t >= 0 && t < 1) {
        crossings++;
        print_message("frame %d: the step from (%.2f %.2f %.2f) to (%.2f %.2f) hits %s at %.2f\n", i, o[0], o[1], o[2],
                      m[3], m[7], lab < VLFF_SIM_CLASSES ? vlff_sim_class_name(lab) : "the ceiling", t);
      }
    }
    memcpy(prev, m, sizeof m);
  }
  assert_int_equal(crossings, 0);
  for (int k = 0; k < flats; k++)
    if (inside[k] < frames / (4 * flats)) fail_msg("the walk spends %d of %d frames in flat %d", inside[k], frames, k + 1);
  assert_int_equal(vlff_sim_flat_at(s, first[3], first[7]), 0);
  /* the last frame of the loop is back in flat 1, and the loop closes */
  double last[16];
  vlff_sim_pose(s, frames - 1, last);
  assert_int_equal(vlff_sim_flat_at(s, last[3], last[7]), 0);
  assert_true(fabs(prev[3] - first[3]) < 1e-9 && fabs(prev[7] - first[7]) < 1e-9);
  return len;
}

static void test_building_layout_and_walk(void **state) {
  (void)state;
  for (int seed = 1; seed <= 3; seed++) {
    struct vlff_config c;
    building_cfg(&c, seed, 2000); /* poses only: fine steps measure the walk */
    struct vlff_sim *s = make(&c);
    check_building_rooms(s, 3);
    double len = check_building_walk(s, c.sim.frames, 3);
    print_message("seed %d: walk %.1f m (the path's %.1f m)\n", seed, len, vlff_sim_walk_length(s));
    assert_true(len >= 90);
    assert_true(fabs(len - vlff_sim_walk_length(s)) < 0.02 * len);
    vlff_sim_destroy(s);
  }
  /* at 240 frames, as the benches walk it: steps stay short */
  struct vlff_config c;
  building_cfg(&c, 1, 240);
  struct vlff_sim *s = make(&c);
  double len = check_building_walk(s, 240, 3);
  assert_true(len / 240 < 0.65);
  vlff_sim_destroy(s);
  /* more flats, a longer box */
  building_cfg(&c, 4, 2000);
  c.sim.flats = 5;
  c.field.scene_min[0] = -20.5, c.field.scene_max[0] = 20.5;
  s = make(&c);
  check_building_rooms(s, 5);
  check_building_walk(s, 2000, 5);
  vlff_sim_destroy(s);
}

/* What the walk's frames see: every flat's surfaces (each with most of the
 * 20 classes), every class somewhere in the building. */
static void test_building_seen(void **state) {
  (void)state;
  struct vlff_config c;
  building_cfg(&c, 2, 240);
  struct vlff_sim *s = make(&c);
  int counts[VLFF_SIM_CLASSES];
  vlff_sim_class_counts(s, counts);
  struct vlff_sim_points p;
  char err[256] = "";
  assert_int_equal(vlff_sim_points(s, 240, 2, 0.05, &p, err, sizeof err), 0);
  long per_flat[3] = {0};
  int cls[3][VLFF_SIM_CLASSES] = {{0}}, all[VLFF_SIM_CLASSES] = {0};
  for (size_t i = 0; i < p.n; i++) {
    if (p.label[i] >= VLFF_SIM_CLASSES) continue;
    all[p.label[i]]++;
    int f = vlff_sim_flat_at(s, p.xyz[3 * i], p.xyz[3 * i + 1]);
    if (f >= 0) per_flat[f]++, cls[f][p.label[i]]++;
  }
  for (int k = 0; k < VLFF_SIM_CLASSES; k++) {
    if (counts[k] == 0) fail_msg("no %s in the building", vlff_sim_class_name(k));
    if (all[k] == 0) fail_msg("no %s point seen", vlff_sim_class_name(k));
  }
  for (int f = 0; f < 3; f++) {
    int nc = 0;
    for (int k = 0; k < VLFF_SIM_CLASSES; k++) nc += cls[f][k] > 0;
    print_message("flat %d: %ld labelled points, %d classes\n", f + 1, per_flat[f], nc);
    assert_true(per_flat[f] > (long)p.n / 6);
    assert_true(nc >= 17);
  }
  vlff_sim_points_free(&p);
  vlff_sim_destroy(s);
}

/* A seed gives the same building, walk and frames; another seed another. */
static void test_building_deterministic(void **state) {
  (void)state;
  struct vlff_config c;
  building_cfg(&c, 5, 240);
  struct vlff_sim *a = make(&c), *b = make(&c);
  c.sim.seed = 6;
  struct vlff_sim *o = make(&c);
  struct vlff_sim_frame *fa = vlff_sim_frame_new(a), *fb = vlff_sim_frame_new(b), *fo = vlff_sim_frame_new(o);
  size_t n = (size_t)fa->width * fa->height, nf = (size_t)fa->feat_width * fa->feat_height * fa->feature_dim;
  int moved = 0;
  for (int i = 0; i < 240; i += 17) {
    double ma[16], mb[16], mo[16];
    vlff_sim_pose(a, i, ma), vlff_sim_pose(b, i, mb), vlff_sim_pose(o, i, mo);
    assert_memory_equal(ma, mb, sizeof ma);
    moved += fabs(ma[3] - mo[3]) > 1e-6 || fabs(ma[7] - mo[7]) > 1e-6;
  }
  assert_true(moved > 0);
  for (int i = 100; i < 240; i += 70) {
    render(a, i, fa), render(b, i, fb), render(o, i, fo);
    assert_memory_equal(fa->rgb, fb->rgb, n * 3);
    assert_memory_equal(fa->depth, fb->depth, n * sizeof(float));
    assert_memory_equal(fa->label, fb->label, n);
    assert_memory_equal(fa->features, fb->features, nf * sizeof(uint16_t));
    assert_true(memcmp(fa->rgb, fo->rgb, n * 3) != 0);
  }
  vlff_sim_frame_free(fa), vlff_sim_frame_free(fb), vlff_sim_frame_free(fo);
  vlff_sim_destroy(a), vlff_sim_destroy(b), vlff_sim_destroy(o);
}

/* A box too small for three 6 x 6 m flats or 200 m^2, or a flat count
 * out of range, is refused with the reason. */
static void test_building_bad_config(void **state) {
  (void)state;
  struct vlff_config c;
  building_cfg(&c, 1, 240);
  c.field.scene_min[0] = -8, c.field.scene_max[0] = 8;
  char err[256] = "";
  assert_null(vlff_sim_create(&c.sim, &c.field, err, sizeof err));
  assert_non_null(strstr(err, "200 m^2"));
  building_cfg(&c, 1, 240);
  c.sim.flats = 9;
  assert_null(vlff_sim_create(&c.sim, &c.field, err, sizeof err));
  assert_non_null(strstr(err, "sim.flats"));
}

static void test_bad_config(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c, 1);
  c.field.scene_min[2] = -1, c.field.scene_max[2] = 1;
  char err[256] = "";
  assert_null(vlff_sim_create(&c.sim, &c.field, err, sizeof err));
  assert_non_null(strstr(err, "scene_min/max"));
  /* The world's own box (sim.scene_min/max) replaces the field's: a node
   * whose box grows (field.grow) starts in a smaller first box. */
  const double lo[3] = {-2, -2, -1.5}, hi[3] = {2, 2, 1.5};
  memcpy(c.sim.scene_min, lo, sizeof lo);
  memcpy(c.sim.scene_max, hi, sizeof hi);
  struct vlff_sim *s = vlff_sim_create(&c.sim, &c.field, err, sizeof err);
  assert_non_null(s);
  vlff_sim_destroy(s);
  c.sim.scene_max[0] = -2.5; /* and is refused by its own name */
  c.sim.layout = VLFF_LAYOUT_FLAT;
  assert_null(vlff_sim_create(&c.sim, &c.field, err, sizeof err));
  assert_non_null(strstr(err, "sim.scene_min/max"));
}

/* sim.range_first/range_count: the stream shows only that part of the
 * walk, repeated; without them the whole loop. */
static void test_stream_range(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c, 1);
  c.sim.frames = 60;
  char err[256] = "";
  struct vlff_sim *s = vlff_sim_create(&c.sim, &c.field, err, sizeof err);
  assert_non_null(s);
  assert_int_equal(vlff_sim_stream_frame(s, 0), 0);
  assert_int_equal(vlff_sim_stream_frame(s, 61), 1);
  vlff_sim_destroy(s);
  c.sim.range_first = 20, c.sim.range_count = 20;
  s = vlff_sim_create(&c.sim, &c.field, err, sizeof err);
  assert_non_null(s);
  assert_int_equal(vlff_sim_stream_frame(s, 0), 20);
  assert_int_equal(vlff_sim_stream_frame(s, 19), 39);
  assert_int_equal(vlff_sim_stream_frame(s, 20), 20);
  assert_int_equal(vlff_sim_stream_frame(s, 45), 25);
  vlff_sim_destroy(s);
}

/* Pixels of class c in a frame rendered (labels only) at index i. */
static int count_class(struct vlff_sim *s, long long i, struct vlff_sim_frame *f, int c) {
  char err[256] = "";
  if (vlff_sim_render(s, i, 0, f, err, sizeof err) < 0) fail_msg("%s", err);
  int n = 0;
  for (int k = 0; k < f->width * f->height; k++) n += f->label[k] == c;
  return n;
}

/* The class seen straight down at (x, y) at sim time t. */
static int down(struct vlff_sim *s, double t, double x, double y) {
  double lo[3], hi[3];
  vlff_sim_bounds(s, lo, hi);
  int label;
  vlff_sim_raycast_at(s, t, (const double[3]){x, y, hi[2] - 0.05}, (const double[3]){0, 0, -1}, &label, NULL);
  return label;
}

/* sim.changes: a chair moved at 2 s stands at its new place from then on,
 * in the exact ray casts and in the rendered labels; frames before are
 * those of the unchanged scene; the same config renders the same frames. */
static void test_change_moves_object(void **state) {
  (void)state;
  const int CHAIR = vlff_sim_class_of("chair"), FLOOR = vlff_sim_class_of("floor");
  struct vlff_config c;
  small_cfg(&c, 7);
  struct vlff_sim *a = make(&c);
  /* A spot of bare floor 0.7 m across. */
  double lo[3], hi[3], to[2] = {0, 0};
  bool found = false;
  vlff_sim_bounds(a, lo, hi);
  for (double x = lo[0] + 0.5; x < hi[0] - 0.5 && !found; x += 0.25)
    for (double y = lo[1] + 0.5; y < hi[1] - 0.5 && !found; y += 0.25) {
      bool bare = true;
      for (int k = 0; k < 9; k++) bare &= down(a, 0, x + 0.35 * (k % 3 - 1), y + 0.35 * (k / 3 - 1)) == FLOOR;
      if (bare) to[0] = x, to[1] = y, found = true;
    }
  assert_true(found);
  c.sim.change_count = 1;
  c.sim.changes[0] = (struct vlff_sim_change){.time_s = 2.0, .object = "chair", .action = VLFF_SIM_MOVE,
                                              .has_to = true, .to = {to[0], to[1]}};
  struct vlff_sim *b = make(&c), *b2 = make(&c);
  assert_int_equal(down(b, 1.99, to[0], to[1]), FLOOR);
  assert_int_equal(down(b, 2.0, to[0], to[1]), CHAIR);
  assert_int_equal(down(b, 100.0, to[0], to[1]), CHAIR);
  assert_int_equal(down(a, 100.0, to[0], to[1]), FLOOR);
  struct vlff_sim_frame *fa = vlff_sim_frame_new(a), *fb = vlff_sim_frame_new(b), *fc = vlff_sim_frame_new(b2);
  const size_t px = (size_t)fa->width * fa->height;
  for (long long i = 0; i < 10; i += 3) { /* 5 Hz: frames before 2 s */
    count_class(a, i, fa, CHAIR), count_class(b, i, fb, CHAIR);
    assert_memory_equal(fa->label, fb->label, px);
  }
  int differ = 0;
  for (long long i = 10; i < 10 + c.sim.frames; i += 3) {
    count_class(a, i, fa, CHAIR), count_class(b, i, fb, CHAIR);
    differ += memcmp(fa->label, fb->label, px) != 0;
  }
  assert_true(differ > 0);
  render(b, 40, fb), render(b2, 40, fc);
  assert_memory_equal(fb->rgb, fc->rgb, px * 3);
  assert_memory_equal(fb->depth, fc->depth, px * sizeof(float));
  assert_memory_equal(fb->features, fc->features, (size_t)fb->feat_width * fb->feat_height * fb->feature_dim * 2);
  vlff_sim_frame_free(fa), vlff_sim_frame_free(fb), vlff_sim_frame_free(fc);
  vlff_sim_destroy(a), vlff_sim_destroy(b), vlff_sim_destroy(b2);
}

/* Removed at 0 s, a chair is in no frame; a table added at 4 s is in none
 * before and where it was built after. Names the scene does not have, and
 * a move out of the scene, are refused naming the change. */
static void test_change_removes_adds_and_refuses(void **state) {
  (void)state;
  const int CHAIR = vlff_sim_class_of("chair"), TABLE = vlff_sim_class_of("table");
  struct vlff_config c;
  small_cfg(&c, 7);
  struct vlff_sim *a = make(&c);
  c.sim.change_count = 1;
  c.sim.changes[0] = (struct vlff_sim_change){.time_s = 0, .object = "chair", .action = VLFF_SIM_REMOVE};
  struct vlff_sim *b = make(&c);
  c.sim.changes[0] = (struct vlff_sim_change){.time_s = 4, .object = "table", .action = VLFF_SIM_ADD};
  struct vlff_sim *d = make(&c);
  struct vlff_sim_frame *fa = vlff_sim_frame_new(a), *fb = vlff_sim_frame_new(b);
  int fewer = 0, tables_before = 0, tables_after = 0;
  for (long long i = 0; i < c.sim.frames; i += 3) {
    int ca = count_class(a, i, fa, CHAIR), cb = count_class(b, i, fb, CHAIR);
    assert_true(cb <= ca);
    fewer += cb < ca;
    int ta = count_class(a, i, fa, TABLE), td = count_class(d, i, fb, TABLE);
    if (i < 20) tables_before += td;
    else tables_after += td, assert_int_equal(td, ta);
  }
  assert_true(fewer > 0);
  assert_int_equal(tables_before, 0);
  assert_true(tables_after > 0);
  vlff_sim_frame_free(fa), vlff_sim_frame_free(fb);
  vlff_sim_destroy(b), vlff_sim_destroy(d);
  char err[256];
  int counts[VLFF_SIM_CLASSES];
  vlff_sim_class_counts(a, counts);
  const char *bad[] = {"chair#99", "stool", "chair#0"};
  const char *why[] = {"sim.changes[0].object 'chair#99': this scene has ", "'stool' is not a class", "class#n"};
  c.sim.change_count = 1;
  for (int k = 0; k < 3; k++) {
    c.sim.changes[0] = (struct vlff_sim_change){.time_s = 1, .action = VLFF_SIM_REMOVE};
    snprintf(c.sim.changes[0].object, sizeof c.sim.changes[0].object, "%s", bad[k]);
    assert_null(vlff_sim_create(&c.sim, &c.field, err, sizeof err));
    if (!strstr(err, why[k])) fail_msg("%s", err);
  }
  c.sim.changes[0] = (struct vlff_sim_change){.time_s = 1, .object = "chair", .action = VLFF_SIM_MOVE,
                                              .has_to = true, .to = {50, 0}};
  assert_null(vlff_sim_create(&c.sim, &c.field, err, sizeof err));
  if (!strstr(err, "sim.changes[0]: 'chair' at (50.00, 0.00) would stand outside the scene")) fail_msg("%s", err);
  /* a move of a removed object (written after it, applied in time order) would bring it back unasked */
  c.sim.change_count = 2;
  c.sim.changes[0] = (struct vlff_sim_change){.time_s = 2, .object = "chair", .action = VLFF_SIM_MOVE,
                                              .has_to = true, .to = {0.5, 0.5}};
  c.sim.changes[1] = (struct vlff_sim_change){.time_s = 1, .object = "chair", .action = VLFF_SIM_REMOVE};
  assert_null(vlff_sim_create(&c.sim, &c.field, err, sizeof err));
  if (!strstr(err, "sim.changes[0]: 'chair' is moved at 2 s while absent")) fail_msg("%s", err);
  vlff_sim_destroy(a);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_deterministic_per_seed), cmocka_unit_test(test_depth_matches_geometry),
    cmocka_unit_test(test_labels_cover_classes), cmocka_unit_test(test_poses_opencv_and_speed),
    cmocka_unit_test(test_embeddings_structure),
    cmocka_unit_test(test_features_imperfect_but_informative), cmocka_unit_test(test_points),
    cmocka_unit_test(test_bad_config), cmocka_unit_test(test_stream_range), cmocka_unit_test(test_flat_walk_through_doorways),
    cmocka_unit_test(test_object_bias_view_consistent), cmocka_unit_test(test_building_layout_and_walk),
    cmocka_unit_test(test_building_seen), cmocka_unit_test(test_building_deterministic),
    cmocka_unit_test(test_building_bad_config), cmocka_unit_test(test_change_moves_object),
    cmocka_unit_test(test_change_removes_adds_and_refuses))
