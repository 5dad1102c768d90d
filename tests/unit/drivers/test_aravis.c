/*
 * Aravis backend against Aravis' fake GigE Vision camera over loopback:
 * frames land in an in-memory sink with the fake camera's pattern, Bayer is
 * demosaiced with the right phase, software triggering yields exactly one
 * frame per trigger, and a killed camera is detected and reconnected.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <arv.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "aravis.h"
#include "fakecam.h"
#include "log.h"
#include "pipe.h"
#include "sink.h"
#include "drvtest.h"
#include "unit.h"

static pid_t cam_pid = -1;

static int setup(void **state) {
  (void)state;
  vlff_log_set_level(VLFF_LOG_WARN);
  cam_pid = fakecam_start(0);
  return cam_pid > 0 ? 0 : -1;
}

static int teardown(void **state) {
  (void)state;
  fakecam_stop(cam_pid);
  vlff_arv_shutdown();
  return 0;
}

static void base_cfg(struct vlff_config *cfg, const char *fmt, int w, int h) {
  vlff_config_defaults(cfg);
  cfg->camera.kind = VLFF_CAM_ARAVIS;
  snprintf(cfg->camera.device, sizeof cfg->camera.device, "127.0.0.1");
  snprintf(cfg->camera.pixel_format, sizeof cfg->camera.pixel_format, "%s", fmt);
  cfg->camera.width = w;
  cfg->camera.height = h;
  cfg->camera.frame_rate = 50;
  cfg->camera.sensor_id = 3;
}

/* Grabs until n frames are committed or timeout_s passes; returns count. */
static int grab_n(struct vlff_arv *a, struct vlff_pipe *p, struct vlff_memsink *m, int n, double timeout_s) {
  uint64_t end = now_ns() + (uint64_t)(timeout_s * 1e9);
  int got = 0;
  while (got < n && now_ns() < end) {
    int rc = vlff_arv_grab(a, 100, p, vlff_memsink_sink(m), NULL);
    assert_true(rc >= 0);
    got += rc;
  }
  return got;
}

static void test_mono8_pattern_and_timestamps(void **state) {
  (void)state;
  struct vlff_config cfg;
  base_cfg(&cfg, "Mono8", 320, 240);
  char err[512] = "";
  struct vlff_pipe *p = vlff_pipe_new(&cfg, err, sizeof err);
  assert_non_null(p);
  struct vlff_arv *a = vlff_arv_open(&cfg.camera, err, sizeof err);
  if (!a) fail_msg("%s", err);
  struct vlff_memsink *m = vlff_memsink_new(8, 640, 480);
  uint64_t t0 = now_ns();
  assert_int_equal(grab_n(a, p, m, 8, 5.0), 8);
  uint64_t t1 = now_ns();
  for (int i = 0; i < 8; i++) {
    const struct vlff_sink_frame *f = vlff_memsink_get(m, i);
    assert_int_equal(f->width, 320);
    assert_int_equal(f->height, 240);
    assert_int_equal(f->sensor_id, 3);
    assert_true(f->host_ns > t0 - 1000000000u && f->host_ns <= t1);
    assert_false(f->pose_valid);
    /* The fake camera's Mono8 pattern: (x + y + frame id) mod 255, as RGB grey. */
    for (int y = 0; y < 240; y += 7)
      for (int x = 0; x < 320; x += 5) {
        const uint8_t *px = f->color + (size_t)y * f->color_stride + (size_t)x * 3;
        uint8_t want = (uint8_t)((x + y + f->device_frame_id) % 255);
        if (px[0] != want || px[1] != want || px[2] != want)
          fail_msg("frame %llu pixel (%d,%d) = %u,%u,%u, expected %u", (unsigned long long)f->device_frame_id, x,
                   y, px[0], px[1], px[2], want);
      }
    if (i > 0) {
      const struct vlff_sink_frame *newer = vlff_memsink_get(m, i - 1);
      assert_true(newer->host_ns > f->host_ns);
      assert_true(newer->device_ns > f->device_ns);
      assert_true(newer->device_frame_id > f->device_frame_id);
    }
  }
  const struct vlff_pipe_stats *st = vlff_pipe_get_stats(p);
  assert_int_equal(st->committed, 8);
  assert_int_equal(st->dropped_format + st->dropped_short + st->dropped_convert + st->dropped_sink, 0);
  vlff_memsink_free(m);
  vlff_arv_close(a);
  vlff_pipe_free(p);
}

/* BayerRG8 through the whole path: the frame arrives demosaiced at the
 * configured size with the pattern's structure. The exact GenICam->OpenCV
 * phase is pinned by test_cvshim on a synthetic mosaic. */
static void test_bayer_frames(void **state) {
  (void)state;
  struct vlff_config cfg;
  base_cfg(&cfg, "BayerRG8", 256, 64);
  char err[512] = "";
  struct vlff_pipe *p = vlff_pipe_new(&cfg, err, sizeof err);
  struct vlff_arv *a = vlff_arv_open(&cfg.camera, err, sizeof err);
  if (!a) fail_msg("%s", err);
  struct vlff_memsink *m = vlff_memsink_new(2, 256, 64);
  int got = grab_n(a, p, m, 2, 5.0);
  vlff_arv_close(a);
  assert_int_equal(got, 2);
  const struct vlff_sink_frame *f = vlff_memsink_get(m, 0);
  assert_int_equal(f->width, 256);
  assert_int_equal(f->height, 64);
  /* A colour image: channels differ somewhere, and it is not constant. */
  int differ = 0, hist[256] = {0}, levels = 0;
  for (int y = 0; y < 64; y++)
    for (int x = 0; x < 256; x++) {
      const uint8_t *px = f->color + (size_t)y * f->color_stride + (size_t)x * 3;
      differ += px[0] != px[1] || px[1] != px[2];
      hist[px[0]]++;
    }
  for (int i = 0; i < 256; i++) levels += hist[i] > 0;
  assert_true(differ > 256 * 64 / 4);
  assert_true(levels > 16);
  vlff_memsink_free(m);
  vlff_pipe_free(p);
}

static void test_software_trigger(void **state) {
  (void)state;
  struct vlff_config cfg;
  base_cfg(&cfg, "Mono8", 160, 120);
  cfg.camera.trigger = VLFF_TRIG_SOFTWARE;
  char err[512] = "";
  struct vlff_pipe *p = vlff_pipe_new(&cfg, err, sizeof err);
  struct vlff_arv *a = vlff_arv_open(&cfg.camera, err, sizeof err);
  if (!a) fail_msg("%s", err);
  struct vlff_memsink *m = vlff_memsink_new(8, 160, 120);
  /* No triggers: nothing for well over the fake camera's 25 Hz tick. */
  assert_int_equal(grab_n(a, p, m, 1, 0.6), 0);
  for (int t = 0; t < 4; t++) {
    assert_int_equal(vlff_arv_software_trigger(a, err, sizeof err), 0);
    assert_int_equal(grab_n(a, p, m, 1, 2.0), 1);
    /* ... and only one frame per trigger. */
    assert_int_equal(grab_n(a, p, m, 1, 0.25), 0);
  }
  assert_int_equal(vlff_memsink_committed(m), 4);
  assert_int_equal(vlff_arv_stats(a)->triggers, 4);
  vlff_memsink_free(m);
  vlff_arv_close(a);
  vlff_pipe_free(p);
}

static void test_loss_and_reconnect(void **state) {
  (void)state;
  struct vlff_config cfg;
  base_cfg(&cfg, "Mono8", 160, 120);
  char err[512] = "";
  struct vlff_pipe *p = vlff_pipe_new(&cfg, err, sizeof err);
  struct vlff_arv *a = vlff_arv_open(&cfg.camera, err, sizeof err);
  if (!a) fail_msg("%s", err);
  struct vlff_memsink *m = vlff_memsink_new(8, 160, 120);
  assert_int_equal(grab_n(a, p, m, 3, 5.0), 3);
  fakecam_kill(cam_pid);
  uint64_t t0 = now_ns();
  int rc = 0;
  while (rc >= 0 && now_ns() - t0 < 15000000000u) rc = vlff_arv_grab(a, 100, p, vlff_memsink_sink(m), NULL);
  assert_int_equal(rc, -1);
  vlff_arv_close(a);
  /* While the camera is away, opening fails with a clear error. */
  a = vlff_arv_open(&cfg.camera, err, sizeof err);
  assert_null(a);
  assert_non_null(strstr(err, "camera.device"));
  cam_pid = fakecam_start(0);
  assert_true(cam_pid > 0);
  a = vlff_arv_open(&cfg.camera, err, sizeof err);
  if (!a) fail_msg("%s", err);
  assert_int_equal(grab_n(a, p, m, 3, 5.0), 3);
  vlff_memsink_free(m);
  vlff_arv_close(a);
  vlff_pipe_free(p);
}

static void test_bad_values_name_the_key(void **state) {
  (void)state;
  struct vlff_config cfg;
  char err[512] = "";
  base_cfg(&cfg, "Mono8", 1024, 1024);
  cfg.camera.offset_x = 1500; /* sensor is 2048 wide */
  struct vlff_arv *a = vlff_arv_open(&cfg.camera, err, sizeof err);
  assert_null(a);
  assert_non_null(strstr(err, "camera.offset_x"));
  assert_non_null(strstr(err, "2048"));
  base_cfg(&cfg, "Mono8", 64, 64);
  cfg.camera.exposure_us = 5; /* fake camera: 10 us minimum */
  a = vlff_arv_open(&cfg.camera, err, sizeof err);
  assert_null(a);
  assert_non_null(strstr(err, "camera.exposure_us"));
  base_cfg(&cfg, "Mono8", 64, 64);
  snprintf(cfg.camera.device, sizeof cfg.camera.device, "no-such-camera-%d", (int)getpid());
  a = vlff_arv_open(&cfg.camera, err, sizeof err);
  assert_null(a);
  assert_non_null(strstr(err, "camera.device"));
}

/* Lost GVSP packets: Aravis asks for resends, and what cannot be completed
 * is counted and dropped, never committed. */
static void test_lossy_link_counts_incomplete(void **state) {
  (void)state;
  fakecam_kill(cam_pid);
  cam_pid = fakecam_start(2);
  assert_true(cam_pid > 0);
  struct vlff_config cfg;
  base_cfg(&cfg, "Mono8", 640, 480);
  cfg.camera.packet_size = 1500;
  char err[512] = "";
  struct vlff_pipe *p = vlff_pipe_new(&cfg, err, sizeof err);
  struct vlff_arv *a = vlff_arv_open(&cfg.camera, err, sizeof err);
  if (!a) fail_msg("%s", err);
  struct vlff_memsink *m = vlff_memsink_new(4, 640, 480);
  uint64_t end = now_ns() + 3000000000u;
  while (now_ns() < end) assert_true(vlff_arv_grab(a, 100, p, vlff_memsink_sink(m), NULL) >= 0);
  const struct vlff_arv_stats *st = vlff_arv_stats(a);
  /* Every popped buffer is either committed or counted as incomplete. */
  assert_true(st->incomplete > 0);
  assert_true(vlff_pipe_get_stats(p)->committed > 0);
  assert_int_equal(st->buffers, vlff_pipe_get_stats(p)->committed + st->incomplete);
  /* Whatever was committed is intact. */
  for (int i = 0; i < 4 && vlff_memsink_get(m, i); i++) {
    const struct vlff_sink_frame *f = vlff_memsink_get(m, i);
    for (int y = 0; y < 480; y += 13)
      for (int x = 0; x < 640; x += 11)
        assert_int_equal(f->color[(size_t)y * f->color_stride + (size_t)x * 3], (x + y + f->device_frame_id) % 255);
  }
  print_message("lossy link: %llu buffers, %llu incomplete\n", (unsigned long long)st->buffers,
                (unsigned long long)st->incomplete);
  vlff_memsink_free(m);
  vlff_arv_close(a);
  vlff_pipe_free(p);
  fakecam_kill(cam_pid);
  cam_pid = fakecam_start(0);
}

VLFF_UNIT_MAIN(setup, teardown,
    cmocka_unit_test(test_mono8_pattern_and_timestamps), cmocka_unit_test(test_bayer_frames),
    cmocka_unit_test(test_software_trigger), cmocka_unit_test(test_bad_values_name_the_key),
    cmocka_unit_test(test_lossy_link_counts_incomplete), cmocka_unit_test(test_loss_and_reconnect))
