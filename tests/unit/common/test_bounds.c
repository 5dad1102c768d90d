/* Physical bounds of intrinsics and poses (bounds.h): real cameras pass,
 * corrupt values are refused with the value and the bound named. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <string.h>
#include <cmocka.h>

#include "bounds.h"
#include "config.h"
#include "unit.h"

static char why[256];

static void test_real_cameras_pass(void **state) {
  (void)state;
  /* vlff-sim (65 degrees), ScanNet colour, a Kinect depth camera, a
   * fisheye-ish 160 degree lens, a 2 degree telephoto, a principal point
   * off centre after a crop. */
  double sim_f = 0.5 * 320 / tan(0.5 * 65.0 * M_PI / 180.0);
  assert_int_equal(vlff_intrinsics_plausible(320, 240, sim_f, sim_f, 160, 120, why, sizeof why), 0);
  assert_int_equal(vlff_intrinsics_plausible(1296, 968, 1170.19, 1170.19, 647.75, 483.75, why, sizeof why), 0);
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 577.87, 577.87, 319.5, 239.5, why, sizeof why), 0);
  assert_int_equal(vlff_intrinsics_plausible(1000, 1000, 90, 90, 500, 500, why, sizeof why), 0);
  assert_int_equal(vlff_intrinsics_plausible(1000, 1000, 28000, 28000, 500, 500, why, sizeof why), 0);
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 500, 500, -100, 600, why, sizeof why), 0);
}

static void test_corrupt_intrinsics_refused(void **state) {
  (void)state;
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 500, 500, -1e9, 1e9, why, sizeof why), -1);
  assert_string_equal(why, "cx -1e+09 outside [-320, 960] (the image grown by half its width)");
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 500, 500, 320, 1e9, why, sizeof why), -1);
  assert_non_null(strstr(why, "cy 1e+09 outside [-240, 720]"));
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 0.001, 500, 320, 240, why, sizeof why), -1);
  assert_non_null(strstr(why, "fx 0.001 outside"));
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 1e-30, 1e-30, 320, 240, why, sizeof why), -1);
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 1e30, 1e30, 320, 240, why, sizeof why), -1);
  assert_non_null(strstr(why, "fx 1e+30 outside"));
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 500, 60, 320, 240, why, sizeof why), -1);
  assert_non_null(strstr(why, "pixel aspect"));
  assert_int_equal(vlff_intrinsics_plausible(640, 480, NAN, 500, 320, 240, why, sizeof why), -1);
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 500, 500, INFINITY, 240, why, sizeof why), -1);
  assert_int_equal(vlff_intrinsics_plausible(640, 480, 500, 500, 320, NAN, why, sizeof why), -1);
  assert_int_equal(vlff_intrinsics_plausible(0, 480, 500, 500, 0, 240, why, sizeof why), -1);
  assert_non_null(strstr(why, "image size 0x480"));
  assert_int_equal(vlff_intrinsics_plausible(100000, 480, 500, 500, 0, 240, NULL, 0), -1);
}

static void test_pose_bounds(void **state) {
  (void)state;
  double m[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  const double lo[3] = {-2.5, -2.5, -1}, hi[3] = {2.5, 2.5, 1};
  assert_int_equal(vlff_pose_plausible(m, lo, hi, why, sizeof why), 0);
  m[3] = 7.5; /* outside the box by its largest extent, 5 m: still a view into it */
  assert_int_equal(vlff_pose_plausible(m, lo, hi, why, sizeof why), 0);
  m[3] = 7.6;
  assert_int_equal(vlff_pose_plausible(m, lo, hi, why, sizeof why), -1);
  assert_string_equal(why, "camera x = 7.6 m outside [-7.5, 7.5] (the scene box grown by its largest extent)");
  m[3] = 0, m[11] = 1e300;
  assert_int_equal(vlff_pose_plausible(m, lo, hi, why, sizeof why), -1);
  assert_non_null(strstr(why, "camera z = 1e+300 m"));
  assert_int_equal(vlff_pose_plausible(m, NULL, NULL, why, sizeof why), -1);
  assert_non_null(strstr(why, "no scene box"));
  m[11] = 9000;
  assert_int_equal(vlff_pose_plausible(m, NULL, NULL, why, sizeof why), 0);
  m[7] = NAN;
  assert_int_equal(vlff_pose_plausible(m, NULL, NULL, why, sizeof why), -1);
}

/* The node's bound by its field section: the box's with a fixed box, the
 * world's limit when the box grows. */
static void test_field_pose_bounds(void **state) {
  (void)state;
  struct vlff_config c;
  vlff_config_defaults(&c);
  c.field.grow = false; /* +-2.5 m, fixed */
  double m[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  m[3] = 7.6;
  assert_int_equal(vlff_field_pose_plausible(&c.field, m, why, sizeof why), -1);
  assert_non_null(strstr(why, "scene box grown by its largest extent"));
  c.field.grow = true;
  c.field.world_limit_m = 10;
  assert_int_equal(vlff_field_pose_plausible(&c.field, m, why, sizeof why), 0);
  m[3] = -10, m[7] = 10;
  assert_int_equal(vlff_field_pose_plausible(&c.field, m, why, sizeof why), 0);
  m[11] = 10.5;
  assert_int_equal(vlff_field_pose_plausible(&c.field, m, why, sizeof why), -1);
  assert_string_equal(why, "camera z = 10.5 m outside [-10, 10] (field.world_limit_m)");
  m[11] = NAN;
  assert_int_equal(vlff_field_pose_plausible(&c.field, m, why, sizeof why), -1);
}

/* The box-free units check: a step between two candidates within the
 * farther depth of the two (at least VLFF_MIN_POSE_STEP_M) passes; the same
 * walk in millimetres does not. */
static void test_pose_step(void **state) {
  (void)state;
  double a[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1}, b[16];
  memcpy(b, a, sizeof b);
  b[3] = 3.0, b[7] = 4.0; /* 5 m */
  assert_int_equal(vlff_pose_step_plausible(a, 5.0, b, 2.0, why, sizeof why), 0);
  assert_int_equal(vlff_pose_step_plausible(a, 2.0, b, 5.0, why, sizeof why), 0);
  assert_int_equal(vlff_pose_step_plausible(a, 4.9, b, 4.9, why, sizeof why), -1);
  assert_string_equal(why, "camera moved 5 m since the keyframe candidate before, farther than the 4.9 m either "
                           "frame's depth reaches");
  /* Facing a wall at 0.3 m, a step of VLFF_MIN_POSE_STEP_M still passes. */
  memcpy(b, a, sizeof b);
  b[11] = VLFF_MIN_POSE_STEP_M;
  assert_int_equal(vlff_pose_step_plausible(a, 0.3, b, 0.3, why, sizeof why), 0);
  /* 8 cm at 5 Hz (a walk at 0.4 m/s) in millimetres, 6 m of depth. */
  memcpy(b, a, sizeof b);
  b[3] = 80;
  assert_int_equal(vlff_pose_step_plausible(a, 6.0, b, 6.0, why, sizeof why), -1);
  /* One wild depth pixel does not lift the bound past VLFF_MAX_POSE_STEP_M. */
  b[3] = 200;
  assert_int_equal(vlff_pose_step_plausible(a, 6.0, b, 1e30, why, sizeof why), -1);
  assert_non_null(strstr(why, "farther than the 100 m"));
  b[3] = NAN;
  assert_int_equal(vlff_pose_step_plausible(a, 6.0, b, 6.0, why, sizeof why), -1);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_real_cameras_pass), cmocka_unit_test(test_pose_step), cmocka_unit_test(test_corrupt_intrinsics_refused),
    cmocka_unit_test(test_pose_bounds), cmocka_unit_test(test_field_pose_bounds))
