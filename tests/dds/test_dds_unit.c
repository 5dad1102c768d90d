/* SPDX-License-Identifier: BSD-3-Clause */
/* vlff-dds's pure parts (dds.h): topic names, the prompt message rule and
 * the point cloud's payload, without a network. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <cmocka.h>

#include "dds.h"
#include "merge.h"

static void test_topic(void **state) {
  (void)state;
  char t[64];
  assert_int_equal(vlff_dds_topic(t, sizeof t, "", "map"), 0);
  assert_string_equal(t, "rt/vlff/map");
  assert_int_equal(vlff_dds_topic(t, sizeof t, "/fleet/robot1", "status"), 0);
  assert_string_equal(t, "rt/fleet/robot1/vlff/status");
  assert_int_equal(vlff_dds_topic(t, 12, "/robot1", "map"), -1);
  /* by id: the image topics as ROS's image_transport names them, the pose
   * on the namespace's tf */
  assert_int_equal(vlff_dds_topic_of(t, sizeof t, "/r1", VLFF_DDS_CAMERA_IMAGE_COMPRESSED), 0);
  assert_string_equal(t, "rt/r1/vlff/camera/image_raw/compressed");
  assert_int_equal(vlff_dds_topic_of(t, sizeof t, "/r1", VLFF_DDS_CAMERA_INFO), 0);
  assert_string_equal(t, "rt/r1/vlff/camera/camera_info");
  assert_int_equal(vlff_dds_topic_of(t, sizeof t, "/r1", VLFF_DDS_TF), 0);
  assert_string_equal(t, "rt/r1/tf");
  assert_int_equal(vlff_dds_topic_of(t, sizeof t, "", VLFF_DDS_TF), 0);
  assert_string_equal(t, "rt/tf");
  assert_int_equal(vlff_dds_topic_of(t, sizeof t, "", VLFF_DDS_NTOPICS), -1);
  assert_string_equal(vlff_dds_topic_key(VLFF_DDS_LABEL_IMAGE_COMPRESSED), "label_image_compressed");
  assert_null(vlff_dds_topic_key(-1));
}

/* sensor_msgs/image_encodings names; depth formats have none here. */
static void test_encoding(void **state) {
  (void)state;
  assert_string_equal(vlff_dds_encoding(VLFF_PIX_RGB8), "rgb8");
  assert_string_equal(vlff_dds_encoding(VLFF_PIX_MONO16), "mono16");
  assert_string_equal(vlff_dds_encoding(VLFF_PIX_BAYER_RG8), "bayer_rggb8");
  assert_string_equal(vlff_dds_encoding(VLFF_PIX_BAYER_GB8), "bayer_gbrg8");
  assert_null(vlff_dds_encoding(VLFF_PIX_DEPTH_F32_M));
  assert_null(vlff_dds_encoding(999));
}

static int parse(const char *s, int *invalid, char *why) {
  static char texts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
  int idx;
  return vlff_dds_parse_prompts(s, strlen(s), texts, &idx, invalid, why, 256);
}

/* The rule of vlff-shm set-prompts (vlff_prompt_check), after JSON. */
static void test_prompts(void **state) {
  (void)state;
  static char texts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
  char why[256];
  int invalid, idx;
  const char *ok = "[\"chair\", \"table\", \"caf\\u00e9\"]";
  assert_int_equal(vlff_dds_parse_prompts(ok, strlen(ok), texts, &idx, &invalid, why, sizeof why), 3);
  assert_string_equal(texts[2], "caf\xc3\xa9");
  assert_int_equal(idx, -1);
  /* A configured set by index, as vlff-shm set-prompts -i. */
  assert_int_equal(vlff_dds_parse_prompts("2", 1, texts, &idx, &invalid, why, sizeof why), 0);
  assert_int_equal(idx, 2);
  static const struct {
    const char *msg, *why;
    int invalid;
  } bad[] = {
      {"chair", "not JSON", 0},
      {"[\"chair\"] x", "not JSON", 0},
      {"[\"chair\"", "not JSON", 0},
      {"{\"a\": 1}", "got a JSON object", 0},
      {"2.5", "got a JSON double", 0},
      {"-1", "expected a prompt set index in 0..2147483647", 1},
      {"2147483648", "expected a prompt set index", 1},
      {"\"chair\"", "got a JSON string", 0},
      {"[\"chair\", 3]", "prompt 1: expected a JSON string, got a JSON int", 0},
      {"[[[[[[\"deep\"]]]]]]", "not JSON", 0},
      {"[]", "expected 1 to 32 prompts, got 0", 1},
      {"[\"a\", \"a\"]", "repeats", 1},
      {"[\"\"]", "", 1},
      {"[\"tab\\there\"]", "control", 1},
      {"[\"nul\\u0000cut\"]", "without NUL", 1},
      {"[\"0123456789012345678901234567890123456789012345678901234567890123\"]", "1 to 63 bytes", 1},
  };
  for (size_t i = 0; i < sizeof bad / sizeof bad[0]; i++) {
    why[0] = 0;
    int n = parse(bad[i].msg, &invalid, why);
    if (n != -1 || invalid != bad[i].invalid || !strstr(why, bad[i].why))
      fail_msg("%s: got %d invalid %d '%s', expected -1 invalid %d '%s'", bad[i].msg, n, invalid, why, bad[i].invalid,
               bad[i].why);
  }
  /* 33 prompts: one over the mailbox's table. */
  char many[33 * 8 + 8] = "[";
  for (int i = 0; i < 33; i++) sprintf(many + strlen(many), "%s\"p%02d\"", i ? "," : "", i);
  strcat(many, "]");
  assert_int_equal(parse(many, &invalid, why), -1);
  assert_int_equal(invalid, 1);
}

static float f32_at(const uint8_t *p) {
  uint32_t u = (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
  float f;
  memcpy(&f, &u, 4);
  return f;
}

/* One point per labelled voxel, at its centre, little-endian, free and
 * unknown voxels left out. */
static void test_cloud(void **state) {
  (void)state;
  uint16_t labels[2 * 3 * 2] = {0};
  uint8_t conf[12] = {0};
  for (int i = 0; i < 12; i++) labels[i] = i % 3 == 0 ? VLFF_LABEL_FREE : i % 3 == 1 ? VLFF_LABEL_UNKNOWN : 0x0102;
  labels[11] = 7;
  conf[11] = 51;
  struct vlff_map_info in = {0};
  in.grid = (struct vlff_map_grid){{1, -2, 0.5}, 0.5, {2, 3, 2}, labels, conf};
  uint8_t *d;
  uint32_t n;
  assert_int_equal(vlff_dds_cloud(&in, &d, &n), 0);
  assert_int_equal(n, 4); /* indices 2, 5, 8, 11 */
  const uint8_t *last = d + 3 * VLFF_DDS_POINT_STEP;
  /* index 11 = (1, 2, 1) */
  assert_float_equal(f32_at(last), 1 + 1.5 * 0.5, 1e-6);
  assert_float_equal(f32_at(last + 4), -2 + 2.5 * 0.5, 1e-6);
  assert_float_equal(f32_at(last + 8), 0.5 + 1.5 * 0.5, 1e-6);
  assert_int_equal(last[12] | last[13] << 8, 7);
  assert_float_equal(f32_at(last + 16), 0.2, 1e-6);
  assert_int_equal(d[12], 0x02);
  assert_int_equal(d[13], 0x01);
  free(d);
  in.grid.confidence = NULL; /* all 255 */
  assert_int_equal(vlff_dds_cloud(&in, &d, &n), 0);
  assert_float_equal(f32_at(d + 16), 1.0, 0);
  free(d);
}

/* One point of vlff-dds's layout. */
static void put_point(uint8_t *p, float x, float y, float z, uint16_t label, float conf) {
  memcpy(p, &x, 4), memcpy(p + 4, &y, 4), memcpy(p + 8, &z, 4);
  p[12] = (uint8_t)label, p[13] = (uint8_t)(label >> 8), p[14] = p[15] = 0;
  memcpy(p + 16, &conf, 4);
}

static const char *const names[5] = {"x", "y", "z", "label", "confidence"};
static const uint32_t offs[5] = {0, 4, 8, 12, 16};
static const uint8_t types[5] = {VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32, VLFF_DDS_UINT16, VLFF_DDS_FLOAT32};

/* Robots' clouds: what is refused, and the merge by confidence, then recency,
 * in the world frame of each robot's transform. */
static void test_merge(void **state) {
  (void)state;
  static struct vlff_merge_robot r[2];
  memset(r, 0, sizeof r);
  char why[256];
  uint8_t d[3 * 20];
  put_point(d, 0.05f, 0.05f, 0.05f, 0, 0.5f);
  put_point(d + 20, 0.15f, 0.05f, 0.05f, 1, 1.0f);
  put_point(d + 40, 0.05f, 0.15f, 0.05f, 1, 0.2f);
  r[0].nprompts = r[1].nprompts = -1;
  /* refused whole: another layout, a short buffer, a NaN, a confidence > 1 */
  const uint8_t bad_types[5] = {VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32};
  assert_int_equal(vlff_merge_take_cloud(&r[0], 3, 1, 20, false, names, offs, bad_types, 5, d, sizeof d, 1, why, sizeof why), -1);
  assert_non_null(strstr(why, "field 3"));
  assert_int_equal(vlff_merge_take_cloud(&r[0], 3, 1, 20, true, names, offs, types, 5, d, sizeof d, 1, why, sizeof why), -1);
  assert_int_equal(vlff_merge_take_cloud(&r[0], 4, 1, 20, false, names, offs, types, 5, d, sizeof d, 1, why, sizeof why), -1);
  uint8_t nan[20];
  put_point(nan, NAN, 0, 0, 0, 0.5f);
  assert_int_equal(vlff_merge_take_cloud(&r[0], 1, 1, 20, false, names, offs, types, 5, nan, 20, 1, why, sizeof why), -1);
  put_point(nan, 0, 0, 0, 0, 1.5f);
  assert_int_equal(vlff_merge_take_cloud(&r[0], 1, 1, 20, false, names, offs, types, 5, nan, 20, 1, why, sizeof why), -1);
  assert_null(r[0].xyz);
  assert_int_equal(vlff_merge_take_cloud(&r[0], 3, 1, 20, false, names, offs, types, 5, d, sizeof d, 100, why, sizeof why), 0);
  /* robot 1: turned 90 degrees, its points land on robot 0's */
  uint8_t e[2 * 20];
  put_point(e, 0.05f, -0.05f, 0.05f, 0, 0.5f); /* same confidence, more recent: wins */
  put_point(e + 20, 0.05f, -0.15f, 0.05f, 1, 0.9f); /* onto robot 0's 0.15,0.05 (1.0): loses */
  assert_int_equal(vlff_merge_take_cloud(&r[1], 2, 1, 20, false, names, offs, types, 5, e, sizeof e, 200, why, sizeof why), 0);
  r[1].yaw = 3.14159265358979323846 / 2, r[1].t[2] = 0.01; /* (x, y) -> (-y, x), 1 cm up */
  r[0].nprompts = 2, r[1].nprompts = 2;
  strcpy(r[0].prompts[0], "chair"), strcpy(r[0].prompts[1], "table");
  strcpy(r[1].prompts[0], "door"), strcpy(r[1].prompts[1], "table");
  static struct vlff_merge_grid g;
  const double lo[3] = {0, 0, 0}, hi[3] = {1, 1, 1}, huge[3] = {1e4, 1e4, 1e4};
  assert_int_equal(vlff_merge_grid_init(&g, lo, huge, 0.01, why, sizeof why), -1);
  assert_non_null(strstr(why, "more than"));
  assert_int_equal(vlff_merge_grid_init(&g, lo, hi, 0.1, why, sizeof why), 0);
  assert_int_equal(vlff_merge_compute(&g, r, 2), 3);
  assert_int_equal(g.nprompts, 3); /* chair table door */
  assert_string_equal(g.prompts[2], "door");
  assert_int_equal(g.labels[0], 2);          /* robot 1's door: equal confidence, newer */
  assert_int_equal(g.labels[1], 1);          /* robot 0's table at 1.0 over robot 1's 0.9 */
  assert_int_equal(g.conf[1], 255);
  assert_int_equal(g.labels[10], 1);         /* 0.05,0.15: robot 0's only */
  assert_int_equal(g.labels[2], VLFF_LABEL_UNKNOWN);
  r[1].stamp_ns = 50; /* older now: robot 0's chair wins the tie */
  vlff_merge_compute(&g, r, 2);
  assert_int_equal(g.labels[0], 0);
  vlff_merge_grid_free(&g);
  vlff_merge_robot_free(&r[0]);
  vlff_merge_robot_free(&r[1]);
}

/* A robot's updates (map/updates) applied to its whole map: relabel, clear,
 * add at the same positions; older ones skipped; a malformed one refused
 * whole. */
static void test_merge_update(void **state) {
  (void)state;
  static struct vlff_merge_robot r;
  memset(&r, 0, sizeof r);
  r.nprompts = 2;
  strcpy(r.prompts[0], "chair"), strcpy(r.prompts[1], "table");
  char why[256];
  static const char *const un[6] = {"x", "y", "z", "label", "confidence", "version"};
  static const uint32_t uo[6] = {0, 4, 8, 12, 16, 20};
  static const uint8_t ut[6] = {VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32,
                                VLFF_DDS_UINT16,  VLFF_DDS_FLOAT32, VLFF_DDS_UINT32};
  uint8_t d[2 * 20];
  put_point(d, 0.05f, 0.05f, 0.05f, 0, 0.5f);
  put_point(d + 20, 0.15f, 0.05f, 0.05f, 1, 1.0f);
  uint8_t u[3 * 24] = {0};
  put_point(u, 0.05f, 0.05f, 0.05f, VLFF_LABEL_FREE, 0.1f); /* clears the chair */
  put_point(u + 24, 0.15f, 0.05f, 0.05f, 0, 0.75f);          /* the table becomes a chair */
  put_point(u + 48, 0.25f, 0.05f, 0.05f, 1, 0.5f);           /* a new table */
  /* no whole map held yet: skipped */
  assert_int_equal(vlff_merge_take_update(&r, 3, 1, 24, false, un, uo, ut, 6, u, sizeof u, 150, why, sizeof why), 0);
  assert_int_equal(vlff_merge_take_cloud(&r, 2, 1, 20, false, names, offs, types, 5, d, sizeof d, 100, why, sizeof why), 0);
  /* refused whole: a map's layout, a label beyond the list */
  assert_int_equal(vlff_merge_take_update(&r, 3, 1, 24, false, names, offs, types, 5, u, sizeof u, 150, why, sizeof why), -1);
  assert_non_null(strstr(why, "6 fields"));
  uint8_t bad[2 * 24] = {0};
  put_point(bad, 0.35f, 0.05f, 0.05f, 1, 0.5f);
  put_point(bad + 24, 0.45f, 0.05f, 0.05f, 7, 0.5f);
  assert_int_equal(vlff_merge_take_update(&r, 2, 1, 24, false, un, uo, ut, 6, bad, sizeof bad, 150, why, sizeof why), -1);
  assert_int_equal(r.n, 2);
  /* older than the whole map: held already */
  assert_int_equal(vlff_merge_take_update(&r, 3, 1, 24, false, un, uo, ut, 6, u, sizeof u, 90, why, sizeof why), 0);
  assert_int_equal(vlff_merge_take_update(&r, 3, 1, 24, false, un, uo, ut, 6, u, sizeof u, 150, why, sizeof why), 1);
  assert_int_equal(r.stamp_ns, 150);
  static struct vlff_merge_grid g;
  const double lo[3] = {0, 0, 0}, hi[3] = {1, 1, 1};
  assert_int_equal(vlff_merge_grid_init(&g, lo, hi, 0.1, why, sizeof why), 0);
  assert_int_equal(vlff_merge_compute(&g, &r, 1), 2);
  assert_int_equal(g.labels[0], VLFF_LABEL_UNKNOWN); /* cleared */
  assert_string_equal(g.prompts[g.labels[1]], "chair");
  assert_int_equal(g.conf[1], 191);
  assert_string_equal(g.prompts[g.labels[2]], "table");
  /* a whole map older than the update: what is held is newer */
  assert_int_equal(vlff_merge_take_cloud(&r, 2, 1, 20, false, names, offs, types, 5, d, sizeof d, 120, why, sizeof why), 0);
  assert_int_equal(vlff_merge_compute(&g, &r, 1), 2);
  assert_int_equal(g.labels[0], VLFF_LABEL_UNKNOWN);
  /* many new points: the index grows */
  static uint8_t many[500 * 24];
  for (int i = 0; i < 500; i++) put_point(many + 24 * i, 0.05f + 0.1f * (float)(i % 10), 0.05f + 0.1f * (float)(i / 10 % 10), 0.05f + 0.1f * (float)(i / 100), 1, 0.25f);
  assert_int_equal(vlff_merge_take_update(&r, 500, 1, 24, false, un, uo, ut, 6, many, sizeof many, 200, why, sizeof why), 1);
  assert_int_equal(r.n, 500);
  assert_int_equal(vlff_merge_compute(&g, &r, 1), 500);
  vlff_merge_grid_free(&g);
  vlff_merge_robot_free(&r);
}

int main(void) {
  const struct CMUnitTest tests[] = {cmocka_unit_test(test_topic), cmocka_unit_test(test_prompts), cmocka_unit_test(test_encoding), cmocka_unit_test(test_merge), cmocka_unit_test(test_merge_update),
                                     cmocka_unit_test(test_cloud)};
  return cmocka_run_group_tests(tests, NULL, NULL);
}
