/*
 * The node end to end: vlff-sim at 5 Hz -> frame ring -> node -> map
 * segment, read back through the controller reader library exactly as a
 * controller would. Ground truth comes from the same synthetic scene.
 *
 * Timings scale with VLFF_E2E_SCALE (sanitizer builds run slower); the
 * quality thresholds do not.
 */
#include <errno.h>
#include <math.h>
#include <setjmp.h>
#include <signal.h>
#include <spawn.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
#include <cmocka.h>

#include "config.h"
#include "metrics.h"
#include "node.h"
#include "sim.h"
#include "vlff/shm.h"

extern char **environ;

static char dir[256], cfg_path[300], tag[64];
static double scale = 1.0;

static double mono_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void sleep_s(double s) {
  struct timespec ts = {(time_t)s, (long)((s - (time_t)s) * 1e9)};
  nanosleep(&ts, NULL);
}

/* A config with this test's own segment names and state directory. */
static void write_config(struct vlff_config *cfg, const char *extra) {
  snprintf(cfg_path, sizeof cfg_path, "%s/node.yaml", dir);
  FILE *f = fopen(cfg_path, "w");
  assert_non_null(f);
  fprintf(f,
          "node:\n  state_dir: %s/state\n  checkpoint_period_s: 4\n"
          "source:\n  kind: sim\n  features: sim\n"
          "sim:\n  seed: 3\n  rate_hz: 5\n  width: 160\n  height: 120\n  frames: 150\n"
          "shm:\n  ring: /%s-f\n  map: /%s-m\n  prompts: /%s-p\n  pose_ring: /%s-q\n  feature_ring: /%s-x\n"
          "  max_width: 320\n  max_height: 240\n"
          "train:\n  image_scale: 1.0\n"
          "keyframes:\n  start_after: 3\n"
          "publish:\n  rate_hz: 1\n  voxel_size_m: 0.1\n  label_width: 80\n  label_height: 60\n"
          "prompts:\n  sets:\n"
          "    - name: scannet20\n      prompts: [wall, floor, cabinet, bed, chair, sofa, table, door, window,\n"
          "        bookshelf, picture, counter, desk, curtain, refrigerator, shower curtain, toilet, sink,\n"
          "        bathtub, other furniture]\n"
          "    - name: coarse\n      prompts: [wall, floor, bed]\n"
          "%s",
          dir, tag, tag, tag, tag, tag, extra ? extra : "");
  fclose(f);
  char err[512];
  if (vlff_config_load(cfg_path, cfg, err, sizeof err)) fail_msg("%s", err);
}

static pid_t spawn(const char *prog, const char *const *args) {
  char path[512];
  snprintf(path, sizeof path, "%s/%s", getenv("VLFF_BINARY_DIR"), prog);
  char *argv[16];
  int n = 0;
  argv[n++] = path;
  for (; args[n - 1] && n < 15; n++) argv[n] = (char *)args[n - 1];
  argv[n] = NULL;
  pid_t pid;
  assert_int_equal(posix_spawn(&pid, path, NULL, NULL, argv, environ), 0);
  return pid;
}

static void stop_child(pid_t pid, int sig) {
  if (pid <= 0) return;
  kill(pid, sig);
  int st;
  waitpid(pid, &st, 0);
}

/* 3D mIoU of the published map at the scene's labelled points, through the
 * controller library; -1 before the first publish. */
static double map_miou3d(const struct vlff_config *cfg, uint64_t *version, int *prompt_count) {
  char err[256];
  struct vlff_map *m = vlff_map_attach(cfg->shm.map);
  if (!m) return -1;
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(m);
  double miou = -1;
  struct vlff_map_info info;
  if (snap && vlff_map_snapshot_take(m, snap) == 0 && vlff_map_snapshot_info(snap, &info) == 0 &&
      info.version > 0) {
    if (version) *version = info.version;
    if (prompt_count) *prompt_count = info.prompt_count;
    struct vlff_sim *s = vlff_sim_create(cfg, err, sizeof err);
    struct vlff_sim_points pts = {0};
    struct vlff_confusion c;
    assert_non_null(s);
    assert_int_equal(vlff_sim_points(s, cfg->sim.frames, 5, 0.05, &pts, err, sizeof err), 0);
    assert_int_equal(vlff_confusion_init(&c, VLFF_SIM_CLASSES, err, sizeof err), 0);
    for (size_t i = 0; i < pts.n; i++) {
      const float *x = pts.xyz + i * 3;
      uint16_t lab = vlff_map_snapshot_label_at(snap, x[0], x[1], x[2], NULL);
      const char *text = vlff_map_snapshot_prompt(snap, lab);
      vlff_confusion_add_one(&c, pts.label[i], text ? vlff_sim_class_of(text) : -1);
    }
    struct vlff_summary sum;
    vlff_confusion_summary(&c, &sum);
    miou = sum.miou * 100;
    vlff_confusion_free(&c);
    vlff_sim_points_free(&pts);
    vlff_sim_destroy(s);
  }
  vlff_map_snapshot_free(snap);
  vlff_map_detach(m);
  return miou;
}

static int setup(void **state) {
  (void)state;
  const char *sc = getenv("VLFF_E2E_SCALE");
  if (sc) scale = atof(sc) > 0 ? atof(sc) : 1;
  snprintf(tag, sizeof tag, "e2e%d", (int)getpid());
  snprintf(dir, sizeof dir, "/tmp/vlff-%s", tag);
  mkdir(dir, 0755);
  return 0;
}

static int teardown(void **state) {
  (void)state;
  char cmd[600];
  snprintf(cmd, sizeof cmd, "rm -rf %s /dev/shm/%s-*", dir, tag);
  return system(cmd) == 0 ? 0 : -1;
}

/* Learns a useful map from the live stream; run-time prompts re-segment it
 * without retraining. */
static void test_learns_and_reprompts(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg, NULL);
  const char *args[] = {"--config", cfg_path, "--quiet", NULL};
  pid_t sim = spawn("node/sim/vlff-sim", args);
  char err[512];
  struct vlff_node *n = vlff_node_create(&cfg, err, sizeof err);
  if (!n) fail_msg("%s", err);
  double best = -1, t0 = mono_s();
  uint64_t version = 0;
  while (mono_s() - t0 < 90 * scale) {
    sleep_s(2);
    best = fmax(best, map_miou3d(&cfg, &version, NULL));
    if (best >= 35) break;
  }
  struct vlff_node_status st;
  vlff_node_status(n, &st);
  printf("after %.0f s: 3D mIoU %.1f, %lld iterations, %d keyframes, map v%llu\n", mono_s() - t0, best,
         st.iteration, st.keyframes, (unsigned long long)version);
  assert_true(best >= 35);
  assert_int_equal(st.frames_invalid, 0);

  /* A controller posts its own prompts: the next publish uses them. */
  struct vlff_prompts *pb = vlff_prompts_attach(cfg.shm.prompts);
  assert_non_null(pb);
  const char *texts[] = {"floor", "wall"};
  assert_int_equal(vlff_prompts_post(pb, texts, 2), 0);
  vlff_prompts_close(pb);
  int count = 0;
  t0 = mono_s();
  while (mono_s() - t0 < 20 * scale && count != 2) {
    sleep_s(0.5);
    map_miou3d(&cfg, NULL, &count);
  }
  assert_int_equal(count, 2);
  struct vlff_map *m = vlff_map_attach(cfg.shm.map);
  assert_non_null(m);
  char text[64];
  assert_int_equal(vlff_map_prompt(m, 0, text, sizeof text), 0);
  assert_string_equal(text, "floor");
  assert_int_equal(vlff_map_prompt(m, 2, text, sizeof text), -1);
  /* Floor points now read "floor", walls "wall". */
  struct vlff_sim *s = vlff_sim_create(&cfg, err, sizeof err);
  struct vlff_sim_points pts = {0};
  assert_int_equal(vlff_sim_points(s, cfg.sim.frames, 5, 0.05, &pts, err, sizeof err), 0);
  int floor_ok = 0, floor_n = 0, wall_ok = 0, wall_n = 0;
  for (size_t i = 0; i < pts.n; i++) {
    uint16_t lab;
    const float *x = pts.xyz + i * 3;
    if (vlff_map_label_at(m, x[0], x[1], x[2], &lab, NULL) != 0) continue;
    if (pts.label[i] == 1) floor_n++, floor_ok += lab == 0;
    if (pts.label[i] == 0) wall_n++, wall_ok += lab == 1;
  }
  printf("two prompts: floor %d/%d, wall %d/%d\n", floor_ok, floor_n, wall_ok, wall_n);
  assert_true(floor_n > 0 && wall_n > 0);
  assert_true(floor_ok > floor_n * 0.7 && wall_ok > wall_n * 0.7);
  vlff_map_detach(m);

  /* A CAN-style command selects a configured set by index. */
  assert_int_equal(vlff_node_command(n, VLFF_CMD_PROMPT_SET, 1), 0);
  assert_int_equal(vlff_node_command(n, VLFF_CMD_PROMPT_SET, 7), -1);
  t0 = mono_s();
  while (mono_s() - t0 < 20 * scale && count != 3) {
    sleep_s(0.5);
    map_miou3d(&cfg, NULL, &count);
  }
  assert_int_equal(count, 3);
  vlff_node_status(n, &st);
  assert_int_equal(st.prompt_set, 1);
  vlff_sim_points_free(&pts);
  vlff_sim_destroy(s);
  vlff_node_destroy(n, false);
  stop_child(sim, SIGTERM);
}

int main(void) {
  const struct CMUnitTest tests[] = {
      cmocka_unit_test_setup_teardown(test_learns_and_reprompts, setup, teardown),
  };
  return cmocka_run_group_tests(tests, NULL, NULL);
}
