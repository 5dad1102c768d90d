/*
 * Whole-pipeline tests of training: the gradient of one work chunk (with the
 * lazily applied feature layer) against finite differences, an analytic slab
 * through the renderer, and convergence on the built-in analytic scene.
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include <cmocka.h>

#include "field_internal.h"
#include "scene.h"
#include "unit.h"

/* Sanitizer builds run fewer steps against looser
 * thresholds; the assertions stay the same. */
#if defined(__SANITIZE_THREAD__) || defined(__SANITIZE_ADDRESS__)
#define SANITIZED 1
#else
#define SANITIZED 0
#endif

/* Under qemu-user (VLFF_EMULATOR set: the aarch64 stage of scripts/test)
 * every vector float operation is a helper call, which makes a training
 * step two orders of magnitude slower than native: the convergence case
 * runs the sanitizers' budget and thresholds there too. The portable
 * kernels' arithmetic is checked in full by the gradient and query cases. */
static bool light(void) { return SANITIZED || vlff_test_emulator(); }

/* Skipped under qemu-user: the two statistical cases (the sampler's and the
 * depth band's behaviour over hundreds of steps, no arithmetic the other
 * cases leave unchecked) take minutes each there. The convergence case
 * stays: the field still learns the scene on the emulated machine. Skipped
 * under TSan too, which they kept busy for 40 s without a thread the
 * convergence case does not run (the Debug and ASan builds run them). */
#if defined(__SANITIZE_THREAD__)
static bool statistical_skip(void) { return true; }
#else
static bool statistical_skip(void) { return vlff_test_emulator(); }
#endif

static void scene_cfg(struct vlff_config *cfg, int d) {
  vlff_config_defaults(cfg);
  cfg->field.grow = false; /* the scene's box; test_growth grows it */
  cfg->node.threads = 2;
  cfg->field.feature_dim = d;
  cfg->field.hash_log2_size = 15;
  cfg->field.finest_resolution = 256;
  for (int a = 0; a < 3; a++) {
    cfg->field.scene_min[a] = -2.0;
    cfg->field.scene_max[a] = 2.5;
  }
}

/* Loss of the chunk over all rays drawn, with the chunk's sampling fixed. */
static double chunk_loss(struct vlff_field *f, int nr) {
  struct vlff_work *w = &f->work[0];
  memset(w->grad, 0, f->nmlp * sizeof(float));
  w->loss_rgb = w->loss_depth = w->loss_feat = w->sq_rgb = 0;
  w->rng = 99;
  int ns;
  vlff_field_chunk(f, w, f->rays, nr, 1, f->step_p, f->step_denc, &ns);
  return w->loss_rgb + w->loss_depth + w->loss_feat;
}

static void test_chunk_gradient(void **state) {
  (void)state;
  struct vlff_config cfg;
  scene_cfg(&cfg, 24);
  cfg.node.threads = 1;
  cfg.field.feature_width = 32;
  cfg.field.density_width = 32;
  cfg.field.color_width = 32;
  cfg.train.rays_per_step = 32;
  cfg.train.samples_per_ray = 16;
  cfg.train.feature_loss = VLFF_FEAT_LOSS_L2;
  cfg.train.feature_weight = 5.0;
  char err[256];
  struct vlff_field *f = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(f);
  struct scene_view sv[4];
  struct vlff_view v[4];
  for (int k = 0; k < 4; k++) {
    double c2w[16];
    scene_pose(k, 4, c2w);
    scene_render(&sv[k], 16, 12, 24, c2w);
    v[k] = sv[k].v;
  }
  for (int i = 0; i < 15; i++) assert_int_equal(vlff_field_step(f, v, 4, NULL, NULL, err, sizeof(err)), 0);
  vlff_field_draw_rays(f, v, 4, NULL, NULL);
  int nr = f->nrays;
  double l0 = chunk_loss(f, nr);
  assert_true(l0 > 0);
  float *g = malloc(f->nmlp * sizeof(float));
  memcpy(g, f->work[0].grad, f->nmlp * sizeof(float));
  float *pm = vlff_mlp_params(f);
  /* Check the largest-gradient parameters of every layer of every MLP
   * (including MLP3's lazily applied output layer). */
  const struct vlff_mlp *mm[3] = {&f->m1, &f->m2, &f->m3};
  int checked = 0, good = 0;
  for (int k = 0; k < 3; k++)
    for (int l = 0; l < mm[k]->nl; l++)
      for (int kind = 0; kind < 2; kind++) {
        size_t o = kind ? mm[k]->boff[l] : mm[k]->woff[l];
        size_t cnt = kind ? (size_t)mm[k]->dout[l] : (size_t)mm[k]->din[l] * mm[k]->dout[l];
        for (int pick = 0; pick < (SANITIZED ? 2 : 3); pick++) {
          size_t best = o;
          float bv = -1;
          for (size_t i = o; i < o + cnt; i++)
            if (fabsf(g[i]) > bv && (pick == 0 || fabsf(g[i]) < 0.7f * fabsf(g[best]) || i % 7 == (size_t)pick)) {
              bv = fabsf(g[i]);
              best = i;
            }
          if (bv < 1e-4f) continue;
          float save = pm[best];
          float h = 2e-3f * fmaxf(1.0f, fabsf(save));
          pm[best] = save + h;
          vlff_field_refresh(f);
          double lp = chunk_loss(f, nr);
          pm[best] = save - h;
          vlff_field_refresh(f);
          double lm = chunk_loss(f, nr);
          pm[best] = save;
          vlff_field_refresh(f);
          double fd = (lp - lm) / (2.0 * h);
          checked++;
          if (fabs(fd - g[best]) <= 0.05 * fabs(fd) + 2e-4) good++;
          else print_message("mlp %d layer %d %s: analytic %g fd %g\n", k + 1, l, kind ? "b" : "W", g[best], fd);
        }
      }
  print_message("chunk gradient: %d of %d parameters within 5%%\n", good, checked);
  assert_true(checked >= (SANITIZED ? 14 : 20));
  assert_true(good >= checked * 9 / 10);
  free(g);
  for (int k = 0; k < 4; k++) scene_view_free(&sv[k]);
  vlff_field_destroy(f);
}

/* A slab of constant density sigma between depths a and b: opacity
 * 1 - exp(-sigma (b - a)), expected depth a + 1/sigma - (b + 1/sigma) e. */
static void test_slab(void **state) {
  (void)state;
  const int ns = 4000;
  float *sig = malloc(ns * 4), *del = malloc(ns * 4), *w = malloc(ns * 4), *tr = malloc(ns * 4), t[4000], dt;
  const float near = 0.0f, far = 4.0f, a = 1.0f, b = 1.5f;
  const float sigmas[] = {0.5f, 2.0f, 8.0f};
  for (int q = 0; q < 3; q++) {
    float s0 = sigmas[q];
    vlff_sample_uniform(near, far, ns, NULL, t, &dt);
    for (int i = 0; i < ns; i++) {
      sig[i] = t[i] >= a && t[i] < b ? s0 : 0.0f;
      del[i] = dt;
    }
    int used = vlff_render_weights(sig, del, ns, w, tr);
    double op = 0, dep = 0;
    for (int i = 0; i < used; i++) {
      op += w[i];
      dep += w[i] * t[i];
    }
    double e = exp(-s0 * (b - a));
    double op_ref = 1 - e, dep_ref = (a + 1 / s0) - (b + 1 / s0) * e;
    assert_true(fabs(op - op_ref) < 2e-3);
    assert_true(fabs(dep - dep_ref) < 2e-3);
    /* Transmittance just past the slab. */
    for (int i = 0; i < used; i++)
      if (t[i] > b + dt) {
        assert_true(fabs(tr[i] - e) < 2e-3);
        break;
      }
  }
  free(sig);
  free(del);
  free(w);
  free(tr);
}

struct eval {
  double psnr, depth_err, label_acc;
};

static struct eval evaluate(struct vlff_field *f, int d, int w, int h) {
  float *cf = malloc((size_t)SCENE_CLASSES * d * sizeof(float));
  scene_class_features(d, cf);
  char err[256];
  assert_int_equal(vlff_field_set_prompts(f, cf, SCENE_CLASSES, err, sizeof(err)), 0);
  struct eval ev = {0, 0, 0};
  double se = 0, de = 0;
  long ok = 0, n = 0;
  float *rgb = malloc((size_t)w * h * 12), *dep = malloc((size_t)w * h * 4);
  int *lab = malloc((size_t)w * h * 4);
  for (int k = 0; k < 2; k++) {
    double c2w[16];
    scene_pose(8 * k + 3, 32, c2w); /* between training poses */
    struct scene_view tv;
    scene_render(&tv, w, h, d, c2w);
    assert_int_equal(vlff_field_render(f, &tv.v, rgb, dep, NULL, lab, NULL), 0);
    for (int i = 0; i < w * h; i++) {
      for (int c = 0; c < 3; c++) {
        double e = rgb[3 * i + c] - tv.rgb[3 * i + c] / 255.0;
        se += e * e;
      }
      de += fabs(dep[i] - tv.depth[i]);
      ok += lab[i] == tv.cls[i];
      n++;
    }
    scene_view_free(&tv);
  }
  ev.psnr = -10 * log10(se / (3.0 * n));
  ev.depth_err = de / n;
  ev.label_acc = (double)ok / n;
  free(rgb);
  free(dep);
  free(lab);
  free(cf);
  return ev;
}

/* The convergence scene's budget: under emulation half the sanitizers'
 * rays (a step there costs what 100 native ones do, and the light
 * thresholds hold with a margin at 128); the thresholds were fixed at 32
 * samples a ray. */
static void convergence_budget(struct vlff_config *cfg) {
  cfg->train.rays_per_step = vlff_test_emulator() ? 128 : light() ? 256 : 512;
  cfg->train.samples_per_ray = 32;
  cfg->train.feature_loss = VLFF_FEAT_LOSS_L1;
}

static struct vlff_field *new_field(const struct vlff_config *cfg) {
  char err[256];
  struct vlff_field *f = vlff_field_create(&cfg->field, &cfg->train, cfg->node.threads, err, sizeof(err));
  if (!f) fail_msg("%s", err);
  return f;
}

/* nv training views around the scene (every other pose of 2 nv). */
static void training_views(struct scene_view *sv, struct vlff_view *v, int nv, int w, int h, int d) {
  for (int k = 0; k < nv; k++) {
    double c2w[16];
    scene_pose(2 * k, 2 * nv, c2w);
    scene_render(&sv[k], w, h, d, c2w);
    v[k] = sv[k].v;
  }
}

static void test_convergence(void **state) {
  (void)state;
  const int d = 16, nv = 16, W = 40, H = 30;
  struct vlff_config cfg;
  scene_cfg(&cfg, d);
  convergence_budget(&cfg);
  const int steps = light() ? 60 : 150;
  char err[256];
  struct vlff_field *f = new_field(&cfg);
  struct scene_view sv[16];
  struct vlff_view v[16];
  training_views(sv, v, nv, W, H, d);
  struct vlff_train_stats st;
  double first = 0;
  for (int i = 0; i < steps; i++) {
    assert_int_equal(vlff_field_step(f, v, nv, NULL, &st, err, sizeof(err)), 0);
    if (i == 0) first = st.loss;
    assert_true(isfinite(st.loss));
  }
  assert_int_equal(vlff_field_steps(f), steps);
  assert_true(st.loss < 0.3 * first);
  struct eval ev = evaluate(f, d, W, H);
  print_message("after %d steps: novel-view PSNR %.2f dB, depth error %.3f m, label accuracy %.3f\n", steps, ev.psnr,
                ev.depth_err, ev.label_acc);
  /* Thresholds sit with a margin below what the deterministic run reaches. */
  if (light()) {
    assert_true(ev.psnr > 17.5);
    assert_true(ev.depth_err < 0.22);
    assert_true(ev.label_acc > 0.9);
  } else {
    assert_true(ev.psnr > 20.5);
    assert_true(ev.depth_err < 0.07);
    assert_true(ev.label_acc > 0.94);
  }
  for (int k = 0; k < nv; k++) scene_view_free(&sv[k]);
  vlff_field_destroy(f);
}

/* Density and features at n points, and their exposure. */
struct answers {
  float dens[8], feat[8 * 16];
  uint16_t expo[8];
};
static void answers_at(struct vlff_field *f, const float *xyz, int n, struct answers *a) {
  memset(a, 0, sizeof *a);
  assert_int_equal(vlff_field_query(f, xyz, (size_t)n, a->dens, a->feat, NULL, NULL, NULL), 0);
  vlff_field_exposure(f, xyz, (size_t)n, a->expo);
}

/* Points in the room's low-x half (on its walls, floor and ceiling, where
 * rays end): what the growth tests ask the field before and after. */
static const float room_points[3 * 4] = {-1.49f, 0.3f,  0.5f, -0.5f, -1.2f, 0.01f,
                                         -1.0f,  1.49f, 1.0f, 0.0f,  0.0f,  1.99f};

/* The analytic room's config for a growing field ([-2, 2.5] on every axis
 * the first box until the caller narrows it) within +-world_limit_m. */
static void growing_room_cfg(struct vlff_config *cfg, int d, double world_limit_m) {
  scene_cfg(cfg, d);
  cfg->field.grow = true;
  cfg->field.world_limit_m = world_limit_m;
  convergence_budget(cfg);
}

/* A growth that takes the box's centre more than 16 m from where the
 * encoding counts positions from moves that origin with it (grow.c), and
 * what was learned stays: the same cells, each point's answers to float
 * rounding. */
static void test_growth_far(void **state) {
  (void)state;
  const int d = 16, nv = 16, W = 40, H = 30;
  struct vlff_config cfg;
  growing_room_cfg(&cfg, d, 100);
  char err[256];
  struct vlff_field *f = new_field(&cfg);
  struct scene_view sv[16];
  struct vlff_view v[16];
  training_views(sv, v, nv, W, H, d);
  for (int i = 0; i < (vlff_test_emulator() ? 3 : 10); i++)
    assert_int_equal(vlff_field_step(f, v, nv, NULL, NULL, err, sizeof(err)), 0);
  const float *in = room_points;
  struct answers before, after;
  answers_at(f, in, 4, &before);
  const float o0 = f->enc.box_min[0];
  const double near_hi[3] = {20, 2.5, 2.5}, far_hi[3] = {40, 2.5, 2.5}, lo[3] = {-2, -2, -2};
  assert_int_equal(vlff_field_grow(f, lo, near_hi, err, sizeof(err)), 1);
  assert_true(f->enc.box_min[0] == o0); /* the centre 9 m away: not moved */
  answers_at(f, in, 4, &after);
  assert_memory_equal(&before, &after, sizeof before);
  assert_int_equal(vlff_field_grow(f, lo, far_hi, err, sizeof(err)), 1);
  double blo[3], bhi[3];
  vlff_field_box(f, blo, bhi);
  assert_true(fabs(f->enc.box_min[0] - 0.5 * (blo[0] + bhi[0])) < 1e-3); /* moved to the box's centre */
  answers_at(f, in, 4, &after);
  assert_memory_equal(before.expo, after.expo, sizeof before.expo);
  for (int i = 0; i < 4; i++) {
    if (fabsf(after.dens[i] - before.dens[i]) > 1e-3f * (1 + fabsf(before.dens[i])))
      fail_msg("density at point %d: %g, %g before the origin moved", i, (double)after.dens[i], (double)before.dens[i]);
    for (int k = 0; k < 16; k++)
      if (fabsf(after.feat[16 * i + k] - before.feat[16 * i + k]) > 1e-3f)
        fail_msg("feature %d at point %d: %g, %g before", k, i, (double)after.feat[16 * i + k],
                 (double)before.feat[16 * i + k]);
  }
  for (int k = 0; k < nv; k++) scene_view_free(&sv[k]);
  vlff_field_destroy(f);
}

/* A growing field (field.grow): trained in a first box that holds the
 * room's low half, then grown to hold the whole room. Growth leaves what
 * was learned exactly as it was (the encoding's frame is the world's, the
 * occupancy cells are copied in place), the field then learns the rest of
 * the room as well as a fixed box does, a checkpoint restores the grown box,
 * and growth past the world's limit, the memory cap, a fixed box or a bad
 * box is refused or clipped with the field untouched. */
static void test_growth(void **state) {
  (void)state;
  const int d = 16, nv = 16, W = 40, H = 30;
  struct vlff_config cfg;
  growing_room_cfg(&cfg, d, 10);
  cfg.field.scene_max[0] = 0.25; /* the first box: x in [-2, 0.25] */
  char err[256];
  struct vlff_field *f = new_field(&cfg);
  struct scene_view sv[16];
  struct vlff_view v[16];
  training_views(sv, v, nv, W, H, d);
  double lo[3], hi[3];
  vlff_field_box(f, lo, hi);
  /* the first box's own cells from its low corner (occupancy_cell_m 0):
   * 2.25 m / 64 in x, 4.5 m / 64 in y and z, as a fixed box of that size
   * has them */
  const double cell = 2.25 / cfg.train.occupancy_resolution;
  assert_true(fabsf(f->occ.cell[0] - (float)cell) < 1e-7f);
  assert_true(fabsf(f->occ.cell[1] - (float)(4.5 / cfg.train.occupancy_resolution)) < 1e-7f);
  assert_true(f->occ.cell[2] == f->occ.cell[1]);
  for (int a = 0; a < 3; a++) assert_true(fabs(lo[a] + 2.0) < 1e-9);
  assert_true(hi[0] >= 0.25 - 1e-6 && hi[0] < 0.25 + cell + 1e-6);
  assert_true(fabs(hi[1] - 2.5) < 1e-6 && fabs(hi[2] - 2.5) < 1e-6);
  /* Under emulation a few steps: what it checks there is the growth's
   * arithmetic, not the learning (test_convergence shows that). */
  const int early = vlff_test_emulator() ? 3 : light() ? 10 : 30;
  for (int i = 0; i < early; i++) assert_int_equal(vlff_field_step(f, v, nv, NULL, NULL, err, sizeof(err)), 0);
  /* points in the first box, and one beyond it */
  const float *in = room_points;
  const float out[3] = {1.2f, 0.2f, 0.8f};
  struct answers before, after;
  answers_at(f, in, 4, &before);
  float dout;
  assert_int_equal(vlff_field_query(f, out, 1, &dout, NULL, NULL, NULL, NULL), 0);
  assert_true(dout == 0.0f); /* outside the box: nothing */
  /* every cell's state, to find each in its place after the growth */
  const int od[3] = {f->occ.dims[0], f->occ.dims[1], f->occ.dims[2]};
  const int ok0[3] = {f->occ_k0[0], f->occ_k0[1], f->occ_k0[2]};
  const size_t ocells = vlff_occ_cells(&f->occ);
  uint16_t *old_expo = malloc(ocells * sizeof *old_expo);
  float *old_dens = malloc(ocells * sizeof *old_dens);
  memcpy(old_expo, f->exposure, ocells * sizeof *old_expo);
  memcpy(old_dens, f->occ.density, ocells * sizeof *old_dens);
  long exposed = 0;
  for (size_t c = 0; c < ocells; c++) exposed += old_expo[c];

  const double room_lo[3] = {-2, -2, -2}, room_hi[3] = {2.5, 2.5, 2.5};
  assert_int_equal(vlff_field_grow(f, room_lo, room_hi, err, sizeof(err)), 1);
  assert_int_equal(vlff_field_growths(f), 1);
  vlff_field_box(f, lo, hi);
  for (int a = 0; a < 3; a++) assert_true(lo[a] <= room_lo[a] + 1e-9 && hi[a] >= room_hi[a] - 1e-6);
  answers_at(f, in, 4, &after);
  assert_memory_equal(&before, &after, sizeof before); /* growing changed nothing learned */
  assert_true(exposed > 0);                             /* ... and there was something */
  for (int z = 0; z < od[2]; z++)                       /* each cell where it was */
    for (int y = 0; y < od[1]; y++)
      for (int x = 0; x < od[0]; x++) {
        size_t c = (size_t)x + (size_t)od[0] * (y + (size_t)od[1] * z);
        size_t gx = (size_t)(x + ok0[0] - f->occ_k0[0]), gy = (size_t)(y + ok0[1] - f->occ_k0[1]),
               gz = (size_t)(z + ok0[2] - f->occ_k0[2]);
        size_t g = gx + (size_t)f->occ.dims[0] * (gy + (size_t)f->occ.dims[1] * gz);
        assert_int_equal(f->exposure[g], old_expo[c]);
        assert_true(f->occ.density[g] == old_dens[c]);
      }
  free(old_expo);
  free(old_dens);
  assert_int_equal(vlff_field_grow(f, room_lo, room_hi, err, sizeof(err)), 0); /* already held */

  const int steps = vlff_test_emulator() ? 6 : light() ? 60 : 150;
  for (int i = early; i < steps; i++) assert_int_equal(vlff_field_step(f, v, nv, NULL, NULL, err, sizeof(err)), 0);
  if (!vlff_test_emulator()) {
    /* the whole room learned, as a fixed box's field learns it (test_convergence) */
    struct eval ev = evaluate(f, d, W, H);
    print_message("grown after %d of %d steps: novel-view PSNR %.2f dB, depth error %.3f m, label accuracy %.3f\n",
                  early, steps, ev.psnr, ev.depth_err, ev.label_acc);
    assert_true(ev.psnr > (light() ? 17.5 : 20.0));
    assert_true(ev.depth_err < (light() ? 0.22 : 0.08));
    assert_true(ev.label_acc > (light() ? 0.9 : 0.93));
  }

  /* A checkpoint restores the grown box; the fixed box's field refuses it. */
  char path[256];
  snprintf(path, sizeof path, "%s/vlff-grow-%ld.ckpt", getenv("TMPDIR") ? getenv("TMPDIR") : "/tmp", (long)getpid());
  assert_int_equal(vlff_field_save(f, path, err, sizeof(err)), 0);
  struct vlff_field *g = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(g);
  assert_int_equal(vlff_field_load(g, path, err, sizeof(err)), 0);
  double glo[3], ghi[3];
  vlff_field_box(g, glo, ghi);
  assert_memory_equal(glo, lo, sizeof lo);
  assert_memory_equal(ghi, hi, sizeof hi);
  answers_at(f, in, 4, &before);
  answers_at(g, in, 4, &after);
  assert_memory_equal(&before, &after, sizeof before);
  struct vlff_config fixed;
  scene_cfg(&fixed, d);
  struct vlff_field *h = vlff_field_create(&fixed.field, &fixed.train, fixed.node.threads, err, sizeof(err));
  assert_non_null(h);
  assert_int_equal(vlff_field_load(h, path, err, sizeof(err)), -1);
  if (!strstr(err, "model configuration") && !strstr(err, "occupancy cells of")) fail_msg("%s", err);
  /* a fixed box does not grow */
  assert_int_equal(vlff_field_grow(h, room_lo, room_hi, err, sizeof(err)), 0);
  const double far_hi[3] = {3, 2.5, 2.5};
  assert_int_equal(vlff_field_grow(h, room_lo, far_hi, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "field.grow is off"));
  /* A fixed box's checkpoint and a growing field in the same box (the same
   * cells): refused by the model's configuration, naming field.grow, each
   * way (growth became the default: an upgraded node is told the key). */
  char boxed[300];
  snprintf(boxed, sizeof boxed, "%s.box", path);
  assert_int_equal(vlff_field_save(h, boxed, err, sizeof(err)), 0);
  struct vlff_config same = fixed;
  same.field.grow = true;
  struct vlff_field *gf = vlff_field_create(&same.field, &same.train, same.node.threads, err, sizeof(err));
  assert_non_null(gf);
  assert_int_equal(vlff_field_load(gf, boxed, err, sizeof(err)), -1);
  if (!strstr(err, "written with field.grow false")) fail_msg("%s", err);
  assert_int_equal(vlff_field_save(gf, boxed, err, sizeof(err)), 0);
  assert_int_equal(vlff_field_load(h, boxed, err, sizeof(err)), -1);
  if (!strstr(err, "written with field.grow true")) fail_msg("%s", err);
  vlff_field_destroy(gf);
  unlink(boxed);
  vlff_field_destroy(h);
  /* Cells in metres (train.occupancy_cell_m): 0.3 m cubes from the first
   * box's low corner, whatever its size; a checkpoint whose cells are the
   * first box's own is refused there (its cells' densities would
   * land in the wrong places); a first box whose cells pass the memory cap
   * is refused at create. */
  struct vlff_config metres = cfg;
  metres.train.occupancy_cell_m = 0.3;
  h = vlff_field_create(&metres.field, &metres.train, metres.node.threads, err, sizeof(err));
  assert_non_null(h);
  for (int a = 0; a < 3; a++) assert_true(h->occ.cell[a] == 0.3f);
  vlff_field_box(h, glo, ghi);
  assert_true(fabs(ghi[0] - 0.4) < 1e-6 && fabs(ghi[1] - 2.5) < 1e-6); /* 8 cells past 0.25, 15 on 4.5 m */
  assert_int_equal(vlff_field_load(h, path, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "occupancy cells of"));
  assert_null(strstr(err, "resumes it")); /* the box's own cells are not cubes here */
  /* Its own checkpoint, in cubes, refused by a field whose cells follow the
   * first box (a growing field written before they did): the key that
   * resumes it is named. */
  char cubes[300];
  snprintf(cubes, sizeof cubes, "%s.cubes", path);
  assert_int_equal(vlff_field_save(h, cubes, err, sizeof(err)), 0);
  vlff_field_destroy(h);
  h = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(h);
  assert_int_equal(vlff_field_load(h, cubes, err, sizeof(err)), -1);
  if (!strstr(err, "occupancy cells of 0.3 m") || !strstr(err, "train.occupancy_cell_m: 0.3 resumes it"))
    fail_msg("%s", err);
  vlff_field_destroy(h);
  unlink(cubes);
  metres.train.occupancy_cell_m = 0.01, metres.train.occupancy_max_mb = 1;
  assert_null(vlff_field_create(&metres.field, &metres.train, metres.node.threads, err, sizeof(err)));
  assert_non_null(strstr(err, "first box"));
  unlink(path);

  /* A mapping reset starts over in the first box. */
  vlff_field_reinit(g);
  vlff_field_box(g, glo, ghi);
  assert_true(ghi[0] < 0.25 + cell + 1e-6);
  assert_int_equal(vlff_field_steps(g), 0);
  vlff_field_destroy(g);

  /* Clipped to the world (+-10 m here), in whole cells; refused past the
   * memory cap, or for a box that is empty or not finite, f unchanged. */
  cfg.train.occupancy_resolution = 16; /* 0.28 m cells: the world is 72^3 of them, 3.9 MB */
  cfg.train.occupancy_max_mb = 8;
  h = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(h);
  const double huge_lo[3] = {-5000, -5000, -5000}, huge_hi[3] = {5000, 5000, 5000};
  const double nan_hi[3] = {NAN, 1, 1}, empty_hi[3] = {-3, 1, 1};
  assert_int_equal(vlff_field_grow(h, room_lo, nan_hi, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "non-finite"));
  assert_int_equal(vlff_field_grow(h, room_lo, empty_hi, err, sizeof(err)), -1);
  assert_int_equal(vlff_field_growths(h), 0);
  assert_int_equal(vlff_field_grow(h, huge_lo, huge_hi, err, sizeof(err)), 1);
  vlff_field_box(h, lo, hi);
  const double c16 = 4.5 / 16;
  for (int a = 0; a < 3; a++) {
    assert_true(lo[a] <= -10 + 1e-9 && lo[a] > -10 - c16);
    assert_true(hi[a] >= 10 - 1e-9 && hi[a] < 10 + c16);
  }
  assert_int_equal(vlff_field_grow(h, huge_lo, huge_hi, err, sizeof(err)), 0); /* the whole world held */
  vlff_field_destroy(h);
  cfg.train.occupancy_max_mb = 1;
  h = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(h);
  assert_int_equal(vlff_field_grow(h, huge_lo, huge_hi, err, sizeof(err)), -1);
  print_message("%s\n", err);
  assert_non_null(strstr(err, "train.occupancy_max_mb"));
  vlff_field_box(h, lo, hi);
  assert_true(hi[0] < 0.25 + c16 + 1e-6);
  /* Beyond the caps (docs/field.md): sliding instead, the box moves to a
   * far box and as much around it as 1 MB of cells holds; a box that alone
   * passes the cap is still refused */
  assert_int_equal(vlff_field_slide(h, huge_lo, huge_hi, err, sizeof(err)), -1);
  const double slide_lo[3] = {7, 7, 7}, slide_hi[3] = {9, 9, 9};
  assert_int_equal(vlff_field_grow(h, slide_lo, slide_hi, err, sizeof(err)), -1); /* growing would pass it */
  assert_int_equal(vlff_field_slide(h, slide_lo, slide_hi, err, sizeof(err)), 2);
  assert_int_equal(vlff_field_slides(h), 1);
  vlff_field_box(h, lo, hi);
  double cells = 1;
  for (int a = 0; a < 3; a++) {
    assert_true(lo[a] <= 7 && hi[a] >= 9);
    cells *= (hi[a] - lo[a]) / c16;
  }
  assert_true(cells * 11 <= 1048576.0 + 1);
  assert_int_equal(vlff_field_slide(h, slide_lo, slide_hi, err, sizeof(err)), 0); /* held */
  vlff_field_destroy(h);
  for (int k = 0; k < nv; k++) scene_view_free(&sv[k]);
  vlff_field_destroy(f);
}

static int cmp_float(const void *a, const void *b) {
  float x = *(const float *)a, y = *(const float *)b;
  return (x > y) - (x < y);
}

static double median(float *x, size_t n) {
  qsort(x, n, sizeof x[0], cmp_float);
  return x[n / 2];
}

/* The point at depth z on pixel i's ray of view v. */
static void ray_point(const struct vlff_view *v, size_t i, float z, float *x) {
  float o[3], d[3];
  vlff_camera_ray(v, (double)(i % v->width) + 0.5, (double)(i / v->width) + 0.5, o, d);
  for (int a = 0; a < 3; a++) x[a] = o[a] + d[a] * z;
}

/* The measured surface points of view sv beyond 1.5 m (truth: its true
 * depth), snapped onto field f's surface: returns the median |depth error|
 * after the snap over before it. Each moved point must stay on its own ray.
 * Also checks what the snap must leave alone: the nearest point that moved
 * (the narrowest band) put a metre behind the surface, outside any noise
 * band; and that point as measured, listed with a pixel outside the image,
 * which moves nothing. */
static double snap_gain(struct vlff_field *f, const struct scene_view *sv, const float *truth) {
  const struct vlff_view *v = &sv->v;
  const size_t npx = (size_t)v->width * v->height;
  float *xyz = malloc(npx * 3 * sizeof(float)), *meas = malloc(npx * 3 * sizeof(float)),
        *before = malloc(npx * sizeof(float)), *after = malloc(npx * sizeof(float));
  uint32_t *pix = malloc(npx * sizeof(uint32_t));
  size_t n = 0, near = SIZE_MAX;
  for (size_t i = 0; i < npx; i++) {
    if (!(truth[i] > 1.5f) || !(v->depth[i] > 0)) continue;
    ray_point(v, i, v->depth[i], xyz + 3 * n);
    before[n] = fabsf(v->depth[i] - truth[i]);
    pix[n++] = (uint32_t)i;
  }
  assert_true(n > 200);
  memcpy(meas, xyz, n * 3 * sizeof(float));
  size_t moved = vlff_field_snap_surface(f, v, pix, n, xyz);
  assert_true(moved > n / 2);
  const double *m = v->c2w;
  for (size_t j = 0; j < n; j++) {
    /* the camera-z of the moved point, which is still on its pixel's ray:
     * its offset from the camera is parallel to the measured one's */
    double z = 0, q[3], r[3], c2 = 0;
    for (int a = 0; a < 3; a++) {
      q[a] = xyz[3 * j + a] - m[4 * a + 3], r[a] = meas[3 * j + a] - m[4 * a + 3];
      z += q[a] * m[4 * a + 2];
    }
    for (int a = 0; a < 3; a++) c2 += pow(q[(a + 1) % 3] * r[(a + 2) % 3] - q[(a + 2) % 3] * r[(a + 1) % 3], 2);
    assert_true(sqrt(c2) / sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]) < 1e-3);
    after[j] = fabsf((float)z - truth[pix[j]]);
    bool was_moved = memcmp(xyz + 3 * j, meas + 3 * j, 3 * sizeof(float)) != 0;
    if (was_moved && (near == SIZE_MAX || truth[pix[j]] < truth[pix[near]])) near = j;
  }
  double gain = median(after, n) / median(before, n);
  /* the nearest point that moved, a metre behind the surface: no sensor
   * would put it there, the field's surface is outside its band, it stays */
  assert_true(near != SIZE_MAX);
  float far[3], x[3];
  ray_point(v, pix[near], truth[pix[near]] + 1.0f, far);
  memcpy(x, far, sizeof x);
  assert_int_equal(vlff_field_snap_surface(f, v, pix + near, 1, x), 0);
  assert_memory_equal(x, far, sizeof far);
  /* the measured point that moved, listed with a pixel outside the image */
  uint32_t bad[2] = {pix[near], (uint32_t)npx};
  float two[6];
  memcpy(two, meas + 3 * near, 3 * sizeof(float));
  memcpy(two + 3, two, 3 * sizeof(float));
  assert_int_equal(vlff_field_snap_surface(f, v, bad, 2, two), 0);
  assert_memory_equal(two, meas + 3 * near, 3 * sizeof(float));
  /* Both depths are estimates: the same points from a sensor ten times
   * more precise move less than half as far (the inverse-variance mean). */
  double move[2];
  const double noise = f->cfg.train.depth_noise_m;
  for (int pass = 0; pass < 2; pass++) {
    f->cfg.train.depth_noise_m = pass ? noise / 10 : noise;
    memcpy(xyz, meas, n * 3 * sizeof(float));
    vlff_field_snap_surface(f, v, pix, n, xyz);
    for (size_t j = 0; j < n; j++)
      after[j] = sqrtf(powf(xyz[3 * j] - meas[3 * j], 2) + powf(xyz[3 * j + 1] - meas[3 * j + 1], 2) +
                       powf(xyz[3 * j + 2] - meas[3 * j + 2], 2));
    move[pass] = median(after, n);
  }
  /* a sensor without noise: every measurement stands */
  f->cfg.train.depth_noise_m = 0;
  memcpy(xyz, meas, n * 3 * sizeof(float));
  assert_int_equal(vlff_field_snap_surface(f, v, pix, n, xyz), 0);
  assert_memory_equal(xyz, meas, n * 3 * sizeof(float));
  f->cfg.train.depth_noise_m = noise;
  print_message("median move of a measured point: %.4f m, from a sensor ten times more precise %.4f m\n", move[0],
                move[1]);
  assert_true(move[0] > 0 && move[1] < 0.5 * move[0]);
  free(xyz), free(meas), free(before), free(after), free(pix);
  return gain;
}

/* Median signed error (m) of the depth a field trained for `steps` steps on
 * views with stereo-like depth noise (sigma = noise d^2) renders at those
 * views' poses, against their true depth; the field's band follows
 * band_noise (train.depth_noise_m). With gain, *gain = snap_gain() of the
 * first view. */
static double noisy_depth_bias(double noise, double band_noise, int steps, double *gain) {
  const int d = 8, nv = 12, W = 40, H = 30;
  struct vlff_config cfg;
  scene_cfg(&cfg, d);
  cfg.train.rays_per_step = 512;
  cfg.train.samples_per_ray = 16;
  cfg.train.depth_noise_m = band_noise;
  /* Pixels drawn uniformly, as the thresholds were set: in the sanitizers'
   * 80 steps, rays drawn by feature loss leave some surfaces too few to fit
   * their depth yet (snap gain 0.79 against 0.56); at 200 steps both read
   * 0.51-0.52. This measures the band and the snap, not the draw. */
  cfg.train.error_sampling = 0;
  char err[256];
  struct vlff_field *f = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(f);
  struct scene_view sv[12];
  struct vlff_view v[12];
  float *truth[12];
  uint64_t s = 7;
  for (int k = 0; k < nv; k++) {
    double c2w[16];
    scene_pose(k, nv, c2w);
    scene_render(&sv[k], W, H, d, c2w);
    truth[k] = malloc((size_t)W * H * sizeof(float));
    memcpy(truth[k], sv[k].depth, (size_t)W * H * sizeof(float));
    for (int i = 0; i < W * H; i++) {
      double z = sv[k].depth[i], g = vlff_test_normal(&s);
      if (z > 0) sv[k].depth[i] = (float)(z + noise * z * z * g);
    }
    v[k] = sv[k].v;
  }
  struct vlff_train_stats st;
  for (int i = 0; i < steps; i++) assert_int_equal(vlff_field_step(f, v, nv, NULL, &st, err, sizeof(err)), 0);
  float *dep = malloc((size_t)W * H * sizeof(float)), *res = malloc((size_t)nv * W * H * sizeof(float));
  size_t m = 0;
  for (int k = 0; k < nv; k += 3) {
    assert_int_equal(vlff_field_render(f, &sv[k].v, NULL, dep, NULL, NULL, NULL), 0);
    for (int i = 0; i < W * H; i++)
      if (truth[k][i] > 1.5f) res[m++] = dep[i] - truth[k][i];
  }
  assert_true(m > 500);
  double bias = median(res, m);
  if (gain) *gain = snap_gain(f, &sv[0], truth[0]);
  for (int k = 0; k < nv; k++) {
    scene_view_free(&sv[k]);
    free(truth[k]);
  }
  free(dep);
  free(res);
  vlff_field_destroy(f);
  return bias;
}

/* Trained on noisy depth, the surface stays where it is: each ray's band
 * covers the sensor's noise at its range, and points measured on it snap to
 * it (vlff_field_snap_surface). With the band fixed at 4 cm +
 * 3 % of the depth, narrower than the noise, it moved toward the camera. */
static void test_noisy_depth_unbiased(void **state) {
  (void)state;
  if (statistical_skip()) skip();
  /* 0.02 m at 1 m: the noise 2-2.5 m from the room's walls is a 0.01
   * stereo camera's at 3-3.5 m. */
  const int steps = light() ? 80 : 200;
  double gain;
  double follows = noisy_depth_bias(0.02, 0.02, steps, &gain);
  print_message("median depth error beyond 1.5 m after %d steps, band following the noise: %.3f m\n", steps, follows);
  assert_true(fabs(follows) < 0.05);
  /* The label image's surface points: one noisy measurement each, moved
   * onto the fitted surface, are off by far less than the sensor. */
  print_message("measured points snapped to the field's surface: median |depth error| x %.2f\n", gain);
  assert_true(gain < 0.7);
  /* The fixed band's field shows the test can fail; under an emulator or
   * the sanitizers the one field is the check (its cost is the binary's). */
  if (light()) return;
  double fixed = noisy_depth_bias(0.02, 0, steps, NULL);
  print_message("with the band fixed: %.3f m\n", fixed);
  assert_true(fixed < -0.1);
}

/* A field for cfg and one 40 x 30 view of the scene (pose 0 of 16). */
static struct vlff_field *one_view_field(const struct vlff_config *cfg, int d, struct scene_view *sv) {
  char err[256];
  struct vlff_field *f = vlff_field_create(&cfg->field, &cfg->train, cfg->node.threads, err, sizeof(err));
  assert_non_null(f);
  double c2w[16];
  scene_pose(0, 16, c2w);
  scene_render(sv, 40, 30, d, c2w);
  return f;
}

/* The node shrinks the batch while it holds few keyframes: the step must
 * draw exactly that many rays, within the memory planned at create. */
static void test_ray_budget(void **state) {
  (void)state;
  const int d = 16;
  struct vlff_config cfg;
  scene_cfg(&cfg, d);
  cfg.train.rays_per_step = 512;
  cfg.train.samples_per_ray = 16;
  char err[256];
  struct scene_view sv;
  struct vlff_field *f = one_view_field(&cfg, d, &sv);
  assert_int_equal(vlff_field_set_rays(f, 0), 1);
  assert_int_equal(vlff_field_set_rays(f, 1 << 20), 512);
  long long samples[2];
  double table[2];
  const int rays[2] = {64, 512};
  for (int k = 0; k < 2; k++) {
    assert_int_equal(vlff_field_set_rays(f, rays[k]), rays[k]);
    struct vlff_train_stats st;
    assert_int_equal(vlff_field_step(f, &sv.v, 1, NULL, &st, err, sizeof(err)), 0);
    assert_true(isfinite(st.loss));
    samples[k] = st.samples;
    /* The roofline's counters: products timed, whole lines of p, m and v
     * each read and written, more of them for more rays. */
    assert_true(st.flops > 0 && st.time_gemm > 0);
    table[k] = st.table_bytes;
    assert_true(table[k] > 0 && fmod(table[k], 6 * 64) == 0);
    /* Every ray of this view hits the scene and has depth: S samples each. */
    assert_true(samples[k] > (long long)rays[k] * cfg.train.samples_per_ray / 2);
    assert_true(samples[k] <= (long long)rays[k] * cfg.train.samples_per_ray);
  }
  assert_true(samples[1] > 4 * samples[0]);
  assert_true(table[1] > table[0]);
  scene_view_free(&sv);
  vlff_field_destroy(f);
}

/* Coarse levels only: the finer levels encode 0 and a step leaves their
 * parameters and moments bit for bit as they were; restoring every level
 * trains them again. */
static void test_level_mask(void **state) {
  (void)state;
  const int d = 16;
  struct vlff_config cfg;
  scene_cfg(&cfg, d);
  cfg.train.rays_per_step = 256;
  char err[256];
  struct scene_view sv;
  struct vlff_field *f = one_view_field(&cfg, d, &sv);
  const int L = f->enc.levels, F = f->enc.feats, keep = 3;
  assert_int_equal(vlff_field_set_levels(f, 0), 1);
  assert_int_equal(vlff_field_set_levels(f, 1000), L);
  assert_int_equal(vlff_field_set_levels(f, keep), keep);
  const size_t nt = f->ntable, split = (size_t)keep * f->enc.size * F;
  float *p0 = malloc(nt * sizeof(float)), *m0 = malloc(nt * sizeof(float));
  assert_non_null(p0);
  assert_non_null(m0);
  memcpy(p0, f->params, nt * sizeof(float));
  memcpy(m0, f->adam_m, nt * sizeof(float));
  struct vlff_train_stats st;
  for (int i = 0; i < 3; i++) assert_int_equal(vlff_field_step(f, &sv.v, 1, NULL, &st, err, sizeof(err)), 0);
  assert_memory_equal(f->params + split, p0 + split, (nt - split) * sizeof(float));
  assert_memory_equal(f->adam_m + split, m0 + split, (nt - split) * sizeof(float));
  assert_memory_not_equal(f->params, p0, split * sizeof(float));
  /* The encoding's masked columns are 0 wherever the point is. */
  float p[3 * 8], out[8 * 64];
  uint64_t r = 5;
  for (int i = 0; i < 3 * 8; i++) p[i] = vlff_rng_uniform(&r);
  assert_true(f->enc.dim <= 64);
  vlff_encoding_forward(&f->enc, f->params, p, 8, out, 64);
  for (int i = 0; i < 8; i++)
    for (int c = keep * F; c < L * F; c++) assert_true(out[i * 64 + c] == 0.0f);
  assert_int_equal(vlff_field_set_levels(f, L), L);
  assert_int_equal(vlff_field_step(f, &sv.v, 1, NULL, &st, err, sizeof(err)), 0);
  assert_memory_not_equal(f->params + split, p0 + split, (nt - split) * sizeof(float));
  free(p0);
  free(m0);
  scene_view_free(&sv);
  vlff_field_destroy(f);
}

/* Each thread's table gradient is zero again after every step (the scatter
 * adds onto it and Adam zeroes what it used), and when a thread's stamp comes
 * round again after 255 levels updated no older mark is left to pass for it. */
static void test_marks_wrap(void **state) {
  (void)state;
  const int d = 16;
  struct vlff_config cfg;
  scene_cfg(&cfg, d);
  cfg.train.rays_per_step = 32;
  cfg.train.samples_per_ray = 8;
  char err[256];
  struct scene_view sv;
  struct vlff_field *f = one_view_field(&cfg, d, &sv);
  const size_t ng = f->enc.size * (size_t)f->enc.feats;
  struct vlff_train_stats st;
  int wrapped = 0;
  uint8_t last[64] = {0};
  assert_true(f->threads <= 64);
  /* Each thread's stamp moves on once per level it updates. Levels go to
   * whichever thread is free, so only the sum over threads is known: levels
   * per step. Enough steps that the busiest thread (at least the mean share)
   * passes 255 twice. */
  const int steps = (2 * 256 * f->threads + f->enc.levels - 1) / f->enc.levels + 1;
  for (int i = 1; i <= steps; i++) {
    assert_int_equal(vlff_field_step(f, &sv.v, 1, NULL, &st, err, sizeof(err)), 0);
    size_t marked = 0;
    for (int t = 0; t < f->threads; t++) {
      const struct vlff_work *w = &f->work[t];
      for (size_t k = 0; k < ng; k++)
        if (w->tgrad[k] != 0.0f) fail_msg("step %d thread %d: table gradient %zu is %g", i, t, k, w->tgrad[k]);
      /* A mark above the thread's stamp is a leftover that a later use
       * would read as its own. */
      for (size_t k = 0; k < f->enc.size; k++) {
        marked += w->tmarks[k] == w->tstamp;
        if (w->tmarks[k] > w->tstamp) fail_msg("step %d thread %d: mark %u above stamp %u", i, t, w->tmarks[k], w->tstamp);
      }
      wrapped += w->tstamp < last[t];
      last[t] = w->tstamp;
    }
    assert_true(marked > 0);
  }
  assert_true(wrapped >= 2);
  scene_view_free(&sv);
  vlff_field_destroy(f);
}

/* A one-thread field of D = 8 that draws rays rays per step under
 * train.class_balance balance and train.error_sampling errb. */
static struct vlff_field *drawing_field(int rays, double balance, double errb) {
  struct vlff_config cfg;
  scene_cfg(&cfg, 8);
  cfg.node.threads = 1;
  cfg.train.rays_per_step = rays;
  cfg.train.class_balance = balance;
  cfg.train.error_sampling = errb;
  char err[256];
  struct vlff_field *f = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof err);
  assert_non_null(f);
  return f;
}

/* train.class_balance: a view whose raw features say "class 1" on a tenth of
 * it (the left column of feature pixels) and "class 0" elsewhere. Without
 * balancing a tenth of the rays land there; with it the dominant class is
 * capped at the mean frequency, so the rare class gets 1/6 of the rays
 * (0.1 / (0.1 + 0.5)). Without prompts nothing changes. */
static double rare_share(double balance, int prompts) {
  struct vlff_field *f = drawing_field(2000, balance, 0);
  char err[256];
  float emb[2 * 8] = {0};
  emb[0] = 1, emb[8 + 1] = 1;
  if (prompts) assert_int_equal(vlff_field_set_prompts(f, emb, 2, err, sizeof err), 0);
  enum { FW = 10, FH = 10 };
  uint16_t feat[FW * FH * 8];
  for (int i = 0; i < FW * FH; i++) {
    float v[8] = {0};
    v[i % FW == 0 ? 1 : 0] = 1;
    vlff_f32_to_f16_n(v, feat + (size_t)i * 8, 8);
  }
  struct vlff_view v = {0};
  v.width = 40, v.height = 30, v.fx = v.fy = 30, v.cx = 20, v.cy = 15;
  const double c2w[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  memcpy(v.c2w, c2w, sizeof c2w);
  v.feat_width = FW, v.feat_height = FH, v.feature_dim = 8, v.features = feat;
  long rare = 0, total = 0;
  for (int draw = 0; draw < 8; draw++) {
    vlff_field_draw_rays(f, &v, 1, NULL, NULL);
    if (draw < 3) continue; /* the running frequencies settle */
    for (int r = 0; r < f->nrays; r++, total++) rare += f->rays[r].feat_index % FW == 0;
  }
  vlff_field_destroy(f);
  return (double)rare / total;
}

static void test_class_balance(void **state) {
  (void)state;
  double plain = rare_share(0, 1), off = rare_share(1, 0), bal = rare_share(1, 1);
  print_message("rare class share of rays: plain %.3f, balance without prompts %.3f, balanced %.3f\n", plain, off, bal);
  assert_true(fabs(plain - 0.1) < 0.015);
  assert_true(fabs(off - 0.1) < 0.015);
  assert_true(fabs(bal - 1.0 / 6) < 0.02);
}

/* train.error_sampling b: a camera at the origin facing a plane 2 m away;
 * occupancy cells left of a cell edge near x = -1 m have a running feature
 * loss of 1, the rest 0.1. A candidate in a cell below the candidates' mean
 * loss m is kept with probability (e / m)^b, so the high-loss strip's share
 * of the rays goes from its share of the pixels, p, to p / (p + (1 - p) 0.1
 * / m), m = p + 0.1 (1 - p); with b = 0 it stays p. */
static double high_loss_share(double b, double *pixel_share) {
  struct vlff_field *f = drawing_field(4000, 0, b);
  enum { W = 40, H = 30 };
  static float depth[W * H];
  for (int i = 0; i < W * H; i++) depth[i] = 2.0f;
  struct vlff_view v = {0};
  v.width = W, v.height = H, v.fx = v.fy = 30, v.cx = 20, v.cy = 15;
  const double c2w[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  memcpy(v.c2w, c2w, sizeof c2w);
  v.depth = depth;
  const struct vlff_occupancy *g = &f->occ;
  const int edge = (int)((-1.0f - g->box_min[0]) / g->cell[0]);
  const double xb = g->box_min[0] + edge * g->cell[0];
  *pixel_share = (v.cx + xb / 2.0 * v.fx) / W;
  for (long c = 0; c < (long)vlff_occ_cells(g); c++) f->cell_err[c] = c % g->dims[0] < edge ? 1.0f : 0.1f;
  long high = 0, total = 0;
  for (int draw = 0; draw < 8; draw++) {
    vlff_field_draw_rays(f, &v, 1, NULL, NULL);
    if (draw < 3) continue; /* the running mean settles */
    for (int r = 0; r < f->nrays; r++, total++) {
      int c = f->rays[r].cell;
      assert_true(c >= 0); /* every pixel's depth ends on the plane, inside the box */
      high += c % g->dims[0] < edge;
    }
  }
  vlff_field_destroy(f);
  return (double)high / total;
}

static void test_error_sampling_share(void **state) {
  (void)state;
  double p, plain = high_loss_share(0, &p), follow = high_loss_share(1, &p);
  double m = p + 0.1 * (1 - p), want = p / (p + (1 - p) * 0.1 / m);
  print_message("high-loss strip: %.3f of the pixels, %.3f of the rays plain, %.3f following the loss (expected %.3f)\n",
                p, plain, follow, want);
  assert_true(fabs(plain - p) < 0.015);
  assert_true(fabs(follow - want) < 0.02);
}

/* With real losses: a field trained on four views from one side of the
 * room, then drawing from those four and one from the opposite side. Error
 * sampling keeps every candidate whose cell no ray has ended in yet (no
 * loss known) and gives up the fitted cells' below-mean ones, so the rays
 * that end on surfaces never trained on grow from their share of the
 * pixels. At b = 2 (by a third at 60 steps, a sixth at the sanitizers' 20):
 * most fitted cells' losses sit near the mean, where b = 1 moves a fifth. */
static double untrained_share(double b) {
  const int d = 16;
  struct vlff_config cfg;
  scene_cfg(&cfg, d);
  cfg.train.rays_per_step = 512;
  cfg.train.error_sampling = b;
  char err[256];
  struct vlff_field *f = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof err);
  assert_non_null(f);
  struct scene_view sv[5];
  struct vlff_view v[5];
  for (int k = 0; k < 5; k++) {
    double c2w[16];
    scene_pose(k < 4 ? k : 8, 16, c2w);
    scene_render(&sv[k], 40, 30, d, c2w);
    v[k] = sv[k].v;
  }
  for (int i = 0; i < (light() ? 20 : 60); i++) assert_int_equal(vlff_field_step(f, v, 4, NULL, NULL, err, sizeof err), 0);
  long fresh = 0, total = 0;
  for (int draw = 0; draw < 16; draw++) {
    vlff_field_draw_rays(f, v, 5, NULL, NULL);
    for (int r = 0; r < f->nrays; r++) {
      int c = f->rays[r].cell;
      total += c >= 0;
      fresh += c >= 0 && f->cell_err[c] < 0;
    }
  }
  for (int k = 0; k < 5; k++) scene_view_free(&sv[k]);
  vlff_field_destroy(f);
  return (double)fresh / total;
}

static void test_error_sampling_new_view(void **state) {
  (void)state;
  if (statistical_skip()) skip();
  double plain = untrained_share(0), follow = untrained_share(2);
  print_message("rays ending on surfaces never trained on: %.3f plain, %.3f following the loss\n", plain, follow);
  assert_true(plain > 0.02);
  assert_true(follow > 1.1 * plain);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_ray_budget), cmocka_unit_test(test_level_mask),
    cmocka_unit_test(test_marks_wrap), cmocka_unit_test(test_slab),
    cmocka_unit_test(test_chunk_gradient), cmocka_unit_test(test_class_balance),
    cmocka_unit_test(test_error_sampling_share), cmocka_unit_test(test_error_sampling_new_view),
    cmocka_unit_test(test_convergence), cmocka_unit_test(test_growth), cmocka_unit_test(test_growth_far),
    cmocka_unit_test(test_noisy_depth_unbiased))
