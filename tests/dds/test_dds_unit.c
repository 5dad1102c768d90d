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
  assert_int_equal(vlff_dds_cloud(&in, NULL, 0, &d, &n, NULL), 0);
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
  assert_int_equal(vlff_dds_cloud(&in, NULL, 0, &d, &n, NULL), 0);
  assert_float_equal(f32_at(d + 16), 1.0, 0);
  free(d);
  /* beside the grid, its far map (what the window left as the robot went
   * on): a block of class 3 beyond it, and a block the grid lies in, whose
   * voxels the grid covers are the grid's (stale there), free and unknown
   * ones left out */
  const struct vlff_map_far_block blocks[2] = {{{-1, 0, 0}, 0}, {{0, 0, 0}, 1}};
  const uint16_t E3 = VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE;
  const struct vlff_map_far_run runs[5] = {{3, E3, 40, 0},
                                           {5, 1, 9, 0},
                                           {VLFF_LABEL_FREE, 1, 0, 0},
                                           {9, 2, 102, 0},
                                           {VLFF_LABEL_UNKNOWN, (uint16_t)(E3 - 4), 0, 0}};
  struct vlff_map_far far = {{1, -2, 0.5}, 0.5, 2, 5, blocks, runs};
  assert_null(vlff_map_far_check(&far));
  assert_int_equal(vlff_dds_cloud(&in, &far, 1 << 20, &d, &n, NULL), 0);
  assert_int_equal(n, 4 + E3 + 2);
  const uint8_t *p = d + 4 * VLFF_DDS_POINT_STEP; /* block (-1, 0, 0)'s first voxel */
  assert_float_equal(f32_at(p), 1 + (-16 + 0.5) * 0.5, 1e-6);
  assert_float_equal(f32_at(p + 4), -2 + 0.25, 1e-6);
  assert_int_equal(p[12] | p[13] << 8, 3);
  assert_float_equal(f32_at(p + 16), 40 / 255.0, 1e-6);
  p = d + (size_t)(n - 2) * VLFF_DDS_POINT_STEP; /* voxel (2, 0, 0): beyond the grid's 2 x 3 x 2 */
  assert_float_equal(f32_at(p), 1 + 2.5 * 0.5, 1e-6);
  assert_float_equal(f32_at(p + 8), 0.5 + 0.25, 1e-6);
  assert_int_equal(p[12] | p[13] << 8, 9);
  assert_int_equal(p[VLFF_DDS_POINT_STEP + 12], 9);
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

/* Robots' clouds: what is refused, and the merge of their evidence in the
 * world frame of each robot's transform. */
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
  put_point(e, 0.05f, -0.05f, 0.05f, 0, 0.5f);      /* same evidence, changed later: wins */
  put_point(e + 20, 0.05f, -0.15f, 0.05f, 1, 0.6f); /* agrees with robot 0's table at 1.0 */
  assert_int_equal(vlff_merge_take_cloud(&r[1], 2, 1, 20, false, names, offs, types, 5, e, sizeof e, 200, why, sizeof why), 0);
  vlff_merge_yaw(r[0].rot, 0);
  vlff_merge_yaw(r[1].rot, 3.14159265358979323846 / 2); /* (x, y) -> (-y, x) */
  r[1].t[2] = 0.01;                                      /* 1 cm up */
  r[0].nprompts = 2, r[1].nprompts = 2;
  strcpy(r[0].prompts[0], "chair"), strcpy(r[0].prompts[1], "table");
  strcpy(r[1].prompts[0], "door"), strcpy(r[1].prompts[1], "table");
  static struct vlff_merge_grid g;
  const double lo[3] = {0, 0, 0}, hi[3] = {1, 1, 1}, huge[3] = {1e4, 1e4, 1e4};
  assert_int_equal(vlff_merge_grid_init(&g, lo, huge, 0.01, 600, why, sizeof why), -1);
  assert_non_null(strstr(why, "more than"));
  assert_int_equal(vlff_merge_grid_init(&g, lo, hi, 0.1, 0, why, sizeof why), -1);
  assert_non_null(strstr(why, "half-life"));
  assert_int_equal(vlff_merge_grid_init(&g, lo, hi, 0.1, 600, why, sizeof why), 0);
  assert_int_equal(vlff_merge_compute(&g, r, 2), 3);
  assert_int_equal(g.nprompts, 3); /* chair table door */
  assert_string_equal(g.prompts[2], "door");
  assert_int_equal(g.labels[0], 2);  /* robot 1's door: 0.5 against chair's 0.5, changed later */
  assert_int_equal(g.conf[0], 64);   /* half the evidence there: 255 x 0.5 / 2 */
  assert_int_equal(g.labels[1], 1);  /* both say table */
  assert_int_equal(g.conf[1], 204);  /* 255 x (1.0 + 0.6) / 2 */
  assert_int_equal(g.labels[10], 1); /* 0.05,0.15: robot 0's only, as it said */
  assert_int_equal(g.conf[10], 51);
  assert_int_equal(g.labels[2], VLFF_LABEL_UNKNOWN);
  r[1].changed_ns[0] = 50; /* robot 1's door older now: robot 0's chair wins the tie */
  vlff_merge_compute(&g, r, 2);
  assert_int_equal(g.labels[0], 0);
  /* a whole map that repeats a voxel keeps when it changed; one that changes it does not */
  put_point(e + 20, 0.05f, -0.15f, 0.05f, 1, 0.8f);
  assert_int_equal(vlff_merge_take_cloud(&r[1], 2, 1, 20, false, names, offs, types, 5, e, sizeof e, 300, why, sizeof why), 0);
  assert_true(r[1].changed_ns[0] == 50);
  assert_true(r[1].changed_ns[1] == 300);
  vlff_merge_grid_free(&g);
  vlff_merge_robot_free(&r[0]);
  vlff_merge_robot_free(&r[1]);
}

/* Evidence, not the single most confident point: two robots that agree
 * outweigh a more confident third; a newer observation outweighs an older,
 * more confident one by the half-life; texts beyond the fleet's 32 are left
 * out, per robot. And transforms from quaternions. */
static void test_merge_evidence(void **state) {
  (void)state;
  static struct vlff_merge_robot r[3];
  memset(r, 0, sizeof r);
  char why[256];
  const int64_t s = 1000000000;
  const float conf[3] = {0.4f, 0.4f, 0.7f};
  const uint16_t lab[3] = {0, 0, 1};
  for (int k = 0; k < 3; k++) {
    uint8_t d[20];
    put_point(d, 0.05f, 0.05f, 0.05f, lab[k], conf[k]);
    r[k].nprompts = 2;
    strcpy(r[k].prompts[0], "chair"), strcpy(r[k].prompts[1], "sofa");
    vlff_merge_yaw(r[k].rot, 0);
    assert_int_equal(vlff_merge_take_cloud(&r[k], 1, 1, 20, false, names, offs, types, 5, d, 20, 100 * s, why, sizeof why), 0);
  }
  static struct vlff_merge_grid g;
  const double lo[3] = {0, 0, 0}, hi[3] = {1, 1, 1};
  assert_int_equal(vlff_merge_grid_init(&g, lo, hi, 0.1, 600, why, sizeof why), 0);
  assert_int_equal(vlff_merge_compute(&g, r, 0), 0); /* no robot, no votes: an empty map */
  assert_int_equal(g.labels[0], VLFF_LABEL_UNKNOWN);
  assert_int_equal(vlff_merge_compute(&g, r, 3), 1);
  assert_int_equal(g.labels[0], 0); /* chair 0.8 over sofa 0.7 (the most confident point says sofa) */
  assert_int_equal(g.conf[0], 68);  /* 255 x 0.8 / 3 */
  /* the sofa seen 600 s later (one half-life): the chairs count half */
  r[2].changed_ns[0] = 700 * s;
  vlff_merge_compute(&g, r, 3);
  assert_int_equal(g.labels[0], 1);  /* sofa 0.7 over chair 0.4 */
  assert_int_equal(g.conf[0], 89);   /* 255 x 0.7 / (0.5 + 0.5 + 1) */
  /* one robot's 32 texts fill the fleet's list: another's new text is left out, with its points */
  r[0].nprompts = 32;
  for (int i = 0; i < 32; i++) snprintf(r[0].prompts[i], sizeof r[0].prompts[i], "thing %d", i);
  strcpy(r[0].prompts[0], "chair");
  vlff_merge_compute(&g, r, 3);
  assert_int_equal(g.nprompts, 32);
  assert_int_equal(r[0].left_out, 0);
  assert_int_equal(r[1].left_out, 2); /* its text 1, sofa */
  assert_int_equal(r[2].left_out, 2);
  assert_int_equal(g.no_label, 1);    /* robot 2's sofa point */
  assert_int_equal(g.labels[0], 0);   /* the chairs' evidence alone */
  /* a published transform: a quaternion turning 90 degrees about +z equals the yaw */
  double qr[9], yr[9];
  const double q[4] = {0, 0, sqrt(0.5), sqrt(0.5)}, bad[4] = {0, 0, 1, 1}, inf[4] = {NAN, 0, 0, 1};
  assert_int_equal(vlff_merge_quat(qr, q, why, sizeof why), 0);
  vlff_merge_yaw(yr, 3.14159265358979323846 / 2);
  for (int i = 0; i < 9; i++) assert_float_equal(qr[i], yr[i], 1e-12);
  assert_int_equal(vlff_merge_quat(qr, bad, why, sizeof why), -1);
  assert_non_null(strstr(why, "unit quaternion"));
  assert_int_equal(vlff_merge_quat(qr, inf, why, sizeof why), -1);
  vlff_merge_grid_free(&g);
  for (int k = 0; k < 3; k++) vlff_merge_robot_free(&r[k]);
}

/* Votes weighed by their distance from the robot's camera path: a robot
 * that walked by a voxel outweighs a more confident one that saw it from
 * 3 m; the path keeps positions VLFF_MERGE_PATH_STEP apart. */
static void test_merge_path(void **state) {
  (void)state;
  static struct vlff_merge_robot r[2];
  memset(r, 0, sizeof r);
  char why[256];
  const float conf[2] = {0.5f, 0.9f};
  for (int k = 0; k < 2; k++) {
    uint8_t d[20];
    put_point(d, 0.05f, 0.05f, 0.05f, (uint16_t)k, conf[k]);
    r[k].nprompts = 2;
    strcpy(r[k].prompts[0], "chair"), strcpy(r[k].prompts[1], "sofa");
    vlff_merge_yaw(r[k].rot, 0);
    assert_int_equal(vlff_merge_take_cloud(&r[k], 1, 1, 20, false, names, offs, types, 5, d, 20, 100, why, sizeof why), 0);
  }
  static struct vlff_merge_grid g;
  const double lo[3] = {0, 0, 0}, hi[3] = {1, 1, 1};
  assert_int_equal(vlff_merge_grid_init(&g, lo, hi, 0.1, 600, why, sizeof why), 0);
  vlff_merge_compute(&g, r, 2);
  assert_int_equal(g.labels[0], 1); /* no paths: the sofa's 0.9 */
  const double here[3] = {0, 0, 0}, near[3] = {0.1, 0, 0}, far[3] = {3, 0, 0}, bad[3] = {NAN, 0, 0};
  assert_int_equal(vlff_merge_add_path(&r[0], here), 1);
  assert_int_equal(vlff_merge_add_path(&r[0], near), 0); /* within a step of one kept */
  assert_int_equal(vlff_merge_add_path(&r[0], bad), -1);
  assert_int_equal(r[0].npath, 1);
  assert_int_equal(vlff_merge_add_path(&r[1], far), 1);
  vlff_merge_compute(&g, r, 2);
  assert_int_equal(g.labels[0], 0); /* the chair of the robot that walked by */
  vlff_merge_grid_free(&g);
  for (int k = 0; k < 2; k++) vlff_merge_robot_free(&r[k]);
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
  assert_int_equal(vlff_merge_grid_init(&g, lo, hi, 0.1, 600, why, sizeof why), 0);
  vlff_merge_yaw(r.rot, 0);
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
  const struct CMUnitTest tests[] = {cmocka_unit_test(test_topic), cmocka_unit_test(test_prompts), cmocka_unit_test(test_encoding), cmocka_unit_test(test_merge), cmocka_unit_test(test_merge_evidence), cmocka_unit_test(test_merge_path), cmocka_unit_test(test_merge_update),
                                     cmocka_unit_test(test_cloud)};
  return cmocka_run_group_tests(tests, NULL, NULL);
}
