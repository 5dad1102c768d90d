/*
 * vlff-replay end to end: a scene directory written to disk (the synthetic
 * room, in the reference layout with features.hdf) is played by the
 * vlff-replay program into the frame, pose and feature rings; the node,
 * reading them as it reads live cameras, must train and publish a map whose
 * labels, read through libvlff-shm at the scene's labelled points, are right.
 * Also: a ScanNet export played into the rings arrives exactly (pixels,
 * depth, poses at the frames' times), the back-pressure mode loses nothing
 * through a small ring, and the command line behaves.
 *
 * Timings scale with VLFF_E2E_SCALE; the quality thresholds do not.
 */
#define _XOPEN_SOURCE 700
#include <errno.h>
#include <ftw.h>
#include <math.h>
#include <setjmp.h>
#include <signal.h>
#include <spawn.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
#include <cmocka.h>

#include "config.h"
#include "dataset.h"
#include "embeddings.h"
#ifdef VLFF_RECORD_BUILT
#include "inputs.h"
#include "mcap.h"
#endif
#include "metrics.h"
#include "node.h"
#include "sim_source.h"
#include "sim.h"
#include "testkit.h"
#include "unit.h"
#include "clock.h"
#include "vlff/shm.h"

#define FRAMES 150

static struct tk tk;
static char scene[300], replay[512];
static const char *cfg_path;

/* The e2e test's room and node settings, fed from rings instead of the sim. */
static void write_config(struct vlff_config *cfg, int ring_slots) {
  cfg_path = tk_config(&tk, cfg,
                       "node:\n  state_dir: %s/state\n"
                       "source:\n  kind: ring\n  features: ring\n"
                       "sim:\n  seed: 3\n  rate_hz: 5\n  width: 160\n  height: 120\n  frames: %d\n"
                       "shm:\n%s"
                       "  max_width: 320\n  max_height: 240\n  ring_slots: %d\n"
                       "train:\n  image_scale: 1.0\n"
                       "keyframes:\n  start_after: 3\n  posecheck_min_steps: 30\n"
                       "publish:\n  rate_hz: 1\n  voxel_size_m: 0.1\n  label_width: 80\n  label_height: 60\n"
                       "prompts:\n  embeddings: %s/prompt_embeddings.txt\n  sets:\n"
                       "    - name: scannet20\n      prompts: [wall, floor, cabinet, bed, chair, sofa, table, door, window,\n"
                       "        bookshelf, picture, counter, desk, curtain, refrigerator, shower curtain, toilet, sink,\n"
                       "        bathtub, other furniture]\n",
                       tk.dir, FRAMES, tk_shm_names(&tk), ring_slots, scene);
}

/* The room's first n frames as a recorded scene in dir: frames, poses,
 * features, prompt vectors. */
static void write_scene_n(const struct vlff_config *cfg, struct vlff_sim_points *gt, const char *dir, int n) {
  char err[1024];
  struct vlff_sim *s = vlff_sim_create(&cfg->sim, &cfg->field, err, sizeof err);
  if (!s) fail_msg("%s", err);
  int W, H, fw, fh, D;
  double fx, fy, cx, cy;
  vlff_sim_size(s, &W, &H, &fw, &fh, &D);
  vlff_sim_intrinsics(s, &fx, &fy, &cx, &cy);
  struct vlff_dataset_writer *w = vlff_dataset_writer_open(dir, n, W, H, fx, fy, cx, cy, cfg->field.scene_min,
                                                           cfg->field.scene_max, "sim", fw, fh, D, err, sizeof err);
  if (!w) fail_msg("%s", err);
  struct vlff_sim_frame *f = vlff_sim_frame_new(s);
  assert_non_null(f);
  for (int i = 0; i < n; i++) {
    if (vlff_sim_render(s, i, VLFF_SIM_ALL, f, err, sizeof err) ||
        vlff_dataset_writer_add(w, i, f->rgb, f->depth_mm, f->label, f->c2w, f->features, err, sizeof err))
      fail_msg("%s", err);
  }
  vlff_sim_frame_free(f);
  if (vlff_dataset_writer_close(w, err, sizeof err)) fail_msg("%s", err);
  const struct vlff_prompt_set *set = &cfg->prompts.sets[cfg->prompts.active];
  float *emb = calloc((size_t)set->count * D, sizeof(float));
  const char *names[VLFF_MAX_PROMPTS];
  assert_non_null(emb);
  for (int k = 0; k < set->count; k++) {
    names[k] = set->text[k];
    vlff_sim_text_embedding(s, set->text[k], emb + (size_t)k * D);
  }
  char p[4200];
  snprintf(p, sizeof p, "%s/prompt_embeddings.txt", dir);
  if (vlff_embeddings_save(p, D, set->count, names, emb, err, sizeof err)) fail_msg("%s", err);
  free(emb);
  if (gt && vlff_sim_points(s, n, 5, 0.05, gt, err, sizeof err)) fail_msg("%s", err);
  vlff_sim_destroy(s);
}

/* The room as a recorded scene: every frame. */
static void write_scene(const struct vlff_config *cfg, struct vlff_sim_points *gt) {
  write_scene_n(cfg, gt, scene, FRAMES);
}

static int setup(void **state) {
  (void)state;
  tk_setup(&tk, "replay");
  snprintf(scene, sizeof scene, "%s/scene", tk.dir);
  snprintf(replay, sizeof replay, "%s/node/dataset/vlff-replay", getenv("VLFF_BINARY_DIR"));
  return 0;
}

static int teardown(void **state) {
  (void)state;
  return tk_teardown(&tk);
}

struct floor_wall {
  int floor_ok, floor_n, wall_ok, wall_n;
};

/* Reads the published map at the scene's floor and wall points: how many
 * are observed (labelled, not unknown or free) and how many of those carry
 * the right prompt. */
static struct floor_wall floor_wall_read(const char *map, const struct vlff_sim_points *gt) {
  struct floor_wall fw = {0};
  struct vlff_map *m = vlff_map_attach(map);
  assert_non_null(m);
  for (size_t i = 0; i < gt->n; i++) {
    uint16_t lab;
    char text[64];
    const float *x = gt->xyz + i * 3;
    if (gt->label[i] > 1 || vlff_map_label_at(m, x[0], x[1], x[2], &lab, NULL) != 0 || lab == VLFF_LABEL_UNKNOWN ||
        lab == VLFF_LABEL_FREE)
      continue;
    int ok = vlff_map_prompt(m, lab, text, sizeof text) == 0 && !strcmp(text, gt->label[i] ? "floor" : "wall");
    if (gt->label[i] == 1) fw.floor_n++, fw.floor_ok += ok;
    else fw.wall_n++, fw.wall_ok += ok;
  }
  vlff_map_detach(m);
  return fw;
}

static bool floor_wall_right(const struct floor_wall *fw) {
  return fw->floor_n >= 300 && fw->wall_n >= 300 && fw->floor_ok > fw->floor_n * 0.7 &&
         fw->wall_ok > fw->wall_n * 0.7;
}

/* The node trains from the replayed scene as from live sensors: every frame
 * paired with its pose (none invalid), keyframes taken, a map published
 * whose labels at the scene's points are right. The map keeps improving
 * while the node trains, so the label check is polled until the deadline
 * rather than read once at the first good mIoU: how far the field has got
 * at a given moment depends on how loaded the host is. */
static void test_node_trains_from_replay(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg, 8);
  struct vlff_sim_points gt = {0};
  write_scene(&cfg, &gt);
  char err[512];
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_node_create(&cfg, &src, err, sizeof err);
  if (!n) fail_msg("%s", err);
  /* The recording's 5 Hz, looped: the node sees the room as vlff-sim shows it. */
  const char *args[] = {"--config", cfg_path, "--fps", "5", "--loop", "--quiet", scene, NULL};
  pid_t pid = tk_spawn(&tk, "node/dataset/vlff-replay", args, NULL);
  double t0 = vlff_seconds(), deadline = 90 * tk.scale;
  uint64_t version = 0;
  double best = tk_wait_miou3d(cfg.shm.map, &gt, 35, deadline, &version);
  struct floor_wall fw = floor_wall_read(cfg.shm.map, &gt);
  while (!floor_wall_right(&fw) && vlff_seconds() - t0 < deadline) {
    tk_sleep_s(0.5);
    fw = floor_wall_read(cfg.shm.map, &gt);
  }
  struct vlff_node_status st;
  tk_report(n, vlff_seconds() - t0, best, version, &st);
  printf("floor %d/%d, wall %d/%d labelled right\n", fw.floor_ok, fw.floor_n, fw.wall_ok, fw.wall_n);
  assert_true(st.frames_in > 0);
  assert_int_equal(st.frames_invalid, 0);
  assert_true(st.keyframes > 0);
  assert_true(version > 0);
  assert_true(best >= 35);
  /* Known points: observed floor points read "floor", walls "wall". */
  assert_true(floor_wall_right(&fw));
  kill(pid, SIGTERM);
  assert_int_equal(tk_wait_child(&tk, pid), 0);
  tk_node_destroy(n, src);
  vlff_sim_points_free(&gt);
}

/* Paced by its reader, a burst far larger than the ring loses nothing, not
 * even the frames before the node attached (on schedule at this rate it
 * loses both), and poses carried in the frame record serve as well as the
 * pose ring. */
static void test_backpressure_loses_nothing(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg, 2);
  assert_int_equal(cfg.shm.ring_slots, 2);
  write_scene(&cfg, NULL);
  char err[512];
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_node_create(&cfg, &src, err, sizeof err);
  if (!n) fail_msg("%s", err);
  const char *args[] = {"-c", cfg_path, "--backpressure", "--pose-in-frame", "--rate", "1000", "--loop", "--count", "240",
                        "--quiet", scene, NULL};
  pid_t pid = tk_spawn(&tk, "node/dataset/vlff-replay", args, NULL);
  assert_int_equal(tk_wait_child(&tk, pid), 0);
  struct vlff_node_status st;
  double t0 = vlff_seconds();
  do {
    tk_sleep_s(0.2);
    vlff_node_status(n, &st);
  } while (st.frames_in < 240 && vlff_seconds() - t0 < 20 * tk.scale);
  printf("%lld frames in, %lld lost, %lld invalid, %d keyframes\n", st.frames_in, st.frames_lost,
         st.frames_invalid, st.keyframes);
  assert_int_equal(st.frames_in, 240);
  assert_int_equal(st.frames_lost, 0);
  assert_int_equal(st.frames_invalid, 0);
  tk_node_destroy(n, src);
}

#ifdef VLFF_RECORD_BUILT
/* A run recorded by vlff-record (docs/replay.md, "MCAP recordings of the
 * inputs") drives the node as the run did: every frame read, none refused
 * (a frame played ahead of its pose would be, "no pose"), none lost. */
static void test_node_reads_mcap_recording(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg, 8);
  write_scene_n(&cfg, NULL, scene, 30);
  char mcap[400], log[400];
  snprintf(mcap, sizeof mcap, "%s/run.mcap", tk.dir);
  snprintf(log, sizeof log, "%s/record.log", tk.dir);
  const char *rargs[] = {"-c", cfg_path, "--quiet", mcap, NULL};
  pid_t rec = tk_spawn(&tk, "node/view/vlff-record", rargs, log);
  const char *args1[] = {"-c", cfg_path, "--backpressure", "--quiet", scene, NULL};
  assert_int_equal(tk_wait_child(&tk, tk_spawn(&tk, "node/dataset/vlff-replay", args1, NULL)), 0);
  kill(rec, SIGINT);
  assert_int_equal(tk_wait_child(&tk, rec), 0);
  printf("%s", tk_slurp(log));
  assert_non_null(strstr(tk_slurp(log), "30 frames, 30 poses, 30 feature maps recorded; 0 records missed"));
  vlff_shm_unlink(cfg.shm.ring);
  vlff_shm_unlink(cfg.shm.pose_ring);
  vlff_shm_unlink(cfg.shm.feature_ring);
  char err[512];
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_node_create(&cfg, &src, err, sizeof err);
  if (!n) fail_msg("%s", err);
  const char *args2[] = {"-c", cfg_path, "--backpressure", "--quiet", mcap, NULL};
  assert_int_equal(tk_wait_child(&tk, tk_spawn(&tk, "node/dataset/vlff-replay", args2, NULL)), 0);
  struct vlff_node_status st;
  double t0 = vlff_seconds();
  do {
    tk_sleep_s(0.2);
    vlff_node_status(n, &st);
  } while (st.frames_in < 30 && vlff_seconds() - t0 < 20 * tk.scale);
  printf("%lld frames in, %lld lost, %lld refused (no pose %lld)\n", st.frames_in, st.frames_lost, st.frames_invalid,
         st.refused[VLFF_REFUSED_NO_POSE]);
  assert_int_equal(st.frames_in, 30);
  assert_int_equal(st.frames_lost, 0);
  assert_int_equal(st.frames_invalid, 0);
  tk_node_destroy(n, src);
}
#endif

/* A ScanNet export (color/, depth/, pose/ camera-to-world, intrinsic/),
 * played paced by a reader that is this test: every frame arrives with the
 * scene's pixels and millimetre depth, its pose waits in the pose ring at the
 * frame's host time (the lookup finds it exactly), and nothing is lost. */
static void test_scannet_layout_into_rings(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg, 2);
  char err[1024], p[512];
  struct vlff_sim *s = vlff_sim_create(&cfg.sim, &cfg.field, err, sizeof err);
  if (!s) fail_msg("%s", err);
  struct vlff_sim_frame *f = vlff_sim_frame_new(s);
  const char *subs[] = {"", "/color", "/depth", "/pose", "/intrinsic"};
  for (int k = 0; k < 5; k++) {
    snprintf(p, sizeof p, "%s%s", scene, subs[k]);
    assert_int_equal(mkdir(p, 0755), 0);
  }
  enum { N = 6 };
  double c2w[N][16];
  for (int i = 0; i < N; i++) {
    assert_int_equal(vlff_sim_render(s, i * 7, VLFF_SIM_RGBD, f, err, sizeof err), 0);
    snprintf(p, sizeof p, "%s/color/%d.png", scene, i);
    if (vlff_png_write(p, f->rgb, f->width, f->height, 3, 0, err, sizeof err)) fail_msg("%s", err);
    snprintf(p, sizeof p, "%s/depth/%d.png", scene, i);
    if (vlff_png_write(p, f->depth_mm, f->width, f->height, 1, 1, err, sizeof err)) fail_msg("%s", err);
    snprintf(p, sizeof p, "%s/pose/%d.txt", scene, i);
    FILE *pf = fopen(p, "w");
    assert_non_null(pf);
    for (int e = 0; e < 16; e++) fprintf(pf, "%.17g%c", f->c2w[e], e % 4 == 3 ? '\n' : ' ');
    fclose(pf);
    memcpy(c2w[i], f->c2w, sizeof c2w[i]);
  }
  snprintf(p, sizeof p, "%s/intrinsic/intrinsic_color.txt", scene);
  FILE *kf = fopen(p, "w");
  assert_non_null(kf);
  /* ScanNet's intrinsics count pixels as OpenCV does (centre of pixel 0 at 0) */
  fprintf(kf, "%.17g 0 %.17g 0\n0 %.17g %.17g 0\n0 0 1 0\n0 0 0 1\n", f->fx, f->cx - 0.5, f->fy, f->cy - 0.5);
  fclose(kf);
  const int W = f->width, H = f->height;
  uint8_t *rgb0 = malloc((size_t)W * H * 3);
  uint16_t *dep0 = malloc((size_t)W * H * 2);
  const char *args[] = {"-c", cfg_path, "--layout", "scannet", "--backpressure", "--quiet", scene, NULL};
  pid_t pid = tk_spawn(&tk, "node/dataset/vlff-replay", args, NULL);
  struct vlff_ring *fr = NULL, *pr = NULL;
  for (int k = 0; k < 200 && !(fr && pr); k++) {
    if (!fr) fr = vlff_ring_attach(cfg.shm.ring, VLFF_RECORD_FRAME);
    if (!pr) pr = vlff_ring_attach(cfg.shm.pose_ring, VLFF_RECORD_POSE);
    if (!(fr && pr)) tk_sleep_s(0.02);
  }
  assert_non_null(fr);
  assert_non_null(pr);
  void *buf = malloc(vlff_ring_slot_size(fr));
  for (int i = 0; i < N; i++) {
    struct vlff_ring_view v;
    ssize_t len = vlff_ring_read_copy(fr, buf, vlff_ring_slot_size(fr), &v, 10ull * 1000 * 1000 * 1000);
    if (len < 0) fail_msg("frame %d: %s", i, vlff_shm_last_message());
    assert_int_equal(vlff_frame_validate(buf, (size_t)len), 0);
    const struct vlff_frame_hdr *h = buf;
    assert_int_equal(h->frame_id, (uint64_t)i);
    assert_false(h->flags & VLFF_FRAME_POSE_VALID);
    assert_true(h->flags & VLFF_FRAME_INTRINSICS_VALID);
    assert_true(fabs(h->fx - f->fx) < 1e-9 && fabs(h->cy - f->cy) < 1e-9);
    struct vlff_pose_rec pose;
    assert_int_equal(vlff_pose_lookup(pr, h->t_host_ns, 0, &pose), 0);
    for (int e = 0; e < 16; e++) assert_true(fabs(pose.pose[e] - c2w[i][e]) < 1e-9);
    assert_int_equal(vlff_sim_render(s, i * 7, VLFF_SIM_RGBD, f, err, sizeof err), 0);
    const uint8_t *rgb = vlff_frame_plane(buf, VLFF_PLANE_COLOR);
    const uint8_t *dep = vlff_frame_plane(buf, VLFF_PLANE_DEPTH);
    for (int y = 0; y < H; y++) {
      memcpy(rgb0 + (size_t)y * W * 3, rgb + (size_t)y * h->plane[0].stride, (size_t)W * 3);
      memcpy(dep0 + (size_t)y * W, dep + (size_t)y * h->plane[1].stride, (size_t)W * 2);
    }
    assert_memory_equal(rgb0, f->rgb, (size_t)W * H * 3);
    assert_memory_equal(dep0, f->depth_mm, (size_t)W * H * 2);
  }
  assert_int_equal(vlff_ring_lost(fr), 0);
  assert_int_equal(tk_wait_child(&tk, pid), 0);
  free(buf), free(rgb0), free(dep0);
  vlff_ring_close(fr);
  vlff_ring_close(pr);
  vlff_sim_frame_free(f);
  vlff_sim_destroy(s);
}

/* Runs the program with output into a file; returns its exit status and
 * the output in out. */
static int run_cli(const char *args, char *out, size_t cap) {
  char cmd[2000], path[300];
  snprintf(path, sizeof path, "%s/cli.out", tk.dir);
  snprintf(cmd, sizeof cmd, "%s %s >%s 2>&1", replay, args, path);
  int st = system(cmd);
  FILE *f = fopen(path, "r");
  assert_non_null(f);
  size_t len = fread(out, 1, cap - 1, f);
  out[len] = 0;
  fclose(f);
  return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

static void test_cli(void **state) {
  (void)state;
  char out[8192], args[1000];
  assert_int_equal(run_cli("--help", out, sizeof out), 0);
  assert_non_null(strstr(out, "Usage: vlff-replay"));
  assert_non_null(strstr(out, "--backpressure"));
  assert_int_equal(run_cli("-V", out, sizeof out), 0);
  assert_non_null(strstr(out, "vlff-replay "));
  assert_int_equal(run_cli("", out, sizeof out), 2);
  assert_non_null(strstr(out, "no SCENE given"));
  assert_int_equal(run_cli("--rate 0 /tmp", out, sizeof out), 2);
  assert_non_null(strstr(out, "--rate"));
  assert_int_equal(run_cli("--layout tum /tmp", out, sizeof out), 2);
  assert_non_null(strstr(out, "--layout"));
  snprintf(args, sizeof args, "%s/nowhere", tk.dir);
  assert_int_equal(run_cli(args, out, sizeof out), 1);
  assert_non_null(strstr(out, "nowhere"));
  /* No config anywhere on the search path: the default ring names, said so
   * (unless this host has the installed config). */
  if (access(vlff_config_default_path(), F_OK) != 0) {
    snprintf(args, sizeof args, "%s/nowhere", tk.dir);
    char *saved = getenv("VLFF_CONFIG") ? strdup(getenv("VLFF_CONFIG")) : NULL;
    unsetenv("VLFF_CONFIG");
    assert_int_equal(run_cli(args, out, sizeof out), 1);
    if (saved) setenv("VLFF_CONFIG", saved, 1), free(saved);
    assert_non_null(strstr(out, "no config: no --config given, $VLFF_CONFIG not set"));
    assert_non_null(strstr(out, "using the default ring names (/vlff-frames, "));
  }
  /* A frame whose image is damaged is named, skipped and counted; the rest
   * are published and the exit status says something was wrong. */
  struct vlff_config cfg;
  write_config(&cfg, 8);
  /* With a config, no word about default names. */
  snprintf(args, sizeof args, "-c %s %s/nowhere", cfg_path, tk.dir);
  assert_int_equal(run_cli(args, out, sizeof out), 1);
  assert_null(strstr(out, "default ring names"));
  write_scene(&cfg, NULL);
  char p[400];
  snprintf(p, sizeof p, "%s/rgb/00003.png", scene);
  FILE *f = fopen(p, "w");
  assert_non_null(f);
  fputs("not a png", f);
  fclose(f);
  snprintf(args, sizeof args, "-c %s --rate 100 --count 6 %s", cfg_path, scene);
  assert_int_equal(run_cli(args, out, sizeof out), 1);
  assert_non_null(strstr(out, "rgb/00003.png"));
  assert_non_null(strstr(out, "5 frames published, 1 unreadable"));
  struct vlff_ring *r = vlff_ring_attach(cfg.shm.ring, VLFF_RECORD_FRAME);
  assert_non_null(r);
  assert_int_equal(vlff_ring_head(r), 5);
  vlff_ring_close(r);
}

/* Frame i's time in the stamped scene below: 4 Hz, frame 3 a little late,
 * the recording starting at 10 s. */
static double stamp(int i) { return 10 + i * 0.25 + (i == 3 ? 0.1 : 0); }

/* Reads n frames as the ring's reader (the replay paced by it) and checks
 * each one's place in the recording, t_device_ns, against want(i). */
static void expect_device_times(const struct vlff_config *cfg, int n, double (*want)(int)) {
  struct vlff_ring *fr = NULL;
  for (int k = 0; k < 200 && !fr; k++)
    if (!(fr = vlff_ring_attach(cfg->shm.ring, VLFF_RECORD_FRAME))) tk_sleep_s(0.02);
  assert_non_null(fr);
  void *buf = malloc(vlff_ring_slot_size(fr));
  for (int i = 0; i < n; i++) {
    struct vlff_ring_view v;
    ssize_t len = vlff_ring_read_copy(fr, buf, vlff_ring_slot_size(fr), &v, 10ull * 1000 * 1000 * 1000);
    if (len < 0) fail_msg("frame %d: %s", i, vlff_shm_last_message());
    const struct vlff_frame_hdr *h = buf;
    double t = (double)h->t_device_ns * 1e-9;
    if (fabs(t - want(i)) > 1e-6) fail_msg("frame %d: t_device %.6f s, expected %.6f s", i, t, want(i));
  }
  free(buf);
  vlff_ring_close(fr);
}

static double stamped(int i) { return stamp(i) - stamp(0); }
static double at_5hz(int i) { return i * 0.2; }

/* The recording's own stamps pace the replay by default (issue 55: the
 * default 30 Hz had to be lowered by hand for a 5 Hz recording); --fps
 * still gives a uniform rate; stamps that go backwards are refused, naming
 * the file and the frame. */
static void test_stamps_pace_the_replay(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg, 2);
  write_scene(&cfg, NULL);
  char p[400], out[8192], args[1000];
  snprintf(p, sizeof p, "%s/timestamps.txt", scene);
  FILE *f = fopen(p, "w");
  assert_non_null(f);
  fprintf(f, "# stem seconds\n");
  for (int i = 0; i < FRAMES; i++) fprintf(f, "%05d %.6f\n", i, stamp(i));
  fclose(f);
  const char *args1[] = {"-c", cfg_path, "--backpressure", "--count", "6", "--quiet", scene, NULL};
  pid_t pid = tk_spawn(&tk, "node/dataset/vlff-replay", args1, NULL);
  expect_device_times(&cfg, 6, stamped);
  assert_int_equal(tk_wait_child(&tk, pid), 0);
  snprintf(args, sizeof args, "-c %s --rate 100 --count 3 %s", cfg_path, scene);
  assert_int_equal(run_cli(args, out, sizeof out), 0);
  assert_non_null(strstr(out, "at the recording's stamps (4.00 Hz on average)"));
  const char *args2[] = {"-c", cfg_path, "--backpressure", "--fps", "5", "--count", "6", "--quiet", scene, NULL};
  pid = tk_spawn(&tk, "node/dataset/vlff-replay", args2, NULL);
  expect_device_times(&cfg, 6, at_5hz);
  assert_int_equal(tk_wait_child(&tk, pid), 0);
  f = fopen(p, "w");
  assert_non_null(f);
  for (int i = 0; i < FRAMES; i++) fprintf(f, "%05d %.6f\n", i, i == 7 ? 1.0 : stamp(i));
  fclose(f);
  snprintf(args, sizeof args, "-c %s --rate 100 --count 3 %s", cfg_path, scene);
  assert_int_equal(run_cli(args, out, sizeof out), 1);
  if (!strstr(out, "timestamps.txt: frame 00007: stamp 1.000000 s is ")) fail_msg("%s", out);
  /* seconds are decimal (0x1p-2 was read as 0.25), and a stem names a frame
   * of the scene (one of no frame was passed over) */
  static const char *const bad[][2] = {{"99999 1.0", "timestamps.txt:151: the scene has no frame 99999"},
                                       {"99999 0x1p-2", "timestamps.txt:151: expected \"STEM SECONDS\" (decimal seconds)"}};
  for (int k = 0; k < 2; k++) {
    f = fopen(p, "w");
    assert_non_null(f);
    for (int i = 0; i < FRAMES; i++) fprintf(f, "%05d %.6f\n", i, stamp(i));
    fprintf(f, "%s\n", bad[k][0]);
    fclose(f);
    assert_int_equal(run_cli(args, out, sizeof out), 1);
    if (!strstr(out, bad[k][1])) fail_msg("%s: %s", bad[k][0], out);
  }
}

extern char **environ;

/* vlff-replay playing dir (a scene or a recording) as fast as it can into
 * the rings (nothing reads them), with the options in more (NULL-terminated,
 * or NULL), its output in log: it must succeed. Its peak resident set in MiB
 * (vlff_test_wait_peak). */
static double replay_rss_args(const char *dir, const char *log, const char *const *more) {
  const char *argv[16] = {replay, "-c", cfg_path, "--fps", "1000", "--quiet"};
  int a = 6;
  while (more && *more && a < 14) argv[a++] = *more++;
  argv[a] = dir;
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  posix_spawn_file_actions_addopen(&fa, 1, log, O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_adddup2(&fa, 1, 2);
  pid_t pid;
  assert_int_equal(posix_spawn(&pid, replay, &fa, NULL, (char *const *)argv, environ), 0);
  posix_spawn_file_actions_destroy(&fa);
  int st;
  double peak = vlff_test_wait_peak(pid, &st);
  if (st == -1 || !WIFEXITED(st) || WEXITSTATUS(st) != 0)
    fail_msg("vlff-replay %s failed (status %d): see %s", dir, st, log);
  assert_true(peak > 0);
  return peak;
}

static double replay_rss(const char *dir, const char *log) { return replay_rss_args(dir, log, NULL); }

/* A scene ten times longer plays in the same memory (issue 48 item 3):
 * frames and features are read as they are played, one at a time. 150
 * frames of 160x120 with 40x30x512 features are about 190 MiB on disk and
 * decoded; 15 of them about 19 MiB. The longer one may peak at most 4 MiB
 * higher (its per-frame index, a few hundred bytes a frame, and allocator
 * slack): far less than the 170 MiB the extra frames hold. */
static void test_replay_memory(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg, 2);
  char small[400], big_log[400], small_log[400];
  snprintf(small, sizeof small, "%s/short", tk.dir);
  write_scene_n(&cfg, NULL, small, 15);
  write_scene(&cfg, NULL);
  snprintf(small_log, sizeof small_log, "%s/short.log", tk.dir);
  snprintf(big_log, sizeof big_log, "%s/long.log", tk.dir);
  double rs = replay_rss(small, small_log), rb = replay_rss(scene, big_log);
  printf("vlff-replay peak RSS: 15 frames %.1f MiB, 150 frames %.1f MiB\n", rs, rb);
  assert_true(rb <= rs + 4);
}

#ifdef VLFF_RECORD_BUILT
/* A recording of n frames of 320 x 240 (pseudo-random colour and depth: no
 * chunk compresses them), frames only, 100 ms apart: about 0.5 MiB a frame. */
static void write_big_recording(const char *path, int n) {
  char err[512];
  struct vlff_mcap_writer_params wp = {"test_replay", 0, 0, 0};
  struct vlff_mcap_writer *w = vlff_mcap_writer_open(path, &wp, err, sizeof err);
  if (!w || vlff_in_declare(w, err, sizeof err)) fail_msg("%s", err);
  enum { BW = 320, BH = 240 };
  size_t cap = vlff_frame_slot_size(BW, BH, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM);
  struct vlff_frame_hdr *h = aligned_alloc(64, (cap + 63) / 64 * 64);
  assert_non_null(h);
  char *scratch = NULL;
  size_t scap = 0;
  uint32_t x = 12345;
  for (int i = 0; i < n; i++) {
    memset(h, 0, cap);
    uint64_t len = vlff_frame_layout(h, cap, BW, BH, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM);
    assert_true(len > 0);
    h->frame_id = (uint64_t)i, h->t_host_ns = 1000000000ull + (uint64_t)i * 100000000ull;
    h->flags = VLFF_FRAME_INTRINSICS_VALID;
    h->fx = h->fy = 250, h->cx = BW / 2.0, h->cy = BH / 2.0;
    uint8_t *c = (uint8_t *)h + h->plane[0].offset;
    for (size_t k = 0; k < (size_t)BW * BH * 3; k++) x = x * 1664525u + 1013904223u, c[k] = (uint8_t)(x >> 24);
    uint16_t *d = (uint16_t *)((uint8_t *)h + h->plane[1].offset);
    for (size_t k = 0; k < (size_t)BW * BH; k++) x = x * 1664525u + 1013904223u, d[k] = (uint16_t)(500 + (x >> 22));
    if (vlff_in_write_frame(w, h, len, &scratch, &scap, err, sizeof err)) fail_msg("%s", err);
  }
  free(scratch);
  free(h);
  if (vlff_mcap_writer_close(w, err, sizeof err)) fail_msg("%s", err);
}

/* A recording ten times longer plays in about the same memory (issue 48 item
 * 3): the file is mapped and the pages the replay has passed go back every
 * 4 MiB, so its resident set does not grow with the file (before, it was
 * read whole: 12 frames 6 MiB, 120 frames 59 MiB; the bound is 20 MiB more). Checked and played twice (--loop
 * --count), so the second pass reads the file again too. */
static void test_long_recording_memory(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg, 2);
  char small[400], big[400], small_log[400], big_log[400];
  snprintf(small, sizeof small, "%s/short.mcap", tk.dir);
  snprintf(big, sizeof big, "%s/long.mcap", tk.dir);
  snprintf(small_log, sizeof small_log, "%s/short.log", tk.dir);
  snprintf(big_log, sizeof big_log, "%s/long.log", tk.dir);
  write_big_recording(small, 12);
  write_big_recording(big, 120);
  struct stat ss, sb;
  assert_int_equal(stat(small, &ss), 0);
  assert_int_equal(stat(big, &sb), 0);
  const char *sargs[] = {"--loop", "--count", "24", NULL}, *bargs[] = {"--loop", "--count", "240", NULL};
  double rs = replay_rss_args(small, small_log, sargs), rb = replay_rss_args(big, big_log, bargs);
  printf("vlff-replay peak RSS: 12 frames (%.1f MiB file) %.1f MiB, 120 frames (%.1f MiB file) %.1f MiB\n",
         ss.st_size / 1048576.0, rs, sb.st_size / 1048576.0, rb);
  assert_true(sb.st_size > 50 << 20);
  assert_true(rb <= rs + 20);
}

/* A recording cut short while it plays (another program rewrote it): the
 * mapped pages past its new end fault, and vlff-replay says so and exits 1,
 * rather than dying of SIGBUS. Held by --backpressure before its first frame
 * (the file was checked whole) while the file is cut to 2 MiB, then read. */
static void test_recording_cut_while_played(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg, 2);
  char rec[400], log[400];
  snprintf(rec, sizeof rec, "%s/cut.mcap", tk.dir);
  snprintf(log, sizeof log, "%s/cut.log", tk.dir);
  write_big_recording(rec, 30);
  const char *args[] = {"-c", cfg_path, "--backpressure", "--quiet", rec, NULL};
  pid_t pid = tk_spawn(&tk, "node/dataset/vlff-replay", args, log);
  struct vlff_ring *r = NULL;
  for (double t0 = vlff_seconds(); !r && vlff_seconds() - t0 < 30 * tk.scale; tk_sleep_s(0.05))
    r = vlff_ring_attach(cfg.shm.ring, VLFF_RECORD_FRAME);
  if (!r) fail_msg("no frame ring: %s", tk_slurp(log));
  assert_int_equal(truncate(rec, 2 << 20), 0);
  int read = 0, ended = 0;
  for (double t0 = vlff_seconds(); !ended && vlff_seconds() - t0 < 30 * tk.scale;) {
    struct vlff_ring_view v;
    if (vlff_ring_read_begin(r, &v, 50000000ull) == 0) read += vlff_ring_read_end(r, &v) == 0;
    siginfo_t si = {0};
    ended = waitid(P_PID, (id_t)pid, &si, WEXITED | WNOHANG | WNOWAIT) == 0 && si.si_pid == pid;
  }
  vlff_ring_close(r);
  if (!ended) fail_msg("vlff-replay still runs with its file cut short: %s", tk_slurp(log));
  int st = tk_wait_child(&tk, pid);
  printf("%d frames read before the cut; vlff-replay: %s", read, tk_slurp(log));
  assert_int_equal(st, 1);
  assert_non_null(strstr(tk_slurp(log), "cut.mcap: the file was cut short while it was played"));
  assert_true(read >= 1 && read < 30);
}
#endif

int main(void) {
  const struct CMUnitTest tests[] = {
      cmocka_unit_test_setup_teardown(test_cli, setup, teardown),
      cmocka_unit_test_setup_teardown(test_replay_memory, setup, teardown),
      cmocka_unit_test_setup_teardown(test_scannet_layout_into_rings, setup, teardown),
      cmocka_unit_test_setup_teardown(test_stamps_pace_the_replay, setup, teardown),
      cmocka_unit_test_setup_teardown(test_backpressure_loses_nothing, setup, teardown),
      cmocka_unit_test_setup_teardown(test_node_trains_from_replay, setup, teardown),
#ifdef VLFF_RECORD_BUILT
      cmocka_unit_test_setup_teardown(test_node_reads_mcap_recording, setup, teardown),
      cmocka_unit_test_setup_teardown(test_long_recording_memory, setup, teardown),
      cmocka_unit_test_setup_teardown(test_recording_cut_while_played, setup, teardown),
#endif
  };
  if (getenv("VLFF_TEST_FILTER")) cmocka_set_test_filter(getenv("VLFF_TEST_FILTER"));
  return cmocka_run_group_tests(tests, NULL, NULL);
}
