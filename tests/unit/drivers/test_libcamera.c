/*
 * libcamera on a machine without cameras (this host: no V4L2 devices): the
 * camera manager starts, finds nothing, and opening says so clearly with
 * errno ENODEV so vlff-camd keeps retrying instead of giving up. The
 * streaming path is tested against vimc inside the VM.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "lcam.h"
#include "unit.h"

static void test_zero_cameras_is_a_clear_error(void **state) {
  (void)state;
  if (access("/dev/media0", F_OK) == 0) skip(); /* a machine with cameras */
  setenv("LIBCAMERA_LOG_LEVELS", "*:ERROR", 1);
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  cfg.camera.kind = VLFF_CAM_LIBCAMERA;
  snprintf(cfg.camera.device, sizeof cfg.camera.device, "0");
  char err[512] = "";
  errno = 0;
  struct vlff_lcam *c = vlff_lcam_open(&cfg.camera, err, sizeof err);
  assert_null(c);
  assert_int_equal(errno, ENODEV);
  assert_non_null(strstr(err, "camera.device"));
  assert_non_null(strstr(err, "no cameras"));
  /* And again: the manager is restartable (vlff-camd retries). */
  c = vlff_lcam_open(&cfg.camera, err, sizeof err);
  assert_null(c);
  assert_int_equal(errno, ENODEV);
}

static void test_unknown_format_names_the_key(void **state) {
  (void)state;
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  cfg.camera.kind = VLFF_CAM_LIBCAMERA;
  snprintf(cfg.camera.pixel_format, sizeof cfg.camera.pixel_format, "Mono16");
  char err[512] = "";
  assert_null(vlff_lcam_open(&cfg.camera, err, sizeof err));
  assert_int_equal(errno, EINVAL);
  assert_non_null(strstr(err, "camera.pixel_format"));
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_zero_cameras_is_a_clear_error),
    cmocka_unit_test(test_unknown_format_names_the_key))
