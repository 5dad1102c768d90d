/* Keyframe selection by time and motion, pose validation, bad-pose check. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <cmocka.h>

#include "select.h"
#include "unit.h"

static void ident(double m[16], double x) {
  memset(m, 0, 16 * sizeof m[0]);
  m[0] = m[5] = m[10] = m[15] = 1;
  m[3] = x;
}

/* A selector at 5 Hz keyframes with the given motion thresholds, and p the
 * identity pose. */
struct sel {
  struct vlff_kf_selector s;
  double p[16];
};

static struct sel start(double min_m, double min_deg) {
  struct sel x;
  vlff_kf_selector_init(&x.s, 5, min_m, min_deg);
  ident(x.p, 0);
  return x;
}

static void test_time_only(void **st) {
  (void)st;
  struct sel x = start(0, 0);
  int n = 0;
  /* 30 Hz for 2 s at 5 Hz keyframes: 10 keyframes. */
  for (int i = 0; i < 60; i++) n += vlff_kf_selector_offer(&x.s, (long long)i * 1000000000ll / 30, x.p);
  assert_int_equal(n, 10);
}

/* A camera at the keyframe rate, each frame up to 30 ms early or late (a
 * fixed pseudo-random pattern): every frame becomes a keyframe but at most
 * one (an early frame before any credit has built up); frames at 100 Hz with
 * the same jitter stay within the rate; a frame older than the last keyframe
 * is refused. */
static void test_time_jitter(void **st) {
  (void)st;
  struct sel x = start(0, 0);
  unsigned r = 12345;
  int n = 0;
  for (int i = 0; i < 100; i++) {
    r = r * 1103515245u + 12345u;
    long long j = (long long)((r >> 16) % 61) - 30; /* ms */
    n += vlff_kf_selector_offer(&x.s, (200ll * i + j) * 1000000ll, x.p);
  }
  assert_in_range(n, 99, 100);
  x = start(0, 0);
  n = 0;
  long long last = 0;
  for (int i = 0; i < 1000; i++) {
    r = r * 1103515245u + 12345u;
    long long t = (10ll * i + (long long)((r >> 16) % 7) - 3) * 1000000ll;
    if (vlff_kf_selector_offer(&x.s, t, x.p)) {
      assert_true(n == 0 || t - last >= 99000000ll); /* never under half an interval apart */
      n++, last = t;
    }
  }
  assert_in_range(n, 49, 51); /* 10 s at 5 Hz */
  assert_false(vlff_kf_selector_offer(&x.s, last - 1000000000ll, x.p));
  assert_false(vlff_kf_selector_due(&x.s, last - 1000000000ll));
}

static void test_motion_required(void **st) {
  (void)st;
  struct sel x = start(0.1, 0);
  assert_true(vlff_kf_selector_offer(&x.s, 0, x.p));
  assert_false(vlff_kf_selector_offer(&x.s, 1000000000ll, x.p)); /* time ok, no motion */
  ident(x.p, 0.05);
  assert_false(vlff_kf_selector_offer(&x.s, 2000000000ll, x.p));
  ident(x.p, 0.2);
  assert_true(vlff_kf_selector_offer(&x.s, 3000000000ll, x.p));
  /* Rotation alone counts when min_rotation_deg is set. */
  x = start(0, 10);
  assert_true(vlff_kf_selector_offer(&x.s, 0, x.p));
  double r[16];
  ident(r, 0);
  double a = 15 * M_PI / 180;
  r[0] = cos(a), r[1] = -sin(a), r[4] = sin(a), r[5] = cos(a);
  assert_true(vlff_kf_selector_offer(&x.s, 1000000000ll, r));
}

static void test_pose_valid(void **st) {
  (void)st;
  double p[16];
  ident(p, 1);
  assert_true(vlff_pose_valid(p));
  p[3] = NAN;
  assert_false(vlff_pose_valid(p));
  ident(p, 1);
  p[0] = 2; /* scaled axis */
  assert_false(vlff_pose_valid(p));
  ident(p, 1);
  p[0] = -1; /* reflection: det -1 */
  assert_false(vlff_pose_valid(p));
  ident(p, 1);
  p[14] = 1;
  assert_false(vlff_pose_valid(p));
}

static void test_posecheck(void **st) {
  (void)st;
  enum { N = 100 };
  float ren[N], meas[N];
  unsigned char hit[N];
  struct vlff_pose_evidence ev;
  /* With no sensor noise a residual is scaled by the floor alone. */
  for (int i = 0; i < N; i++) ren[i] = 2.0f, meas[i] = 2.02f, hit[i] = 1;
  meas[3] = 9; /* an outlier does not move the median */
  assert_int_equal(vlff_pose_evidence(ren, hit, meas, N, 0.2, 0.1, 0, &ev), VLFF_POSE_OK);
  assert_float_equal(ev.residual_m, 0.02, 1e-5);
  assert_float_equal(ev.residual, 0.2, 1e-4);
  assert_float_equal(ev.inlier_frac, 0.99, 1e-9);
  assert_int_equal(vlff_pose_verdict(&ev, 0, 0), VLFF_POSE_OK);
  /* Half the view 0.6 m off: far from what good frames show. */
  for (int i = 0; i < N; i++) meas[i] = i % 2 ? 2.6f : 2.02f;
  meas[0] = 2.6f;
  assert_int_equal(vlff_pose_evidence(ren, hit, meas, N, 0.2, 0.1, 0, &ev), VLFF_POSE_OK);
  assert_true(ev.residual_m > 0.5 && ev.residual > 5 && ev.inlier_frac < 0.5);
  assert_int_equal(vlff_pose_verdict(&ev, 1, 0.85), VLFF_POSE_BAD);
  /* The same evidence when good frames disagree as much: a young map. */
  assert_int_equal(vlff_pose_verdict(&ev, 5, 0.5), VLFF_POSE_OK);
  /* Without history only a gross residual is bad: 6 floors, not 2. */
  assert_int_equal(vlff_pose_verdict(&ev, 0, 0), VLFF_POSE_BAD);
  assert_int_equal(vlff_pose_evidence(ren, hit, meas, N, 0.2, 0.3, 0, &ev), VLFF_POSE_OK);
  assert_int_equal(vlff_pose_verdict(&ev, 0, 0), VLFF_POSE_OK);
  /* Within what a good frame shows is always fine. */
  ev.residual = 0.9;
  assert_int_equal(vlff_pose_verdict(&ev, 0.1, 0.99), VLFF_POSE_OK);
  /* Too little of the view is known to the map: no verdict. */
  for (int i = 0; i < N; i++) hit[i] = i < 10;
  assert_int_equal(vlff_pose_evidence(ren, hit, meas, N, 0.2, 0.1, 0, &ev), VLFF_POSE_UNKNOWN);
  assert_int_equal(vlff_pose_verdict(&ev, 1, 0.9), VLFF_POSE_UNKNOWN);
  /* Invalid measured depth is not evidence. */
  for (int i = 0; i < N; i++) hit[i] = 1, meas[i] = 0;
  assert_int_equal(vlff_pose_evidence(ren, hit, meas, N, 0.2, 0.1, 0, &ev), VLFF_POSE_UNKNOWN);
}

/* A stereo camera's noise grows with range squared: a good frame looking
 * down a 6 m sight line shows a median residual near 0.25 m, most of it the
 * sensor's. Judged in metres against near frames it looked like a wrong
 * pose; scaled by its range's noise it is a good frame, and a pose 1 m off
 * along the sight line is still refused. */
static void test_posecheck_far_view(void **st) {
  (void)st;
  enum { N = 2000 };
  static float ren[N], near_m[N], far_m[N], far_bad[N];
  static unsigned char hit[N];
  uint64_t seed = 12345;
  for (int i = 0; i < N; i++) {
    /* The sensor's and the map's errors. */
    double g[2] = {vlff_test_normal(&seed), vlff_test_normal(&seed)};
    hit[i] = 1;
    near_m[i] = (float)(1.5 + 0.01 * 1.5 * 1.5 * g[0] + 0.05 * g[1]);
    far_m[i] = (float)(6.0 + 0.01 * 36 * g[0] + 0.05 * g[1]);
    far_bad[i] = far_m[i] + 1.0f;
  }
  struct vlff_pose_evidence ev;
  /* The near frames a walk admitted before looking down the hall. */
  for (int i = 0; i < N; i++) ren[i] = 1.5f;
  assert_int_equal(vlff_pose_evidence(ren, hit, near_m, N, 0.2, 0.1, 0.01, &ev), VLFF_POSE_OK);
  double near_z = ev.residual, near_in = ev.inlier_frac;
  assert_true(near_z < 0.5 && near_in > 0.95);
  for (int i = 0; i < N; i++) ren[i] = 6.0f;
  /* Judged without the sensor's noise, the far good frame is refused. */
  assert_int_equal(vlff_pose_evidence(ren, hit, far_m, N, 0.2, 0.1, 0, &ev), VLFF_POSE_OK);
  assert_true(ev.residual_m > 0.2 && ev.residual_m < 0.3);
  assert_int_equal(vlff_pose_verdict(&ev, near_z, near_in), VLFF_POSE_BAD);
  /* With it, the same frame passes. */
  assert_int_equal(vlff_pose_evidence(ren, hit, far_m, N, 0.2, 0.1, 0.01, &ev), VLFF_POSE_OK);
  assert_true(ev.residual < 1 && ev.inlier_frac > 0.9);
  assert_int_equal(vlff_pose_verdict(&ev, near_z, near_in), VLFF_POSE_OK);
  /* A pose 1 m off along the sight line is still refused. */
  assert_int_equal(vlff_pose_evidence(ren, hit, far_bad, N, 0.2, 0.1, 0.01, &ev), VLFF_POSE_OK);
  assert_true(ev.residual > 1 && ev.inlier_frac < 0.8 * near_in);
  assert_int_equal(vlff_pose_verdict(&ev, near_z, near_in), VLFF_POSE_BAD);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_time_only), cmocka_unit_test(test_time_jitter), cmocka_unit_test(test_motion_required),
    cmocka_unit_test(test_pose_valid), cmocka_unit_test(test_posecheck),
    cmocka_unit_test(test_posecheck_far_view))
