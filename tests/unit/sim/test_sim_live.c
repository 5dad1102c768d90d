/* vlff-sim as a live source: run the real program, read its frame and
 * feature rings, and compare every published frame with the same frame
 * rendered in-process (the sim is a pure function of config and index). */
#include <errno.h>
#include <setjmp.h>
#include <signal.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include <cmocka.h>

#include "config.h"
#include "sim.h"
#include "unit.h"
#include "vlff/shm.h"

static void test_live_frames_match(void **state) {
  (void)state;
  const char *bin = getenv("VLFF_BINARY_DIR");
  assert_non_null(bin);
  char exe[1024], cfgpath[256], ring[64], fring[64];
  snprintf(exe, sizeof exe, "%s/node/sim/vlff-sim", bin);
  snprintf(ring, sizeof ring, "/vlff-test-simframes-%ld", (long)getpid());
  snprintf(fring, sizeof fring, "/vlff-test-simfeat-%ld", (long)getpid());
  snprintf(cfgpath, sizeof cfgpath, "/tmp/vlff-test-sim-live-%ld.yaml", (long)getpid());
  FILE *f = fopen(cfgpath, "w");
  assert_non_null(f);
  fprintf(f, "shm:\n  ring: \"%s\"\n  feature_ring: \"%s\"\n  ring_slots: 16\nsim:\n  width: 64\n  height: 48\n"
             "  seed: 9\n  frames: 4\n  rate_hz: 20\nfield:\n  feature_dim: 16\n",
          ring, fring);
  fclose(f);
  struct vlff_config cfg;
  char err[256];
  assert_int_equal(vlff_config_load(cfgpath, &cfg, err, sizeof err), 0);
  pid_t pid = fork();
  assert_true(pid >= 0);
  if (pid == 0) {
    /* through the shell for $VLFF_EMULATOR (qemu-user in a cross-built tree) */
    execl("/bin/sh", "sh", "-c", "exec ${VLFF_EMULATOR:-} \"$0\" \"$@\"", exe, "--config", cfgpath, "--count", "6",
          "--quiet", (char *)NULL);
    _exit(127);
  }
  int status;
  assert_int_equal(waitpid(pid, &status, 0), pid);
  assert_true(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  /* the rings outlive their producer: read the history back */
  struct vlff_ring *r = vlff_ring_attach(ring, VLFF_RECORD_FRAME);
  struct vlff_ring *fr = vlff_ring_attach(fring, VLFF_RECORD_FEATURE);
  if (!r || !fr) fail_msg("attach: %s", vlff_shm_last_message());
  vlff_ring_seek_oldest(r);
  vlff_ring_seek_oldest(fr);
  struct vlff_sim *s = vlff_sim_create(&cfg.sim, &cfg.field, err, sizeof err);
  assert_non_null(s);
  struct vlff_sim_frame *sf = vlff_sim_frame_new(s);
  size_t cap = vlff_ring_slot_size(r), fcap = vlff_ring_slot_size(fr);
  uint8_t *buf = malloc(cap), *fbuf = malloc(fcap);
  for (int i = 0; i < 6; i++) {
    struct vlff_ring_view v;
    ssize_t n = vlff_ring_read_copy(r, buf, cap, &v, 0);
    assert_true(n > 0);
    assert_int_equal(vlff_frame_validate(buf, (size_t)n), 0);
    const struct vlff_frame_hdr *h = (const void *)buf;
    assert_int_equal(h->frame_id, (uint64_t)i);
    assert_int_equal(vlff_sim_render(s, i % 4, VLFF_SIM_ALL, sf, err, sizeof err), 0);
    assert_true(h->flags & VLFF_FRAME_POSE_VALID);
    assert_memory_equal(h->pose, sf->c2w, sizeof h->pose);
    assert_true(h->fx == sf->fx && h->cy == sf->cy);
    assert_int_equal(h->plane[0].width, 64);
    const uint8_t *rgb = vlff_frame_plane(buf, VLFF_PLANE_COLOR);
    const uint8_t *dep = vlff_frame_plane(buf, VLFF_PLANE_DEPTH);
    for (int y = 0; y < 48; y++) {
      assert_memory_equal(rgb + (size_t)y * h->plane[0].stride, sf->rgb + y * 64 * 3, 64 * 3);
      assert_memory_equal(dep + (size_t)y * h->plane[1].stride, sf->depth_mm + y * 64, 64 * 2);
    }
    n = vlff_ring_read_copy(fr, fbuf, fcap, &v, 0);
    assert_true(n > 0);
    assert_int_equal(vlff_feature_validate(fbuf, (size_t)n), 0);
    const struct vlff_feature_hdr *fh = (const void *)fbuf;
    assert_int_equal(fh->frame_id, (uint64_t)i);
    assert_int_equal(fh->dim, 16);
    const uint16_t *chw = (const uint16_t *)(fbuf + fh->data_offset);
    size_t hw = (size_t)fh->width * fh->height;
    for (size_t p = 0; p < hw; p++)
      for (int d = 0; d < 16; d++) assert_int_equal(chw[d * hw + p], sf->features[p * 16 + d]);
  }
  free(buf), free(fbuf);
  vlff_sim_frame_free(sf);
  vlff_sim_destroy(s);
  vlff_ring_close(r), vlff_ring_close(fr);
  vlff_shm_unlink(ring), vlff_shm_unlink(fring);
  unlink(cfgpath);
}

/* Options whose value is not a finite number in range are usage errors
 * (exit 2, the option named): --rate nan passed the range test and the
 * simulator slept for ever after its first frame. */
static void test_option_values_refused(void **state) {
  (void)state;
  const char *bin = getenv("VLFF_BINARY_DIR");
  assert_non_null(bin);
  static const char *const cases[][2] = {{"--rate nan", "--rate: expected a number in 0.1..1000, got 'nan'"},
                                         {"--rate inf", "--rate: expected"},
                                         {"--frames nan", "--frames"},
                                         {"--count nan", "--count"}};
  for (size_t k = 0; k < sizeof cases / sizeof cases[0]; k++) {
    char cmd[1400], out[4096];
    snprintf(cmd, sizeof cmd, "timeout 30 ${VLFF_EMULATOR:-} %s/node/sim/vlff-sim --count 1 --quiet %s 2>&1", bin,
             cases[k][0]);
    FILE *f = popen(cmd, "r");
    assert_non_null(f);
    size_t n = fread(out, 1, sizeof out - 1, f);
    out[n] = 0;
    int st = pclose(f);
    if (!WIFEXITED(st) || WEXITSTATUS(st) != 2 || !strstr(out, cases[k][1]))
      fail_msg("%s: status %d: %s", cases[k][0], WIFEXITED(st) ? WEXITSTATUS(st) : -1, out);
  }
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_live_frames_match), cmocka_unit_test(test_option_values_refused))
