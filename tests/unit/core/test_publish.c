/* The map publisher against hostile views: implausible intrinsics and poses
 * are refused and counted, and no depth or pose makes a ray's march run
 * longer than the map is wide. Before the bound, a view of plausible
 * intrinsics with depth reaching far beyond the map (or cx = -1e9 /
 * fx = 0.001) marched hundreds of millions of steps per pixel: the test
 * then hung until ctest's timeout. */
#include <fcntl.h>
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <sys/stat.h>
#include <cmocka.h>

#include "evidence.h"
#include "field.h"
#include "hash.h"
#include "publish.h"
#include "unit.h"
#include "vlff/shm.h"

enum { W = 64, H = 48 };
static char err[512];
static float depth[W * H];

/* The tests' config: defaults, a map segment named by tag, 64^3 voxels of
 * 8 cm over the default 5 m box. */
static void config_for(struct vlff_config *cfg, const char *tag) {
  vlff_config_defaults(cfg);
  cfg->field.grow = false; /* the default box's grid; the tests that grow it say so */
  snprintf(cfg->shm.map, sizeof cfg->shm.map, "/vlff-test-publish-%s-%d", tag, (int)getpid());
  cfg->shm.map_max_voxels = 1 << 18;
  cfg->publish.voxel_size_m = 0.08;
}

static struct vlff_publisher *create(struct vlff_config *cfg) {
  struct vlff_publisher *p = vlff_publisher_create(&cfg->publish, &cfg->shm, &cfg->field, NULL, err, sizeof err);
  if (!p) fail_msg("%s", err);
  return p;
}

static struct vlff_publisher *make(struct vlff_config *cfg) {
  config_for(cfg, "main");
  return create(cfg);
}

/* A camera at the origin looking along +z, sim-like 65 degree field of view. */
static struct vlff_view view(float d) {
  struct vlff_view v = {.width = W, .height = H, .depth = depth};
  v.fx = v.fy = 0.5 * W / tan(0.5 * 65.0 * M_PI / 180.0);
  v.cx = W / 2.0, v.cy = H / 2.0;
  v.c2w[0] = v.c2w[5] = v.c2w[10] = v.c2w[15] = 1;
  for (int i = 0; i < W * H; i++) depth[i] = d;
  return v;
}

static void test_absurd_intrinsics_refused(void **state) {
  (void)state;
  struct vlff_config cfg;
  struct vlff_publisher *p = make(&cfg);
  struct vlff_view v = view(1.0f);
  v.cx = -1e9, v.cy = 1e9;
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), -1);
  assert_non_null(strstr(err, "view refused: cx -1e+09 outside [-32, 96]"));
  v = view(1.0f);
  v.fx = 0.001;
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), -1);
  assert_non_null(strstr(err, "fx 0.001 outside"));
  assert_int_equal(vlff_publisher_set_camera(p, &v, 1, 1, err, sizeof err), -1);
  v = view(1.0f);
  v.c2w[3] = 1e300;
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), -1);
  assert_non_null(strstr(err, "camera x = 1e+300 m outside [-7.5, 7.5]"));
  v.c2w[3] = NAN;
  assert_int_equal(vlff_publisher_check_view(p, &v, err, sizeof err), -1);
  /* A refused view accounts nothing: the map stays empty. */
  struct vlff_view ok = view(1.0f);
  double x[3] = {0, 0, 1.0};
  assert_false(vlff_publisher_surface_known(p, x));
  assert_int_equal(vlff_publisher_observe(p, &ok, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_observe(p, &ok, err, sizeof err), 0);
  assert_true(vlff_publisher_surface_known(p, x));
  assert_int_equal(vlff_publisher_set_camera(p, &ok, 1, 1, err, sizeof err), 0);
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* A box the map's capacity can hold only in voxels larger than a map may
 * have (shm.h: VLFF_MAP_VOXEL_MAX_M): refused at creation, naming the keys,
 * where every publish would have been refused at run time. */
static void test_voxels_past_bound_refused(void **state) {
  (void)state;
  struct vlff_config cfg;
  config_for(&cfg, "bigvox");
  for (int a = 0; a < 2; a++) cfg.field.scene_min[a] = -1e4, cfg.field.scene_max[a] = 1e4;
  cfg.shm.map_max_voxels = 256;
  assert_null(vlff_publisher_create(&cfg.publish, &cfg.shm, &cfg.field, NULL, err, sizeof err));
  if (!strstr(err, "more than a map may have (1000 m): raise shm.map_max_voxels or give a smaller box"))
    fail_msg("%s", err);
}

/* Plausible intrinsics, depth claiming tens of thousands of kilometres
 * (a float depth plane can say anything): the march stops at the map's
 * edge, the voxels the rays crossed inside the map are observed, and no
 * surface is invented. */
static void test_far_depth_bounded(void **state) {
  (void)state;
  struct vlff_config cfg;
  struct vlff_publisher *p = make(&cfg);
  struct vlff_view v = view(3e7f);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  v = view(1e30f);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  double x[3] = {0, 0, 2.0};
  assert_false(vlff_publisher_surface_known(p, x));
  /* A camera outside the box (within the plausible range) looking in:
   * its rays enter the map part-way and march through it. */
  v = view(8.0f);
  v.c2w[11] = -6.0;
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  /* Pixel (32, 24)'s measured point. */
  double hit[3] = {0.5 / v.fx * 8.0, 0.5 / v.fy * 8.0, 2.0};
  assert_true(vlff_publisher_surface_known(p, hit));
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* A publisher with evidence of feature_dim features in voxels of ev_m
 * metres and a budget of mb MB, its map segment named by tag. */
static struct vlff_publisher *make_ev(struct vlff_config *cfg, int mb, double ev_m, const char *tag) {
  config_for(cfg, tag);
  cfg->publish.evidence_max_mb = mb;
  cfg->publish.evidence_voxel_m = ev_m;
  return create(cfg);
}

/* Surfaces the map has seen along the camera's axis, 8-cm steps. */
static int count_known(const struct vlff_publisher *p) {
  int n = 0;
  for (double z = 0.3; z < 2.4; z += 0.08) n += vlff_publisher_surface_known(p, (const double[3]){0, 0, z});
  return n;
}

/* A saved map reloads as it was; a map saved under a larger evidence budget
 * loads into a smaller one with the budget full and the rest given up,
 * rather than losing all of it; one of another evidence voxel, and a node
 * without evidence, load its observations alone; an evidence length over
 * 16 times the budget and a corrupt or truncated file are refused and leave
 * what was loaded. Features: 32 x 24 pixels of field.feature_dim,
 * each pixel's depth random in 0.3-2.4 m, so every view reaches a few
 * thousand 10-cm evidence voxels. */
static void test_saved_map_loads_within_budget(void **state) {
  (void)state;
  struct vlff_config ca, cb, cc, cd;
  struct vlff_publisher *a = make_ev(&ca, 8, 0.1, "a"), *b = make_ev(&cb, 2, 0.1, "b"), *c = make_ev(&cc, 8, 0.1, "c"),
                        *d = make_ev(&cd, 8, 0.2, "d");
  const int FW = 32, FH = 24, D = ca.field.feature_dim;
  uint16_t *feat = malloc((size_t)FW * FH * D * sizeof *feat);
  assert_non_null(feat);
  unsigned seed = 7;
  for (int r = 0; r < 2; r++) {
    struct vlff_view v = view(1.0f);
    for (int i = 0; i < W * H; i++) depth[i] = 0.3f + 2.1f * (float)rand_r(&seed) / (float)RAND_MAX;
    for (size_t i = 0; i < (size_t)FW * FH * D; i++) feat[i] = vlff_f32_to_f16((float)rand_r(&seed) / (float)RAND_MAX);
    v.features = feat, v.feat_width = FW, v.feat_height = FH, v.feature_dim = D;
    assert_int_equal(vlff_publisher_observe(a, &v, err, sizeof err), 0);
  }
  const struct vlff_evidence *ea = vlff_publisher_evidence(a), *eb = vlff_publisher_evidence(b),
                             *ec = vlff_publisher_evidence(c);
  assert_true(vlff_evidence_voxels(ea) > vlff_evidence_capacity(eb));
  assert_int_equal(vlff_evidence_evicted(ea), 0);
  /* Prompt 2 of 3 lost, as a census leaves it: saved with the map, it is
   * read from the loaded evidence at once (before, only after the restarted
   * node's first census). */
  uint8_t lost[VLFF_EVIDENCE_LOST_BYTES] = {0};
  const uint64_t stamp = 42;
  const int32_t nk = 3;
  const uint32_t one = 1;
  memcpy(lost, &stamp, 8), memcpy(lost + 8, &nk, 4), memcpy(lost + 12, &one, 4), lost[16 + 2] = 1;
  vlff_evidence_lost_set((struct vlff_evidence *)ea, lost); /* a's own evidence: the test made it */
  char path[] = "/tmp/vlff-test-publish-XXXXXX";
  int fd = mkstemp(path);
  assert_true(fd >= 0);
  close(fd);
  assert_int_equal(vlff_publisher_save(a, path, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_load(c, path, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(ec), vlff_evidence_voxels(ea));
  assert_int_equal(count_known(c), count_known(a));
  assert_true(vlff_evidence_lost(ec, 2, NULL, NULL));
  assert_false(vlff_evidence_lost(ec, 1, NULL, NULL));
  assert_int_equal(vlff_publisher_load(b, path, err, sizeof err), 0);
  const size_t cap = vlff_evidence_capacity(eb);
  assert_int_equal(vlff_evidence_voxels(eb), cap);
  assert_int_equal(vlff_evidence_evicted(eb), (long long)(vlff_evidence_voxels(ea) - cap));
  const int known = count_known(a);
  assert_true(known > 0);
  assert_int_equal(count_known(b), known);
  /* Evidence of another voxel size (a config changed): the observations
   * load, the evidence starts empty. */
  assert_int_equal(vlff_publisher_load(d, path, err, sizeof err), 0);
  assert_int_equal(vlff_evidence_voxels(vlff_publisher_evidence(d)), 0);
  assert_false(vlff_evidence_lost(vlff_publisher_evidence(d), 2, NULL, NULL)); /* of evidence not loaded */
  assert_int_equal(count_known(d), known);
  /* Without evidence (publish.evidence_weight 0) the observations load and
   * the evidence is passed over. */
  struct vlff_config ce;
  config_for(&ce, "e");
  ce.publish.evidence_weight = 0;
  struct vlff_publisher *pe = create(&ce);
  assert_int_equal(vlff_publisher_load(pe, path, err, sizeof err), 0);
  assert_null(vlff_publisher_evidence(pe));
  assert_int_equal(count_known(pe), known);
  vlff_publisher_destroy(pe);
  vlff_shm_unlink(ce.shm.map);
  /* An evidence length of 4 GB, more than 16 times b's 2 MB and twice its
   * page file's 512 MB: refused before a byte of it is read or hashed. */
  const long evn_at = -(long)vlff_evidence_save_size(ea) - 16;
  FILE *f = fopen(path, "r+b");
  assert_non_null(f);
  uint64_t evn, huge = 1ull << 32;
  assert_int_equal(fseek(f, evn_at, SEEK_END), 0);
  assert_int_equal(fread(&evn, 8, 1, f), 1);
  assert_int_equal(evn, vlff_evidence_save_size(ea));
  assert_int_equal(fseek(f, evn_at, SEEK_END), 0);
  assert_int_equal(fwrite(&huge, 8, 1, f), 1);
  fclose(f);
  assert_int_equal(vlff_publisher_load(b, path, err, sizeof err), -1);
  assert_non_null(strstr(err, "refused unread"));
  assert_int_equal(vlff_evidence_voxels(eb), cap);
  f = fopen(path, "r+b");
  assert_non_null(f);
  assert_int_equal(fseek(f, evn_at, SEEK_END), 0);
  assert_int_equal(fwrite(&evn, 8, 1, f), 1);
  fclose(f);
  /* One byte flipped in the evidence, then one byte short. */
  f = fopen(path, "r+b");
  assert_non_null(f);
  assert_int_equal(fseek(f, -1000, SEEK_END), 0);
  int ch = fgetc(f);
  assert_int_equal(fseek(f, -1000, SEEK_END), 0);
  fputc(ch ^ 1, f);
  fclose(f);
  assert_int_equal(vlff_publisher_load(b, path, err, sizeof err), -1);
  assert_non_null(strstr(err, "checksum mismatch"));
  assert_int_equal(vlff_evidence_voxels(eb), cap);
  assert_int_equal(truncate(path, 1000), 0);
  assert_int_equal(vlff_publisher_load(b, path, err, sizeof err), -1);
  assert_non_null(strstr(err, "expected"));
  assert_int_equal(vlff_evidence_voxels(eb), cap);
  unlink(path);
  free(feat);
  vlff_publisher_destroy(a);
  vlff_publisher_destroy(b);
  vlff_publisher_destroy(c);
  vlff_publisher_destroy(d);
  vlff_shm_unlink(cd.shm.map);
  vlff_shm_unlink(ca.shm.map);
  vlff_shm_unlink(cb.shm.map);
  vlff_shm_unlink(cc.shm.map);
}

/* A wall measured just in front of a voxel face (issue 55's coverage gap):
 * the voxel behind the face holds the same wall and is a known surface, so
 * its points are labelled; it used to stay unobserved (unknown for good).
 * The surface is one voxel thick there, no thicker, and the voxels in
 * front stay free space. Voxels of 8 cm from -2.5 m: a face at z = 1.02. */
static void test_surface_behind_voxel_face(void **state) {
  (void)state;
  struct vlff_config cfg;
  config_for(&cfg, "face");
  struct vlff_publisher *p = create(&cfg);
  struct vlff_view v = view(1.019f);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_true(vlff_publisher_surface_known(p, (const double[3]){0, 0, 1.0}));   /* the measured voxel */
  assert_true(vlff_publisher_surface_known(p, (const double[3]){0, 0, 1.03}));  /* behind the face */
  assert_false(vlff_publisher_surface_known(p, (const double[3]){0, 0, 1.11})); /* two voxels on */
  assert_false(vlff_publisher_surface_known(p, (const double[3]){0, 0, 0.9}));  /* in front */
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* Every pixel's measured point counts, not only those of the pixels whose
 * rays are marched (every other one of a large view): a view whose only
 * valid depth is at odd pixels still shows its wall. Subsampled, a wall
 * seen at a grazing angle kept holes between the sampled points, and the
 * labelled points there stayed unknown (issue 55). */
static void test_every_pixel_counts(void **state) {
  (void)state;
  enum { BW = 160, BH = 120 };
  static float big[BW * BH];
  struct vlff_config cfg;
  config_for(&cfg, "odd");
  struct vlff_publisher *p = create(&cfg);
  struct vlff_view v = {.width = BW, .height = BH, .depth = big};
  v.fx = v.fy = 0.5 * BW / tan(0.5 * 65.0 * M_PI / 180.0);
  v.cx = BW / 2.0, v.cy = BH / 2.0;
  v.c2w[0] = v.c2w[5] = v.c2w[10] = v.c2w[15] = 1;
  for (int y = 0; y < BH; y++)
    for (int x = 0; x < BW; x++) big[y * BW + x] = x % 2 && y % 2 ? 1.5f : 0.0f;
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  /* pixel (81, 61)'s point */
  double x[3] = {(81.5 - v.cx) / v.fx * 1.5, (61.5 - v.cy) / v.fy * 1.5, 1.5};
  assert_true(vlff_publisher_surface_known(p, x));
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* A floor seen at a grazing angle: its rows' points lie more than a voxel
 * apart, and the voxels between them hold the same floor (issue 55: the
 * labelled points there stayed unknown for good). They are known surfaces
 * now; the voxel between a box's edge and the wall 25 cm behind it, two
 * surfaces, is not. Voxels of 8 cm from -2.5 m; the floor 0.34 m below
 * the camera (mid-voxel), seen from 1.2 to 2.3 m (rows 2.7 to 0.9 voxels
 * apart); the box at 1 m over the upper left quarter, the wall at 1.25 m. */
static void test_grazing_surface_filled(void **state) {
  (void)state;
  struct vlff_config cfg;
  config_for(&cfg, "graze");
  struct vlff_publisher *p = create(&cfg);
  struct vlff_view v = view(0.0f);
  const double h = 0.34;
  for (int y = 0; y < H; y++)
    for (int x = 0; x < W; x++) {
      double d = y < H / 2 ? (x < W / 2 ? 1.0 : 1.25) : h * v.fy / (y + 0.5 - v.cy);
      depth[y * W + x] = d <= 2.4 ? (float)d : 0.0f;
    }
  for (int i = 0; i < 2; i++) assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  for (double z = 1.3; z <= 2.2; z += 0.04) {
    const double x[3] = {0.005, h, z};
    if (!vlff_publisher_surface_known(p, x)) fail_msg("the floor at z = %.2f m: no surface", z);
  }
  /* Row 10's points either side of the box's edge (columns 31 and 32), and
   * the voxel between them. */
  const double y0 = (10.5 - v.cy) / v.fy, mid[3] = {0.001, y0 * 1.125, 1.125};
  assert_true(vlff_publisher_surface_known(p, (const double[3]){(31.5 - v.cx) / v.fx, y0, 1.0}));
  assert_true(vlff_publisher_surface_known(p, (const double[3]){(32.5 - v.cx) / v.fx * 1.25, y0 * 1.25, 1.25}));
  assert_false(vlff_publisher_surface_known(p, mid));
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* The test views' depth: d everywhere but an object at depth 1 m over
 * columns x0..x0+15 of rows 16..31. */
static void object_at(int x0, float d) {
  for (int y = 0; y < H; y++)
    for (int x = 0; x < W; x++) depth[y * W + x] = y >= 16 && y < 32 && x >= x0 && x < x0 + 16 ? 1.0f : d;
}

/* A thing moves: the map shows it at its new place, and its old place,
 * which the rays of two newer views pass through to the wall behind, is
 * FREE in the published map whatever the (untrained) field's density says
 * there; the views that showed it there are contradicted. Before depth
 * cleared what it passed through, the old place kept its measured surface
 * and its class for good. */
static void test_moved_object_clears(void **state) {
  (void)state;
  struct vlff_config cfg;
  config_for(&cfg, "moved");
  cfg.field.feature_dim = 24;
  cfg.field.hash_log2_size = 12;
  cfg.field.hash_levels = 8;
  cfg.field.finest_resolution = 128;
  cfg.publish.evidence_weight = 0;
  struct vlff_publisher *p = create(&cfg);
  struct vlff_field *f = vlff_field_create(&cfg.field, &cfg.train, 1, err, sizeof err);
  assert_non_null(f);
  float emb[2 * 24];
  for (int i = 0; i < 2 * 24; i++) emb[i] = (float)((i * 37 % 11) - 5) + (i < 24 ? 0.5f : -0.5f);
  assert_int_equal(vlff_field_set_prompts(f, emb, 2, err, sizeof err), 0);
  const char *prompts[2] = {"chair", "wall"};
  struct vlff_map *rd = vlff_map_attach(cfg.shm.map);
  assert_non_null(rd);
  struct vlff_publish_result r;
  /* Pixel column x's object point at 1 m, and the wall at 2 m behind the old place. */
  const double fx = 0.5 * W / tan(0.5 * 65.0 * M_PI / 180.0);
  const double old_pt[3] = {(40 - 32) / fx, (24 - 24) / fx, 1.0}, new_pt[3] = {(8 - 32) / fx, 0, 1.0};
  struct vlff_view v = view(2.0f);
  object_at(32, 2.0f);
  for (int i = 0; i < 2; i++) assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 2, &r, err, sizeof err), 0);
  uint16_t lab;
  assert_int_equal(vlff_map_label_at(rd, old_pt[0], old_pt[1], old_pt[2], &lab, NULL), 0);
  assert_true(lab <= VLFF_LABEL_MAX);
  assert_true(vlff_publisher_surface_known(p, old_pt));
  /* The object moves left: one view through the old place is not enough
   * (a single view's holes and noise), the second clears it. */
  object_at(0, 2.0f);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_true(vlff_publisher_surface_known(p, old_pt));
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_false(vlff_publisher_surface_known(p, old_pt));
  assert_true(vlff_publisher_surface_known(p, new_pt));
  assert_true(vlff_publisher_cleared(p) > 0);
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 2, &r, err, sizeof err), 0);
  assert_int_equal(vlff_map_label_at(rd, old_pt[0], old_pt[1], old_pt[2], &lab, NULL), 0);
  assert_int_equal(lab, VLFF_LABEL_FREE);
  assert_int_equal(vlff_map_label_at(rd, new_pt[0], new_pt[1], new_pt[2], &lab, NULL), 0);
  assert_true(lab <= VLFF_LABEL_MAX);
  /* The wall behind the old place stays a surface. */
  assert_int_equal(vlff_map_label_at(rd, old_pt[0], old_pt[1], 2.0, &lab, NULL), 0);
  assert_true(lab <= VLFF_LABEL_MAX);
  /* A keyframe that showed the object at its old place is contradicted
   * by the newer depth; one of the new place is not. */
  object_at(32, 2.0f);
  assert_true(vlff_publisher_contradicted(p, &v));
  object_at(0, 2.0f);
  assert_false(vlff_publisher_contradicted(p, &v));
  vlff_map_detach(rd);
  vlff_field_destroy(f);
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* ------------------------------------------------ incremental publication */

/* A small field (random, untrained: its answers are deterministic, which is
 * all the comparisons below need) with K random prompts of seed. */
static struct vlff_field *small_field(struct vlff_config *cfg, int K, unsigned seed) {
  cfg->node.threads = 1;
  cfg->field.feature_dim = 16;
  cfg->field.hash_log2_size = 12;
  cfg->field.hash_levels = 8;
  struct vlff_field *f = vlff_field_create(&cfg->field, &cfg->train, 1, err, sizeof err);
  if (!f) fail_msg("%s", err);
  float e[8 * 16];
  for (int i = 0; i < K * 16; i++) e[i] = (float)rand_r(&seed) / (float)RAND_MAX - 0.5f;
  assert_int_equal(vlff_field_set_prompts(f, e, K, err, sizeof err), 0);
  return f;
}

/* A camera at x looking along +z at a wall depth d away, with a bump. */
static struct vlff_view view_at(double x, float d) {
  struct vlff_view v = view(d);
  v.c2w[3] = x;
  for (int i = 0; i < W * H; i += 7) depth[i] = d * 0.6f;
  return v;
}

static void take(struct vlff_map *m, struct vlff_map_snapshot *s, struct vlff_map_info *in) {
  assert_int_equal(vlff_map_snapshot_take(m, s), 0);
  vlff_map_snapshot_info(s, in);
}

/* What a keyframe changed is relabelled and published alone, and leaves the
 * map exactly as relabelling the whole grid would; slices refresh the rest,
 * a round of them equal to a whole publish, logging only what changed; new
 * prompts, a reset or a load make the next publish whole. Before incremental
 * publication every publish relabelled the whole grid. */
static void test_incremental_publication(void **state) {
  (void)state;
  struct vlff_config cfg;
  config_for(&cfg, "inc");
  cfg.publish.evidence_weight = 0; /* labels are the field's alone: exactly reproducible */
  struct vlff_field *f = small_field(&cfg, 3, 11); /* the publisher's feature_dim is the field's */
  struct vlff_publisher *p = create(&cfg);
  const char *prompts[3] = {"wall", "floor", "chair"};
  struct vlff_map *m = vlff_map_attach(cfg.shm.map);
  assert_non_null(m);
  struct vlff_map_snapshot *fol = vlff_map_snapshot_new(m), *a = vlff_map_snapshot_new(m), *b = vlff_map_snapshot_new(m);
  assert_non_null(fol);
  struct vlff_publish_result r;
  struct vlff_map_info ia, ib;

  /* The first publish is whole, whatever was asked. */
  struct vlff_view v = view_at(0, 1.5f);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_true(vlff_publisher_pending(p) > 0);
  assert_int_equal(vlff_publisher_publish_changed(p, f, prompts, 3, &r, err, sizeof err), 0);
  assert_true(r.whole);
  assert_int_equal(vlff_publisher_pending(p), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, fol), 1);
  /* Nothing observed since: nothing published. */
  assert_int_equal(vlff_publisher_publish_changed(p, f, prompts, 3, &r, err, sizeof err), 0);
  assert_int_equal(r.changed, 0);
  assert_int_equal(r.version, 1);

  /* A second keyframe elsewhere: only its voxels, logged. */
  v = view_at(0.8, 2.0f);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  size_t touched = vlff_publisher_pending(p);
  assert_true(touched > 100 && touched < 62 * 62 * 62 / 4);
  assert_int_equal(vlff_publisher_publish_changed(p, f, prompts, 3, &r, err, sizeof err), 0);
  assert_false(r.whole);
  assert_int_equal(r.changed, touched);
  assert_int_equal(r.version, 2);
  assert_int_equal(vlff_map_snapshot_follow(m, fol), 0);
  const struct vlff_map_range *runs;
  size_t nr = vlff_map_snapshot_changes(fol, &runs, NULL), logged = 0;
  for (size_t i = 0; i < nr; i++) logged += runs[i].count;
  assert_true(logged >= touched && logged < 62 * 62 * 62 / 4);
  take(m, a, &ia);
  assert_true(ia.grid.labels[0] == VLFF_LABEL_UNKNOWN);
  /* The same map as relabelling everything. */
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 3, &r, err, sizeof err), 0);
  assert_true(r.whole && r.cycle_done);
  take(m, b, &ib);
  size_t nv = (size_t)ib.grid.dims[0] * ib.grid.dims[1] * ib.grid.dims[2];
  assert_memory_equal(ia.grid.labels, ib.grid.labels, nv * 2);
  assert_memory_equal(ia.grid.confidence, ib.grid.confidence, nv);
  assert_true(r.labelled + r.free_voxels > touched / 2);

  /* The field answers otherwise (new embeddings, the same prompt texts): a
   * round of slices brings the whole map to what a whole publish makes. */
  float e2[3 * 16];
  unsigned seed = 99;
  for (int i = 0; i < 3 * 16; i++) e2[i] = (float)rand_r(&seed) / (float)RAND_MAX - 0.5f;
  assert_int_equal(vlff_field_set_prompts(f, e2, 3, err, sizeof err), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, fol), 0);
  /* In pieces of at most 300 queried voxels: a slice stops short of its
   * target, and the caller goes on to it as the trainer does. */
  vlff_publisher_set_slice_piece(p, 300);
  size_t changed = 0;
  int calls = 0, short_of = 0;
  for (int s = 0; s < 5; s++) {
    do {
      assert_int_equal(vlff_publisher_publish_slice(p, f, prompts, 3, (s + 1) / 5.0, &r, err, sizeof err), 0);
      assert_false(r.whole);
      calls++;
      short_of += !r.cycle_done && vlff_publisher_refresh_done(p) < (s + 1) / 5.0;
      changed += r.changed;
      assert_int_equal(vlff_map_snapshot_follow(m, fol), 0);
    } while (!r.cycle_done && vlff_publisher_refresh_done(p) < (s + 1) / 5.0);
    assert_int_equal(r.cycle_done, s == 4);
    assert_true(fabs(vlff_publisher_refresh_done(p) - (s == 4 ? 0 : (s + 1) / 5.0)) < 1e-3);
  }
  assert_true(short_of >= 3 && calls == 5 + short_of); /* pieces stopped short, and went on from there */
  assert_true(changed > 0);
  vlff_publisher_set_slice_piece(p, SIZE_MAX); /* below, each slice reaches its target */
  take(m, a, &ia);
  struct vlff_map_info fi;
  vlff_map_snapshot_info(fol, &fi);
  assert_memory_equal(fi.grid.labels, ia.grid.labels, nv * 2); /* the follower kept up from the log */
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 3, &r, err, sizeof err), 0);
  take(m, b, &ib);
  assert_memory_equal(ia.grid.labels, ib.grid.labels, nv * 2);
  assert_memory_equal(ia.grid.confidence, ib.grid.confidence, nv);
  /* Nothing changed since: a round logs nothing, in slices of any size (a
   * target behind the last slice's end still refreshes a voxel). */
  const double to[] = {0.3, 0.1, 0.31, 0.9, 2};
  for (int s = 0; s < 5; s++) {
    assert_int_equal(vlff_publisher_publish_slice(p, f, prompts, 3, to[s], &r, err, sizeof err), 0);
    assert_int_equal(r.changed, 0);
    assert_int_equal(r.cycle_done, s == 4);
  }

  /* Other prompts, a reset: the next publish is whole. */
  const char *other[3] = {"wall", "floor", "door"};
  assert_int_equal(vlff_publisher_publish_slice(p, f, other, 3, 0.2, &r, err, sizeof err), 0);
  assert_true(r.whole);
  vlff_publisher_reset(p);
  assert_int_equal(vlff_publisher_publish_changed(p, f, other, 3, &r, err, sizeof err), 0);
  assert_true(r.whole);
  assert_int_equal(r.labelled + r.free_voxels, 0);

  vlff_map_snapshot_free(fol);
  vlff_map_snapshot_free(a);
  vlff_map_snapshot_free(b);
  vlff_map_detach(m);
  vlff_field_destroy(f);
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* Refresh rounds alternate: after a round that relabelled every voxel, the
 * next passes over the settled ones (a class leading the second best by at
 * least 0.1 when last relabelled) and relabels only the rest; the round
 * after it relabels all again, ending where a whole publish would. A field
 * that answers otherwise (here another field with the same prompt
 * embeddings, as training moves one) reaches the settled voxels within two
 * rounds. Before, every round relabelled every voxel, and a round's cost
 * (mostly the settled voxels' queries) stretched the refresh interval. */
static void test_refresh_skips_settled(void **state) {
  (void)state;
  struct vlff_config cfg;
  config_for(&cfg, "settled");
  cfg.publish.evidence_weight = 0;
  cfg.publish.label_hysteresis = 0; /* the map's label at every publish: rounds compare exactly */
  /* a small image in pieces of a fixed size (on any host, the restart
   * below comes halfway): the test renders it eight times, which took a
   * minute under qemu-user at 160 x 120 */
  cfg.publish.label_width = 64, cfg.publish.label_height = 48;
  struct vlff_field *f = small_field(&cfg, 3, 11);
  cfg.field.hash_log2_size = 13; /* another table: another field, the same embeddings (seed 11) */
  struct vlff_field *g = vlff_field_create(&cfg.field, &cfg.train, 1, err, sizeof err);
  assert_non_null(g);
  int K;
  const float *E = vlff_field_prompt_embeddings(f, &K);
  assert_int_equal(vlff_field_set_prompts(g, E, K, err, sizeof err), 0);
  cfg.field.hash_log2_size = 12;
  struct vlff_publisher *p = create(&cfg);
  vlff_publisher_set_image_piece(p, 1024);
  vlff_publisher_set_slice_piece(p, SIZE_MAX); /* each slice reaches its target: the test counts rounds */
  const char *prompts[3] = {"wall", "floor", "chair"};
  struct vlff_map *m = vlff_map_attach(cfg.shm.map);
  assert_non_null(m);
  struct vlff_map_snapshot *a = vlff_map_snapshot_new(m), *b = vlff_map_snapshot_new(m), *c = vlff_map_snapshot_new(m);
  struct vlff_publish_result r;
  struct vlff_map_info ia, ib, ic;
  struct vlff_view v = view_at(0, 1.5f);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  v = view_at(0.8, 2.0f);
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 3, &r, err, sizeof err), 0); /* a full round */
  take(m, a, &ia);
  size_t nv = (size_t)ia.grid.dims[0] * ia.grid.dims[1] * ia.grid.dims[2];

  /* The skipping round, with field g: settled voxels keep f's labels. */
  assert_int_equal(vlff_publisher_set_camera(p, &v, 123, 7, err, sizeof err), 0);
  for (int s = 0; s < 4; s++) {
    assert_int_equal(vlff_publisher_publish_slice(p, g, prompts, 3, (s + 1) / 4.0, &r, err, sizeof err), 0);
    assert_false(r.scored);
    /* Until the round ends, no label image is owed. */
    assert_int_equal(vlff_publisher_image_owed(p), s == 3);
  }
  /* The round's label image, in pieces, then its scores: one version, the
   * image's, which changes no voxel; a camera set halfway (a keyframe
   * admitted between two pieces) changes nothing of it. */
  take(m, c, &ic);
  assert_false(ic.has_label_image);
  int calls = 0;
  uint64_t ver = ic.version;
  do {
    assert_int_equal(vlff_publisher_publish_image(p, g, prompts, 3, &r, err, sizeof err), 0);
    if (++calls == 1) {
      struct vlff_view v2 = view_at(-0.5, 1.0f);
      assert_int_equal(vlff_publisher_set_camera(p, &v2, 456, 8, err, sizeof err), 0);
    }
    assert_true(r.version == ver || r.version == ver + 1);
    ver = r.version;
  } while (!r.scored);
  assert_int_equal(calls, 4); /* three pieces of 1024 pixels of 64 x 48, the scores */
  assert_int_equal(ver, ic.version + 1);
  assert_false(vlff_publisher_image_owed(p));
  take(m, b, &ib);
  assert_true(ib.has_label_image);
  assert_int_equal(ib.label_image.t_ns, 123);
  assert_int_equal(vlff_map_snapshot_follow(m, c), 0);
  const struct vlff_map_range *runs;
  assert_int_equal(vlff_map_snapshot_changes(c, &runs, NULL), 0);
  /* None owed twice. */
  assert_int_equal(vlff_publisher_publish_image(p, g, prompts, 3, &r, err, sizeof err), 0);
  assert_false(r.scored);
  assert_int_equal(r.version, ib.version);
  size_t settled = 0, unsettled = 0, moved = 0;
  for (size_t i = 0; i < nv; i++) {
    if (ia.grid.labels[i] <= VLFF_LABEL_MAX && ia.grid.confidence[i] == 255) {
      settled++;
      assert_int_equal(ib.grid.labels[i], ia.grid.labels[i]);
      assert_int_equal(ib.grid.confidence[i], 255);
    } else if (ia.grid.labels[i] <= VLFF_LABEL_MAX) {
      unsettled++;
      moved += ib.grid.labels[i] != ia.grid.labels[i] || ib.grid.confidence[i] != ia.grid.confidence[i];
    }
  }
  assert_true(settled > 20 && unsettled > 20); /* the test sees both kinds */
  assert_true(moved > 0);                       /* the unsettled ones were relabelled by g */

  /* The next round relabels every voxel: as a whole publish with g. */
  for (int s = 0; s < 4; s++)
    assert_int_equal(vlff_publisher_publish_slice(p, g, prompts, 3, (s + 1) / 4.0, &r, err, sizeof err), 0);
  take(m, c, &ic);
  /* The pieced image is the image rendered whole (at its camera). */
  size_t li = (size_t)ic.label_image.width * ic.label_image.height;
  uint16_t *pieced = malloc(li * sizeof *pieced);
  assert_non_null(pieced);
  memcpy(pieced, ic.label_image.labels, li * sizeof *pieced);
  v = view_at(0.8, 2.0f); /* its depth again (view_at writes one buffer) */
  assert_int_equal(vlff_publisher_set_camera(p, &v, 123, 7, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_publish(p, g, prompts, 3, &r, err, sizeof err), 0);
  take(m, b, &ib);
  assert_int_equal(ib.label_image.t_ns, 123);
  assert_memory_equal(pieced, ib.label_image.labels, li * sizeof *pieced);
  free(pieced);
  assert_memory_equal(ic.grid.labels, ib.grid.labels, nv * 2);
  assert_memory_equal(ic.grid.confidence, ib.grid.confidence, nv);
  size_t differ = 0;
  for (size_t i = 0; i < nv; i++)
    differ += ia.grid.labels[i] <= VLFF_LABEL_MAX && ia.grid.confidence[i] == 255 && ic.grid.labels[i] != ia.grid.labels[i];
  assert_true(differ > 0); /* some settled voxel did change with g, in the full round */

  /* New embeddings (the same prompt texts) after an image's first piece:
   * it begins again, with them, at the latest camera, and equals the image
   * rendered whole. */
  for (int s = 0; s < 2; s++)
    assert_int_equal(vlff_publisher_publish_slice(p, g, prompts, 3, (s + 1) / 2.0, &r, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_publish_image(p, g, prompts, 3, &r, err, sizeof err), 0);
  struct vlff_view v3 = view_at(0.3, 1.8f);
  assert_int_equal(vlff_publisher_set_camera(p, &v3, 789, 9, err, sizeof err), 0);
  float e3[3 * 16];
  unsigned seed3 = 5;
  for (int i = 0; i < 3 * 16; i++) e3[i] = (float)rand_r(&seed3) / (float)RAND_MAX - 0.5f;
  assert_int_equal(vlff_field_set_prompts(g, e3, 3, err, sizeof err), 0);
  do assert_int_equal(vlff_publisher_publish_image(p, g, prompts, 3, &r, err, sizeof err), 0);
  while (!r.scored);
  take(m, c, &ic);
  assert_int_equal(ic.label_image.t_ns, 789);
  pieced = malloc(li * sizeof *pieced);
  assert_non_null(pieced);
  memcpy(pieced, ic.label_image.labels, li * sizeof *pieced);
  assert_int_equal(vlff_publisher_publish(p, g, prompts, 3, &r, err, sizeof err), 0);
  take(m, b, &ib);
  assert_int_equal(ib.label_image.t_ns, 789);
  assert_memory_equal(pieced, ib.label_image.labels, li * sizeof *pieced);
  free(pieced);

  vlff_map_snapshot_free(a);
  vlff_map_snapshot_free(b);
  vlff_map_snapshot_free(c);
  vlff_map_detach(m);
  vlff_field_destroy(f);
  vlff_field_destroy(g);
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* ------------------------------------------------------ restart: the hold */

/* Rewrites byte `at` of a saved map and its checksum, as a forger who knows
 * the format would. */
static void forge(const char *path, long at, uint8_t byte) {
  FILE *f = fopen(path, "r+b");
  assert_non_null(f);
  assert_int_equal(fseek(f, 0, SEEK_END), 0);
  long len = ftell(f);
  uint8_t *b = malloc((size_t)len);
  assert_non_null(b);
  rewind(f);
  assert_int_equal(fread(b, 1, (size_t)len, f), (size_t)len);
  b[at] = byte;
  uint64_t sum = vlff_fnv1a64(VLFF_FNV1A64_INIT, b, (size_t)len - 8);
  memcpy(b + len - 8, &sum, 8);
  rewind(f);
  assert_int_equal(fwrite(b, 1, (size_t)len, f), (size_t)len);
  fclose(f);
  free(b);
}

/* The label hold and the see-through marks are saved with the observation
 * grid: a restarted publisher publishes the labels it held (a field that
 * answers otherwise, without new evidence, does not flip them), and a
 * surface one view had seen through before the restart is cleared by the
 * next view through it, as without the restart. A forged label or mark is
 * refused naming the voxel, and the publisher keeps what it had. Before,
 * a restart forgot both: every held label was decided afresh by the field
 * and the run of views through a surface started over. */
static void test_hold_survives_restart(void **state) {
  (void)state;
  struct vlff_config ca, cb, cc;
  config_for(&ca, "ha");
  struct vlff_field *f1 = small_field(&ca, 3, 11);
  config_for(&cb, "hb");
  config_for(&cc, "hc");
  cb.field = cc.field = ca.field;
  ca.publish.evidence_weight = cb.publish.evidence_weight = cc.publish.evidence_weight = 0;
  ca.publish.label_hysteresis = cb.publish.label_hysteresis = 2; /* a cosine margin never exceeds it: always held */
  cc.publish.label_hysteresis = 0;                               /* the field's label always */
  /* Another field (another hash grid) with the same prompts: it answers
   * otherwise at many voxels. */
  struct vlff_cfg_field f2c = ca.field;
  f2c.hash_log2_size = 13;
  f2c.finest_resolution *= 2;
  struct vlff_field *f2 = vlff_field_create(&f2c, &ca.train, 1, err, sizeof err);
  assert_non_null(f2);
  int K;
  const float *E = vlff_field_prompt_embeddings(f1, &K);
  assert_int_equal(vlff_field_set_prompts(f2, E, K, err, sizeof err), 0);
  struct vlff_publisher *pa = create(&ca), *pb = create(&cb), *pc = create(&cc);
  const char *prompts[3] = {"wall", "floor", "chair"};
  struct vlff_publish_result r;
  const double fx = 0.5 * W / tan(0.5 * 65.0 * M_PI / 180.0), old_pt[3] = {(40 - 32) / fx, 0, 1.0};
  struct vlff_view v = view(2.0f);
  object_at(32, 2.0f);
  for (int i = 0; i < 2; i++) assert_int_equal(vlff_publisher_observe(pa, &v, err, sizeof err), 0);
  object_at(0, 2.0f); /* one view through the object's old place: not cleared yet */
  assert_int_equal(vlff_publisher_observe(pa, &v, err, sizeof err), 0);
  assert_true(vlff_publisher_surface_known(pa, old_pt));
  assert_int_equal(vlff_publisher_publish(pa, f1, prompts, 3, &r, err, sizeof err), 0);
  assert_int_equal(r.flips, 0); /* every voxel was new: none flipped */
  assert_true(r.labelled > 100);
  char path[] = "/tmp/vlff-test-hold-XXXXXX";
  int fd = mkstemp(path);
  assert_true(fd >= 0);
  close(fd);
  assert_int_equal(vlff_publisher_save(pa, path, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_load(pb, path, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_load(pc, path, err, sizeof err), 0);

  /* Restarted with another field: pb holds pa's labels, pc (no hold) shows
   * the field's. */
  struct vlff_map *ma = vlff_map_attach(ca.shm.map), *mb = vlff_map_attach(cb.shm.map),
                  *mc = vlff_map_attach(cc.shm.map);
  assert_true(ma && mb && mc);
  assert_int_equal(vlff_publisher_publish(pb, f2, prompts, 3, &r, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_publish(pc, f2, prompts, 3, &r, err, sizeof err), 0);
  struct vlff_map_snapshot *sa = vlff_map_snapshot_new(ma), *sb = vlff_map_snapshot_new(mb),
                           *sc = vlff_map_snapshot_new(mc);
  struct vlff_map_info ia, ib, ic;
  take(ma, sa, &ia);
  take(mb, sb, &ib);
  take(mc, sc, &ic);
  size_t nv = (size_t)ia.grid.dims[0] * ia.grid.dims[1] * ia.grid.dims[2], both = 0, held = 0, differ = 0;
  for (size_t i = 0; i < nv; i++) {
    uint16_t a = ia.grid.labels[i], b = ib.grid.labels[i], c = ic.grid.labels[i];
    if (a > VLFF_LABEL_MAX || b > VLFF_LABEL_MAX || c > VLFF_LABEL_MAX) continue;
    both++;
    held += a == b;
    differ += a != c;
  }
  assert_true(both > 100);
  assert_int_equal(held, both);
  assert_true(differ > 0);

  /* The run of views through the old place went on: one more clears it. */
  assert_true(vlff_publisher_surface_known(pb, old_pt));
  assert_int_equal(vlff_publisher_cleared(pb), 0);
  assert_int_equal(vlff_publisher_observe(pb, &v, err, sizeof err), 0);
  assert_false(vlff_publisher_surface_known(pb, old_pt));
  assert_true(vlff_publisher_cleared(pb) > 0);

  /* Forged: a label no prompt has, a mark no view makes, a lost-class
   * block no census writes. The file: a 56-byte header, 15 bytes a voxel
   * of grids, 1 of marks, 16 of counts, 3 of hold, the lost classes, the
   * evidence's length (0 here) and the checksum. */
  struct stat st;
  assert_int_equal(stat(path, &st), 0);
  const long LB = VLFF_EVIDENCE_LOST_BYTES;
  const long n = ((long)st.st_size - 56 - 16 - LB - 16) / 19, hold_at = 56 + 16 * n + 16;
  assert_int_equal(56 + 19 * n + LB + 32, st.st_size);
  forge(path, hold_at + 3 * n + 16 + 3, 1); /* prompt 3 lost, of none */
  assert_int_equal(vlff_publisher_load(pc, path, err, sizeof err), -1);
  assert_non_null(strstr(err, "lost classes: prompt 3 marked 1 (of 0 prompts)"));
  assert_int_equal(vlff_publisher_save(pa, path, err, sizeof err), 0);
  forge(path, hold_at + 3 * 7, 0);
  forge(path, hold_at + 3 * 7 + 1, 0x12);
  assert_int_equal(vlff_publisher_load(pc, path, err, sizeof err), -1);
  assert_non_null(strstr(err, "label hold: voxel 7 holds label 4608"));
  assert_int_equal(vlff_publisher_save(pa, path, err, sizeof err), 0);
  forge(path, 56 + 15 * n + 9, 0x40 /* a view's mark (THRU_HIT), never saved */);
  assert_int_equal(vlff_publisher_load(pc, path, err, sizeof err), -1);
  assert_non_null(strstr(err, "voxel 9 has see-through marks 0x40"));
  assert_true(vlff_publisher_surface_known(pc, old_pt)); /* pc kept what it had */

  vlff_map_snapshot_free(sa);
  vlff_map_snapshot_free(sb);
  vlff_map_snapshot_free(sc);
  vlff_map_detach(ma);
  vlff_map_detach(mb);
  vlff_map_detach(mc);
  unlink(path);
  vlff_field_destroy(f1);
  vlff_field_destroy(f2);
  vlff_publisher_destroy(pa);
  vlff_publisher_destroy(pb);
  vlff_publisher_destroy(pc);
  vlff_shm_unlink(ca.shm.map);
  vlff_shm_unlink(cb.shm.map);
  vlff_shm_unlink(cc.shm.map);
}

/* ------------------------------------------------------ a refitted grid */

/* A growing map at its capacity (shm.map_max_voxels) is refitted to the
 * voxels that hold something and the box asked for: the first box's
 * margins where nothing was seen are dropped, every voxel seen keeps its
 * place and label for a reader attached throughout, the new part is mapped,
 * and a save of the refitted grid (which does not hold the first box)
 * loads into a new map; a box that even a refit cannot hold is refused,
 * nothing changed. Before, such a growth was refused: the map's margins
 * took the capacity that the world seen needed. */
static void test_refit_under_reader(void **state) {
  (void)state;
  struct vlff_config cfg;
  config_for(&cfg, "refit"); /* 8 cm voxels: the 5 m first box is 63^3, near the 2^18 capacity */
  cfg.field.grow = true;
  cfg.publish.evidence_weight = 0;
  struct vlff_field *f = small_field(&cfg, 3, 11);
  struct vlff_publisher *p = create(&cfg);
  const char *prompts[3] = {"wall", "floor", "chair"};
  struct vlff_map *m = vlff_map_attach(cfg.shm.map);
  assert_non_null(m);
  struct vlff_publish_result r;
  struct vlff_view v = view(2.0f); /* from the origin, a wall 2 m along +z */
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 3, &r, err, sizeof err), 0);
  const double pts[4][3] = {{0, 0, 2.02}, {0.5, 0.5, 2.03}, {0.3, -0.2, 1.0}, {0, 0, -2.0}};
  uint16_t before[4], got;
  uint8_t conf;
  for (int i = 0; i < 4; i++) assert_int_equal(vlff_map_label_at(m, pts[i][0], pts[i][1], pts[i][2], &before[i], &conf), 0);
  assert_true(before[0] < 3 && before[1] < 3);
  assert_int_equal(before[2], VLFF_LABEL_FREE);
  assert_int_equal(before[3], VLFF_LABEL_UNKNOWN); /* behind the camera: never seen */
  double lo0[3], hi0[3], lo[3], hi[3];
  long long grown;
  vlff_publisher_box(p, lo0, hi0, &grown);
  assert_int_equal(grown, 0);

  /* 3.5 m further along +z: holding the first box too would take 63 x 63 x 107 */
  const double glo[3] = {-0.5, -0.5, 2.5}, ghi[3] = {0.5, 0.5, 6};
  assert_int_equal(vlff_field_grow(f, glo, ghi, err, sizeof err), 1);
  assert_int_equal(vlff_publisher_grow(p, glo, ghi, glo, ghi, err, sizeof err), 2); /* refitted */
  vlff_publisher_box(p, lo, hi, &grown);
  assert_int_equal(grown, 1);
  assert_true(lo[2] > -0.2 && lo[2] <= 0 && hi[2] >= 6);  /* from the camera on: the -z half dropped */
  assert_true(lo[0] > lo0[0] + 1 && hi[0] < hi0[0] - 1); /* and the x margins no ray reached */
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 3, &r, err, sizeof err), 0);
  assert_true(r.whole);
  for (int i = 0; i < 4; i++) {
    assert_int_equal(vlff_map_label_at(m, pts[i][0], pts[i][1], pts[i][2], &got, &conf), 0);
    assert_int_equal(got, before[i]); /* the same place, the same label (or unknown: beyond the grid) */
  }
  v = view(2.0f);
  v.c2w[11] = 3.0; /* a wall at z = 5, in the new part */
  assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 3, &r, err, sizeof err), 0);
  assert_int_equal(vlff_map_label_at(m, 0, 0, 5.02, &got, &conf), 0);
  assert_true(got < 3);
  assert_int_equal(vlff_map_label_at(m, 0, 0, 4.0, &got, &conf), 0);
  assert_int_equal(got, VLFF_LABEL_FREE);

  /* too large even refitted: refused, nothing changed */
  const double huge_lo[3] = {-40, -40, 0}, huge_hi[3] = {40, 40, 6};
  assert_int_equal(vlff_publisher_grow(p, huge_lo, huge_hi, huge_lo, huge_hi, err, sizeof err), -1);
  assert_non_null(strstr(err, "even without the voxels that hold nothing"));
  double lo2[3], hi2[3];
  vlff_publisher_box(p, lo2, hi2, &grown);
  assert_memory_equal(lo2, lo, sizeof lo);
  assert_memory_equal(hi2, hi, sizeof hi);

  /* saved refitted, loaded into a map that starts again in the first box */
  char path[128];
  snprintf(path, sizeof path, "/tmp/vlff-test-refit-%d.obs", (int)getpid());
  assert_int_equal(vlff_publisher_save(p, path, err, sizeof err), 0);
  struct vlff_config c2;
  config_for(&c2, "refit2");
  c2.field.grow = true;
  c2.publish.evidence_weight = 0;
  struct vlff_publisher *q = create(&c2);
  if (vlff_publisher_load(q, path, err, sizeof err)) fail_msg("%s", err);
  vlff_publisher_box(q, lo2, hi2, NULL);
  assert_memory_equal(lo2, lo, sizeof lo);
  assert_memory_equal(hi2, hi, sizeof hi);
  const double wall5[3] = {0, 0, 5.02}, wall2[3] = {0.5, 0.5, 2.03};
  assert_true(vlff_publisher_surface_known(q, wall5) && vlff_publisher_surface_known(q, wall2));
  unlink(path);
  vlff_publisher_destroy(q);
  vlff_shm_unlink(c2.shm.map);

  /* the wanted box (a view's margins ahead) too large even refitted, the
   * needed one inside it fitting: one call grows to the needed one */
  const double want_lo[3] = {-40, -40, 0}, want_hi[3] = {40, 40, 7}, need_lo[3] = {-0.5, -0.5, 6},
               need_hi[3] = {0.5, 0.5, 7};
  int g = vlff_publisher_grow(p, want_lo, want_hi, need_lo, need_hi, err, sizeof err);
  assert_true(g == 1 || g == 2);
  vlff_publisher_box(p, lo2, hi2, NULL);
  assert_true(hi2[2] >= 7 && hi2[0] < 40 && lo2[0] > -40);
  assert_true(vlff_publisher_surface_known(p, wall5)); /* nothing held moved */
  /* held: nothing to do */
  assert_int_equal(vlff_publisher_grow(p, want_lo, want_hi, need_lo, need_hi, err, sizeof err), 0);
  vlff_map_detach(m);
  vlff_field_destroy(f);
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* Beyond the caps (docs/field.md "Beyond the caps"): a map whose grid holds
 * one view's box walks 300 m along a corridor of walls. Each growth past
 * shm.map_max_voxels slides the grid with the camera; what it leaves is
 * published as far blocks beside it, so a reader attached throughout reads
 * every wall it passed with the label it had, through the same handle; a
 * followed snapshot holds the far blocks; walking back restores them into
 * the grid as measured surfaces. */
static void test_slide_under_reader(void **state) {
  (void)state;
  struct vlff_config cfg;
  config_for(&cfg, "slide");
  cfg.field.grow = true;
  cfg.publish.evidence_weight = 0;
  cfg.shm.map_max_voxels = 50000; /* 8 cm voxels: about two views' boxes */
  const double first_lo[3] = {-1.5, -1.2, -0.2}, first_hi[3] = {1.5, 1.2, 2.3};
  memcpy(cfg.field.scene_min, first_lo, sizeof first_lo);
  memcpy(cfg.field.scene_max, first_hi, sizeof first_hi);
  struct vlff_field *f = small_field(&cfg, 3, 11);
  struct vlff_publisher *p = create(&cfg);
  const char *prompts[3] = {"wall", "floor", "chair"};
  struct vlff_map *m = vlff_map_attach(cfg.shm.map);
  assert_non_null(m);
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(m);
  assert_non_null(snap);
  struct vlff_publish_result r;
  enum { STEPS = 76 }; /* 300 m */
  uint16_t seen[STEPS], front[STEPS];
  int slides = 0;
  for (int k = 0; k < STEPS; k++) {
    const double x = 4.0 * k; /* a camera every 4 m along x, a wall 2 m ahead along +z */
    const double lo[3] = {x - 1.4, -1.1, -0.1}, hi[3] = {x + 1.4, 1.1, 2.2};
    if (k) {
      /* the field grows, and past train.occupancy_max_mb slides too */
      if (vlff_field_grow(f, lo, hi, err, sizeof err) < 0) assert_int_equal(vlff_field_slide(f, lo, hi, err, sizeof err), 2);
      int g = vlff_publisher_grow(p, lo, hi, lo, hi, err, sizeof err);
      if (g < 0) fail_msg("step %d: %s", k, err);
      slides += g == 3;
      double blo[3], bhi[3];
      vlff_publisher_box(p, blo, bhi, NULL);
      assert_true(blo[0] <= lo[0] && bhi[0] >= hi[0]); /* the view is held */
      assert_true(blo[0] > x - 4.0);                   /* the first walls are not */
    }
    struct vlff_view v = view_at(x, 2.0f);
    assert_int_equal(vlff_publisher_observe(p, &v, err, sizeof err), 0);
    assert_int_equal(vlff_publisher_publish(p, f, prompts, 3, &r, err, sizeof err), 0);
    uint8_t conf;
    assert_int_equal(vlff_map_label_at(m, x + 0.3, 0.2, 2.02, &seen[k], &conf), 0);
    assert_true(seen[k] < 3); /* a wall, labelled */
    assert_int_equal(vlff_map_label_at(m, x + 0.3, 0.2, 1.0, &front[k], &conf), 0);
    assert_int_not_equal(front[k], VLFF_LABEL_UNKNOWN); /* the space in front, observed */
  }
  assert_int_equal(slides, STEPS - 1);
  /* every wall the camera passed, through the same handle: the far map's
   * answer is the label each had when the grid left it */
  for (int k = 0; k < STEPS; k++) {
    uint16_t got;
    uint8_t conf;
    assert_int_equal(vlff_map_label_at(m, 4.0 * k + 0.3, 0.2, 2.02, &got, &conf), 0);
    assert_int_equal(got, seen[k]);
    assert_int_equal(vlff_map_label_at(m, 4.0 * k + 0.3, 0.2, 1.0, &got, &conf), 0);
    assert_int_equal(got, front[k]);
  }
  uint16_t got;
  uint8_t conf;
  assert_int_equal(vlff_map_label_at(m, 2.0, 0.2, -3.0, &got, &conf), 0);
  assert_int_equal(got, VLFF_LABEL_UNKNOWN); /* never seen */
  assert_int_equal(vlff_map_snapshot_take(m, snap), 0);
  struct vlff_map_far far;
  assert_int_equal(vlff_map_snapshot_far(snap, &far), 0);
  assert_true(far.nblocks > 10);
  assert_int_equal(vlff_map_snapshot_label_at(snap, 0.3, 0.2, 2.02, &conf), seen[0]);
  /* a checkpoint holds the far map beside the grid: a restarted node
   * publishes it again with its first map */
  char path[128];
  snprintf(path, sizeof path, "/tmp/vlff-test-slide-%d.obs", (int)getpid());
  assert_int_equal(vlff_publisher_save(p, path, err, sizeof err), 0);
  /* written only when it changed: a second save leaves the far file as it
   * was (atomic writes would give it a new inode) */
  char fpath[160];
  snprintf(fpath, sizeof fpath, "%s.far", path);
  struct stat st0, st1;
  assert_int_equal(stat(fpath, &st0), 0);
  assert_int_equal(vlff_publisher_save(p, path, err, sizeof err), 0);
  assert_int_equal(stat(fpath, &st1), 0);
  assert_true(st0.st_ino == st1.st_ino);
  struct vlff_config c2 = cfg;
  snprintf(c2.shm.map, sizeof c2.shm.map, "/vlff-test-publish-slide2-%d", (int)getpid());
  struct vlff_publisher *q = create(&c2);
  if (vlff_publisher_load(q, path, err, sizeof err)) fail_msg("%s", err);
  assert_int_equal(vlff_publisher_publish(q, f, prompts, 3, &r, err, sizeof err), 0);
  struct vlff_map *m2 = vlff_map_attach(c2.shm.map);
  assert_non_null(m2);
  for (int k = 0; k + 1 < STEPS; k++) {
    assert_int_equal(vlff_map_label_at(m2, 4.0 * k + 0.3, 0.2, 2.02, &got, &conf), 0);
    assert_int_equal(got, seen[k]);
  }
  vlff_map_detach(m2);
  vlff_publisher_destroy(q);
  vlff_shm_unlink(c2.shm.map);
  unlink(path), unlink(fpath);
  /* back to the start: the grid slides back over the far blocks, which come
   * back as measured surfaces (their labels kept until they are relabelled) */
  const double lo[3] = {-1.4, -1.1, -0.1}, hi[3] = {1.4, 1.1, 2.2};
  if (vlff_field_grow(f, lo, hi, err, sizeof err) < 0) assert_int_equal(vlff_field_slide(f, lo, hi, err, sizeof err), 2);
  assert_int_equal(vlff_publisher_grow(p, lo, hi, lo, hi, err, sizeof err), 3);
  const double wall0[3] = {0.3, 0.2, 2.02};
  assert_true(vlff_publisher_surface_known(p, wall0));
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 3, &r, err, sizeof err), 0);
  assert_int_equal(vlff_map_label_at(m, 0.3, 0.2, 2.02, &got, &conf), 0);
  assert_true(got < 3);
  assert_int_equal(vlff_map_label_at(m, 0.3, 0.2, 1.0, &got, &conf), 0);
  assert_int_not_equal(got, VLFF_LABEL_UNKNOWN);
  assert_int_equal(vlff_map_label_at(m, 4.0 * (STEPS - 1) + 0.3, 0.2, 2.02, &got, &conf), 0);
  assert_int_equal(got, seen[STEPS - 1]); /* the far end, now far */
  /* the far map changed with the slide back: written again; then kept; a
   * far file gone from beside the grid is written again */
  assert_int_equal(vlff_publisher_save(p, path, err, sizeof err), 0);
  assert_int_equal(stat(fpath, &st0), 0);
  assert_int_equal(vlff_publisher_save(p, path, err, sizeof err), 0);
  assert_int_equal(stat(fpath, &st1), 0);
  assert_true(st0.st_ino == st1.st_ino);
  unlink(fpath);
  assert_int_equal(vlff_publisher_save(p, path, err, sizeof err), 0);
  assert_int_equal(stat(fpath, &st1), 0);
  /* and one written over since (a byte flipped in place: the same file and
   * size, a later time) is written again, as it was */
  const ssize_t len = (ssize_t)st1.st_size;
  assert_true(len > 64);
  uint8_t *before = malloc((size_t)len), *after = malloc((size_t)len);
  assert_non_null(before), assert_non_null(after);
  int fd = open(fpath, O_RDWR);
  assert_true(fd >= 0);
  assert_int_equal(pread(fd, before, (size_t)len, 0), len);
  usleep(30000); /* past the file system's clock tick */
  assert_int_equal(pwrite(fd, "\xff", 1, 60), 1);
  close(fd);
  assert_int_equal(stat(fpath, &st0), 0);
  assert_true(st0.st_ino == st1.st_ino);
  assert_int_equal(vlff_publisher_save(p, path, err, sizeof err), 0);
  assert_int_equal(stat(fpath, &st1), 0);
  assert_true(st0.st_ino != st1.st_ino);
  fd = open(fpath, O_RDONLY);
  assert_true(fd >= 0);
  assert_int_equal(pread(fd, after, (size_t)len, 0), len);
  close(fd);
  assert_memory_equal(before, after, (size_t)len);
  free(before), free(after);
  unlink(path), unlink(fpath);
  vlff_map_snapshot_free(snap);
  vlff_map_detach(m);
  vlff_field_destroy(f);
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
}

/* The label image's regions (publish.region_weight, regions.h): a wall 2 m
 * in front of the camera whose evidence reads prompt 0, but for a patch
 * whose views leaned to prompt 1 by a little. In a camera image of one
 * colour the patch reads what the wall reads; without the vote, or where
 * the image shows the patch in a colour of its own, it keeps prompt 1. The
 * field is not fitted (no rays): the labels are the evidence's. An image
 * made in pieces, with a camera set halfway, is the image made whole. */
static uint16_t image_label_at(struct vlff_publisher *p, struct vlff_field *f, struct vlff_map *m,
                               struct vlff_map_snapshot *s, int x, int y) {
  const char *prompts[3] = {"wall", "door", "chair"};
  struct vlff_publish_result r;
  struct vlff_map_info in;
  assert_int_equal(vlff_publisher_publish(p, f, prompts, 3, &r, err, sizeof err), 0);
  take(m, s, &in);
  assert_true(in.has_label_image);
  return in.label_image.labels[(size_t)y * in.label_image.width + x];
}

static void test_label_image_regions(void **state) {
  (void)state;
  enum { FW = 32, FH = 24, D = 16 };
  static uint16_t feat[FW * FH * D];
  static uint8_t rgb[W * H * 3];
  for (int j = 0; j < FH; j++)
    for (int i = 0; i < FW; i++) {
      float v[D] = {0};
      const bool patch = i >= 12 && i < 20 && j >= 8 && j < 16;
      v[0] = patch ? 0.55f : 1.0f, v[1] = patch ? 0.6f : 0.0f;
      vlff_f32_to_f16_n(v, feat + ((size_t)j * FW + i) * D, D);
    }
  memset(rgb, 120, sizeof rgb);
  struct vlff_publisher *p[2];
  struct vlff_config cfg[2];
  struct vlff_field *f = NULL;
  float e[3 * D] = {0};
  e[0] = e[D + 1] = e[2 * D + 2] = 1; /* prompts along the first three axes */
  for (int k = 0; k < 2; k++) {
    config_for(&cfg[k], k ? "noregions" : "regions");
    cfg[k].publish.label_width = W, cfg[k].publish.label_height = H;
    cfg[k].publish.region_weight = k ? 0 : 1;
    if (!f) {
      f = small_field(&cfg[k], 3, 1);
      assert_int_equal(vlff_field_set_prompts(f, e, 3, err, sizeof err), 0);
    } else {
      cfg[k].field = cfg[0].field, cfg[k].node.threads = 1;
    }
    p[k] = create(&cfg[k]);
    struct vlff_view v = view(2.0f);
    v.rgb = rgb, v.features = feat, v.feat_width = FW, v.feat_height = FH, v.feature_dim = D;
    assert_int_equal(vlff_publisher_observe(p[k], &v, err, sizeof err), 0);
    assert_int_equal(vlff_publisher_set_camera(p[k], &v, 1, 1, err, sizeof err), 0);
  }
  struct vlff_map *m[2] = {vlff_map_attach(cfg[0].shm.map), vlff_map_attach(cfg[1].shm.map)};
  assert_true(m[0] && m[1]);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m[0]), *s1 = vlff_map_snapshot_new(m[1]);
  /* the patch's middle, and the wall beside it */
  assert_int_equal(image_label_at(p[1], f, m[1], s1, W / 2, H / 2), 1);
  assert_int_equal(image_label_at(p[1], f, m[1], s1, 4, 4), 0);
  assert_int_equal(image_label_at(p[0], f, m[0], s, W / 2, H / 2), 0);
  assert_int_equal(image_label_at(p[0], f, m[0], s, 4, 4), 0);

  /* The patch's middle in a colour of its own (inside the evidence's
   * blend with the wall at the patch's edge): a region of its own. */
  for (int y = 20; y < 28; y++)
    for (int x = 28; x < 36; x++) rgb[(y * W + x) * 3] = 230, rgb[(y * W + x) * 3 + 2] = 20;
  struct vlff_view v = view(2.0f);
  v.rgb = rgb;
  assert_int_equal(vlff_publisher_set_camera(p[0], &v, 2, 2, err, sizeof err), 0);
  assert_int_equal(image_label_at(p[0], f, m[0], s, W / 2, H / 2), 1);
  assert_int_equal(image_label_at(p[0], f, m[0], s, 4, 4), 0);
  struct vlff_map_info in;
  take(m[0], s, &in);
  const size_t li = (size_t)W * H;
  uint16_t *whole = malloc(li * sizeof *whole);
  assert_non_null(whole);
  memcpy(whole, in.label_image.labels, li * sizeof *whole);

  /* In pieces, a grey camera set after the first: the coloured camera's
   * image, voted with its own regions. */
  const char *prompts[3] = {"wall", "door", "chair"};
  struct vlff_publish_result r;
  vlff_publisher_set_image_piece(p[0], 700);
  vlff_publisher_set_slice_piece(p[0], SIZE_MAX); /* each slice reaches its target: the round ends */
  for (int sl = 0; sl < 2; sl++)
    assert_int_equal(vlff_publisher_publish_slice(p[0], f, prompts, 3, (sl + 1) / 2.0, &r, err, sizeof err), 0);
  int calls = 0;
  do {
    assert_int_equal(vlff_publisher_publish_image(p[0], f, prompts, 3, &r, err, sizeof err), 0);
    if (++calls == 1) {
      static uint8_t grey[W * H * 3];
      memset(grey, 120, sizeof grey);
      struct vlff_view g = view(2.0f);
      g.rgb = grey;
      assert_int_equal(vlff_publisher_set_camera(p[0], &g, 3, 3, err, sizeof err), 0);
    }
  } while (!r.scored && calls < 100);
  assert_true(calls > 2);
  take(m[0], s, &in);
  assert_int_equal(in.label_image.t_ns, 2);
  assert_memory_equal(whole, in.label_image.labels, li * sizeof *whole);
  free(whole);

  vlff_map_snapshot_free(s);
  vlff_map_snapshot_free(s1);
  for (int k = 0; k < 2; k++) {
    vlff_map_detach(m[k]);
    vlff_publisher_destroy(p[k]);
    vlff_shm_unlink(cfg[k].shm.map);
  }
  vlff_field_destroy(f);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_label_image_regions),
    cmocka_unit_test(test_moved_object_clears),
    cmocka_unit_test(test_absurd_intrinsics_refused), cmocka_unit_test(test_far_depth_bounded),
    cmocka_unit_test(test_voxels_past_bound_refused),
    cmocka_unit_test(test_saved_map_loads_within_budget), cmocka_unit_test(test_surface_behind_voxel_face),
    cmocka_unit_test(test_every_pixel_counts), cmocka_unit_test(test_incremental_publication),
      cmocka_unit_test(test_refresh_skips_settled),
    cmocka_unit_test(test_grazing_surface_filled), cmocka_unit_test(test_hold_survives_restart),
    cmocka_unit_test(test_refit_under_reader), cmocka_unit_test(test_slide_under_reader))
