/*
 * MCAP recordings of the node's inputs, round trip: a scene written to disk
 * (reference layout, features.hdf, timestamps.txt) is played by vlff-replay
 * into rings, vlff-record writes every record to an MCAP file (checked with
 * @mcap/core through tests/bench/mcap_check.js where node and the npm packages
 * are installed), vlff-replay plays that file into fresh rings, and a ring
 * reader finds every frame (colour and depth bytes, intrinsics), pose (within
 * float rounding, at its frame's time) and feature map (float16 bits, its
 * frame's id and time) of the scene, as many, in order.
 * Also: a recording without features plays without them and says so; files
 * cut short, corrupted, or holding a message out of bounds are refused with
 * the documented error, naming the channel and the message, before any ring
 * is created.
 */
#define _XOPEN_SOURCE 700
#include <errno.h>
#include <math.h>
#include <setjmp.h>
#include <signal.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>
#include <cmocka.h>

#include "config.h"
#include "bounds.h"
#include "dataset.h"
#include "files.h"
#include "inputs.h"
#include "mcap.h"
#include "testkit.h"
#include "vlff/shm.h"

#define N 9
#define W 40
#define H 30
#define FD 5
#define FH 3
#define FW 4

static struct tk tk;
static char scene[300];

/* The scene as written: the reference the rings are compared with. */
static uint8_t rgb[N][H * W * 3];
static uint16_t depth[N][H * W];
static uint16_t feat_hwc[N][FH * FW * FD];
static double c2w[N][16];
static const double FX = 35.5, FY = 36.25, CX = 20.25, CY = 15.75;

static uint32_t rng = 12345;
static uint32_t next_rand(void) {
  rng ^= rng << 13, rng ^= rng >> 17, rng ^= rng << 5;
  return rng;
}

static void fill_scene(void) {
  rng = 12345;
  for (int i = 0; i < N; i++) {
    for (int k = 0; k < H * W * 3; k++) rgb[i][k] = (uint8_t)next_rand();
    for (int k = 0; k < H * W; k++) depth[i][k] = k % 7 == 0 ? 0 : (uint16_t)(300 + next_rand() % 5000);
    for (int k = 0; k < FH * FW * FD; k++) {
      /* half floats of both signs within +-1000 (bounds.h: no NaN,
       * infinity or value beyond any model's) */
      uint32_t r = next_rand();
      uint16_t h = (uint16_t)((r & 0x8000u) | ((r >> 16) % (VLFF_FEATURE_MAX_ABS_F16 + 1)));
      feat_hwc[i][k] = h;
    }
    double a = 0.3 * i + 0.1, b = -0.2 * i;
    double ca = cos(a), sa = sin(a), cb = cos(b), sb = sin(b);
    /* R = Rz(a) Rx(b) */
    double R[9] = {ca, -sa * cb, sa * sb, sa, ca * cb, -ca * sb, 0, sb, cb};
    double *P = c2w[i];
    memset(P, 0, sizeof c2w[i]);
    for (int r = 0; r < 3; r++)
      for (int c = 0; c < 3; c++) P[r * 4 + c] = R[r * 3 + c];
    P[3] = 0.1 * i - 0.4, P[7] = 0.05 * i, P[11] = -0.3 + 0.02 * i, P[15] = 1;
  }
}

static void write_scene(void) {
  char err[1024];
  const double lo[3] = {-2, -2, -2}, hi[3] = {2, 2, 2};
  struct vlff_dataset_writer *w =
      vlff_dataset_writer_open(scene, N, W, H, FX, FY, CX, CY, lo, hi, "clip", FW, FH, FD, err, sizeof err);
  if (!w) fail_msg("%s", err);
  double t[N];
  for (int i = 0; i < N; i++) {
    const double *P = c2w[i];
    static uint8_t label[H * W]; /* the writer labels every frame: all class 0 */
    if (vlff_dataset_writer_add(w, i, rgb[i], depth[i], label, P, feat_hwc[i], err, sizeof err)) fail_msg("%s", err);
    t[i] = 0.031 * i + (i % 3) * 0.004; /* uneven, as a real camera's */
  }
  if (vlff_dataset_writer_close(w, err, sizeof err)) fail_msg("%s", err);
  if (vlff_dataset_write_stamps(scene, N, t, err, sizeof err)) fail_msg("%s", err);
}

static const char *config(struct vlff_config *cfg) {
  return tk_config(&tk, cfg, "shm:\n%s  ring_slots: 16\n", tk_shm_names(&tk));
}

static void unlink_rings(const struct vlff_config *cfg) {
  vlff_shm_unlink(cfg->shm.ring);
  vlff_shm_unlink(cfg->shm.pose_ring);
  vlff_shm_unlink(cfg->shm.feature_ring);
}

static struct vlff_ring *attach_wait(const char *name, uint32_t kind, double timeout_s) {
  for (double t = 0; t < timeout_s; t += 0.02) {
    struct vlff_ring *r = vlff_ring_attach(name, kind);
    if (r) {
      vlff_ring_seek_oldest(r);
      return r;
    }
    tk_sleep_s(0.02);
  }
  fail_msg("ring %s never appeared", name);
  return NULL;
}

/* vlff-replay ARGS... (NULL-terminated), its output into log: the exit status. */
static int run_replay(const char *log, ...) {
  const char *args[16];
  int n = 0;
  va_list ap;
  va_start(ap, log);
  const char *a;
  while ((a = va_arg(ap, const char *)) && n < 15) args[n++] = a;
  va_end(ap);
  args[n] = NULL;
  pid_t pid = tk_spawn(&tk, "node/dataset/vlff-replay", args, log);
  return tk_wait_child(&tk, pid);
}

/* The recording checked by @mcap/core, when node and the packages are here. */
static void mcap_check(const char *path, int messages) {
  const char *node = getenv("VLFF_NODEJS"), *script = getenv("VLFF_MCAP_CHECK");
  if (!node || !*node || !script || !*script) {
    printf("# @mcap/core check skipped: node or the npm packages not installed\n");
    return;
  }
  char cmd[1200], line[2048] = "";
  snprintf(cmd, sizeof cmd, "'%s' '%s' '%s'", node, script, path);
  FILE *p = popen(cmd, "r");
  assert_non_null(p);
  if (!fgets(line, sizeof line, p)) line[0] = 0;
  assert_int_equal(pclose(p), 0);
  printf("# mcap_check: %s", line);
  char want[64];
  snprintf(want, sizeof want, "\"messages\":%d,", messages);
  assert_non_null(strstr(line, "\"ok\":1"));
  assert_non_null(strstr(line, want));
  assert_non_null(strstr(line, "\"channels\":6,"));
}

static void test_round_trip(void **state) {
  (void)state;
  struct vlff_config cfg;
  const char *cfg_path = config(&cfg);
  write_scene();
  char mcap[300], rec_log[300], log1[300], log2[300];
  snprintf(mcap, sizeof mcap, "%s/inputs.mcap", tk.dir);
  snprintf(rec_log, sizeof rec_log, "%s/record.log", tk.dir);
  snprintf(log1, sizeof log1, "%s/replay1.log", tk.dir);
  snprintf(log2, sizeof log2, "%s/replay2.log", tk.dir);

  /* scene -> rings -> vlff-record -> MCAP */
  const char *rargs[] = {"--config", cfg_path, "--quiet", mcap, NULL};
  pid_t rec = tk_spawn(&tk, "node/view/vlff-record", rargs, rec_log);
  int rc = run_replay(log1, "--config", cfg_path, "--backpressure", "--quiet", scene, NULL);
  if (rc) fail_msg("vlff-replay of the scene: %d: %s", rc, tk_slurp(log1));
  /* the recorder reads what the rings still hold before it closes the file */
  kill(rec, SIGINT);
  assert_int_equal(tk_wait_child(&tk, rec), 0);
  const char *said = tk_slurp(rec_log);
  printf("# %s", said);
  assert_non_null(strstr(said, "9 frames, 9 poses, 9 feature maps recorded; 0 records missed, 0 malformed"));
  mcap_check(mcap, 5 * N);
  /* in the file, each frame's pose before it, its feature map after it: the
   * order the producers committed them, which the node's pose lookup needs */
  {
    uint8_t *d = NULL;
    size_t dn = 0;
    char err[256];
    assert_int_equal(vlff_read_file(mcap, 1 << 26, &d, &dn, err, sizeof err), 0);
    struct vlff_in_reader *in = vlff_in_reader_new(d, dn, err, sizeof err);
    assert_non_null(in);
    struct vlff_in_event ev;
    uint64_t last_pose = 0, last_frame = 0;
    int frames = 0, next;
    while ((next = vlff_in_next(in, &ev, err, sizeof err)) == 1) {
      if (ev.kind == VLFF_IN_EV_POSE) last_pose = ev.t_ns;
      if (ev.kind == VLFF_IN_EV_FRAME) {
        if (last_pose != ev.t_ns) fail_msg("frame %d (message %llu) before its pose", frames, (unsigned long long)ev.index);
        last_frame = ev.t_ns;
        frames++;
      }
      if (ev.kind == VLFF_IN_EV_FEATURES && ev.t_ns != last_frame)
        fail_msg("the feature map of message %llu not after its frame", (unsigned long long)ev.index);
    }
    assert_int_equal(next, 0);
    assert_int_equal(frames, N);
    vlff_in_reader_free(in);
    free(d);
  }
  unlink_rings(&cfg);

  /* MCAP -> vlff-replay -> fresh rings -> this reader */
  const char *pargs[] = {"--config", cfg_path, "--backpressure", mcap, NULL};
  pid_t play = tk_spawn(&tk, "node/dataset/vlff-replay", pargs, log2);
  struct vlff_ring *fr = attach_wait(cfg.shm.ring, VLFF_RECORD_FRAME, 20 * tk.scale);
  struct vlff_ring *pr = attach_wait(cfg.shm.pose_ring, VLFF_RECORD_POSE, 5 * tk.scale);
  struct vlff_ring *xr = attach_wait(cfg.shm.feature_ring, VLFF_RECORD_FEATURE, 5 * tk.scale);
  size_t fcap = vlff_ring_slot_size(fr), xcap = vlff_ring_slot_size(xr);
  uint8_t *fb = malloc(fcap), *xb = malloc(xcap);
  assert_non_null(fb);
  assert_non_null(xb);
  uint64_t t_host[N];
  for (int i = 0; i < N; i++) {
    struct vlff_ring_view v;
    ssize_t n = vlff_ring_read_copy(fr, fb, fcap, &v, (uint64_t)(10e9 * tk.scale));
    if (n < 0) fail_msg("frame %d: %s", i, strerror(errno));
    assert_int_equal(vlff_frame_validate(fb, (size_t)n), 0);
    const struct vlff_frame_hdr *h = (const void *)fb;
    assert_int_equal(h->frame_id, i);
    assert_int_equal(h->plane[0].width, W);
    assert_int_equal(h->plane[0].height, H);
    assert_int_equal(h->plane[0].format, VLFF_PIX_RGB8);
    assert_int_equal(h->plane[1].format, VLFF_PIX_DEPTH_U16_MM);
    assert_true(h->fx == FX && h->fy == FY && h->cx == CX && h->cy == CY);
    const uint8_t *c = vlff_frame_plane(fb, 0), *d = vlff_frame_plane(fb, 1);
    for (int y = 0; y < H; y++) {
      assert_memory_equal(c + (size_t)y * h->plane[0].stride, rgb[i] + y * W * 3, W * 3);
      assert_memory_equal(d + (size_t)y * h->plane[1].stride, depth[i] + y * W, W * 2);
    }
    t_host[i] = h->t_host_ns;
  }
  for (int i = 0; i < N; i++) {
    struct vlff_pose_rec p;
    struct vlff_ring_view v;
    ssize_t n = vlff_ring_read_copy(pr, &p, sizeof p, &v, (uint64_t)(5e9 * tk.scale));
    if (n < 0) fail_msg("pose %d: %s", i, strerror(errno));
    assert_int_equal(p.t_ns, t_host[i]); /* at its frame's time: the node's lookup finds it exactly */
    for (int k = 0; k < 16; k++)
      if (fabs(p.pose[k] - c2w[i][k]) > 1e-12) fail_msg("pose %d [%d]: %.17g, the scene's %.17g", i, k, p.pose[k], c2w[i][k]);
  }
  for (int i = 0; i < N; i++) {
    struct vlff_ring_view v;
    ssize_t n = vlff_ring_read_copy(xr, xb, xcap, &v, (uint64_t)(5e9 * tk.scale));
    if (n < 0) fail_msg("feature map %d: %s", i, strerror(errno));
    assert_int_equal(vlff_feature_validate(xb, (size_t)n), 0);
    const struct vlff_feature_hdr *f = (const void *)xb;
    assert_int_equal(f->frame_id, i);
    assert_int_equal(f->t_host_ns, t_host[i]);
    assert_true(f->dim == FD && f->height == FH && f->width == FW);
    const uint16_t *x = (const uint16_t *)(xb + f->data_offset);
    for (int k = 0; k < FD; k++)
      for (int p = 0; p < FH * FW; p++)
        if (x[k * FH * FW + p] != feat_hwc[i][p * FD + k])
          fail_msg("feature map %d [%d][%d]: %04x, the scene's %04x", i, k, p, x[k * FH * FW + p],
                   feat_hwc[i][p * FD + k]);
  }
  assert_int_equal(tk_wait_child(&tk, play), 0);
  /* nothing more than the scene */
  struct vlff_ring_view v;
  assert_true(vlff_ring_read_copy(fr, fb, fcap, &v, 0) < 0 && errno == EAGAIN);
  assert_true(vlff_ring_read_copy(pr, xb, xcap, &v, 0) < 0 && errno == EAGAIN);
  assert_true(vlff_ring_read_copy(xr, xb, xcap, &v, 0) < 0 && errno == EAGAIN);
  assert_int_equal(vlff_ring_lost(fr) + vlff_ring_lost(pr) + vlff_ring_lost(xr), 0);
  printf("# %s", tk_slurp(log2));
  assert_non_null(strstr(tk_slurp(log2), "9 frames, 9 poses, 9 feature maps published; 0 maps without their frame"));
  free(fb);
  free(xb);
  vlff_ring_close(fr);
  vlff_ring_close(pr);
  vlff_ring_close(xr);
}

/* A camera with its own tracker: the pose travels in the frame record
 * (vlff-replay --pose-in-frame), is recorded on /input/frame_pose and comes
 * back in the frame record, at the frame's new time; the pose ring stays empty. */
static void test_pose_in_frame(void **state) {
  (void)state;
  struct vlff_config cfg;
  const char *cfg_path = config(&cfg);
  write_scene();
  char mcap[300], rec_log[300], log1[300], log2[300];
  snprintf(mcap, sizeof mcap, "%s/inframe.mcap", tk.dir);
  snprintf(rec_log, sizeof rec_log, "%s/record.log", tk.dir);
  snprintf(log1, sizeof log1, "%s/replay1.log", tk.dir);
  snprintf(log2, sizeof log2, "%s/replay2.log", tk.dir);
  const char *rargs[] = {"--config", cfg_path, "--quiet", "--no-features", mcap, NULL};
  pid_t rec = tk_spawn(&tk, "node/view/vlff-record", rargs, rec_log);
  int rc = run_replay(log1, "--config", cfg_path, "--backpressure", "--quiet", "--pose-in-frame", "--no-features",
                      scene, NULL);
  if (rc) fail_msg("vlff-replay of the scene: %d: %s", rc, tk_slurp(log1));
  kill(rec, SIGINT);
  assert_int_equal(tk_wait_child(&tk, rec), 0);
  const char *said = tk_slurp(rec_log);
  printf("# %s", said);
  assert_non_null(strstr(said, "9 frames, 0 poses, 0 feature maps recorded; 0 records missed"));
  mcap_check(mcap, 4 * N);
  unlink_rings(&cfg);
  const char *pargs[] = {"--config", cfg_path, "--backpressure", mcap, NULL};
  pid_t play = tk_spawn(&tk, "node/dataset/vlff-replay", pargs, log2);
  struct vlff_ring *fr = attach_wait(cfg.shm.ring, VLFF_RECORD_FRAME, 20 * tk.scale);
  size_t fcap = vlff_ring_slot_size(fr);
  uint8_t *fb = malloc(fcap);
  assert_non_null(fb);
  for (int i = 0; i < N; i++) {
    struct vlff_ring_view v;
    ssize_t n = vlff_ring_read_copy(fr, fb, fcap, &v, (uint64_t)(10e9 * tk.scale));
    if (n < 0) fail_msg("frame %d: %s", i, strerror(errno));
    assert_int_equal(vlff_frame_validate(fb, (size_t)n), 0);
    const struct vlff_frame_hdr *h = (const void *)fb;
    assert_int_equal(h->frame_id, i);
    assert_true(h->flags & VLFF_FRAME_POSE_VALID);
    assert_int_equal(h->pose_t_ns, h->t_host_ns);
    for (int k = 0; k < 16; k++)
      if (fabs(h->pose[k] - c2w[i][k]) > 1e-12) fail_msg("frame %d pose [%d]: %.17g, the scene's %.17g", i, k, h->pose[k], c2w[i][k]);
    assert_memory_equal(vlff_frame_plane(fb, 0), rgb[i], W * 3); /* the first row */
  }
  assert_int_equal(tk_wait_child(&tk, play), 0);
  struct vlff_ring *pr = vlff_ring_attach(cfg.shm.pose_ring, VLFF_RECORD_POSE);
  assert_non_null(pr);
  assert_int_equal(vlff_ring_head(pr), 0);
  printf("# %s", tk_slurp(log2));
  vlff_ring_close(pr);
  vlff_ring_close(fr);
  free(fb);
}

/* ------------------------------------------------- recordings written here */

static struct vlff_mcap_writer *writer(const char *path) {
  char err[512];
  struct vlff_mcap_writer_params wp = {"test_replay_mcap", 0, 0, 1};
  struct vlff_mcap_writer *w = vlff_mcap_writer_open(path, &wp, err, sizeof err);
  if (!w) fail_msg("%s", err);
  if (vlff_in_declare(w, err, sizeof err)) fail_msg("%s", err);
  return w;
}

/* Frame i of the scene as a ring record, written as its messages at t. */
static void put_frame(struct vlff_mcap_writer *w, int i, uint64_t t) {
  size_t cap = vlff_frame_slot_size(W, H, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM);
  struct vlff_frame_hdr *h = aligned_alloc(64, (cap + 63) / 64 * 64);
  assert_non_null(h);
  memset(h, 0, cap);
  uint64_t len = vlff_frame_layout(h, cap, W, H, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM);
  assert_true(len > 0);
  h->frame_id = (uint64_t)i, h->t_host_ns = t, h->flags = VLFF_FRAME_INTRINSICS_VALID;
  h->fx = FX, h->fy = FY, h->cx = CX, h->cy = CY;
  memcpy((uint8_t *)h + h->plane[0].offset, rgb[i], sizeof rgb[i]);
  memcpy((uint8_t *)h + h->plane[1].offset, depth[i], sizeof depth[i]);
  char *scratch = NULL, err[512];
  size_t scap = 0;
  if (vlff_in_write_frame(w, h, len, &scratch, &scap, err, sizeof err)) fail_msg("%s", err);
  free(scratch);
  free(h);
}

static void put_raw(struct vlff_mcap_writer *w, int ch, uint64_t t, const char *json) {
  assert_int_equal(vlff_mcap_writer_message(w, (uint16_t)ch, t, t, json, strlen(json)), 0);
}

static void close_writer(struct vlff_mcap_writer *w) {
  char err[512];
  if (vlff_mcap_writer_close(w, err, sizeof err)) fail_msg("%s", err);
}

/* Frames 50 ms apart (a pose at each, one between, one 5 s before the first
 * frame): played at their stamps,
 * --rate 2 twice as fast, --fps 10 at a mean 10 Hz, and --loop --count going on
 * after the last frame with one mean interval; each pose at its frame's time
 * or, between frames, at its own place. Times are the schedule's (base + the
 * recorded offset / rate): exact unless the replay ran late, which a host this
 * idle does not make it (a late record, frame or pose, is counted: the test
 * then says so; a late pose was not, and shifted the frames after it). */
static void check_pace(const struct vlff_config *cfg, const char *cfg_path, const char *path, const char *log,
                       double scale, int frames, const char *a1, const char *a2, const char *a3) {
  unlink_rings(cfg);
  const char *args[] = {"--config", cfg_path, "--wait-reader", path, a1, a2, a3, NULL}; /* a1 NULL: none */
  pid_t play = tk_spawn(&tk, "node/dataset/vlff-replay", args, log);
  struct vlff_ring *fr = attach_wait(cfg->shm.ring, VLFF_RECORD_FRAME, 20 * tk.scale);
  struct vlff_ring *pr = attach_wait(cfg->shm.pose_ring, VLFF_RECORD_POSE, 5 * tk.scale);
  size_t cap = vlff_ring_slot_size(fr);
  uint8_t *b = malloc(cap);
  assert_non_null(b);
  uint64_t t[16];
  assert_true(frames <= 16);
  for (int i = 0; i < frames; i++) {
    struct vlff_ring_view v;
    if (vlff_ring_read_copy(fr, b, cap, &v, (uint64_t)(10e9 * tk.scale)) < 0) fail_msg("frame %d: %s", i, strerror(errno));
    const struct vlff_frame_hdr *h = (const void *)b;
    assert_int_equal(h->frame_id, i);
    t[i] = h->t_host_ns;
  }
  assert_int_equal(tk_wait_child(&tk, play), 0);
  const char *said = tk_slurp(log);
  printf("# %s", said);
  if (!strstr(said, " 0 late\n")) {
    printf("# the replay ran late on this host: the pace is not checked\n");
  } else {
    for (int i = 1; i < frames; i++) {
      int64_t want = (int64_t)llround(50e6 * scale), got = (int64_t)(t[i] - t[i - 1]);
      if (llabs(got - want) > 1) fail_msg("frame %d %lld ns after the previous, not %lld", i, (long long)got, (long long)want);
    }
    /* poses: one at each frame's time, and one half-way to the next */
    for (int i = 0; i < frames && i < 6; i++) {
      struct vlff_pose_rec p;
      struct vlff_ring_view v;
      assert_true(vlff_ring_read_copy(pr, &p, sizeof p, &v, 0) == sizeof p);
      assert_int_equal(p.t_ns, t[i]);
      if (i == 2) {
        assert_true(vlff_ring_read_copy(pr, &p, sizeof p, &v, 0) == sizeof p);
        int64_t d = (int64_t)(p.t_ns - t[2]), want = (int64_t)llround(20e6 * scale);
        if (llabs(d - want) > 1) fail_msg("the pose between frames %lld ns after frame 2, not %lld", (long long)d, (long long)want);
      }
    }
  }
  free(b);
  vlff_ring_close(fr);
  vlff_ring_close(pr);
}

static void test_pace(void **state) {
  (void)state;
  struct vlff_config cfg;
  const char *cfg_path = config(&cfg);
  char path[300], log[300], err[256];
  snprintf(path, sizeof path, "%s/pace.mcap", tk.dir);
  snprintf(log, sizeof log, "%s/pace.log", tk.dir);
  struct vlff_mcap_writer *w = writer(path);
  const uint64_t t0 = 7000000000ull, dt = 50000000ull;
  /* a pose long before the first frame (a pose ring's history): passed over,
   * in every loop, not waited for */
  if (vlff_in_write_pose(w, t0 - 5000000000ull, c2w[0], err, sizeof err)) fail_msg("%s", err);
  for (int i = 0; i < 6; i++) {
    if (vlff_in_write_pose(w, t0 + i * dt, c2w[i], err, sizeof err)) fail_msg("%s", err);
    put_frame(w, i, t0 + i * dt);
    if (i == 2 && vlff_in_write_pose(w, t0 + i * dt + 20000000ull, c2w[i], err, sizeof err)) fail_msg("%s", err);
  }
  close_writer(w);
  check_pace(&cfg, cfg_path, path, log, 1, 6, NULL, NULL, NULL);
  check_pace(&cfg, cfg_path, path, log, 0.5, 6, "--rate", "2", NULL);
  check_pace(&cfg, cfg_path, path, log, 2, 6, "--fps", "10", NULL);
  check_pace(&cfg, cfg_path, path, log, 0.5, 9, "--rate=2", "--loop", "--count=9");
}

/* A recorder that falls behind (stopped here while the replay goes on, as a
 * slow disk would stall it) is lapped: it logs and counts the records it
 * missed, the producer never waits for it, and the file it closes holds what
 * it did read, which plays (maps whose frame was missed passed over). */
static void test_recorder_behind(void **state) {
  (void)state;
  struct vlff_config cfg;
  const char *cfg_path = tk_config(&tk, &cfg, "shm:\n%s  ring_slots: 2\n", tk_shm_names(&tk));
  write_scene();
  char mcap[300], rec_log[300], log1[300], log2[300];
  snprintf(mcap, sizeof mcap, "%s/behind.mcap", tk.dir);
  snprintf(rec_log, sizeof rec_log, "%s/record.log", tk.dir);
  snprintf(log1, sizeof log1, "%s/replay1.log", tk.dir);
  snprintf(log2, sizeof log2, "%s/replay2.log", tk.dir);
  const char *rargs[] = {"--config", cfg_path, mcap, NULL};
  pid_t rec = tk_spawn(&tk, "node/view/vlff-record", rargs, rec_log);
  const char *pargs[] = {"--config", cfg_path, "--quiet", "--loop", "--rate", "10", scene, NULL};
  pid_t play = tk_spawn(&tk, "node/dataset/vlff-replay", pargs, log1);
  assert_true(tk_wait_for_text(rec_log, "recording the feature ring", 20 * tk.scale));
  tk_sleep_s(0.3);
  kill(rec, SIGSTOP);
  tk_sleep_s(1.0); /* the replay publishes some 300 frames into 2 slots meanwhile */
  kill(rec, SIGCONT);
  tk_sleep_s(0.3);
  kill(rec, SIGINT);
  assert_int_equal(tk_wait_child(&tk, rec), 0);
  kill(play, SIGTERM);
  assert_int_equal(tk_wait_child(&tk, play), 0);
  const char *said = tk_slurp(rec_log);
  printf("# %s", said);
  assert_non_null(strstr(said, "vlff-record: fell behind the frame ring: "));
  const char *sum = strstr(said, "feature maps recorded; ");
  assert_non_null(sum);
  unsigned long long missed = strtoull(sum + strlen("feature maps recorded; "), NULL, 10);
  assert_true(missed >= 100);
  unlink_rings(&cfg);
  assert_int_equal(run_replay(log2, "--config", cfg_path, "--rate", "20", mcap, NULL), 0);
  printf("# %s", tk_slurp(log2));
  assert_non_null(strstr(tk_slurp(log2), "feature maps published;"));
}

/* vlff-record's command line: an existing file is kept without --force. */
static void test_record_cli(void **state) {
  (void)state;
  struct vlff_config cfg;
  const char *cfg_path = config(&cfg);
  char path[300], log[300], err[256];
  snprintf(path, sizeof path, "%s/exists.mcap", tk.dir);
  snprintf(log, sizeof log, "%s/cli.log", tk.dir);
  assert_int_equal(vlff_write_file_atomic(path, "keep", 4, err, sizeof err), 0);
  const char *a1[] = {"--config", cfg_path, path, NULL};
  assert_int_equal(tk_wait_child(&tk, tk_spawn(&tk, "node/view/vlff-record", a1, log)), 1);
  assert_non_null(strstr(tk_slurp(log), "exists (--force replaces it)"));
  assert_string_equal(tk_slurp(path), "keep");
  const char *a2[] = {"--config", cfg_path, "--zstd", "20", path, NULL};
  assert_int_equal(tk_wait_child(&tk, tk_spawn(&tk, "node/view/vlff-record", a2, log)), 2);
  const char *a3[] = {"--config", cfg_path, NULL};
  assert_int_equal(tk_wait_child(&tk, tk_spawn(&tk, "node/view/vlff-record", a3, log)), 2);
  /* --force, --count: stops by itself after that many frames */
  const char *a4[] = {"--config", cfg_path, "--force", "--count", "2", "--quiet", path, NULL};
  pid_t rec = tk_spawn(&tk, "node/view/vlff-record", a4, log);
  struct vlff_mcap_writer *w;
  char src[300];
  snprintf(src, sizeof src, "%s/three.mcap", tk.dir);
  w = writer(src);
  for (int i = 0; i < 3; i++) put_frame(w, i, 1000000000ull + (uint64_t)i * 10000000ull);
  close_writer(w);
  char log2[300];
  snprintf(log2, sizeof log2, "%s/cli2.log", tk.dir);
  /* --wait-reader, not --backpressure: a recorder that has its frames stops reading */
  assert_int_equal(run_replay(log2, "--config", cfg_path, "--wait-reader", "--quiet", src, NULL), 0);
  assert_int_equal(tk_wait_child(&tk, rec), 0);
  printf("# %s", tk_slurp(log));
  assert_non_null(strstr(tk_slurp(log), ": 2 frames, 0 poses, 0 feature maps recorded"));
}

/* A recording of frames and poses only: played without features, saying so. */
static void test_no_features(void **state) {
  (void)state;
  struct vlff_config cfg;
  const char *cfg_path = config(&cfg);
  char path[300], log[300];
  snprintf(path, sizeof path, "%s/nofeat.mcap", tk.dir);
  snprintf(log, sizeof log, "%s/nofeat.log", tk.dir);
  struct vlff_mcap_writer *w = writer(path);
  for (int i = 0; i < 3; i++) {
    uint64_t t = 1000000000ull + (uint64_t)i * 20000000ull;
    char err[256];
    if (vlff_in_write_pose(w, t, c2w[i], err, sizeof err)) fail_msg("%s", err);
    put_frame(w, i, t);
  }
  close_writer(w);
  assert_int_equal(run_replay(log, "--config", cfg_path, path, NULL), 0);
  const char *said = tk_slurp(log);
  printf("# %s", said);
  assert_non_null(strstr(said, "has no feature maps (/input/features): playing without features, as --no-features"));
  assert_non_null(strstr(said, "3 frames, 3 poses, 0 feature maps published"));
  struct vlff_ring *x = vlff_ring_attach(cfg.shm.feature_ring, VLFF_RECORD_FEATURE);
  assert_null(x); /* no feature ring */
  struct vlff_ring *f = vlff_ring_attach(cfg.shm.ring, VLFF_RECORD_FRAME);
  assert_non_null(f);
  assert_int_equal(vlff_ring_head(f), 3);
  vlff_ring_close(f);
}

/* vlff-replay refuses path: exit 1, the error text on stderr, no ring made. */
static void refused(const struct vlff_config *cfg, const char *cfg_path, const char *path, const char *error) {
  char log[400];
  snprintf(log, sizeof log, "%s.log", path);
  int rc = run_replay(log, "--config", cfg_path, "--quiet", path, NULL);
  const char *said = tk_slurp(log);
  printf("# %s", said);
  assert_int_equal(rc, 1); /* refused, not a crash (128 + signal) */
  if (!strstr(said, error)) fail_msg("expected '%s' in: %s", error, said);
  assert_null(vlff_ring_attach(cfg->shm.ring, VLFF_RECORD_FRAME));
}

/* A recording at dir/name: frame 0 at t0, and the one message json on
 * channel ch at t, before the frame or after it. */
static const char *one_bad(const char *dir, const char *name, uint64_t t0, bool before, int ch, uint64_t t,
                           const char *json) {
  static char path[512];
  snprintf(path, sizeof path, "%s/%s", dir, name);
  struct vlff_mcap_writer *w = writer(path);
  if (!before) put_frame(w, 0, t0);
  put_raw(w, ch, t, json);
  if (before) put_frame(w, 0, t0);
  close_writer(w);
  return path;
}

static void test_bad_recordings_refused(void **state) {
  (void)state;
  struct vlff_config cfg;
  const char *cfg_path = config(&cfg);
  char path[300];
  const uint64_t t0 = 5000000000ull, dt = 33000000ull;

  /* a good recording of 4 frames with poses, features on frame 0 */
  snprintf(path, sizeof path, "%s/good.mcap", tk.dir);
  struct vlff_mcap_writer *w = writer(path);
  char err[256];
  for (int i = 0; i < 4; i++) {
    if (vlff_in_write_pose(w, t0 + i * dt, c2w[i], err, sizeof err)) fail_msg("%s", err);
    put_frame(w, i, t0 + i * dt);
    assert_int_equal(vlff_mcap_writer_flush(w), 0); /* a chunk per frame */
  }
  close_writer(w);
  uint8_t *good = NULL;
  size_t n = 0;
  assert_int_equal(vlff_read_file(path, 1 << 26, &good, &n, err, sizeof err), 0);

  /* cut short inside a chunk, as a killed recorder leaves it */
  snprintf(path, sizeof path, "%s/cut.mcap", tk.dir);
  assert_int_equal(vlff_write_file_atomic(path, good, n * 6 / 10, err, sizeof err), 0);
  refused(&cfg, cfg_path, path, "without its footer: a recording cut short");
  /* cut inside the header */
  snprintf(path, sizeof path, "%s/header-cut.mcap", tk.dir);
  assert_int_equal(vlff_write_file_atomic(path, good, 12, err, sizeof err), 0);
  refused(&cfg, cfg_path, path, "header-cut.mcap");
  /* a byte flipped in the middle: a chunk's CRC or its compression fails */
  snprintf(path, sizeof path, "%s/flip.mcap", tk.dir);
  good[n / 2] ^= 0x5a;
  assert_int_equal(vlff_write_file_atomic(path, good, n, err, sizeof err), 0);
  good[n / 2] ^= 0x5a;
  refused(&cfg, cfg_path, path, ": byte ");
  free(good);

  /* out of bounds: each file good but for one message, named by channel and index */
  const char *cal_bad =
      "{\"timestamp\":{\"sec\":5,\"nsec\":33000000},\"frame_id\":\"camera\",\"width\":40,\"height\":30,"
      "\"distortion_model\":\"\",\"D\":[],\"K\":[-35,0,19.75,0,36,15.25,0,0,1],\"R\":[1,0,0,0,1,0,0,0,1],"
      "\"P\":[35,0,19.75,0,0,36,15.25,0,0,0,1,0]}";
  /* a colour image whose data is not its size */
  refused(&cfg, cfg_path,
          one_bad(tk.dir, "empty.mcap", t0, false, VLFF_IN_COLOR, t0 + dt,
                  "{\"timestamp\":{\"sec\":5,\"nsec\":33000000},\"frame_id\":\"camera\",\"width\":40,"
                  "\"height\":30,\"encoding\":\"rgb8\",\"step\":120,\"data\":\"\"}"),
          "channel /input/color message 3: 'data' holds 0 base64 characters");

  snprintf(path, sizeof path, "%s/fx2.mcap", tk.dir);
  w = writer(path);
  put_frame(w, 0, t0);
  /* a calibration message with fx < 0 right after a good frame's colour: the
   * good frame is re-sent at the next stamp with its calibration replaced */
  {
    struct vlff_mcap_writer *tmp_w;
    char tmp[300];
    snprintf(tmp, sizeof tmp, "%s/tmp.mcap", tk.dir);
    tmp_w = writer(tmp);
    put_frame(tmp_w, 1, t0 + dt);
    close_writer(tmp_w);
    uint8_t *d = NULL;
    size_t dn = 0;
    assert_int_equal(vlff_read_file(tmp, 1 << 26, &d, &dn, err, sizeof err), 0);
    struct vlff_mcap_reader *r = vlff_mcap_reader_new(d, dn, err, sizeof err);
    assert_non_null(r);
    struct vlff_mcap_message m;
    while (vlff_mcap_next(r, &m, err, sizeof err) == 1)
      if (m.channel != VLFF_IN_CALIBRATION)
        assert_int_equal(vlff_mcap_writer_message(w, m.channel, m.log_ns, m.publish_ns, m.data, m.len), 0);
    vlff_mcap_reader_free(r);
    free(d);
    put_raw(w, VLFF_IN_CALIBRATION, t0 + dt, cal_bad);
  }
  close_writer(w);
  refused(&cfg, cfg_path, path, "channel /input/calibration message 5: fx");

  /* a pose whose rotation is not a unit quaternion */
#define POSE_AT(xyz, w) \
  "{\"timestamp\":{\"sec\":5,\"nsec\":0},\"parent_frame_id\":\"world\",\"child_frame_id\":\"camera\"," \
  "\"translation\":{" xyz "},\"rotation\":{\"x\":0,\"y\":0,\"z\":0,\"w\":" w "}}"
  refused(&cfg, cfg_path,
          one_bad(tk.dir, "quat.mcap", t0, false, VLFF_IN_POSE, t0, POSE_AT("\"x\":0,\"y\":0,\"z\":0", "2")),
          "channel /input/pose message 3: rotation is not a unit quaternion");
  /* a pose far outside any room */
  refused(&cfg, cfg_path,
          one_bad(tk.dir, "far.mcap", t0, true, VLFF_IN_POSE, t0, POSE_AT("\"x\":1e9,\"y\":0,\"z\":0", "1")),
          "channel /input/pose message 0: ");
#undef POSE_AT
  /* a feature map of dimension 0 */
  refused(&cfg, cfg_path,
          one_bad(tk.dir, "dim.mcap", t0, false, VLFF_IN_FEATURES, t0,
                  "{\"timestamp\":{\"sec\":5,\"nsec\":0},\"frame_id\":0,\"dim\":0,\"height\":1,\"width\":1,"
                  "\"encoding\":\"float16\",\"data\":\"\"}"),
          "channel /input/features message 3: 'dim' 0 is outside [1, 4096]");

  /* frames whose stamps go back */
  snprintf(path, sizeof path, "%s/back.mcap", tk.dir);
  w = writer(path);
  put_frame(w, 0, t0);
  put_frame(w, 1, t0 - dt);
  close_writer(w);
  refused(&cfg, cfg_path, path, "channel /input/color message 3: stamp ");

  /* a vlff-view-like recording: no input channels */
  snprintf(path, sizeof path, "%s/view.mcap", tk.dir);
  {
    struct vlff_mcap_writer_params wp = {"test", 0, 0, 0};
    w = vlff_mcap_writer_open(path, &wp, err, sizeof err);
    assert_non_null(w);
    assert_int_equal(vlff_mcap_writer_channel(w, 1, "/tf", "json", "foxglove.FrameTransform", "jsonschema", "{}", 2), 0);
    put_raw(w, 1, t0, "{}");
    close_writer(w);
  }
  refused(&cfg, cfg_path, path, "no frames on /input/color (1 messages on other channels");
  /* a real vlff-view recording (the fuzzer's seed) */
  char view[1200];
  snprintf(view, sizeof view, "%s/tests/fuzz/seeds/mcap/status-zstd.mcap", getenv("VLFF_SOURCE_DIR"));
  snprintf(path, sizeof path, "%s/viewer.mcap", tk.dir);
  uint8_t *d = NULL;
  size_t dn = 0;
  assert_int_equal(vlff_read_file(view, 1 << 26, &d, &dn, err, sizeof err), 0);
  assert_int_equal(vlff_write_file_atomic(path, d, dn, err, sizeof err), 0);
  free(d);
  refused(&cfg, cfg_path, path, "a vlff-view recording holds no inputs; vlff-record records them");
}

static int setup(void **state) {
  (void)state;
  tk_setup(&tk, "rmcap");
  fill_scene();
  snprintf(scene, sizeof scene, "%s/scene", tk.dir);
  return 0;
}

static int teardown(void **state) {
  (void)state;
  return tk_teardown(&tk);
}

int main(void) {
  const struct CMUnitTest tests[] = {
      cmocka_unit_test_setup_teardown(test_round_trip, setup, teardown),
      cmocka_unit_test_setup_teardown(test_pose_in_frame, setup, teardown),
      cmocka_unit_test_setup_teardown(test_pace, setup, teardown),
      cmocka_unit_test_setup_teardown(test_recorder_behind, setup, teardown),
      cmocka_unit_test_setup_teardown(test_record_cli, setup, teardown),
      cmocka_unit_test_setup_teardown(test_no_features, setup, teardown),
      cmocka_unit_test_setup_teardown(test_bad_recordings_refused, setup, teardown),
  };
  return cmocka_run_group_tests(tests, NULL, NULL);
}
