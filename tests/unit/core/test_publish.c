/* The map publisher against hostile views: implausible intrinsics and poses
 * are refused and counted, and no depth or pose makes a ray's march run
 * longer than the map is wide. Before the bound, a view of plausible
 * intrinsics with depth reaching far beyond the map (or cx = -1e9 /
 * fx = 0.001) marched hundreds of millions of steps per pixel: the test
 * then hung until ctest's timeout. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <cmocka.h>

#include "publish.h"
#include "unit.h"
#include "vlff/shm.h"

enum { W = 64, H = 48 };
static char err[512];
static float depth[W * H];

static struct vlff_publisher *make(struct vlff_config *cfg) {
  vlff_config_defaults(cfg);
  snprintf(cfg->shm.map, sizeof cfg->shm.map, "/vlff-test-publish-%d", (int)getpid());
  cfg->shm.map_max_voxels = 1 << 18; /* 64^3 voxels of 8 cm over the default 5 m box */
  cfg->publish.voxel_size_m = 0.08;
  struct vlff_publisher *p = vlff_publisher_create(&cfg->publish, &cfg->shm, &cfg->field, NULL, err, sizeof err);
  if (!p) fail_msg("%s", err);
  return p;
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
  assert_int_equal(vlff_publisher_refused(p), 5);
  /* A refused view accounts nothing: the map stays empty. */
  struct vlff_view ok = view(1.0f);
  double x[3] = {0, 0, 1.0};
  assert_false(vlff_publisher_surface_known(p, x));
  assert_int_equal(vlff_publisher_observe(p, &ok, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_observe(p, &ok, err, sizeof err), 0);
  assert_true(vlff_publisher_surface_known(p, x));
  assert_int_equal(vlff_publisher_set_camera(p, &ok, 1, 1, err, sizeof err), 0);
  assert_int_equal(vlff_publisher_refused(p), 5);
  vlff_publisher_destroy(p);
  vlff_shm_unlink(cfg.shm.map);
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

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_absurd_intrinsics_refused), cmocka_unit_test(test_far_depth_bounded))
