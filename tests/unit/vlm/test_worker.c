/* The image worker: frames in from one thread, features out on another,
 * identical to a direct run, queue overflow dropping the oldest frame. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include <cmocka.h>

#include "config.h"
#include "dnn_shim.h"
#include "image_encoder.h"
#include "unit.h"
#include "vlm_fixture.h"

static void test_worker(void **state) {
  if (!fixture_have_torch()) skip();
  const char *dir = fixture_dir("worker");
  char cmd[1024];
  snprintf(cmd, sizeof cmd, "/usr/bin/python3 %s/node/vlm/export/export_lseg.py --random --small --seed 4 --out %s/lseg.onnx",
           getenv("VLFF_SOURCE_DIR"), dir);
  fixture_run(cmd);
  /* OpenCV's TBB pool synchronises in uninstrumented code, which
   * ThreadSanitizer reports as races; this test is about our worker's
   * threads, so OpenCV runs sequentially inside it. */
  assert_int_equal(vlff_dnn_set_threads(0, NULL, 0), 0);
  assert_int_equal(vlff_dnn_set_threads(-1, NULL, 0), -1);
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  snprintf(cfg.vlm.image_model, sizeof cfg.vlm.image_model, "%s/lseg.onnx", dir);
  cfg.vlm.input_width = cfg.vlm.input_height = 64;
  cfg.field.feature_dim = 32;
  char err[512];
  struct vlff_image_encoder *direct = vlff_image_encoder_open(&cfg.vlm, cfg.field.feature_dim, err, sizeof err);
  if (!direct) fail_msg("%s", err);
  const size_t n = 32 * 32 * 32;
  enum { FRAMES = 6 };
  uint8_t *img[FRAMES];
  uint16_t *want[FRAMES];
  for (int f = 0; f < FRAMES; f++) {
    img[f] = malloc(80 * 60 * 3);
    for (int i = 0; i < 80 * 60 * 3; i++) img[f][i] = (uint8_t)(i * (f + 3) + f * 17);
    want[f] = malloc(n * sizeof(uint16_t));
    assert_int_equal(vlff_image_encoder_run(direct, img[f], 80, 60, 240, want[f], err, sizeof err), 0);
  }
  vlff_image_encoder_close(direct);

  struct vlff_image_encoder *enc = vlff_image_encoder_open(&cfg.vlm, cfg.field.feature_dim, err, sizeof err);
  assert_non_null(enc);
  struct vlff_image_worker *w = vlff_image_worker_start(enc, 2, err, sizeof err);
  assert_non_null(w);
  assert_int_equal(vlff_image_worker_submit(w, 99, img[0], 0, 60, 240), -1);
  for (int f = 0; f < FRAMES; f++) assert_int_equal(vlff_image_worker_submit(w, (uint64_t)f + 100, img[f], 80, 60, 240), 0);
  uint16_t *out = malloc(n * sizeof *out);
  int got = 0;
  uint64_t last = 0;
  struct vlff_image_worker_stats st;
  for (int spin = 0; spin < 12000; spin++) {
    uint64_t id;
    int r = vlff_image_worker_poll(w, &id, out, err, sizeof err);
    if (r == 0) {
      vlff_image_worker_stats(w, &st);
      if (st.encoded + st.dropped_frames == FRAMES && (uint64_t)got == st.encoded - st.dropped_results) break;
      usleep(5000);
      continue;
    }
    assert_int_equal(r, 1);
    assert_true(id >= 100 && id < 100 + FRAMES && id > last);
    last = id;
    assert_memory_equal(out, want[id - 100], n * sizeof *out);
    got++;
  }
  vlff_image_worker_stats(w, &st);
  print_message("worker: %d results, %llu frames dropped, %llu results dropped\n", got,
                (unsigned long long)st.dropped_frames, (unsigned long long)st.dropped_results);
  assert_int_equal(st.submitted, FRAMES);
  assert_int_equal(st.failed, 0);
  assert_int_equal(st.encoded + st.dropped_frames, FRAMES);
  assert_true(got >= 1);
  assert_int_equal(last, 100 + FRAMES - 1); /* the newest frame is never the one dropped */
  vlff_image_worker_stop(w);
  for (int f = 0; f < FRAMES; f++) free(img[f]), free(want[f]);
  free(out);
  fixture_cleanup();
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_worker))
