/* The TUM line parser and the feed's checks: what becomes a pose record and
 * what is refused, counted and explained. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "tum.h"
#include "unit.h"

static char why[256];

/* Strict TUM: exactly eight fields. */
static int parse8(const char *line, struct vlff_tum_sample *s, char *w, size_t wl) {
  return vlff_tum_parse(line, 0, s, w, wl);
}

static void identity(double m[16]) {
  memset(m, 0, 16 * sizeof m[0]);
  m[0] = m[5] = m[10] = m[15] = 1;
}

static void feed_init(struct vlff_tum_feed *f, int stamp, int64_t offset_ns) {
  struct vlff_tum_feed_params p = {.stamp = stamp, .clock_offset_ns = offset_ns, .quat_tolerance = 0.01};
  identity(p.body_to_camera);
  assert_int_equal(vlff_tum_feed_init(f, &p, why, sizeof why), 0);
}

static void test_parse(void **state) {
  (void)state;
  struct vlff_tum_sample s;
  assert_int_equal(parse8("1305031102.175304 1.2334 -0.0113 1.6941 0.7907 0.4393 -0.1770 -0.3879\n", &s, why,
                                  sizeof why),
                   VLFF_TUM_OK);
  assert_true(s.t == 1305031102.175304);
  assert_true(s.p[0] == 1.2334 && s.p[2] == 1.6941);
  assert_true(s.q[0] == 0.7907 && s.q[3] == -0.3879);
  assert_true(s.t_ns == 1305031102175304000ll);
  /* Nanoseconds exact where a double is not. */
  assert_int_equal(parse8("9876543.123456789 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_OK);
  assert_true(s.t_ns == 9876543123456789ll);
  assert_int_equal(parse8("7 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_OK);
  assert_true(s.t_ns == 7000000000ll);
  assert_int_equal(parse8(".5 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_OK);
  assert_true(s.t_ns == 500000000ll);
  assert_int_equal(parse8("1e30 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  /* Tabs, leading blanks, exponent notation. */
  assert_int_equal(parse8("\t 2e0\t0 0 0  0 0 0 1", &s, why, sizeof why), VLFF_TUM_OK);
  assert_true(s.t == 2.0 && s.q[3] == 1);
  assert_true(s.t_ns == 2000000000ll);
  assert_int_equal(parse8("# timestamp tx ty tz qx qy qz qw\n", &s, why, sizeof why), VLFF_TUM_SKIP);
  assert_int_equal(parse8("   \n", &s, why, sizeof why), VLFF_TUM_SKIP);
  assert_int_equal(parse8("", &s, why, sizeof why), VLFF_TUM_SKIP);
  assert_int_equal(parse8("1 2 3 4 5 6 7", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_non_null(strstr(why, "7 fields, expected 8"));
  assert_int_equal(parse8("1 2 3 4 5 6 7 8 9", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_non_null(strstr(why, "more than 8"));
  /* OpenVINS' recorder appends covariances: ignored when asked. */
  assert_int_equal(vlff_tum_parse("1 2 3 4 0 0 0 1 0.1 0.2 0.3 0.4 0.5 0.6 0.7 0.8 0.9 1.0 1.1 1.2", 1, &s, why,
                                  sizeof why),
                   VLFF_TUM_OK);
  assert_true(s.p[2] == 4 && s.q[3] == 1);
  assert_int_equal(vlff_tum_parse("1 2 3 4 0 0 0 1 x", 1, &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8("1 2 3 x 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_non_null(strstr(why, "field 4 'x'"));
  /* bytes of the line are quoted escaped (vlff/escape.h): no raw ESC or quote */
  assert_int_equal(parse8("1 2 3 \x1b]0;t\x07'\xff 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_non_null(strstr(why, "field 4 '\\x1b]0;t\\x07\\'\\xff'"));
  assert_int_equal(parse8("1,2,3,4,0,0,0,1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8("1 2 3 4m 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8("1 nan 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_NOT_FINITE);
  assert_non_null(strstr(why, "tx is nan"));
  assert_int_equal(parse8("1 0 0 0 0 0 0 inf", &s, why, sizeof why), VLFF_TUM_NOT_FINITE);
  assert_int_equal(parse8("1 0 0 0 0 0 0 1e999", &s, why, sizeof why), VLFF_TUM_NOT_FINITE);
  /* finite but no tracker's: 1e300 m was written into the ring, and an
   * extrinsic's offset on top of 1.7e308 made it infinite */
  assert_int_equal(parse8("1 1e300 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_FAR);
  assert_string_equal(why, "tx is 1e+300 m, beyond 1e+07 m");
  assert_int_equal(parse8("1 0 0 -1.7e308 0 0 0 1", &s, why, sizeof why), VLFF_TUM_FAR);
  assert_int_equal(parse8("1 6378137 0 -9999999 0 0 0 1", &s, why, sizeof why), VLFF_TUM_OK); /* Earth-centred */
  assert_string_equal(vlff_tum_result_name(VLFF_TUM_FAR), "position out of range");
}

/* The matrix of a quaternion rotates as the quaternion does. */
static void test_matrix(void **state) {
  (void)state;
  double m[16];
  /* 90 degrees about z: x -> y. */
  double q[4] = {0, 0, sin(M_PI / 4), cos(M_PI / 4)}, p[3] = {1, 2, 3};
  vlff_tum_matrix(p, q, m);
  assert_true(fabs(m[0]) < 1e-12 && fabs(m[4] - 1) < 1e-12 && fabs(m[8]) < 1e-12); /* first column = R x */
  assert_true(fabs(m[1] + 1) < 1e-12);
  assert_true(m[3] == 1 && m[7] == 2 && m[11] == 3 && m[15] == 1 && m[12] == 0);
}

static void test_feed_checks(void **state) {
  (void)state;
  struct vlff_tum_feed f;
  struct vlff_pose_rec r;
  feed_init(&f, VLFF_TUM_STAMP_SOURCE, 1000000000);
  assert_int_equal(vlff_tum_feed_line(&f, "# header", 0, &r, why, sizeof why), VLFF_TUM_SKIP);
  assert_int_equal(vlff_tum_feed_line(&f, "10.5 1 2 3 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_true(r.t_ns == 11500000000ull); /* t + the clock offset */
  assert_true(r.pose[3] == 1 && r.pose[7] == 2 && r.pose[11] == 3 && r.pose[0] == 1);
  assert_int_equal(vlff_tum_feed_line(&f, "10.5 1 2 3 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_DUPLICATE);
  assert_int_equal(vlff_tum_feed_line(&f, "10.4 1 2 3 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OUT_OF_ORDER);
  assert_non_null(strstr(why, "before the previous line's"));
  /* Slightly off unit: normalised. Clearly off: refused. */
  assert_int_equal(vlff_tum_feed_line(&f, "10.6 0 0 0 0 0 0 1.004", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_true(fabs(r.pose[0] - 1) < 1e-12 && fabs(r.pose[5] - 1) < 1e-12);
  assert_int_equal(vlff_tum_feed_line(&f, "10.7 0 0 0 0 0 0 1.5", 0, &r, why, sizeof why), VLFF_TUM_BAD_QUATERNION);
  assert_non_null(strstr(why, "norm 1.500000"));
  assert_int_equal(vlff_tum_feed_line(&f, "10.7 0 0 0 0 0 0 0", 0, &r, why, sizeof why), VLFF_TUM_BAD_QUATERNION);
  assert_int_equal(vlff_tum_feed_line(&f, "10.7 0 0 nan 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_NOT_FINITE);
  assert_int_equal(vlff_tum_feed_line(&f, "10.7 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(vlff_tum_feed_line(&f, "-5 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OUT_OF_ORDER);
  /* Refused lines do not move the order: 10.65 follows the accepted 10.6. */
  assert_int_equal(vlff_tum_feed_line(&f, "10.65 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_int_equal(f.accepted, 3);
  assert_int_equal(f.refused[VLFF_TUM_DUPLICATE], 1);
  assert_int_equal(f.refused[VLFF_TUM_OUT_OF_ORDER], 2);
  assert_int_equal(f.refused[VLFF_TUM_BAD_QUATERNION], 2);
  assert_int_equal(f.refused[VLFF_TUM_NOT_FINITE], 1);
  assert_int_equal(f.refused[VLFF_TUM_MALFORMED], 1);
  assert_int_equal(vlff_tum_feed_refused(&f), 7);
  assert_string_equal(vlff_tum_result_name(VLFF_TUM_OUT_OF_ORDER), "out of order");

  /* One nanosecond apart at a long uptime: in order, not duplicates. */
  feed_init(&f, VLFF_TUM_STAMP_SOURCE, 0);
  assert_int_equal(vlff_tum_feed_line(&f, "9876543.123456789 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_true(r.t_ns == 9876543123456789ull);
  assert_int_equal(vlff_tum_feed_line(&f, "9876543.123456790 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_true(r.t_ns == 9876543123456790ull);
  assert_int_equal(vlff_tum_feed_line(&f, "9876543.12345679 0 0 0 0 0 0 1", 0, &r, why, sizeof why),
                   VLFF_TUM_DUPLICATE);

  /* A stamp that lands before the clock's zero after the offset. */
  feed_init(&f, VLFF_TUM_STAMP_SOURCE, -20000000000);
  assert_int_equal(vlff_tum_feed_line(&f, "10 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_BAD_STAMP);
}

/* Host stamping: receipt time minus the latency, strictly increasing. */
static void test_feed_host_stamps(void **state) {
  (void)state;
  struct vlff_tum_feed_params p = {.stamp = VLFF_TUM_STAMP_HOST, .latency_ns = 30000000, .quat_tolerance = 0.01};
  identity(p.body_to_camera);
  struct vlff_tum_feed f;
  assert_int_equal(vlff_tum_feed_init(&f, &p, why, sizeof why), 0);
  struct vlff_pose_rec r;
  assert_int_equal(vlff_tum_feed_line(&f, "1 0 0 0 0 0 0 1", 5000000000ull, &r, why, sizeof why), VLFF_TUM_OK);
  assert_true(r.t_ns == 4970000000ull);
  assert_int_equal(vlff_tum_feed_line(&f, "2 0 0 0 0 0 0 1", 5000000000ull, &r, why, sizeof why), VLFF_TUM_OK);
  assert_true(r.t_ns == 4970000001ull);
  /* The line's own stamps are still checked for order. */
  assert_int_equal(vlff_tum_feed_line(&f, "1.5 0 0 0 0 0 0 1", 6000000000ull, &r, why, sizeof why),
                   VLFF_TUM_OUT_OF_ORDER);
}

/* A tracker reporting its body's (IMU's) pose: the record is the camera's. */
static void test_feed_extrinsic(void **state) {
  (void)state;
  struct vlff_tum_feed_params p = {.quat_tolerance = 0.01};
  /* Camera 0.1 m along the body's x, rotated 90 degrees about the body's z. */
  double q[4] = {0, 0, sin(M_PI / 4), cos(M_PI / 4)}, t[3] = {0.1, 0, 0};
  vlff_tum_matrix(t, q, p.body_to_camera);
  struct vlff_tum_feed f;
  assert_int_equal(vlff_tum_feed_init(&f, &p, why, sizeof why), 0);
  struct vlff_pose_rec r;
  /* Body at (1, 0, 0) turned 90 degrees about z: its x axis is the world's y. */
  char line[128];
  snprintf(line, sizeof line, "1 1 0 0 0 0 %.17g %.17g", sin(M_PI / 4), cos(M_PI / 4));
  assert_int_equal(vlff_tum_feed_line(&f, line, 0, &r, why, sizeof why), VLFF_TUM_OK);
  /* The camera sits 0.1 m along the world's y from the body, turned 180 degrees. */
  assert_true(fabs(r.pose[3] - 1) < 1e-12 && fabs(r.pose[7] - 0.1) < 1e-12 && fabs(r.pose[11]) < 1e-12);
  assert_true(fabs(r.pose[0] + 1) < 1e-12 && fabs(r.pose[5] + 1) < 1e-12 && fabs(r.pose[10] - 1) < 1e-12);
  /* A non-rigid extrinsic is refused at init. */
  p.body_to_camera[0] = 2;
  assert_int_equal(vlff_tum_feed_init(&f, &p, why, sizeof why), -1);
  assert_non_null(strstr(why, "not a rigid transform"));
}

/* Plain decimals only: strtod(3) would read "0x10" as 16 s and "0x1p-2" as
 * 0.25; words for non-finite values are not finite, not malformed. */
static void test_parse_decimal_only(void **state) {
  (void)state;
  struct vlff_tum_sample s;
  assert_int_equal(parse8("0x10 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_non_null(strstr(why, "field 1 '0x10' is not a decimal number"));
  assert_int_equal(parse8("0X10 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8("1 0x1p-2 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_non_null(strstr(why, "field 2 '0x1p-2'"));
  assert_int_equal(parse8("1 0 0 0 0 0 0 0x1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8("1e 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8("1.5e+ 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8(". 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8("nan(1) 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8("infinite 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(parse8("inf 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_NOT_FINITE);
  assert_non_null(strstr(why, "t is inf"));
  assert_int_equal(parse8("1 -Infinity 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_NOT_FINITE);
  assert_non_null(strstr(why, "tx is -inf"));
  assert_int_equal(parse8("1 0 0 0 0 0 0 -NaN", &s, why, sizeof why), VLFF_TUM_NOT_FINITE);
  assert_int_equal(parse8("+1.25 -2 3. .5 0 0 0 1E0", &s, why, sizeof why), VLFF_TUM_OK);
  assert_true(s.t == 1.25 && s.p[0] == -2 && s.p[1] == 3 && s.p[2] == 0.5 && s.q[3] == 1);
  assert_int_equal(parse8("1.5e-3 0 0 0 0 0 0 1", &s, why, sizeof why), VLFF_TUM_OK);
  assert_true(s.t_ns == 1500000);
}

/* A NUL inside the line (the reader's length says where the line ends), and
 * a line of 64 KiB or more: refused and counted, never parsed. */
static void test_feed_nul_and_long(void **state) {
  (void)state;
  struct vlff_tum_feed f;
  struct vlff_pose_rec r;
  feed_init(&f, VLFF_TUM_STAMP_SOURCE, 0);
  static const char nul[] = "1.0 0 0 0 0 0 0 1\0\n2.0 0 0 0 0 0 0 1";
  assert_int_equal(vlff_tum_feed_buf(&f, nul, sizeof nul - 1, 0, &r, why, sizeof why), VLFF_TUM_NUL);
  assert_non_null(strstr(why, "NUL byte at column 18"));
  assert_int_equal(vlff_tum_feed_buf(&f, "\0", 1, 0, &r, why, sizeof why), VLFF_TUM_NUL);
  static char big[70 * 1024 + 1];
  memset(big, '7', sizeof big - 1);
  assert_int_equal(vlff_tum_feed_buf(&f, big, sizeof big - 1, 0, &r, why, sizeof why), VLFF_TUM_TOO_LONG);
  assert_non_null(strstr(why, "65536 bytes or more"));
  /* One byte under the limit is parsed (and malformed: one long field). */
  big[VLFF_TUM_LINE_MAX - 1] = 0;
  assert_int_equal(vlff_tum_feed_buf(&f, big, VLFF_TUM_LINE_MAX - 1, 0, &r, why, sizeof why), VLFF_TUM_MALFORMED);
  assert_int_equal(vlff_tum_feed_line(&f, "1.0 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_int_equal(f.refused[VLFF_TUM_NUL], 2);
  assert_int_equal(f.refused[VLFF_TUM_TOO_LONG], 1);
  assert_int_equal(f.refused[VLFF_TUM_MALFORMED], 1);
  vlff_tum_feed_count(&f, VLFF_TUM_FOREIGN);
  vlff_tum_feed_count(&f, VLFF_TUM_OK); /* not a refusal: ignored */
  assert_int_equal(f.refused[VLFF_TUM_FOREIGN], 1);
  assert_int_equal(vlff_tum_feed_refused(&f), 5);
  assert_string_equal(vlff_tum_result_name(VLFF_TUM_NUL), "NUL byte");
  assert_string_equal(vlff_tum_result_name(VLFF_TUM_TOO_LONG), "too long");
  assert_string_equal(vlff_tum_result_name(VLFF_TUM_FOREIGN), "foreign sender");
  assert_string_equal(vlff_tum_result_name(VLFF_TUM_CLOCK), "clock error");
}

/* Stamps ahead of the clock by more than the tolerance are a clock error;
 * a refused one does not move the order. */
static void test_feed_future(void **state) {
  (void)state;
  struct vlff_tum_feed_params p = {.clock_offset_ns = 0, .quat_tolerance = 0.01, .future_tolerance_ns = 5000000000};
  identity(p.body_to_camera);
  struct vlff_tum_feed f;
  assert_int_equal(vlff_tum_feed_init(&f, &p, why, sizeof why), 0);
  struct vlff_pose_rec r;
  const uint64_t now = 1000000000000ull; /* 1000 s */
  assert_int_equal(vlff_tum_feed_line(&f, "999.5 0 0 0 0 0 0 1", now, &r, why, sizeof why), VLFF_TUM_OK);
  assert_int_equal(vlff_tum_feed_line(&f, "2000000 0 0 0 0 0 0 1", now, &r, why, sizeof why), VLFF_TUM_CLOCK);
  assert_non_null(strstr(why, "ahead of the clock"));
  assert_int_equal(vlff_tum_feed_line(&f, "1005.000000001 0 0 0 0 0 0 1", now, &r, why, sizeof why),
                   VLFF_TUM_CLOCK);
  /* The tracker's next line follows its last accepted one, not the forgery. */
  assert_int_equal(vlff_tum_feed_line(&f, "999.6 0 0 0 0 0 0 1", now, &r, why, sizeof why), VLFF_TUM_OK);
  assert_int_equal(vlff_tum_feed_line(&f, "1005 0 0 0 0 0 0 1", now, &r, why, sizeof why), VLFF_TUM_OK);
  assert_int_equal(f.refused[VLFF_TUM_CLOCK], 2);
  /* The offset counts: the record's stamp is what is checked. */
  p.clock_offset_ns = -1000000000000;
  assert_int_equal(vlff_tum_feed_init(&f, &p, why, sizeof why), 0);
  assert_int_equal(vlff_tum_feed_line(&f, "2004 0 0 0 0 0 0 1", now, &r, why, sizeof why), VLFF_TUM_OK);
  assert_int_equal(vlff_tum_feed_line(&f, "2006 0 0 0 0 0 0 1", now, &r, why, sizeof why), VLFF_TUM_CLOCK);
  /* Host stamps are the clock itself: the lines' stamps only order them. */
  p.stamp = VLFF_TUM_STAMP_HOST;
  assert_int_equal(vlff_tum_feed_init(&f, &p, why, sizeof why), 0);
  assert_int_equal(vlff_tum_feed_line(&f, "1e9 0 0 0 0 0 0 1", now, &r, why, sizeof why), VLFF_TUM_OK);
}

/* A stream that stays older than its last accepted line restarts: the
 * out_of_order_reset-th line in a row is taken, and the order goes on from
 * it. Without the setting a line forged ahead locks every later one out. */
static void test_feed_out_of_order_reset(void **state) {
  (void)state;
  struct vlff_tum_feed_params p = {.quat_tolerance = 0.01, .out_of_order_reset = 10};
  identity(p.body_to_camera);
  struct vlff_tum_feed f;
  assert_int_equal(vlff_tum_feed_init(&f, &p, why, sizeof why), 0);
  struct vlff_pose_rec r;
  char line[64];
  assert_int_equal(vlff_tum_feed_line(&f, "100 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_int_equal(vlff_tum_feed_line(&f, "1000000 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  for (int i = 1; i <= 9; i++) {
    snprintf(line, sizeof line, "%d.5 0 0 0 0 0 0 1", 100 + i);
    assert_int_equal(vlff_tum_feed_line(&f, line, 0, &r, why, sizeof why), VLFF_TUM_OUT_OF_ORDER);
    /* a duplicate or a malformed line neither extends nor ends the run */
    assert_int_equal(vlff_tum_feed_line(&f, "1000000 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_DUPLICATE);
    assert_int_equal(vlff_tum_feed_line(&f, "1 2 3", 0, &r, why, sizeof why), VLFF_TUM_MALFORMED);
  }
  assert_int_equal(f.resets, 0);
  assert_int_equal(vlff_tum_feed_line(&f, "110.5 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_true(r.t_ns == 110500000000ull);
  assert_int_equal(f.resets, 1);
  assert_true(f.reset_from_t_ns == 1000000000000000ll);
  assert_int_equal(vlff_tum_feed_line(&f, "110.6 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_int_equal(vlff_tum_feed_line(&f, "110.55 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OUT_OF_ORDER);
  assert_int_equal(f.out_of_order_run, 1);
  assert_int_equal(vlff_tum_feed_line(&f, "110.7 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  assert_int_equal(f.out_of_order_run, 0);
  assert_int_equal(f.refused[VLFF_TUM_OUT_OF_ORDER], 10);
  assert_int_equal(f.accepted, 5);

  /* 0: never (the order is the order). */
  p.out_of_order_reset = 0;
  assert_int_equal(vlff_tum_feed_init(&f, &p, why, sizeof why), 0);
  assert_int_equal(vlff_tum_feed_line(&f, "1000000 0 0 0 0 0 0 1", 0, &r, why, sizeof why), VLFF_TUM_OK);
  for (int i = 0; i < 50; i++) {
    snprintf(line, sizeof line, "%d 0 0 0 0 0 0 1", 100 + i);
    assert_int_equal(vlff_tum_feed_line(&f, line, 0, &r, why, sizeof why), VLFF_TUM_OUT_OF_ORDER);
  }
  assert_int_equal(f.resets, 0);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_parse), cmocka_unit_test(test_matrix),
    cmocka_unit_test(test_feed_checks), cmocka_unit_test(test_feed_host_stamps),
    cmocka_unit_test(test_feed_extrinsic), cmocka_unit_test(test_parse_decimal_only),
    cmocka_unit_test(test_feed_nul_and_long), cmocka_unit_test(test_feed_future),
    cmocka_unit_test(test_feed_out_of_order_reset))
