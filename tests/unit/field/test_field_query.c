/*
 * Queries and persistence: folded prompt labels equal the unfolded argmax
 * over features (3D and 2D), checkpoints round-trip bit-exactly and bad
 * files are refused without touching the field, bad inputs are refused, and
 * training is deterministic.
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cmocka.h>

#include "field_internal.h"
#include "small_field.h"
#include "unit.h"

static void random_prompts(float *e, int k) {
  uint64_t r = 5;
  for (int i = 0; i < k * D; i++) e[i] = 2.0f * vlff_rng_uniform(&r) - 1.0f;
}

/* A field trained for a few steps with K random prompts e[K*D] set. */
static struct vlff_field *trained_with_prompts(const struct vlff_config *cfg, float *e, int K) {
  struct vlff_field *f = trained(cfg, 20);
  random_prompts(e, K);
  char err[256];
  assert_int_equal(vlff_field_set_prompts(f, e, K, err, sizeof(err)), 0);
  return f;
}

/* Best and second-best cos(E_k, f) in double; returns the best k. */
static int best_cosines(const float *feat, const float *e, int K, double *best, double *second) {
  double fn = 0;
  int bk = -1;
  *best = *second = -1e30;
  for (int j = 0; j < D; j++) fn += (double)feat[j] * feat[j];
  fn = sqrt(fn);
  for (int k = 0; k < K; k++) {
    double en = 0, dot = 0;
    for (int j = 0; j < D; j++) {
      en += (double)e[k * D + j] * e[k * D + j];
      dot += (double)e[k * D + j] * feat[j];
    }
    double c = dot / (sqrt(en) * fn);
    if (c > *best) {
      *second = *best;
      *best = c;
      bk = k;
    } else if (c > *second) {
      *second = c;
    }
  }
  return bk;
}

/* Max |score - best cosine| over n points, the cosine in double from the
 * unfolded features. */
static double score_error(struct vlff_field *f, const float *e, int K, size_t n) {
  float *xyz = calloc(n, 12), *feat = calloc(n, D * 4), *score = calloc(n, 4);
  int *label = malloc(n * sizeof(int));
  uint64_t r = 21;
  for (size_t i = 0; i < n; i++)
    for (int a = 0; a < 3; a++) xyz[3 * i + a] = -1.5f + 3.0f * vlff_rng_uniform(&r);
  assert_int_equal(vlff_field_query(f, xyz, n, NULL, feat, label, score, NULL), 0);
  double worst = 0;
  for (size_t i = 0; i < n; i++) {
    double best, second;
    best_cosines(feat + i * D, e, K, &best, &second);
    if (fabs(score[i] - best) > worst) worst = fabs(score[i] - best);
  }
  free(xyz), free(feat), free(score), free(label);
  return worst;
}

/* Feature norms come from the Cholesky factor of the Gram matrix of [W b]
 * when it has full rank, and from the Gram matrix itself when it does not;
 * both give the scores of the unfolded features. */
static void test_norm_paths(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  cfg.field.feature_width = 16; /* H < D: W can have full column rank */
  const int K = 6;
  float e[K * D];
  struct vlff_field *f = trained_with_prompts(&cfg, e, K);
  assert_int_equal(f->chol_ok, 1);
  assert_true(score_error(f, e, K, 400) < 1e-3);
  /* Two hidden units with the same output weights: WᵀW is singular. */
  const struct vlff_mlp *m3 = &f->m3;
  float *wt = f->avg + m3->woff[m3->nl - 1]; /* [H][D], the weights queries read */
  memcpy(wt + D, wt, D * sizeof(float));
  vlff_field_refresh(f);
  assert_int_equal(f->chol_ok, 0);
  assert_true(score_error(f, e, K, 400) < 1e-3);
  vlff_field_destroy(f);
}

/* Labels from folded prompts equal argmax_k cos(E_k, f) computed in double
 * from the unfolded features; scores and margins match too. */
static void test_folded_equals_unfolded(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  const int K = 20;
  float e[K * D];
  struct vlff_field *f = trained_with_prompts(&cfg, e, K);
  const size_t n = 3000;
  float *xyz = malloc(n * 12), *feat = malloc(n * D * 4), *dens = malloc(n * 4), *score = malloc(n * 4),
        *margin = malloc(n * 4);
  int *label = malloc(n * sizeof(int));
  uint64_t r = 9;
  for (size_t i = 0; i < n; i++)
    for (int a = 0; a < 3; a++) xyz[3 * i + a] = -2.2f + 5.0f * vlff_rng_uniform(&r); /* some outside the box */
  assert_int_equal(vlff_field_query(f, xyz, n, dens, feat, label, score, margin), 0);
  size_t inside = 0, agree = 0, close = 0;
  for (size_t i = 0; i < n; i++) {
    int in = xyz[3 * i] >= -2 && xyz[3 * i] <= 2.5 && xyz[3 * i + 1] >= -2 && xyz[3 * i + 1] <= 2.5 &&
             xyz[3 * i + 2] >= -2 && xyz[3 * i + 2] <= 2.5;
    if (!in) {
      assert_int_equal(label[i], -1);
      assert_true(dens[i] == 0.0f);
      continue;
    }
    inside++;
    assert_true(dens[i] > 0 && isfinite(dens[i]));
    double best, second;
    int bk = best_cosines(feat + i * D, e, K, &best, &second);
    if (label[i] == bk) agree++;
    else if (best - second < 1e-4) close++;  /* a float tie: either label is right */
    assert_true(fabs(score[i] - best) < 1e-3);
    assert_true(fabs(margin[i] - (best - second)) < 1e-3);
  }
  assert_true(inside > n / 2);
  assert_int_equal(agree + close, inside);
  assert_true(close * 100 < inside);
  /* Per-prompt cosines (the publisher's evidence path) equal E_k . f / |f|
   * from the unfolded features, and 0 outside the box. */
  float *cs = malloc(n * K * 4);
  assert_int_equal(vlff_field_query_cosines(f, xyz, n, cs), 0);
  int k_out;
  const float *eu = vlff_field_prompt_embeddings(f, &k_out);
  assert_int_equal(k_out, K);
  for (size_t i = 0; i < n; i++) {
    double nf = 0;
    for (int j = 0; j < D; j++) nf += (double)feat[i * D + j] * feat[i * D + j];
    for (int k = 0; k < K; k++) {
      double dot = 0;
      for (int j = 0; j < D; j++) dot += (double)feat[i * D + j] * eu[k * D + j];
      double want = label[i] < 0 || !(nf > 0) ? 0 : dot / sqrt(nf);
      assert_true(fabs(cs[i * K + k] - want) < 1e-3);
    }
  }
  free(cs);
  /* 2D: rendered labels equal the argmax over rendered features. */
  const int w = 24, h = 18; /* the size of views[1] */
  float *rf = malloc((size_t)w * h * D * 4), *rs = malloc((size_t)w * h * 4);
  int *rl = malloc((size_t)w * h * sizeof(int));
  struct vlff_view cam = views[1];
  assert_int_equal(vlff_field_render(f, &cam, NULL, NULL, rf, rl, rs), 0);
  int ok2 = 0, hit = 0;
  for (int i = 0; i < w * h; i++) {
    if (rl[i] < 0) continue;
    hit++;
    double best, second;
    ok2 += best_cosines(rf + i * D, e, K, &best, &second) == rl[i];
  }
  assert_true(hit > w * h / 2);
  assert_true(ok2 >= hit - hit / 100);
  /* A pixel list, out of order, renders those pixels as the whole view
   * does and leaves every other pixel alone. */
  uint32_t pix[24 * 18];
  size_t np = 0;
  for (int i = w * h - 1; i >= 0; i -= 3) pix[np++] = (uint32_t)i;
  int *pl = malloc((size_t)w * h * sizeof(int));
  float *ps = malloc((size_t)w * h * 4);
  for (int i = 0; i < w * h; i++) pl[i] = -7, ps[i] = -7;
  assert_int_equal(vlff_field_render_pixels(f, &cam, pix, np, NULL, NULL, NULL, pl, ps), 0);
  for (int i = 0; i < w * h; i++) {
    if ((w * h - 1 - i) % 3) {
      assert_int_equal(pl[i], -7);
      assert_true(ps[i] == -7);
      continue;
    }
    assert_true(fabsf(ps[i] - rs[i]) < 1e-4f);
    if (pl[i] != rl[i]) assert_true(pl[i] >= 0 && rl[i] >= 0 && fabsf(ps[i] - rs[i]) < 1e-4f);
  }
  pix[0] = (uint32_t)(w * h); /* off the image: refused */
  assert_int_equal(vlff_field_render_pixels(f, &cam, pix, np, NULL, NULL, NULL, pl, ps), -1);
  free(pl);
  free(ps);
  free(rf);
  free(rs);
  free(rl);
  free(xyz);
  free(feat);
  free(dens);
  free(score);
  free(margin);
  free(label);
  vlff_field_destroy(f);
}

static void test_checkpoint(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  struct vlff_field *a = trained(&cfg, 10);
  char path[512], err[512];
  tmp_path(path, sizeof(path), "rt");
  /* A FIFO planted at the writer's temporary name neither blocks the save
   * nor receives it; a FIFO at the checkpoint's name is refused on load. */
  char planted[600];
  snprintf(planted, sizeof planted, "%s.tmp.%ld", path, (long)getpid());
  assert_int_equal(mkfifo(planted, 0600), 0);
  assert_int_equal(mkfifo(path, 0600), 0);
  assert_int_equal(vlff_field_load(a, path, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "is a FIFO, expected a regular file"));
  assert_int_equal(vlff_field_save(a, path, err, sizeof(err)), 0);
  assert_int_equal(access(planted, F_OK), -1);
  struct vlff_field *b = trained(&cfg, 3);  /* different state, same model */
  assert_false(same_queries(a, b));
  assert_int_equal(vlff_field_load(b, path, err, sizeof(err)), 0);
  assert_int_equal(vlff_field_steps(b), 10);
  assert_true(same_queries(a, b));
  /* Bit-exact: training on continues identically, and a re-save is the
   * same file byte for byte. */
  assert_int_equal(vlff_field_step(a, views, NV, NULL, NULL, err, sizeof(err)), 0);
  assert_int_equal(vlff_field_step(b, views, NV, NULL, NULL, err, sizeof(err)), 0);
  assert_true(same_queries(a, b));
  char path2[512];
  tmp_path(path2, sizeof(path2), "rt2");
  assert_int_equal(vlff_field_save(a, path, err, sizeof(err)), 0);
  assert_int_equal(vlff_field_save(b, path2, err, sizeof(err)), 0);
  FILE *fa = fopen(path, "rb"), *fb = fopen(path2, "rb");
  assert_non_null(fa);
  assert_non_null(fb);
  fseek(fa, 0, SEEK_END);
  long size = ftell(fa);
  rewind(fa);
  unsigned char *ba = malloc(size), *bb = malloc(size + 1);
  assert_int_equal(fread(ba, 1, size, fa), size);
  assert_int_equal(fread(bb, 1, size + 1, fb), size);
  assert_memory_equal(ba, bb, size);
  fclose(fa);
  fclose(fb);

  /* Corrupt: one flipped bit anywhere is refused and b stays as it was. */
  struct vlff_field *c = trained(&cfg, 2);
  long offsets[] = {3, 40, size / 2, size - 3};
  for (size_t q = 0; q < sizeof(offsets) / sizeof(offsets[0]); q++) {
    ba[offsets[q]] ^= 0x10;
    FILE *o = fopen(path2, "wb");
    fwrite(ba, 1, size, o);
    fclose(o);
    ba[offsets[q]] ^= 0x10;
    err[0] = 0;
    assert_int_equal(vlff_field_load(c, path2, err, sizeof(err)), -1);
    assert_non_null(strstr(err, "refused"));
    assert_int_equal(vlff_field_steps(c), 2);
  }
  /* Truncated. */
  FILE *o = fopen(path2, "wb");
  fwrite(ba, 1, size - 100, o);
  fclose(o);
  assert_int_equal(vlff_field_load(c, path2, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "truncated"));
  o = fopen(path2, "wb");
  fwrite(ba, 1, 20, o);
  fclose(o);
  assert_int_equal(vlff_field_load(c, path2, err, sizeof(err)), -1);
  /* Missing file. */
  unlink(path2);
  assert_int_equal(vlff_field_load(c, path2, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "cannot open"));
  struct vlff_field *c_ref = trained(&cfg, 2);
  assert_true(same_queries(c, c_ref));
  /* Mismatched model configuration. */
  struct vlff_config cfg2 = cfg;
  cfg2.field.geo_dim = 14;
  char e2[256];
  struct vlff_field *m = vlff_field_create(&cfg2.field, &cfg2.train, cfg2.node.threads, e2, sizeof(e2));
  assert_non_null(m);
  assert_int_equal(vlff_field_load(m, path, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "configuration"));
  assert_int_equal(vlff_field_steps(m), 0);
  vlff_field_destroy(m);
  unlink(path);
  free(ba);
  free(bb);
  vlff_field_destroy(a);
  vlff_field_destroy(b);
  vlff_field_destroy(c);
  vlff_field_destroy(c_ref);
}

/* The checkpoint's checksum as docs/field.md states it, written out again
 * here so that the test can forge an older version's file: 64-bit words
 * (host order, the tail zero-padded and tagged with its length) mixed as
 * h ^= w, h *= FNV prime, h ^= h >> 29, from the FNV offset basis. */
static uint64_t ckpt_sum(const unsigned char *p, size_t n) {
  uint64_t h = 0xcbf29ce484222325ull;
  size_t i = 0;
  for (;; i += 8) {
    uint64_t w = 0;
    size_t k = n - i < 8 ? n - i : 8;
    memcpy(&w, p + i, k);
    if (k < 8) w ^= (uint64_t)k << 56;
    h ^= w;
    h *= 0x100000001b3ull;
    h ^= h >> 29;
    if (k < 8) return h;
  }
}

/* Writes the first len bytes of a checkpoint file b to path as the given
 * version, its checksum recomputed into the last 8 of them. */
static void forge(const char *path, unsigned char *b, size_t len, uint32_t version) {
  memcpy(b + 8, &version, 4);
  uint64_t sum = ckpt_sum(b, len - 8);
  memcpy(b + len - 8, &sum, 8);
  FILE *out = fopen(path, "wb");
  assert_non_null(out);
  assert_int_equal(fwrite(b, 1, len, out), len);
  assert_int_equal(fclose(out), 0);
}

/* A version must agree with the body's length: the body of `longer` bytes
 * claiming version - 1 and the body of `shorter` bytes claiming version
 * are both refused, the latter as truncated. */
static void refuses_mismatched_version(struct vlff_field *g, const char *path, unsigned char *b, size_t longer,
                                       size_t shorter, uint32_t version) {
  char err[256];
  forge(path, b, longer, version - 1);
  assert_int_equal(vlff_field_load(g, path, err, sizeof(err)), -1);
  forge(path, b, shorter, version);
  assert_int_equal(vlff_field_load(g, path, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "truncated"));
}

/* Exposure counts each training ray with depth once, in the occupancy cell
 * where its depth ends: the surface the views see, never the free space in
 * front of it. A checkpoint keeps it, the averaged weights and each cell's
 * running loss (train.error_sampling); one of version 1, which lacks all
 * three, loads as fitted everywhere, one of version 2 with the average
 * restarted from the trained weights, one of version 3 with no loss known. */
static void test_exposure(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  char err[512];
  struct vlff_field *f = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(f);
  /* The centre pixel's surface point of view 0, its camera, and a point
   * outside the box. */
  const struct vlff_view *v = &views[0];
  float o[3], d[3], pts[9];
  vlff_camera_ray(v, v->width / 2 + 0.5, v->height / 2 + 0.5, o, d);
  float dep = v->depth[(size_t)(v->height / 2) * v->width + v->width / 2];
  assert_true(dep > 0);
  for (int a = 0; a < 3; a++) pts[a] = o[a] + d[a] * dep, pts[3 + a] = o[a], pts[6 + a] = 9.0f;
  uint16_t rays[3];
  vlff_field_exposure(f, pts, 3, rays);
  assert_int_equal(rays[0], 0);
  const int steps = 20;
  for (int i = 0; i < steps; i++) assert_int_equal(vlff_field_step(f, views, NV, NULL, NULL, err, sizeof(err)), 0);
  vlff_field_exposure(f, pts, 3, rays);
  assert_true(rays[0] > 0);
  assert_int_equal(rays[1], 0);
  assert_int_equal(rays[2], 0);
  size_t nc = vlff_occ_cells(&f->occ);
  long long total = 0;
  for (size_t i = 0; i < nc; i++) total += f->exposure[i];
  assert_true(total <= (long long)steps * cfg.train.rays_per_step);
  assert_true(total >= (long long)steps * cfg.train.rays_per_step / 2); /* most pixels hold depth */
  char path[512];
  tmp_path(path, sizeof(path), "expo");
  assert_int_equal(vlff_field_save(f, path, err, sizeof(err)), 0);
  struct vlff_field *g = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(g);
  assert_int_equal(vlff_field_load(g, path, err, sizeof(err)), 0);
  /* Where the field was fitted survives a restart, cell for cell. */
  uint16_t back[3];
  vlff_field_exposure(g, pts, 3, back);
  assert_memory_equal(back, rays, sizeof rays);
  assert_memory_equal(g->exposure, f->exposure, nc * sizeof *f->exposure);
  assert_memory_equal(g->avg, f->avg, f->nmlp * sizeof(float));
  assert_memory_not_equal(g->avg, vlff_mlp_params(g), f->nmlp * sizeof(float));
  assert_true(same_queries(f, g));
  /* So do the cells' running losses, which decide where rays are drawn. */
  size_t known = 0;
  for (size_t i = 0; i < nc; i++) known += f->cell_err[i] >= 0;
  assert_true(known > 0);
  assert_memory_equal(g->cell_err, f->cell_err, nc * sizeof *f->cell_err);
  assert_true(g->err_mean == f->err_mean);

  /* Checkpoints of versions 1 (before exposure was saved) and 2 (before
   * the average was) are the same file without those arrays. They still
   * load: the field counting as fitted everywhere (version 1), the
   * average restarted from the trained weights (both). A version that
   * disagrees with the body's length is refused, the field untouched. */
  FILE *in = fopen(path, "rb");
  assert_non_null(in);
  assert_int_equal(fseek(in, 0, SEEK_END), 0);
  long size = ftell(in);
  assert_true(size > 0);
  rewind(in);
  unsigned char *b = malloc((size_t)size);
  assert_non_null(b);
  assert_int_equal(fread(b, 1, (size_t)size, in), (size_t)size);
  fclose(in);
  uint32_t version;
  memcpy(&version, b + 8, 4);
  assert_int_equal(version, 7);
  /* Version 7 adds the occupancy cells' size (three float64 after the box):
   * another size is refused by name, the field untouched; without it, the
   * file is version 6's, which loads (a fixed box's cells are its
   * resolution's). */
  double cell_m[3];
  memcpy(cell_m, b + 104, sizeof cell_m);
  assert_true(cell_m[0] == f->occ.cell[0] && cell_m[2] == f->occ.cell[2]);
  const double other_cell = cell_m[1] * 1.5;
  memcpy(b + 104 + 8, &other_cell, sizeof other_cell);
  forge(path, b, (size_t)size, 7);
  struct vlff_field *h6 = trained(&cfg, 2);
  assert_int_equal(vlff_field_load(h6, path, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "occupancy cells of"));
  assert_int_equal(vlff_field_steps(h6), 2);
  memmove(b + 104, b + 128, (size_t)size - 128);
  size -= 24;
  forge(path, b, (size_t)size, 6);
  assert_int_equal(vlff_field_load(h6, path, err, sizeof(err)), 0);
  assert_true(same_queries(f, h6));
  vlff_field_destroy(h6);
  /* Version 6 adds the box (24 bytes after the 80-byte header): without
   * it, the file is version 5's. */
  memmove(b + 80, b + 104, (size_t)size - 104);
  size -= 24;
  size_t v3 = (size_t)size - nc * sizeof(float) - sizeof(double); /* the same file without the losses */
  size_t v2 = v3 - f->nmlp * sizeof(float); /* ... and without the average */
  size_t v1 = v2 - nc * sizeof(uint16_t);              /* ... and without the exposure */
  /* Each forgery writes its checksum into its last 8 bytes: the longer
   * files first, so the shorter ones' bodies are still the original. */
  struct vlff_field *young = trained(&cfg, 2);
  /* A loss that is neither -1 nor a loss, or a negative mean, is refused
   * by name. */
  unsigned char *bad = malloc((size_t)size);
  assert_non_null(bad);
  const float forged_loss = -5.0f;
  const double forged_mean = -1.0;
  memcpy(bad, b, (size_t)size);
  memcpy(bad + v3 - 8 + 7 * sizeof(float), &forged_loss, sizeof forged_loss);
  forge(path, bad, (size_t)size, 5);
  assert_int_equal(vlff_field_load(young, path, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "running loss out of range"));
  memcpy(bad, b, (size_t)size);
  memcpy(bad + size - 16, &forged_mean, sizeof forged_mean);
  forge(path, bad, (size_t)size, 5);
  assert_int_equal(vlff_field_load(young, path, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "mean loss out of range"));
  /* The encoding's cells (header bytes 76-79, from version 5): cubic as
   * saved; neither cubic nor per axis is refused. */
  int32_t cells;
  memcpy(&cells, b + 76, sizeof cells);
  assert_int_equal(cells, 1);
  memcpy(bad, b, (size_t)size);
  cells = 7;
  memcpy(bad + 76, &cells, sizeof cells);
  forge(path, bad, (size_t)size, 5);
  assert_int_equal(vlff_field_load(young, path, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "cells neither cubic"));
  /* Version 4 (the same body) was learned in cells scaled per axis: it
   * loads in those, whatever its header's last word, and says so in its
   * next checkpoint, which loads in them again; a mapping reset makes them
   * cubic. */
  forge(path, bad, (size_t)size, 4);
  struct vlff_field *h4 = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(h4);
  assert_int_equal(h4->enc.cubic, 1);
  assert_int_equal(vlff_field_load(h4, path, err, sizeof(err)), 0);
  assert_int_equal(h4->enc.cubic, 0);
  assert_int_equal(vlff_field_save(h4, path, err, sizeof(err)), 0);
  struct vlff_field *h5 = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(h5);
  assert_int_equal(vlff_field_load(h5, path, err, sizeof(err)), 0);
  assert_int_equal(h5->enc.cubic, 0);
  vlff_field_reinit(h5);
  assert_int_equal(h5->enc.cubic, 1);
  vlff_field_destroy(h4);
  vlff_field_destroy(h5);
  free(bad);
  refuses_mismatched_version(young, path, b, (size_t)size, v3, 4); /* 3 with the losses, 4 without */
  forge(path, b, v3, 3);
  struct vlff_field *h3 = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(h3);
  assert_int_equal(vlff_field_load(h3, path, err, sizeof(err)), 0);
  assert_memory_equal(h3->avg, f->avg, f->nmlp * sizeof(float));
  for (size_t i = 0; i < nc; i++) assert_true(h3->cell_err[i] == -1.0f);
  vlff_field_destroy(h3);
  refuses_mismatched_version(young, path, b, (size_t)size, v2, 3); /* 2 with the average, 3 without */
  forge(path, b, v2, 1);           /* version 1 with the exposure */
  assert_int_equal(vlff_field_load(young, path, err, sizeof(err)), -1);
  forge(path, b, v2, 2);
  struct vlff_field *h2 = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(h2);
  assert_int_equal(vlff_field_load(h2, path, err, sizeof(err)), 0);
  assert_memory_equal(h2->exposure, f->exposure, nc * sizeof *f->exposure);
  assert_memory_equal(h2->avg, vlff_mlp_params(f), f->nmlp * sizeof(float));
  vlff_field_destroy(h2);
  forge(path, b, v1, 2);           /* version 2 without the exposure */
  assert_int_equal(vlff_field_load(young, path, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "truncated"));
  assert_int_equal(vlff_field_steps(young), 2);
  vlff_field_destroy(young);
  forge(path, b, v1, 1);
  free(b);
  struct vlff_field *h = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(h);
  assert_int_equal(vlff_field_load(h, path, err, sizeof(err)), 0);
  assert_memory_equal(h->avg, vlff_mlp_params(f), f->nmlp * sizeof(float));
  assert_memory_equal(h->params, f->params, f->nparams * sizeof(float));
  vlff_field_exposure(h, pts, 3, back);
  assert_int_equal(back[0], UINT16_MAX);
  assert_int_equal(back[1], UINT16_MAX);
  assert_int_equal(back[2], 0);
  unlink(path);
  vlff_field_destroy(f);
  vlff_field_destroy(g);
  vlff_field_destroy(h);
}

/* Queries read a moving average of the MLP weights
 * (train.weight_average): each step moves it by 1 - b toward the trained
 * weights, b = min(decay, (1 + t) / (10 + t)) at step t; it never feeds
 * back into training; with decay 0 it is the trained weights. */
static void test_average(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  cfg.train.weight_average = 0.99;
  const int steps = 30;
  struct vlff_field *a = trained(&cfg, steps);
  const size_t n = a->nmlp;
  float *before = malloc(n * sizeof(float));
  assert_non_null(before);
  memcpy(before, a->avg, n * sizeof(float));
  char err[256];
  assert_int_equal(vlff_field_step(a, views, NV, NULL, NULL, err, sizeof(err)), 0);
  const float b = fminf(0.99f, (1.0f + steps + 1) / (10.0f + steps + 1)), *p = vlff_mlp_params(a);
  size_t moved = 0;
  for (size_t i = 0; i < n; i++) {
    float want = before[i] + (1.0f - b) * (p[i] - before[i]);
    assert_true(fabsf(a->avg[i] - want) <= 1e-6f * (1.0f + fabsf(want)));
    moved += a->avg[i] != before[i];
  }
  assert_true(moved > n / 2);
  assert_memory_not_equal(a->avg, p, n * sizeof(float));
  free(before);
  /* The same fit without the average: the same trained weights, which its
   * queries read; they differ from the averaged field's until it is given
   * the average as its weights. */
  struct vlff_config c0 = cfg;
  c0.train.weight_average = 0;
  struct vlff_field *z = trained(&c0, steps + 1);
  assert_memory_equal(z->params, a->params, a->nparams * sizeof(float));
  assert_memory_equal(z->avg, vlff_mlp_params(z), n * sizeof(float));
  assert_false(same_queries(a, z));
  memcpy(vlff_mlp_params(z), a->avg, n * sizeof(float));
  vlff_field_reset_average(z);
  assert_true(same_queries(a, z));
  vlff_field_destroy(a);
  vlff_field_destroy(z);
}

static void test_determinism(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  struct vlff_field *a = trained(&cfg, 6), *b = trained(&cfg, 6);
  assert_true(same_queries(a, b));
  vlff_field_destroy(a);
  vlff_field_destroy(b);
}

static void test_bad_inputs(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  char err[256];
  struct vlff_field *f = vlff_field_create(&cfg.field, &cfg.train, cfg.node.threads, err, sizeof(err));
  assert_non_null(f);
  struct vlff_view v = views[0];
  v.feature_dim = D + 1;
  assert_int_equal(vlff_field_step(f, &v, 1, NULL, NULL, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "feature dimension"));
  v = views[0];
  v.c2w[3] = NAN;
  assert_int_equal(vlff_field_step(f, &v, 1, NULL, NULL, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "pose"));
  v = views[0];
  v.fx = 0;
  assert_int_equal(vlff_field_step(f, &v, 1, NULL, NULL, err, sizeof(err)), -1);
  float wts[2] = {0, 0};
  assert_int_equal(vlff_field_step(f, views, 2, wts, NULL, err, sizeof(err)), -1);
  assert_int_equal(vlff_field_step(f, NULL, 0, NULL, NULL, err, sizeof(err)), -1);
  assert_int_equal(vlff_field_steps(f), 0);
  float e[D] = {0};
  assert_int_equal(vlff_field_set_prompts(f, e, 1, err, sizeof(err)), -1);
  assert_non_null(strstr(err, "zero"));
  e[0] = NAN;
  assert_int_equal(vlff_field_set_prompts(f, e, 1, err, sizeof(err)), -1);
  assert_int_equal(vlff_field_set_prompts(f, e, VLFF_MAX_PROMPTS + 1, err, sizeof(err)), -1);
  /* Labels need prompts. */
  float xyz[3] = {0, 0, 1};
  int lab;
  assert_int_equal(vlff_field_query(f, xyz, 1, NULL, NULL, &lab, NULL, NULL), -1);
  float dens;
  assert_int_equal(vlff_field_query(f, xyz, 1, &dens, NULL, NULL, NULL, NULL), 0);
  /* Weighted views: a zero weight view never supplies rays. */
  float w2[2] = {1, 0};
  struct vlff_view two[2] = {views[0], views[1]};
  two[1].feature_dim = D + 3; /* would be an error if it were validated lazily */
  assert_int_equal(vlff_field_step(f, two, 2, w2, NULL, err, sizeof(err)), -1);
  vlff_field_destroy(f);
}

/* Resident memory, in bytes (/proc/self/statm's second field). */
static uint64_t rss_bytes(void) {
  FILE *f = fopen("/proc/self/statm", "r");
  unsigned long long size = 0, rss = 0;
  if (f) {
    if (fscanf(f, "%llu %llu", &size, &rss) != 2) rss = 0;
    fclose(f);
  }
  return rss * (uint64_t)sysconf(_SC_PAGE_SIZE);
}

/* The field's memory plan: a lower bound of what create writes (so that it
 * never refuses a field that would fit), growing with the keys it names, and
 * a field larger than the machine refused at create before a byte of it is
 * written (it was written whole, and the OOM killer ended the process). */
static void test_memory_plan(void **state) {
  (void)state;
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  cfg.node.threads = 1;
  uint64_t plan = vlff_field_plan_bytes(&cfg.field, &cfg.train);
  uint64_t table = (uint64_t)cfg.field.hash_levels * (1u << cfg.field.hash_log2_size) * cfg.field.hash_features;
  assert_true(plan >= table * 3 * sizeof(float)); /* the table with Adam's moments */
  char err[512] = "";
  uint64_t before = rss_bytes();
  struct vlff_field *f = vlff_field_create(&cfg.field, &cfg.train, 1, err, sizeof err);
  if (!f) fail_msg("%s", err);
  uint64_t grew = rss_bytes() - before;
  vlff_field_destroy(f);
  /* within a tenth: small buffers may reuse pages earlier tests freed */
  if (grew < plan - plan / 10) fail_msg("create wrote %llu bytes, the plan says %llu", (unsigned long long)grew,
                            (unsigned long long)plan);
  struct vlff_config more = cfg;
  more.train.rays_per_step *= 2;
  assert_true(vlff_field_plan_bytes(&more.field, &more.train) > plan);
  more = cfg;
  more.field.hash_log2_size++;
  assert_true(vlff_field_plan_bytes(&more.field, &more.train) >= plan + table * 3 * sizeof(float));
  /* terabytes of step buffers: no machine of ours has them */
  struct vlff_config huge = cfg;
  huge.field.hash_levels = 32, huge.field.hash_log2_size = 24, huge.field.hash_features = 8;
  huge.train.rays_per_step = 1 << 20, huge.train.samples_per_ray = 4096;
  assert_true(vlff_field_plan_bytes(&huge.field, &huge.train) > (1ull << 42));
  assert_int_equal(vlff_field_check_memory(&huge.field, &huge.train, err, sizeof err), -1);
  assert_non_null(strstr(err, "more than this machine's"));
  err[0] = 0;
  before = rss_bytes();
  assert_null(vlff_field_create(&huge.field, &huge.train, 1, err, sizeof err));
  assert_non_null(strstr(err, "field.hash_levels 32 x 2^field.hash_log2_size 24 x field.hash_features 8"));
  assert_true(rss_bytes() < before + (64u << 20));
  assert_int_equal(vlff_field_check_memory(&cfg.field, &cfg.train, err, sizeof err), 0);
}

VLFF_UNIT_MAIN(setup, teardown,
    cmocka_unit_test(test_folded_equals_unfolded), cmocka_unit_test(test_norm_paths),
    cmocka_unit_test(test_checkpoint), cmocka_unit_test(test_exposure), cmocka_unit_test(test_average),
    cmocka_unit_test(test_determinism),
    cmocka_unit_test(test_bad_inputs), cmocka_unit_test(test_memory_plan))
