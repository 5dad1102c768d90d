/*
 * The frame pipeline without a camera: Bayer phase on a synthetic mosaic,
 * Mono16 range -> depth plane, stereo depth from a synthetic pair with a
 * known disparity, undistortion, calibration YAML, pose matching, config
 * combinations rejected with the key named.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "cvshim.h"
#include "log.h"
#include "pipe.h"
#include "sink.h"

static void cfg_for(struct vlff_config *c, const char *fmt) {
  vlff_config_defaults(c);
  c->camera.kind = VLFF_CAM_ARAVIS;
  snprintf(c->camera.pixel_format, sizeof c->camera.pixel_format, "%s", fmt);
}

/* GenICam BayerRG8: (0,0)=R (0,1)=G (1,0)=G (1,1)=B. A smooth image sampled
 * that way must come back with each channel close to the original. */
static void test_bayer_phase(void **state) {
  (void)state;
  enum { W = 64, H = 48 };
  static const struct { vlff_pix_t pix; int rx, ry; } pats[] = {
      {VLFF_PIX_BAYER_RG8, 0, 0}, {VLFF_PIX_BAYER_BG8, 1, 1}, {VLFF_PIX_BAYER_GR8, 1, 0}, {VLFF_PIX_BAYER_GB8, 0, 1}};
  for (size_t k = 0; k < 4; k++) {
    uint8_t mosaic[W * H], out[W * H * 3];
    for (int y = 0; y < H; y++)
      for (int x = 0; x < W; x++) {
        int r = 40 + 2 * x, g = 100, b = 200 - 2 * y; /* distinct per channel */
        bool rs = (x & 1) == pats[k].rx && (y & 1) == pats[k].ry;
        bool bs = (x & 1) != pats[k].rx && (y & 1) != pats[k].ry;
        mosaic[y * W + x] = (uint8_t)(rs ? r : bs ? b : g);
      }
    char err[256];
    assert_int_equal(vlff_cv_to_rgb(mosaic, W, W, H, pats[k].pix, out, W * 3, err, sizeof err), 0);
    for (int y = 4; y < H - 4; y++)
      for (int x = 4; x < W - 4; x++) {
        const uint8_t *p = out + (y * W + x) * 3;
        if (abs(p[0] - (40 + 2 * x)) > 3 || abs(p[1] - 100) > 3 || abs(p[2] - (200 - 2 * y)) > 3)
          fail_msg("%s (%d,%d): %u %u %u", vlff_pix_name(pats[k].pix), x, y, p[0], p[1], p[2]);
      }
  }
}

/* A range camera beside a colour camera: its pipeline turns counts into a
 * millimetre depth plane and writes no colour plane (the pairing puts the
 * colour camera's there). */
static void test_range_stream_to_depth(void **state) {
  (void)state;
  struct vlff_config c;
  cfg_for(&c, "RGB8");
  c.camera.depth = VLFF_DEPTH_STREAM;
  c.depth_camera.kind = VLFF_DCAM_ARAVIS;
  snprintf(c.depth_camera.calibration, sizeof c.depth_camera.calibration, "rig.yaml");
  c.depth_camera.scale_m = 0.0005; /* 0.5 mm per count */
  char err[256];
  struct vlff_pipe *p = vlff_pipe_new_depth(&c, err, sizeof err);
  if (!p) fail_msg("%s", err);
  assert_int_equal(vlff_pipe_pix(p), VLFF_PIX_MONO16);
  uint16_t img[8 * 4];
  for (int i = 0; i < 32; i++) img[i] = (uint16_t)(i * 1000);
  struct vlff_memsink *m = vlff_memsink_new(2, 8, 4);
  struct vlff_raw_frame raw = {img, sizeof img, 16, 8, 4, VLFF_PIX_MONO16, 7, 100, 200};
  assert_int_equal(vlff_pipe_push(p, &raw, vlff_memsink_sink(m), NULL), 0);
  const struct vlff_sink_frame *f = vlff_memsink_get(m, 0);
  assert_int_equal(f->color_format, VLFF_PIX_NONE);
  assert_null(f->color);
  assert_int_equal(f->depth_format, VLFF_DEPTH_FMT_U16_MM);
  const uint16_t *d = f->depth;
  assert_int_equal(d[0], 0);        /* 0 counts: invalid stays invalid */
  assert_int_equal(d[1], 500);      /* 1000 counts * 0.5 mm */
  assert_int_equal(d[8 + 3], 5500); /* row stride honoured */
  /* A short buffer is dropped and counted, never read past its end. */
  raw.size = 20;
  assert_int_equal(vlff_pipe_push(p, &raw, vlff_memsink_sink(m), NULL), -1);
  assert_int_equal(vlff_pipe_get_stats(p)->dropped_short, 1);
  /* Wrong format for the config: dropped and counted. */
  raw.size = sizeof img;
  raw.pix = VLFF_PIX_MONO8;
  assert_int_equal(vlff_pipe_push(p, &raw, vlff_memsink_sink(m), NULL), -1);
  assert_int_equal(vlff_pipe_get_stats(p)->dropped_format, 1);
  vlff_memsink_free(m);
  vlff_pipe_free(p);
}

static void write_file(const char *path, const char *text) {
  FILE *f = fopen(path, "w");
  assert_non_null(f);
  fputs(text, f);
  fclose(f);
}

/* A rectified pair (identity rotation, baseline 0.1 m along x, f = 200 px):
 * a random texture shifted by 16 px is a plane at 200 * 0.1 / 16 = 1.25 m. */
static void test_stereo_depth(void **state) {
  (void)state;
  char calib[128];
  snprintf(calib, sizeof calib, "/tmp/vlff-test-stereo-%d.yaml", (int)getpid());
  write_file(calib,
             "%YAML:1.0\n"
             "M1: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [200, 0, 80, 0, 200, 60, 0, 0, 1]\n"
             "D1: !!opencv-matrix\n  rows: 1\n  cols: 5\n  dt: d\n  data: [0, 0, 0, 0, 0]\n"
             "M2: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [200, 0, 80, 0, 200, 60, 0, 0, 1]\n"
             "D2: !!opencv-matrix\n  rows: 1\n  cols: 5\n  dt: d\n  data: [0, 0, 0, 0, 0]\n"
             "R: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
             "T: !!opencv-matrix\n  rows: 3\n  cols: 1\n  dt: d\n  data: [-0.1, 0, 0]\n");
  struct vlff_config c;
  cfg_for(&c, "Mono8");
  c.camera.depth = VLFF_DEPTH_STEREO;
  c.camera.depth_unit = VLFF_DEPTH_UNIT_M;
  snprintf(c.camera.calibration, sizeof c.camera.calibration, "%s", calib);
  char err[512];
  struct vlff_pipe *p = vlff_pipe_new(&c, err, sizeof err);
  if (!p) fail_msg("%s", err);
  enum { W = 160, H = 120, D = 16 };
  uint8_t *pair = malloc(2 * W * H);
  srand(1);
  uint8_t tex[W + D][H];
  for (int x = 0; x < W + D; x++)
    for (int y = 0; y < H; y++) tex[x][y] = (uint8_t)(rand() & 0xff);
  /* right eye: the same texture shifted left by D (x_r = x_l - D). */
  for (int y = 0; y < H; y++)
    for (int x = 0; x < W; x++) pair[y * 2 * W + W + x] = tex[x][y] == 0 ? 0 : tex[x][y];
  for (int y = 0; y < H; y++)
    for (int x = 0; x < W; x++) pair[y * 2 * W + x] = x >= D ? tex[x - D][y] : tex[0][y];
  struct vlff_memsink *m = vlff_memsink_new(1, W, H);
  struct vlff_raw_frame raw = {pair, 2 * W * H, 2 * W, 2 * W, H, VLFF_PIX_MONO8, 1, 1, 1};
  assert_int_equal(vlff_pipe_push(p, &raw, vlff_memsink_sink(m), NULL), 0);
  const struct vlff_sink_frame *f = vlff_memsink_get(m, 0);
  assert_int_equal(f->width, W);
  assert_int_equal(f->depth_format, VLFF_DEPTH_FMT_F32_M);
  assert_true(f->intrinsics[0] > 150 && f->intrinsics[0] < 300); /* rectification may zoom */
  int good = 0, valid = 0;
  for (int y = 10; y < H - 10; y++)
    for (int x = 70; x < W - 10; x++) { /* SGBM leaves the first numDisparities columns empty */
      float z = ((const float *)((const char *)f->depth + (size_t)y * f->depth_stride))[x];
      valid += z > 0;
      good += fabsf(z - 1.25f) < 0.05f;
    }
  int n = (H - 20) * (W - 80);
  if (good < n * 9 / 10 || good < valid * 98 / 100) fail_msg("stereo: %d of %d pixels at 1.25 m (%d valid)", good, n, valid);
  free(pair);
  vlff_memsink_free(m);
  vlff_pipe_free(p);
  /* Mono calibration only: stereo refused, naming the key. */
  write_file(calib, "%YAML:1.0\ncamera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n"
                    "  data: [200, 0, 80, 0, 200, 60, 0, 0, 1]\n");
  assert_null(vlff_pipe_new(&c, err, sizeof err));
  assert_non_null(strstr(err, "camera.calibration"));
  unlink(calib);
}

static void test_calibration_and_undistort(void **state) {
  (void)state;
  char calib[128];
  snprintf(calib, sizeof calib, "/tmp/vlff-test-calib-%d.yaml", (int)getpid());
  write_file(calib, "%YAML:1.0\nimage_width: 64\nimage_height: 48\n"
                    "camera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n"
                    "  data: [60, 0, 32, 0, 60, 24, 0, 0, 1]\n"
                    "distortion_coefficients: !!opencv-matrix\n  rows: 1\n  cols: 5\n  dt: d\n"
                    "  data: [-0.3, 0.1, 0, 0, 0]\n");
  struct vlff_config c;
  cfg_for(&c, "Mono8");
  snprintf(c.camera.calibration, sizeof c.camera.calibration, "%s", calib);
  char err[512];
  struct vlff_pipe *p = vlff_pipe_new(&c, err, sizeof err);
  if (!p) fail_msg("%s", err);
  uint8_t img[64 * 48];
  for (int i = 0; i < 64 * 48; i++) img[i] = (uint8_t)((i % 64) * 4);
  struct vlff_memsink *m = vlff_memsink_new(1, 64, 48);
  struct vlff_raw_frame raw = {img, sizeof img, 64, 64, 48, VLFF_PIX_MONO8, 1, 1, 1};
  assert_int_equal(vlff_pipe_push(p, &raw, vlff_memsink_sink(m), NULL), 0);
  const struct vlff_sink_frame *f = vlff_memsink_get(m, 0);
  assert_true(f->intrinsics[0] == 60 && f->intrinsics[3] == 24);
  /* The principal point maps to itself; with barrel distortion removed a
   * pixel near the edge samples from further in, so the ramp changes there. */
  const uint8_t *centre = f->color + 24 * f->color_stride + 32 * 3;
  assert_true(abs(centre[0] - 128) <= 4);
  int changed = 0;
  for (int x = 0; x < 64; x++) changed += f->color[2 * f->color_stride + x * 3] != img[2 * 64 + x];
  assert_true(changed > 10);
  vlff_memsink_free(m);
  vlff_pipe_free(p);
  /* A calibration for another size is refused on the first frame, counted. */
  c.camera.calibration[0] = 0;
  vlff_pipe_free(NULL);
  cfg_for(&c, "Mono8");
  snprintf(c.camera.calibration, sizeof c.camera.calibration, "%s", calib);
  p = vlff_pipe_new(&c, err, sizeof err);
  m = vlff_memsink_new(1, 64, 48);
  raw.width = 32;
  raw.stride = 32;
  assert_int_equal(vlff_pipe_push(p, &raw, vlff_memsink_sink(m), NULL), -1);
  assert_int_equal(vlff_pipe_get_stats(p)->dropped_convert, 1);
  vlff_memsink_free(m);
  vlff_pipe_free(p);
  write_file(calib, "%YAML:1.0\ncamera_matrix: [1, 2]\n");
  assert_null(vlff_pipe_new(&c, err, sizeof err));
  assert_non_null(strstr(err, "camera.calibration"));
  unlink(calib);
}

static int fake_pose(void *ctx, uint64_t t, double tol, double pose[16], uint64_t *pt, bool *untrusted) {
  (void)ctx;
  if (t < 1000 || tol <= 0) return -1;
  for (int i = 0; i < 16; i++) pose[i] = i % 5 == 0;
  *pt = t - 1;
  *untrusted = t == 2000;
  return 0;
}

static void test_pose_marking(void **state) {
  (void)state;
  struct vlff_config c;
  cfg_for(&c, "Mono8");
  char err[256];
  struct vlff_pipe *p = vlff_pipe_new(&c, err, sizeof err);
  uint8_t img[16] = {0};
  struct vlff_memsink *m = vlff_memsink_new(4, 4, 4);
  struct vlff_pose_source ps = {fake_pose, NULL};
  uint64_t ts[3] = {500, 1500, 2000};
  for (int i = 0; i < 3; i++) {
    struct vlff_raw_frame raw = {img, 16, 4, 4, 4, VLFF_PIX_MONO8, (uint64_t)i, ts[i], ts[i]};
    assert_int_equal(vlff_pipe_push(p, &raw, vlff_memsink_sink(m), &ps), 0);
  }
  assert_false(vlff_memsink_get(m, 2)->pose_valid); /* no pose within tolerance */
  assert_true(vlff_memsink_get(m, 1)->pose_valid);
  assert_false(vlff_memsink_get(m, 1)->pose_untrusted);
  assert_int_equal(vlff_memsink_get(m, 1)->pose_ns, 1499);
  assert_true(vlff_memsink_get(m, 0)->pose_untrusted);
  assert_int_equal(vlff_pipe_get_stats(p)->no_pose, 2);
  vlff_memsink_free(m);
  vlff_pipe_free(p);
}

static void test_config_combinations(void **state) {
  (void)state;
  static const struct { const char *yaml, *key; } cases[] = {
      {"camera: {kind: aravis, pixel_format: YUV422}\n", "camera.pixel_format"},
      {"camera: {kind: aravis, depth: stereo}\n", "camera.calibration"},
      {"camera: {kind: aravis, pixel_format: Mono16}\n", "camera.pixel_format"},
      {"camera: {kind: aravis, depth: stream}\n", "camera.depth"},
      {"camera: {kind: aravis, depth: stream}\ndepth_camera: {kind: aravis}\n", "depth_camera.calibration"},
      {"camera: {kind: aravis, depth: stream}\ndepth_camera: {kind: aravis, pixel_format: Mono8, calibration: r.yaml}\n",
       "depth_camera.pixel_format"},
      {"camera: {kind: aravis, depth: stream, frame_rate: 30}\n"
       "depth_camera: {kind: aravis, calibration: r.yaml, pair_tolerance_s: 0.02}\n",
       "depth_camera.pair_tolerance_s"},
      {"camera: {kind: aravis, depth: stream, intrinsics: [500, 500, 320, 240]}\n"
       "depth_camera: {kind: aravis, calibration: r.yaml}\n",
       "camera.intrinsics"},
      {"camera: {kind: aravis}\ndepth_camera: {kind: aravis, calibration: r.yaml}\n", "depth_camera.kind"},
      {"camera: {kind: aravis, depth: stream}\ndepth_camera: {kind: aravis, calibration: r.yaml, register_width: 320}\n",
       "depth_camera.register_height"},
      {"camera: {kind: aravis, depth: stream}\nshm: {max_width: 640}\n"
       "depth_camera: {kind: aravis, calibration: r.yaml, register_width: 1280, register_height: 960}\n",
       "depth_camera.register_width"},
      {"camera: {kind: aravis, depth: stream}\n"
       "depth_camera: {kind: aravis, calibration: r.yaml, register_width: 8, register_height: 6}\n",
       "depth_camera.register_width"},
      {"camera: {kind: aravis, depth: stream, width: 640, height: 480}\n"
       "depth_camera: {kind: aravis, calibration: r.yaml, register_width: 640, register_height: 360}\n",
       "depth_camera.register_width"},
      {"camera: {kind: aravis, intrinsics: [500, 0, 320, 240]}\n", "camera.intrinsics"},
      {"camera: {kind: aravis, distortion: [0.1, 0, 0, 0, 0]}\n", "camera.distortion"},
      {"camera: {kind: aravis, width: 4000}\n", "camera.width"},
      {"camera: {kind: aravis, offset_x: 8}\n", "camera.offset_x"},
      {"camera: {kind: libcamera, trigger: software}\n", "camera.trigger"},
      {"camera: {kind: aravis}\ngpio: {mode: output, rate_hz: 100, pulse_us: 20000}\n", "gpio.pulse_us"},
  };
  for (size_t i = 0; i < sizeof cases / sizeof cases[0]; i++) {
    struct vlff_config c;
    char err[512] = "";
    assert_int_equal(vlff_config_load_mem(cases[i].yaml, strlen(cases[i].yaml), "t.yaml", &c, err, sizeof err), 0);
    assert_int_equal(vlff_camcfg_check(&c, "t.yaml", err, sizeof err), -1);
    if (!strstr(err, cases[i].key) || !strstr(err, "t.yaml")) fail_msg("case %zu: %s", i, err);
  }
  struct vlff_config c;
  char err[512];
  /* The default camera.kind is one vlff-camd drives. */
  assert_int_equal(vlff_config_load_mem("", 0, "t.yaml", &c, err, sizeof err), 0);
  if (vlff_camcfg_check(&c, "t.yaml", err, sizeof err)) fail_msg("%s", err);
  const char *ok = "camera: {kind: aravis, pixel_format: BayerRG8, width: 640, height: 480}\n";
  assert_int_equal(vlff_config_load_mem(ok, strlen(ok), "t.yaml", &c, err, sizeof err), 0);
  assert_int_equal(vlff_camcfg_check(&c, "t.yaml", err, sizeof err), 0);
  const char *pair = "camera: {kind: aravis, depth: stream}\n"
                     "depth_camera: {kind: aravis, device: Fake, pixel_format: Coord3D_C16, calibration: r.yaml}\n";
  assert_int_equal(vlff_config_load_mem(pair, strlen(pair), "t.yaml", &c, err, sizeof err), 0);
  if (vlff_camcfg_check(&c, "t.yaml", err, sizeof err)) fail_msg("%s", err);
  /* A colour camera larger than the ring, registered down to a size the
   * ring holds: the record's size is what the ring bounds. */
  const char *big = "camera: {kind: aravis, depth: stream, width: 2560, height: 1920}\nshm: {max_width: 640}\n"
                    "depth_camera: {kind: aravis, calibration: r.yaml, register_width: 640, register_height: 480}\n";
  assert_int_equal(vlff_config_load_mem(big, strlen(big), "t.yaml", &c, err, sizeof err), 0);
  if (vlff_camcfg_check(&c, "t.yaml", err, sizeof err)) fail_msg("%s", err);
  /* the shipped RGB-D example passes the camera checks */
  char path[1024];
  snprintf(path, sizeof path, "%s/configs/aravis-rgbd.yaml", getenv("VLFF_SOURCE_DIR"));
  if (vlff_config_load(path, &c, err, sizeof err) || vlff_camcfg_check(&c, path, err, sizeof err)) fail_msg("%s", err);
}

int main(void) {
  vlff_log_set_level(VLFF_LOG_ERROR);
  const struct CMUnitTest tests[] = {
      cmocka_unit_test(test_bayer_phase),        cmocka_unit_test(test_range_stream_to_depth),
      cmocka_unit_test(test_stereo_depth),       cmocka_unit_test(test_calibration_and_undistort),
      cmocka_unit_test(test_pose_marking),       cmocka_unit_test(test_config_combinations),
  };
  return cmocka_run_group_tests(tests, NULL, NULL);
}
