/*
 * The small field the query and checkpoint tests share: the analytic scene
 * (scene.h) seen from NV views at 24x18 with D-dimensional features, a field
 * config small enough to train in milliseconds, and cmocka's setup and
 * teardown that render and free the views. Header-only, for tests.
 */
#ifndef VLFF_TEST_SMALL_FIELD_H
#define VLFF_TEST_SMALL_FIELD_H

#include "config.h"
#include "scene.h"

#include <stdio.h>
#include <unistd.h>

#define D 24
#define NV 4

static struct scene_view sv[NV];
static struct vlff_view views[NV];

static void cfg_small(struct vlff_config *cfg) {
  vlff_config_defaults(cfg);
  cfg->field.grow = false; /* the scene's box */
  cfg->node.threads = 2;
  cfg->field.feature_dim = D;
  cfg->field.feature_width = 32;
  cfg->field.hash_log2_size = 12;
  cfg->field.hash_levels = 8;
  cfg->field.finest_resolution = 128;
  for (int a = 0; a < 3; a++) {
    cfg->field.scene_min[a] = -2.0;
    cfg->field.scene_max[a] = 2.5;
  }
  cfg->train.rays_per_step = 128;
  cfg->train.samples_per_ray = 16;
  cfg->train.occupancy_resolution = 16;
  cfg->train.occupancy_update_steps = 4;
}

static struct vlff_field *trained(const struct vlff_config *cfg, int steps) {
  char err[256];
  struct vlff_field *f = vlff_field_create(&cfg->field, &cfg->train, cfg->node.threads, err, sizeof(err));
  assert_non_null(f);
  for (int i = 0; i < steps; i++) assert_int_equal(vlff_field_step(f, views, NV, NULL, NULL, err, sizeof(err)), 0);
  return f;
}

static int setup(void **state) {
  (void)state;
  for (int k = 0; k < NV; k++) {
    double c2w[16];
    scene_pose(k, NV, c2w);
    scene_render(&sv[k], 24, 18, D, c2w);
    views[k] = sv[k].v;
  }
  return 0;
}

static int teardown(void **state) {
  (void)state;
  for (int k = 0; k < NV; k++) scene_view_free(&sv[k]);
  return 0;
}

/* A checkpoint path of this test process in $TMPDIR (else /tmp). */
static void tmp_path(char *buf, size_t n, const char *tag) {
  const char *dir = getenv("TMPDIR");
  snprintf(buf, n, "%s/vlff-field-%s-%ld.ckpt", dir ? dir : "/tmp", tag, (long)getpid());
}

/* Whether two fields answer the same density and features at 64 random points. */
static int same_queries(struct vlff_field *a, struct vlff_field *b) {
  float xyz[3 * 64], da[64], db[64], fa[64 * D], fb[64 * D];
  uint64_t r = 3;
  for (int i = 0; i < 3 * 64; i++) xyz[i] = -1.5f + 3.0f * vlff_rng_uniform(&r);
  vlff_field_query(a, xyz, 64, da, fa, NULL, NULL, NULL);
  vlff_field_query(b, xyz, 64, db, fb, NULL, NULL, NULL);
  return !memcmp(da, db, sizeof(da)) && !memcmp(fa, fb, sizeof(fa));
}

#endif
