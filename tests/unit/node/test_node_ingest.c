/*
 * The node's frame ingest against the real programs: vlff-node says why it
 * refuses frames (per reason, on --status and in its log), and frames
 * without a pose are refused until vlff-pose feeds the matching trajectory
 * into the pose ring, from a file and over UDP; then they become keyframes.
 * Frames come from the synthetic scene, written into a frame ring as a
 * camera driver would.
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
#include <sys/mman.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <netinet/in.h>
#include <arpa/inet.h>
#include <fcntl.h>
#include <time.h>
#include <unistd.h>
#include <cmocka.h>
#include <stdbool.h>

#include "config.h"
#include "log.h"
#include "node.h"
#include "sim_source.h"
#include "sim.h"
#include "testkit.h"
#include "clock.h"
#include "vlff/shm.h"

static struct tk tk;
static const char *cfg_path;

/* The ring carries the simulator's frames, so its features are forced on. */
static void write_config(struct vlff_config *cfg) {
  cfg_path = tk_config(&tk, cfg,
                       "node:\n  state_dir: %s/state\n  checkpoint_period_s: 0\n  log_level: info\n"
                       "source:\n  kind: ring\n  features: sim\n  allow_sim_features: true\n  pose_wait_s: 1\n"
                       "sim:\n  seed: 3\n  width: 160\n  height: 120\n  frames: 150\n"
                       "shm:\n%s"
                       "  max_width: 320\n  max_height: 240\n"
                       "train:\n  image_scale: 0.5\n"
                       "keyframes:\n  start_after: 3\n"
                       "publish:\n  rate_hz: 1\n  label_width: 40\n  label_height: 30\n",
                       tk.dir, tk_shm_names(&tk));
}

static int setup(void **state) {
  (void)state;
  tk_setup(&tk, "ing");
  return 0;
}

static int teardown(void **state) {
  (void)state;
  return tk_teardown(&tk);
}

enum frame_kind { GOOD, NO_POSE_FLAG, NO_DEPTH, BAD_INTRINSICS, FUTURE_POSE, POSE_CM, POSE_JUMPED, FAR_DEPTH };

/* Writes simulator frame `index` into the ring, stamped t_ns. The pose
 * travels in the frame except for NO_POSE_FLAG (the pose ring must give
 * it). */
static void put_frame(struct vlff_ring *ring, struct vlff_sim *s, struct vlff_sim_frame *f, long long index,
                      uint64_t t_ns, enum frame_kind kind) {
  char err[256];
  assert_int_equal(vlff_sim_render(s, index, VLFF_SIM_RGBD, f, err, sizeof err), 0);
  uint64_t len;
  struct vlff_frame_hdr *h = tk_frame_reserve(ring, f, index, t_ns, f->width, f->height,
                                              kind == NO_DEPTH ? VLFF_PIX_NONE : VLFF_PIX_DEPTH_U16_MM, &len);
  /* A focal length in millimetres where pixels belong. */
  if (kind == BAD_INTRINSICS) h->fx = h->fy = 3.6;
  if (kind == NO_POSE_FLAG) { /* no pose at all in the frame, as layout left it */
    h->flags &= ~(uint32_t)VLFF_FRAME_POSE_VALID;
    memset(h->pose, 0, sizeof h->pose);
  }
  if (kind == FUTURE_POSE) h->pose_t_ns = vlff_shm_now_ns() + 3000000000ull; /* a camera clock 3 s ahead */
  /* A tracker reporting centimetres; one that relocalised 40 m away. */
  for (int r = 0; r < 3; r++) h->pose[r * 4 + 3] *= kind == POSE_CM ? 100 : 1;
  if (kind == POSE_JUMPED) h->pose[3] += 40;
  memcpy((uint8_t *)h + h->plane[0].offset, f->rgb, (size_t)f->width * f->height * 3);
  if (kind != NO_DEPTH) memcpy((uint8_t *)h + h->plane[1].offset, f->depth_mm, (size_t)f->width * f->height * 2);
  if (kind == FAR_DEPTH) /* a 16-bit sensor's 65535 everywhere: 65.5 m, no measurement */
    memset((uint8_t *)h + h->plane[1].offset, 0xff, (size_t)f->width * f->height * 2);
  assert_int_equal(vlff_ring_commit(ring, len), 0);
}

/* A node fed frames lacking a pose, lacking depth and with millimetre focal
 * lengths counts each reason on its --status line and says why in its log
 * at info, once per reason with the detail, then as counts. */
static void test_status_says_why(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg);
  char log[400];
  snprintf(log, sizeof log, "%s/node.log", tk.dir);
  struct tk_scene sc;
  tk_scene_open(&sc, &cfg, 16, 320, 240);
  struct vlff_sim *s = sc.sim;
  struct vlff_sim_frame *f = sc.frame;
  struct vlff_ring *ring = sc.ring;
  const char *args[] = {"--config", cfg_path, "--status", NULL};
  pid_t node = tk_spawn(&tk, "node/vlff-node", args, log);
  assert_true(tk_wait_for_text(log, "attached to ring", 30 * tk.scale));
  const enum frame_kind kinds[] = {NO_POSE_FLAG, NO_DEPTH, BAD_INTRINSICS, NO_POSE_FLAG, NO_DEPTH, NO_POSE_FLAG};
  const int nk = sizeof kinds / sizeof kinds[0];
  long long id = 0;
  /* Two rounds a summary period apart, so the counts line comes too. */
  for (int round = 0; round < 2; round++) {
    for (int i = 0; i < nk; i++, id++) {
      put_frame(ring, s, f, id, vlff_shm_now_ns(), kinds[i]);
      tk_sleep_s(0.05);
    }
    if (round == 0) tk_sleep_s(5.5);
  }
  /* 6 no pose, 4 no depth, 2 bad intrinsics. */
  bool seen = tk_wait_for_text(log, "refused 12 (bad intrinsics 2, no pose 6, no depth 4)", 20 * tk.scale);
  kill(node, SIGTERM);
  assert_int_equal(tk_wait_child(&tk, node), 0);
  const char *text = tk_slurp(log);
  if (!seen) fail_msg("no status line with the per-reason counts in:\n%s", text);
  /* The first of each reason at info, with what is wrong and what to do. */
  assert_non_null(strstr(text, " I node: frame 0 refused, no pose: the frame carries no pose and the pose ring "
                               "cannot be attached: "));
  assert_non_null(strstr(text, "(start vlff-pose"));
  assert_non_null(strstr(text, " I node: frame 1 refused, no depth: the frame has no depth plane"));
  assert_non_null(strstr(text, " I node: frame 2 refused, bad intrinsics: fx 3.6 outside ["));
  assert_non_null(strstr(text, "(millimetres, or another image size's values?)"));
  /* Then counts, not a line per frame. */
  assert_non_null(strstr(text, " I node: frames refused in the last"));
  assert_null(strstr(text, "frame 3 refused"));
  assert_non_null(strstr(text, "refused 12 (bad intrinsics 2, no pose 6, no depth 4)"));
  tk_scene_close(&sc);
}

/* Rotation matrix (row-major 4x4's block) to a unit quaternion x y z w. */
static void quat_of(const double m[16], double q[4]) {
  double r00 = m[0], r11 = m[5], r22 = m[10], tr = r00 + r11 + r22;
  if (tr > 0) {
    double S = sqrt(tr + 1.0) * 2;
    q[3] = 0.25 * S, q[0] = (m[9] - m[6]) / S, q[1] = (m[2] - m[8]) / S, q[2] = (m[4] - m[1]) / S;
  } else if (r00 > r11 && r00 > r22) {
    double S = sqrt(1.0 + r00 - r11 - r22) * 2;
    q[3] = (m[9] - m[6]) / S, q[0] = 0.25 * S, q[1] = (m[1] + m[4]) / S, q[2] = (m[2] + m[8]) / S;
  } else if (r11 > r22) {
    double S = sqrt(1.0 + r11 - r00 - r22) * 2;
    q[3] = (m[2] - m[8]) / S, q[0] = (m[1] + m[4]) / S, q[1] = 0.25 * S, q[2] = (m[6] + m[9]) / S;
  } else {
    double S = sqrt(1.0 + r22 - r00 - r11) * 2;
    q[3] = (m[4] - m[1]) / S, q[0] = (m[2] + m[8]) / S, q[1] = (m[6] + m[9]) / S, q[2] = 0.25 * S;
  }
}

/* The TUM line of simulator frame index at stamp t_ns (CLOCK_MONOTONIC). */
static void tum_line(struct vlff_sim *s, struct vlff_sim_frame *f, long long index, uint64_t t_ns, char *out,
                     size_t len) {
  char err[256];
  assert_int_equal(vlff_sim_render(s, index, 0, f, err, sizeof err), 0);
  double q[4];
  quat_of(f->c2w, q);
  snprintf(out, len, "%llu.%09llu %.9f %.9f %.9f %.12f %.12f %.12f %.12f\n", (unsigned long long)(t_ns / 1000000000),
           (unsigned long long)(t_ns % 1000000000), f->c2w[3], f->c2w[7], f->c2w[11], q[0], q[1], q[2], q[3]);
}

static void wait_keyframes(struct vlff_node *n, int want, struct vlff_node_status *st) {
  double t0 = vlff_seconds();
  do {
    tk_sleep_s(0.1);
    vlff_node_status(n, st);
  } while (st->keyframes < want && vlff_seconds() - t0 < 20 * tk.scale);
}

/* Frames without poses are refused "no pose"; once vlff-pose has written
 * their trajectory into the pose ring (from a file, then over UDP), the
 * same kind of frames become keyframes, also when each pose comes after
 * its frame (live), within source.pose_wait_s. */
static void test_pose_adapter_feeds_node(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg);
  struct tk_scene sc;
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_scene_node(&sc, &cfg, 16, 320, 240, &src);
  struct vlff_sim *s = sc.sim;
  struct vlff_sim_frame *f = sc.frame;
  struct vlff_ring *ring = sc.ring;
  const uint64_t step = 200000000; /* the keyframe rate: every posed frame is a candidate */
  /* The frames' stamps start in the past and advance faster than the test
   * runs, so a trajectory written ahead of its frames is never ahead of the
   * clock, which vlff-pose and the node refuse (pose.future_tolerance_s). */
  uint64_t t = vlff_shm_now_ns() - 6000000000ull;
  long long id = 0;
  for (int i = 0; i < 4; i++, id++, t += step) put_frame(ring, s, f, id, t, NO_POSE_FLAG);
  struct vlff_node_status st;
  double t0 = vlff_seconds();
  do {
    tk_sleep_s(0.1);
    vlff_node_status(n, &st);
  } while (st.refused[VLFF_REFUSED_NO_POSE] < 4 && vlff_seconds() - t0 < 10 * tk.scale);
  assert_int_equal(st.refused[VLFF_REFUSED_NO_POSE], 4);
  assert_int_equal(st.last_refusal, VLFF_REFUSED_NO_POSE);
  assert_int_equal(st.keyframes, 0);

  /* From a file: a TUM trajectory of the next frames, with a header, a
   * duplicate line and a malformed one that vlff-pose refuses and counts. */
  char traj[400], plog[400], line[256];
  snprintf(traj, sizeof traj, "%s/CameraTrajectory.txt", tk.dir);
  snprintf(plog, sizeof plog, "%s/pose-file.log", tk.dir);
  FILE *tf = fopen(traj, "w");
  assert_non_null(tf);
  fputs("# timestamp tx ty tz qx qy qz qw\n", tf);
  const int nfile = 6;
  uint64_t t_file = t;
  for (int i = 0; i < nfile; i++) {
    tum_line(s, f, id + i, t_file + (uint64_t)i * step, line, sizeof line);
    fputs(line, tf);
    if (i == 2) fputs(line, tf);
  }
  fputs("1 2 3\n", tf);
  fclose(tf);
  const char *fargs[] = {"--config", cfg_path, traj, NULL};
  assert_int_equal(tk_wait_child(&tk, tk_spawn(&tk, "drivers/pose/vlff-pose", fargs, plog)), 0);
  const char *ptext = tk_slurp(plog);
  assert_non_null(strstr(ptext, "CameraTrajectory.txt:5: refused, duplicate stamp"));
  assert_non_null(strstr(ptext, "CameraTrajectory.txt:9: refused, malformed: 3 fields, expected 8"));
  assert_non_null(strstr(ptext, "6 poses written to /"));
  assert_non_null(strstr(ptext, "2 lines refused (malformed 1, duplicate stamp 1)"));
  /* Paced like a camera: the trainer takes a few candidates at a time. */
  for (int i = 0; i < nfile; i++, id++, t += step) {
    put_frame(ring, s, f, id, t, NO_POSE_FLAG);
    tk_sleep_s(0.1);
  }
  wait_keyframes(n, nfile, &st);
  printf("file: %d keyframes, %lld refused for no pose\n", st.keyframes, st.refused[VLFF_REFUSED_NO_POSE]);
  assert_int_equal(st.keyframes, nfile);
  assert_int_equal(st.refused[VLFF_REFUSED_NO_POSE], 4);

  /* Over UDP: a tracker streaming lines, some datagrams with two. */
  int port = 20000 + (int)(getpid() % 20000);
  char addr[64];
  snprintf(addr, sizeof addr, "127.0.0.1:%d", port);
  snprintf(plog, sizeof plog, "%s/pose-udp.log", tk.dir);
  const char *uargs[] = {"--config", cfg_path, "--udp", addr, NULL};
  pid_t pu = tk_spawn(&tk, "drivers/pose/vlff-pose", uargs, plog);
  assert_true(tk_wait_for_text(plog, "-> pose ring", 10 * tk.scale));
  int us = socket(AF_INET, SOCK_DGRAM, 0);
  assert_true(us >= 0);
  struct sockaddr_in sa = {.sin_family = AF_INET, .sin_port = htons((uint16_t)port)};
  inet_pton(AF_INET, "127.0.0.1", &sa.sin_addr);
  const int nudp = 6;
  struct vlff_ring *pr = vlff_ring_attach(cfg.shm.pose_ring, VLFF_RECORD_POSE);
  assert_non_null(pr);
  uint64_t head0 = vlff_ring_head(pr);
  for (int i = 0; i < nudp; i += 2) {
    char two[512];
    tum_line(s, f, id + i, t + (uint64_t)i * step, two, sizeof two);
    tum_line(s, f, id + i + 1, t + (uint64_t)(i + 1) * step, line, sizeof line);
    strncat(two, line, sizeof two - strlen(two) - 1);
    assert_true(sendto(us, two, strlen(two), 0, (struct sockaddr *)&sa, sizeof sa) == (ssize_t)strlen(two));
  }
  const char *nan_line = "12.5 0 0 nan 0 0 0 1\n";
  assert_true(sendto(us, nan_line, strlen(nan_line), 0, (struct sockaddr *)&sa, sizeof sa) > 0);
  close(us);
  t0 = vlff_seconds();
  while (vlff_ring_head(pr) < head0 + nudp && vlff_seconds() - t0 < 10 * tk.scale) tk_sleep_s(0.05);
  assert_true(vlff_ring_head(pr) == head0 + nudp);
  vlff_ring_close(pr);
  for (int i = 0; i < nudp; i++, id++, t += step) {
    put_frame(ring, s, f, id, t, NO_POSE_FLAG);
    tk_sleep_s(0.1);
  }
  wait_keyframes(n, nfile + nudp, &st);
  printf("udp: %d keyframes (%lld candidates dropped), %lld refused for no pose\n", st.keyframes,
         st.candidates_dropped, st.refused[VLFF_REFUSED_NO_POSE]);
  assert_int_equal(st.keyframes, nfile + nudp);
  assert_int_equal(st.refused[VLFF_REFUSED_NO_POSE], 4);
  assert_int_equal(st.frames_invalid, 4);

  /* Live: a tracker posing the node's own frames sends each pose after its
   * frame reached the ring; the candidate waits for it (source.pose_wait_s). */
  us = socket(AF_INET, SOCK_DGRAM, 0);
  assert_true(us >= 0);
  const int nlive = 3;
  for (int i = 0; i < nlive; i++, id++, t += step) {
    tum_line(s, f, id, t, line, sizeof line); /* before the frame: rendering is slow under the sanitizers */
    put_frame(ring, s, f, id, t, NO_POSE_FLAG);
    tk_sleep_s(0.15);
    assert_true(sendto(us, line, strlen(line), 0, (struct sockaddr *)&sa, sizeof sa) == (ssize_t)strlen(line));
    tk_sleep_s(0.1);
  }
  close(us);
  wait_keyframes(n, nfile + nudp + nlive, &st);
  printf("live: %d keyframes, %lld refused for no pose\n", st.keyframes, st.refused[VLFF_REFUSED_NO_POSE]);
  assert_int_equal(st.keyframes, nfile + nudp + nlive);
  assert_int_equal(st.refused[VLFF_REFUSED_NO_POSE], 4);
  /* A pose that never comes: refused once the wait is over. */
  put_frame(ring, s, f, id, t, NO_POSE_FLAG);
  t0 = vlff_seconds();
  do {
    tk_sleep_s(0.1);
    vlff_node_status(n, &st);
  } while (st.refused[VLFF_REFUSED_NO_POSE] < 5 && vlff_seconds() - t0 < 5 * tk.scale);
  assert_int_equal(st.refused[VLFF_REFUSED_NO_POSE], 5);
  assert_true(vlff_seconds() - t0 >= 0.9); /* not before source.pose_wait_s */
  assert_int_equal(st.keyframes, nfile + nudp + nlive);
  kill(pu, SIGTERM);
  assert_int_equal(tk_wait_child(&tk, pu), 0);
  ptext = tk_slurp(plog);
  assert_non_null(strstr(ptext, "udp datagram 4 line 1: refused, not finite: tz is nan"));
  assert_non_null(strstr(ptext, "9 poses written to /"));
  tk_node_destroy(n, src);
  tk_scene_close(&sc);
}

/* A pose source whose clock runs 3 s ahead: the pose ring holds the poses
 * of the frames' stamps, and the newest, just written, 3 s ahead of the
 * clock. Each frame would take a pose from 3 s earlier; the node refuses
 * them all as "future pose", as it does a frame carrying a pose stamped
 * 3 s ahead. Before, both kinds became keyframes. */
static void test_future_pose_refused(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg);
  struct tk_scene sc;
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_scene_node(&sc, &cfg, 16, 320, 240, &src);
  struct vlff_ring_params pp = {VLFF_RECORD_POSE, 64, sizeof(struct vlff_pose_rec), {0}};
  struct vlff_ring *poses = vlff_ring_create(cfg.shm.pose_ring, &pp);
  assert_non_null(poses);
  const uint64_t step = 200000000;
  const int nframes = 4;
  uint64_t t = vlff_shm_now_ns() - 2000000000ull;
  for (int i = 0; i <= nframes; i++) {
    char err[256];
    assert_int_equal(vlff_sim_render(sc.sim, i, 0, sc.frame, err, sizeof err), 0);
    struct vlff_pose_rec pr = {.t_ns = t + (uint64_t)i * step};
    memcpy(pr.pose, sc.frame->c2w, sizeof pr.pose);
    if (i == nframes) pr.t_ns = vlff_shm_now_ns() + 3000000000ull;
    assert_true(vlff_ring_write(poses, &pr, sizeof pr) >= 0);
  }
  for (int i = 0; i < nframes; i++) {
    put_frame(sc.ring, sc.sim, sc.frame, i, t + (uint64_t)i * step, NO_POSE_FLAG);
    tk_sleep_s(0.1);
  }
  /* A camera's own pose, 3 s ahead. */
  put_frame(sc.ring, sc.sim, sc.frame, nframes, vlff_shm_now_ns(), FUTURE_POSE);
  struct vlff_node_status st;
  double t0 = vlff_seconds();
  do {
    tk_sleep_s(0.1);
    vlff_node_status(n, &st);
  } while (st.refused[VLFF_REFUSED_FUTURE_POSE] < nframes + 1 && vlff_seconds() - t0 < 10 * tk.scale);
  printf("%d keyframes, %lld refused as future pose\n", st.keyframes, st.refused[VLFF_REFUSED_FUTURE_POSE]);
  assert_int_equal(st.refused[VLFF_REFUSED_FUTURE_POSE], nframes + 1);
  assert_int_equal(st.frames_invalid, nframes + 1);
  assert_int_equal(st.keyframes, 0);
  assert_string_equal(vlff_refusal_name(VLFF_REFUSED_FUTURE_POSE), "future pose");
  vlff_ring_close(poses);
  shm_unlink(cfg.shm.pose_ring);
  tk_node_destroy(n, src);
  tk_scene_close(&sc);
}

/* A frame stamped 1000 s ahead of the clock is refused (one stopped all
 * keyframe selection after it, silently), and one whose every depth pixel
 * is beyond any sensor (a 16-bit sensor's 65535) is refused as empty depth
 * (it passed the bad-pose check as 100 % inliers and cleared the map's
 * surfaces); good frames after them are still taken. */
static void test_future_frame_and_far_depth_refused(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg);
  struct tk_scene sc;
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_scene_node(&sc, &cfg, 16, 320, 240, &src);
  put_frame(sc.ring, sc.sim, sc.frame, 0, vlff_shm_now_ns() + 1000000000000ull, GOOD);
  put_frame(sc.ring, sc.sim, sc.frame, 1, vlff_shm_now_ns(), FAR_DEPTH);
  struct vlff_node_status st;
  double t0 = vlff_seconds();
  /* frames until three are keyframes, however slow the host (sanitizers,
   * qemu-user): the simulator's trajectory loops, so indices wrap */
  for (long long i = 2;; i++) {
    put_frame(sc.ring, sc.sim, sc.frame, 2 + (i - 2) % 38, vlff_shm_now_ns(), GOOD);
    tk_sleep_s(0.05);
    vlff_node_status(n, &st);
    if (st.keyframes >= 3 || vlff_seconds() - t0 > 60 * tk.scale) break;
  }
  printf("%d keyframes; refused: future frame %lld, empty depth %lld\n", st.keyframes,
         st.refused[VLFF_REFUSED_FUTURE_FRAME], st.refused[VLFF_REFUSED_EMPTY_DEPTH]);
  assert_int_equal(st.refused[VLFF_REFUSED_FUTURE_FRAME], 1);
  assert_int_equal(st.refused[VLFF_REFUSED_EMPTY_DEPTH], 1);
  assert_true(st.keyframes >= 3);
  assert_string_equal(vlff_refusal_name(VLFF_REFUSED_FUTURE_FRAME), "future frame");
  tk_node_destroy(n, src);
  tk_scene_close(&sc);
}

/* The in-process node's log is this process's stderr: kept in the file
 * path until stderr_back (with what stderr_to returned). */
static int stderr_to(const char *path) {
  fflush(stderr);
  int saved = dup(2), fd = open(path, O_WRONLY | O_CREAT | O_TRUNC, 0644);
  assert_true(saved >= 0 && fd >= 0);
  dup2(fd, 2);
  close(fd);
  return saved;
}

static void stderr_back(int saved) {
  fflush(stderr);
  dup2(saved, 2);
  close(saved);
}

/* Poses in the wrong units without a box to catch them (field.grow: the
 * world's limit is a kilometre). A tracker that jumps once (relocalised 40 m
 * away) costs the one keyframe candidate after the jump; one that reports
 * centimetres has every candidate refused, each step between them far
 * longer than the depth reaches, with the reason in the log. */
static void test_pose_units_refused(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg);
  cfg.field.grow = true;
  char log[400];
  snprintf(log, sizeof log, "%s/units.log", tk.dir);
  int saved = stderr_to(log);
  struct tk_scene sc;
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_scene_node(&sc, &cfg, 16, 320, 240, &src);
  /* Frames 0.25 s apart (keyframes.rate_hz 5), 6 walk frames apart: the
   * jump comes with frame 30. */
  const int nmetres = 10, ncm = 6;
  for (int i = 0; i < nmetres + ncm; i++) {
    enum frame_kind kind = i < nmetres / 2 ? GOOD : i < nmetres ? POSE_JUMPED : POSE_CM;
    put_frame(sc.ring, sc.sim, sc.frame, i * 6, vlff_shm_now_ns(), kind);
    tk_sleep_s(0.25);
  }
  struct vlff_node_status st;
  double t0 = vlff_seconds();
  do {
    tk_sleep_s(0.1);
    vlff_node_status(n, &st);
  } while (st.refused[VLFF_REFUSED_POSE_RANGE] < 1 + ncm && vlff_seconds() - t0 < 10 * tk.scale);
  tk_sleep_s(0.5);
  vlff_node_status(n, &st);
  printf("%lld candidates refused for their pose, %lld frames refused\n", st.refused[VLFF_REFUSED_POSE_RANGE],
         st.frames_invalid);
  tk_node_destroy(n, src);
  stderr_back(saved);
  assert_int_equal(st.refused[VLFF_REFUSED_POSE_RANGE], 1 + ncm);
  assert_int_equal(st.frames_invalid, 1 + ncm);
  const char *text = tk_slurp(log);
  if (!strstr(text, "frame 30 refused, pose out of range: camera moved ") ||
      !strstr(text, " m since the keyframe candidate before, farther than the ") ||
      !strstr(text, "poses in millimetres, or a jump of the tracker?"))
    fail_msg("no line on the jump in:\n%s", text);
  tk_scene_close(&sc);
}

/* A keyframe page file that cannot be made (a directory has its name): the
 * node starts all the same, says so, and will drop what it evicts. */
static void test_kf_page_file_refused(void **state) {
  (void)state;
  struct vlff_config cfg;
  write_config(&cfg);
  char path[600], log[400];
  snprintf(path, sizeof path, "%s/keyframes.pages", cfg.node.state_dir);
  assert_int_equal(mkdir(cfg.node.state_dir, 0750), 0);
  assert_int_equal(mkdir(path, 0750), 0);
  snprintf(log, sizeof log, "%s/kfpage.log", tk.dir);
  int saved = stderr_to(log);
  struct tk_scene sc;
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_scene_node(&sc, &cfg, 16, 320, 240, &src);
  tk_node_destroy(n, src);
  stderr_back(saved);
  const char *text = tk_slurp(log);
  if (!strstr(text, " W node: keyframes: keyframe page file ") ||
      !strstr(text, "keyframes.pages: File exists: evicted keyframes will be dropped (counted), not paged"))
    fail_msg("no warning on the page file in:\n%s", text);
  rmdir(path);
  tk_scene_close(&sc);
}

int main(void) {
  const struct CMUnitTest tests[] = {
      cmocka_unit_test_setup_teardown(test_status_says_why, setup, teardown),
      cmocka_unit_test_setup_teardown(test_pose_adapter_feeds_node, setup, teardown),
      cmocka_unit_test_setup_teardown(test_future_pose_refused, setup, teardown),
      cmocka_unit_test_setup_teardown(test_future_frame_and_far_depth_refused, setup, teardown),
      cmocka_unit_test_setup_teardown(test_pose_units_refused, setup, teardown),
      cmocka_unit_test_setup_teardown(test_kf_page_file_refused, setup, teardown),
  };
  if (getenv("VLFF_TEST_FILTER")) cmocka_set_test_filter(getenv("VLFF_TEST_FILTER"));
  if (getenv("VLFF_TEST_DEBUG")) vlff_log_set_level(VLFF_LOG_DEBUG); /* every refusal's detail */
  return cmocka_run_group_tests(tests, NULL, NULL);
}
