/*
 * vlff-camd end to end: the real binary streams Aravis' fake GigE camera
 * into a real frame ring, read back here as a consumer through libvlff-shm.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
#include <vlff/shm.h>

#include "fakecam.h"
#include "drvtest.h"
#include "unit.h"

static pid_t cam_pid = -1;
static char ring_name[64], cfg_path[256], out_path[256];
static int case_no;

static int setup(void **state) {
  (void)state;
  cam_pid = fakecam_start(0);
  return cam_pid > 0 ? 0 : -1;
}

static int teardown(void **state) {
  (void)state;
  fakecam_stop(cam_pid);
  return 0;
}

/* Writes a config with a unique ring name; extra is appended to camera:. */
static void write_cfg(const char *fmt, int w, int h, const char *camera_extra) {
  snprintf(ring_name, sizeof ring_name, "/vlff-test-camd-%d-%d", (int)getpid(), ++case_no);
  snprintf(cfg_path, sizeof cfg_path, "/tmp/vlff-test-camd-%d-%d.yaml", (int)getpid(), case_no);
  snprintf(out_path, sizeof out_path, "/tmp/vlff-test-camd-%d-%d.out", (int)getpid(), case_no);
  FILE *f = fopen(cfg_path, "w");
  assert_non_null(f);
  fprintf(f,
          "node:\n  log_level: warn\nshm:\n  ring: %s\n  pose_ring: %s-poses\n  ring_slots: 64\n"
          "  max_width: 640\n  max_height: 480\n"
          "camera:\n  kind: aravis\n  device: 127.0.0.1\n  pixel_format: %s\n  width: %d\n  height: %d\n"
          "  frame_rate: 40\n  reconnect_max_s: 0.5\n%s%s",
          ring_name, ring_name, fmt, w, h,
          camera_extra && strstr(camera_extra, "intrinsics:") ? "" : "  intrinsics: [500, 500, 160, 120]\n",
          camera_extra ? camera_extra : "");
  fclose(f);
}

static pid_t spawn_camd(const char *args) {
  pid_t parent = getpid();
  pid_t pid = fork();
  assert_true(pid >= 0);
  if (pid == 0) {
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (getppid() != parent) _exit(1);
    int fd = open(out_path, O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd >= 0) dup2(fd, 1);
    char bin[512];
    snprintf(bin, sizeof bin, "%s/drivers/camd/vlff-camd", getenv("VLFF_BINARY_DIR"));
    char frames[32] = "";
    if (args) snprintf(frames, sizeof frames, "%s", args);
    if (frames[0])
      execl(bin, bin, "--config", cfg_path, "--frames", frames, (char *)NULL);
    else
      execl(bin, bin, "--config", cfg_path, (char *)NULL);
    _exit(127);
  }
  return pid;
}

static int wait_exit(pid_t pid, int timeout_s) {
  for (int i = 0; i < timeout_s * 20; i++) {
    int st;
    if (waitpid(pid, &st, WNOHANG) == pid) return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
    sleep_ms(50);
  }
  kill(pid, SIGKILL);
  waitpid(pid, NULL, 0);
  return -1;
}

static struct vlff_ring *attach(void) {
  for (int i = 0; i < 100; i++) {
    struct vlff_ring *r = vlff_ring_attach(ring_name, VLFF_RECORD_FRAME);
    if (r) return r;
    sleep_ms(50);
  }
  fail_msg("ring %s never appeared: %s", ring_name, vlff_shm_last_message());
  return NULL;
}

static uint64_t stat_of(const char *key) { return stats_value(out_path, key); }

static void cleanup(void) {
  vlff_shm_unlink(ring_name);
  unlink(cfg_path);
  unlink(out_path);
}

static void check_frame(const void *rec, size_t len, int w, int h) {
  assert_int_equal(vlff_frame_validate(rec, len), 0);
  const struct vlff_frame_hdr *hd = rec;
  assert_int_equal(hd->plane[VLFF_PLANE_COLOR].width, w);
  assert_int_equal(hd->plane[VLFF_PLANE_COLOR].height, h);
  assert_int_equal(hd->plane[VLFF_PLANE_COLOR].format, VLFF_PIX_RGB8);
  assert_int_equal(hd->nplanes, 1);
  assert_true(hd->flags & VLFF_FRAME_INTRINSICS_VALID);
  assert_false(hd->flags & VLFF_FRAME_POSE_VALID); /* no SLAM publishing poses */
  assert_true(hd->fx == 500.0 && hd->cy == 120.5); /* OpenCV's 120, centred at +0.5 */
  const uint8_t *px = vlff_frame_plane(rec, VLFF_PLANE_COLOR);
  uint32_t stride = hd->plane[VLFF_PLANE_COLOR].stride;
  for (int y = 0; y < h; y += 3)
    for (int x = 0; x < w; x += 7) {
      uint8_t want = (uint8_t)((x + y + hd->frame_id) % 255);
      const uint8_t *p = px + (size_t)y * stride + (size_t)x * 3;
      if (p[0] != want || p[1] != want || p[2] != want)
        fail_msg("frame %llu (%d,%d): %u, expected %u", (unsigned long long)hd->frame_id, x, y, p[0], want);
    }
}

#ifdef VLFF_HAVE_SYSTEMD
/* A notify socket of our own, as systemd gives a Type=notify service. */
static int notify_listen(char *path, size_t len) {
  snprintf(path, len, "/tmp/vlff-test-camd-notify-%ld", (long)getpid());
  unlink(path);
  int fd = socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  assert_true(fd >= 0);
  struct sockaddr_un a = {.sun_family = AF_UNIX};
  snprintf(a.sun_path, sizeof a.sun_path, "%s", path);
  assert_int_equal(bind(fd, (struct sockaddr *)&a, sizeof a), 0);
  setenv("NOTIFY_SOCKET", path, 1);
  setenv("WATCHDOG_USEC", "2000000", 1); /* a few messages a second: the queue never fills */
  return fd;
}

/* Appends every datagram received so far, one per line. Called while camd
 * runs: a unix datagram socket's queue is short and a full one blocks the
 * sender, as it would under a systemd that stopped reading. */
static void notify_collect(int fd, char *out, size_t cap) {
  size_t n = strlen(out);
  char msg[256];
  ssize_t got;
  while ((got = recv(fd, msg, sizeof msg - 1, MSG_DONTWAIT)) > 0 && n + (size_t)got + 2 < cap) {
    memcpy(out + n, msg, (size_t)got);
    n += (size_t)got;
    out[n++] = '\n';
    out[n] = 0;
  }
}
#endif

static void test_streams_n_frames(void **state) {
  (void)state;
  write_cfg("Mono8", 320, 240, NULL);
#ifdef VLFF_HAVE_SYSTEMD
  char npath[108], notes[8192] = "";
  int nfd = notify_listen(npath, sizeof npath);
#endif
  pid_t pid = spawn_camd("30");
#ifdef VLFF_HAVE_SYSTEMD
  unsetenv("NOTIFY_SOCKET");
  unsetenv("WATCHDOG_USEC");
#endif
  struct vlff_ring *r = attach();
  vlff_ring_seek_oldest(r);
  size_t cap = vlff_ring_slot_size(r);
  void *buf = malloc(cap);
  uint64_t last_host = 0, last_dev = 0, last_id = 0;
  int n = 0;
  while (n < 30) {
    struct vlff_ring_view v;
    ssize_t len = vlff_ring_read_copy(r, buf, cap, &v, 5000000000ull);
    if (len < 0) fail_msg("read: %s after %d frames", strerror(errno), n);
    check_frame(buf, (size_t)len, 320, 240);
    const struct vlff_frame_hdr *hd = buf;
    if (n) {
      assert_true(hd->t_host_ns > last_host);
      assert_true(hd->t_device_ns > last_dev);
      assert_true(hd->frame_id > last_id);
    }
    last_host = hd->t_host_ns, last_dev = hd->t_device_ns, last_id = hd->frame_id;
    n++;
#ifdef VLFF_HAVE_SYSTEMD
    notify_collect(nfd, notes, sizeof notes);
#endif
  }
  assert_int_equal(wait_exit(pid, 10), 0);
  assert_int_equal(vlff_ring_head(r), 30);
  assert_int_equal(vlff_ring_lost(r), 0);
  assert_int_equal(stat_of("committed"), 30);
  assert_int_equal(stat_of("dropped"), 0);
#ifdef VLFF_HAVE_SYSTEMD
  /* Type=notify: ready, watchdog fed while streaming, stopping. */
  notify_collect(nfd, notes, sizeof notes);
  close(nfd);
  unlink(npath);
  if (!strstr(notes, "READY=1\n") || !strstr(notes, "WATCHDOG=1\n") || !strstr(notes, "STOPPING=1\n"))
    fail_msg("notify messages: %s", notes);
#endif
  free(buf);
  vlff_ring_close(r);
  cleanup();
}

static void test_software_trigger_one_frame_each(void **state) {
  (void)state;
  write_cfg("Mono8", 160, 120, "  trigger: software\n");
  pid_t pid = spawn_camd(NULL);
  struct vlff_ring *r = attach();
  sleep_ms(800); /* camera opened and idle: no triggers, no frames */
  assert_int_equal(vlff_ring_head(r), 0);
  for (int i = 1; i <= 5; i++) {
    kill(pid, SIGUSR1);
    for (int k = 0; k < 100 && vlff_ring_head(r) < (uint64_t)i; k++) sleep_ms(20);
    assert_int_equal(vlff_ring_head(r), i);
    sleep_ms(200); /* > the fake camera's 25 Hz trigger tick: still one frame */
    assert_int_equal(vlff_ring_head(r), i);
  }
  kill(pid, SIGTERM);
  assert_int_equal(wait_exit(pid, 10), 0);
  assert_int_equal(stat_of("committed"), 5);
  assert_int_equal(stat_of("triggers"), 5);
  vlff_ring_close(r);
  cleanup();
}

/* Once `want` entries are in the ring (within wait_tries polls), the fake
 * camera loses power for 1.5 s and comes back; `want` more entries follow. */
static void restart_camera(struct vlff_ring *r, uint64_t want, int wait_tries) {
  for (int k = 0; k < wait_tries && vlff_ring_head(r) < want; k++) sleep_ms(50);
  assert_true(vlff_ring_head(r) >= want);
  fakecam_kill(cam_pid);
  sleep_ms(1500);
  uint64_t during = vlff_ring_head(r);
  cam_pid = fakecam_start(0);
  assert_true(cam_pid > 0);
  for (int k = 0; k < 400 && vlff_ring_head(r) < during + want; k++) sleep_ms(50);
  assert_true(vlff_ring_head(r) >= during + want);
}

static void test_reconnects_after_camera_restart(void **state) {
  (void)state;
  write_cfg("Mono8", 160, 120, NULL);
  pid_t pid = spawn_camd(NULL);
  struct vlff_ring *r = attach();
  /* The ring stays, the driver keeps running, frames flow again. */
  restart_camera(r, 10, 100);
  assert_int_equal(kill(pid, 0), 0);
  uint32_t gen = vlff_ring_generation(r);
  kill(pid, SIGTERM);
  assert_int_equal(wait_exit(pid, 15), 0);
  assert_int_equal(stat_of("lost"), 1);
  assert_int_equal(stat_of("reconnects"), 1);
  assert_int_equal(gen, 1); /* same ring generation throughout */
  /* The newest frame after reconnection is whole and right. */
  struct vlff_ring_view v;
  void *buf = malloc(vlff_ring_slot_size(r));
  ssize_t len = vlff_ring_read_latest(r, buf, vlff_ring_slot_size(r), &v);
  assert_true(len > 0);
  check_frame(buf, (size_t)len, 160, 120);
  free(buf);
  vlff_ring_close(r);
  cleanup();
}

/* Two cameras, one record: the fake GigE camera streams colour (RGB8), the
 * in-process fake camera a Mono16 range image, both free-running at 40 Hz.
 * Pairs within the tolerance become records with the colour plane and the
 * range image registered into it; through an identity rig (one camera
 * matrix, no offset) the depth plane is the range image itself, in mm.
 * The record's ids and intrinsics are the colour camera's. */
static char rig_path[256];
/* The range camera's size in the pair's config: its own 320 x 240. */
#define PAIR_DEPTH_SIZE "  width: 320\n  height: 240\n"

/* The pair's config: the fake GigE camera as colour, the in-process fake
 * camera as range, an identity rig (rig_extra: more lines of its file);
 * depth_size: the range camera's size keys ("" leaves it to the camera). */
static void write_pair_cfg_rig(const char *depth_size, const char *depth_extra, const char *rig_extra) {
  snprintf(rig_path, sizeof rig_path, "/tmp/vlff-test-camd-%d-rig.yaml", (int)getpid());
  FILE *f = fopen(rig_path, "w");
  assert_non_null(f);
  fputs("%YAML:1.0\n---\n"
        "K1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 300., 0., 159.5, 0., 300., 119.5, 0., 0., 1. ]\n"
        "D1: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
        "K2: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 300., 0., 159.5, 0., 300., 119.5, 0., 0., 1. ]\n"
        "D2: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
        "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]\n"
        "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ 0., 0., 0. ]\n",
        f);
  if (rig_extra) fputs(rig_extra, f);
  fclose(f);
  char extra[1024];
  snprintf(extra, sizeof extra,
           "  depth: stream\n  intrinsics: [0, 0, 0, 0]\n"
           "depth_camera:\n  kind: aravis\n  device: Fake\n  pixel_format: Mono16\n%s"
           "  frame_rate: 40\n  scale_m: 0.001\n  calibration: %s\n  pair_tolerance_s: 0.012\n%s",
           depth_size, rig_path, depth_extra ? depth_extra : "");
  write_cfg("Mono8", 320, 240, extra);
}

static void write_pair_cfg(const char *depth_extra) { write_pair_cfg_rig(PAIR_DEPTH_SIZE, depth_extra, NULL); }

/* vlff-camd run on the pair for `frames` records, all committed; the ring
 * is returned read from its oldest record, *buf sized for one of them. */
static struct vlff_ring *run_pair(const char *depth_extra, const char *frames, void **buf) {
  write_pair_cfg(depth_extra);
  pid_t pid = spawn_camd(frames);
  struct vlff_ring *r = attach();
  vlff_ring_seek_oldest(r);
  assert_int_equal(wait_exit(pid, 60), 0);
  assert_int_equal(vlff_ring_head(r), atoi(frames));
  *buf = malloc(vlff_ring_slot_size(r));
  assert_non_null(*buf);
  return r;
}

/* The next record, valid and holding two planes: colour and range. */
static const struct vlff_frame_hdr *next_pair(struct vlff_ring *r, void *buf) {
  struct vlff_ring_view v;
  ssize_t len = vlff_ring_read_copy(r, buf, vlff_ring_slot_size(r), &v, 0);
  assert_true(len > 0);
  assert_int_equal(vlff_frame_validate(buf, (size_t)len), 0);
  const struct vlff_frame_hdr *hd = buf;
  assert_int_equal(hd->nplanes, 2);
  return hd;
}

/* Record n's depth plane holds the fake range camera's ramp along x + y,
 * landed edge to edge: constant along anti-diagonals, and valid at both
 * side edges in at least border_min rows. With step_256 (at the range
 * camera's own size) it also rises by 256 counts a pixel in x until it
 * wraps. A shifted or resampled image breaks the ramp or leaves a border
 * empty. */
static void check_range_ramp(int n, const struct vlff_frame_hdr *hd, const void *buf, bool step_256, int border_min) {
  const uint8_t *dp = vlff_frame_plane(buf, VLFF_PLANE_DEPTH);
  const size_t ds = hd->plane[VLFF_PLANE_DEPTH].stride;
  const int w = (int)hd->plane[VLFF_PLANE_DEPTH].width, h = (int)hd->plane[VLFF_PLANE_DEPTH].height;
#define D(x, y) (((const uint16_t *)(dp + (size_t)(y) * ds))[x])
  int border = 0;
  for (int y = 0; y < h; y++) {
    border += D(0, y) != 0 && D(w - 1, y) != 0;
    for (int x = 0; x < w - 1; x++) {
      uint16_t a = D(x, y), b = D(x + 1, y);
      if (step_256 && a && b && b != a + 256 && b > a) fail_msg("record %d depth (%d,%d): %u then %u", n, x, y, a, b);
      if (y && D(x, y) != D(x + 1, y - 1))
        fail_msg("record %d depth (%d,%d) = %u, (%d,%d) = %u", n, x, y, D(x, y), x + 1, y - 1, D(x + 1, y - 1));
    }
  }
#undef D
  assert_true(border >= border_min);
}

static void pair_done(struct vlff_ring *r, void *buf) {
  free(buf);
  vlff_ring_close(r);
  unlink(rig_path);
  cleanup();
}

static void test_pairs_colour_and_range(void **state) {
  (void)state;
  void *buf;
  struct vlff_ring *r = run_pair(NULL, "12", &buf);
  assert_int_equal(stat_of("committed"), 12);
  assert_true(stat_of("unmatched_color") != UINT64_MAX && stat_of("unmatched_depth") != UINT64_MAX);
  assert_true(stat_of("color_frames") >= 12 && stat_of("depth_frames") >= 12);
  for (int n = 0; n < 12; n++) {
    const struct vlff_frame_hdr *hd = next_pair(r, buf);
    assert_int_equal(hd->plane[VLFF_PLANE_COLOR].format, VLFF_PIX_RGB8);
    assert_int_equal(hd->plane[VLFF_PLANE_DEPTH].format, VLFF_PIX_DEPTH_U16_MM);
    assert_int_equal(hd->plane[VLFF_PLANE_DEPTH].width, 320);
    assert_int_equal(hd->plane[VLFF_PLANE_DEPTH].height, 240);
    /* camera.intrinsics are OpenCV's; the record centres pixels at +0.5 */
    assert_true(hd->fx == 300 && hd->fy == 300 && hd->cx == 160 && hd->cy == 120);
    /* colour: the GigE camera's grey ramp of this frame */
    const uint8_t *px = vlff_frame_plane(buf, VLFF_PLANE_COLOR);
    for (int y = 0; y < 240; y += 7)
      for (int x = 0; x < 320; x += 5)
        assert_int_equal(px[(size_t)y * hd->plane[0].stride + (size_t)x * 3], (x + y + hd->frame_id) % 255);
    /* depth: the fake range camera's image at one millimetre per count,
     * landing pixel for pixel */
    check_range_ramp(n, hd, buf, true, 230);
  }
  pair_done(r, buf);
}

/* A calibration made for another resolution (640x480 range images; the
 * range camera sends its own, smaller size): every pair is dropped, and vlff-camd says
 * so within seconds, with the reason, not only in its exit line. Failed
 * before: 5 warnings, then nothing while 0 pairs were committed. */
static void test_pair_calibration_other_size(void **state) {
  (void)state;
  /* No size in the config: start-up (and --check-config) cannot compare
   * (test_check_config_calibration_sizes), the frames tell. */
  write_pair_cfg_rig("", NULL, "depth_width: 640\ndepth_height: 480\n");
  char log[300];
  snprintf(log, sizeof log, "%s.log", out_path);
  pid_t parent = getpid(), pid = fork();
  assert_true(pid >= 0);
  if (pid == 0) {
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (getppid() != parent) _exit(1);
    int fd = open(log, O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd >= 0) dup2(fd, 1), dup2(fd, 2);
    char bin[512];
    snprintf(bin, sizeof bin, "%s/drivers/camd/vlff-camd", getenv("VLFF_BINARY_DIR"));
    execl(bin, bin, "--config", cfg_path, "--seconds", "60", (char *)NULL);
    _exit(127);
  }
  /* Stopped once a pair was dropped: whether the periodic report came first
   * or not, the one said at exit names the reason. On a loaded host (TSan
   * beside other tests) the cameras' start-up frames can fill the first
   * seconds, so the wait is for the first drop, not a fixed time. */
  static char text[1 << 16];
  for (int i = 0; i < 600; i++) {
    FILE *f = fopen(log, "r"); /* not there until the child opened it */
    if (f) {
      text[fread(text, 1, sizeof text - 1, f)] = 0;
      fclose(f);
      if (strstr(text, "pair dropped: ")) break;
    }
    sleep_ms(50);
  }
  kill(pid, SIGTERM);
  assert_int_equal(wait_exit(pid, 30), 0);
  FILE *f = fopen(log, "r");
  assert_non_null(f);
  text[fread(text, 1, sizeof text - 1, f)] = 0;
  fclose(f);
  /* A report names the reason once its window dropped pairs: under load the
   * first window can end before any pair was tried, and the next is then
   * the one said at exit. */
  const char *rep = strstr(text, "E camd: pairing, last ");
  if (!rep) fail_msg("no pairing report in vlff-camd's log:\n%s", text);
  const char *why = NULL;
  for (const char *r = rep; r && !why; r = strstr(r + 1, "E camd: pairing, last ")) {
    const char *eol = strchr(r, '\n'), *c = strstr(r, "calibrated for depth 640x480");
    if (c && (!eol || c < eol)) why = r;
  }
  if (!why) fail_msg("no pairing report names the calibration's size:\n%s", text);
  assert_non_null(strstr(why, " 0 pairs of "));
  unlink(log);
  cleanup(); /* camd leaves its ring for readers: it would stay in /dev/shm */
}

/* The same pair registered at half the colour camera's size
 * (depth_camera.register_width/height): both planes of every record are
 * 160x120, the intrinsics those of the halved camera, the colour plane the
 * ramp averaged over 2x2 blocks, the depth plane the range ramp registered
 * at that size (still constant along anti-diagonals, edge to edge). */
static void test_pairs_at_register_size(void **state) {
  (void)state;
  void *buf;
  struct vlff_ring *r = run_pair("  register_width: 160\n  register_height: 120\n", "6", &buf);
  for (int n = 0; n < 6; n++) {
    const struct vlff_frame_hdr *hd = next_pair(r, buf);
    for (int pl = 0; pl < 2; pl++) {
      assert_int_equal(hd->plane[pl].width, 160);
      assert_int_equal(hd->plane[pl].height, 120);
    }
    /* OpenCV's cx 159.5 of 320 pixels is 79.5 of 160, 80 in the record's
     * pixel-centre convention */
    assert_true(hd->fx == 150 && hd->fy == 150 && hd->cx == 80 && hd->cy == 60);
    const uint8_t *px = vlff_frame_plane(buf, VLFF_PLANE_COLOR);
    for (int y = 0; y < 120; y += 3)
      for (int x = 0; x < 160; x += 5) {
        unsigned a = (unsigned)(2 * x + 2 * y + hd->frame_id) % 255;
        if (a > 252) continue; /* the ramp wraps inside this block */
        assert_int_equal(px[(size_t)y * hd->plane[0].stride + (size_t)x * 3], a + 1);
      }
    check_range_ramp(n, hd, buf, false, 115);
  }
  pair_done(r, buf);
}

/* The colour camera of a pair loses power and comes back: the range
 * camera's frames meanwhile find no partner and are counted, the ring stays,
 * and pairs flow again after the reconnection. */
static void test_pair_survives_camera_restart(void **state) {
  (void)state;
  write_pair_cfg(NULL);
  pid_t pid = spawn_camd(NULL);
  struct vlff_ring *r = attach();
  restart_camera(r, 5, 200);
  kill(pid, SIGTERM);
  assert_int_equal(wait_exit(pid, 15), 0);
  assert_int_equal(stat_of("lost"), 1);
  assert_int_equal(stat_of("reconnects"), 1);
  assert_true(stat_of("unmatched_depth") > 0);
  assert_int_equal(stat_of("committed"), vlff_ring_head(r));
  pair_done(r, NULL);
}

/* Bad configurations are refused before any camera is touched, naming the key. */
static void test_bad_configs(void **state) {
  (void)state;
  static const struct {
    const char *extra, *key;
  } cases[] = {
      {"  depth: stereo\n", "camera.calibration"},
      {"  depth: stream\n", "camera.depth"},
      {"  distortion: [0.1, 0, 0, 0, 0]\n  intrinsics: [0, 0, 0, 0]\n", "camera.distortion"},
      {"  offset_x: 1900\n", "camera.offset_x"}, /* sensor is 2048 wide: the camera says so */
      {"  calibration: /nonexistent/calib.yaml\n", "camera.calibration"},
  };
  for (size_t i = 0; i < sizeof cases / sizeof cases[0]; i++) {
    write_cfg("Mono8", 320, 240, cases[i].extra);
    char cmd[1024];
    snprintf(cmd, sizeof cmd, "%s/drivers/camd/vlff-camd --config %s --frames 1 2>&1", getenv("VLFF_BINARY_DIR"),
             cfg_path);
    FILE *p = popen(cmd, "r");
    char out[2048] = "";
    size_t n = fread(out, 1, sizeof out - 1, p);
    out[n] = 0;
    int st = pclose(p);
    if (!strstr(out, cases[i].key)) fail_msg("case %zu: output lacks '%s': %s", i, cases[i].key, out);
    assert_int_equal(WEXITSTATUS(st), 1);
    cleanup();
  }
  /* A FIFO as calibration file is refused at once, naming it (issue 29): OpenCV
   * opening it would wait for a writer for ever. timeout ends a camd that does. */
  char fifo[128], extra[192];
  snprintf(fifo, sizeof fifo, "/tmp/vlff-test-camd-%d.fifo", (int)getpid());
  unlink(fifo);
  assert_int_equal(mkfifo(fifo, 0600), 0);
  snprintf(extra, sizeof extra, "  calibration: %s\n", fifo);
  write_cfg("Mono8", 320, 240, extra);
  char cmd[1024], out[2048] = "";
  snprintf(cmd, sizeof cmd, "timeout 20 %s/drivers/camd/vlff-camd --config %s --frames 1 2>&1",
           getenv("VLFF_BINARY_DIR"), cfg_path);
  FILE *p = popen(cmd, "r");
  size_t n = fread(out, 1, sizeof out - 1, p);
  out[n] = 0;
  int st = pclose(p);
  unlink(fifo);
  if (WEXITSTATUS(st) != 1 || !strstr(out, "key 'camera.calibration'") || !strstr(out, "is a FIFO, expected a regular file"))
    fail_msg("a FIFO as camera.calibration: rc %d (124: blocked), output: %s", WEXITSTATUS(st), out);
  cleanup();
  write_cfg("Mono9", 320, 240, NULL);
  snprintf(cmd, sizeof cmd, "%s/drivers/camd/vlff-camd --check-config %s 2>&1", getenv("VLFF_BINARY_DIR"), cfg_path);
  p = popen(cmd, "r");
  n = fread(out, 1, sizeof out - 1, p);
  out[n] = 0;
  assert_int_equal(WEXITSTATUS(pclose(p)), 1);
  assert_non_null(strstr(out, "camera.pixel_format"));
  assert_non_null(strstr(out, "Mono9"));
  cleanup();
}

/* vlff-camd --check-config on the config last written: its exit status,
 * its output in out; the config is removed. */
static int check_config(char *out, size_t len) {
  char cmd[1024];
  snprintf(cmd, sizeof cmd, "%s/drivers/camd/vlff-camd --check-config %s 2>&1", getenv("VLFF_BINARY_DIR"), cfg_path);
  FILE *p = popen(cmd, "r");
  size_t n = fread(out, 1, len - 1, p);
  out[n] = 0;
  int st = pclose(p);
  cleanup();
  return WEXITSTATUS(st);
}

/* --check-config refuses a calibration made for other image sizes than the
 * config's camera.width/height (and depth_camera's) when both say theirs, as
 * start-up does; before, it said ok and every pair was dropped at the first. */
static void test_check_config_calibration_sizes(void **state) {
  (void)state;
  char out[2048];
  write_pair_cfg_rig(PAIR_DEPTH_SIZE, NULL,
                     "depth_width: 320\ndepth_height: 240\ncolor_width: 320\ncolor_height: 240\n");
  if (check_config(out, sizeof out) != 0) fail_msg("sizes that agree refused: %s", out);
  write_pair_cfg_rig(PAIR_DEPTH_SIZE, NULL, "color_width: 640\ncolor_height: 480\n");
  assert_int_equal(check_config(out, sizeof out), 1);
  if (!strstr(out, "key 'depth_camera.calibration': ") ||
      !strstr(out, "is calibrated for colour 640x480, but camera.width/height say 320x240"))
    fail_msg("no colour size refusal in: %s", out);
  write_pair_cfg_rig(PAIR_DEPTH_SIZE, NULL, "depth_width: 640\ndepth_height: 480\n");
  assert_int_equal(check_config(out, sizeof out), 1);
  if (!strstr(out, "is calibrated for depth 640x480, but depth_camera.width/height say 320x240"))
    fail_msg("no depth size refusal in: %s", out);
  unlink(rig_path);
  /* A single camera's calibration of another image size. */
  char calib[256], extra[400];
  snprintf(calib, sizeof calib, "/tmp/vlff-test-camd-%d-mono.yaml", (int)getpid());
  FILE *f = fopen(calib, "w");
  assert_non_null(f);
  fputs("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 600., 0., 319.5, 0., 600., 239.5, 0., 0., 1. ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n",
        f);
  fclose(f);
  snprintf(extra, sizeof extra, "  calibration: %s\n", calib);
  write_cfg("Mono8", 320, 240, extra);
  assert_int_equal(check_config(out, sizeof out), 1);
  if (!strstr(out, "key 'camera.calibration': ") ||
      !strstr(out, "is calibrated for 640x480 images (image_width/height), but camera.width/height say 320x240"))
    fail_msg("no camera.calibration size refusal in: %s", out);
  write_cfg("Mono8", 640, 480, extra);
  if (check_config(out, sizeof out) != 0) fail_msg("a calibration of the camera's size refused: %s", out);
  unlink(calib);
}

VLFF_UNIT_MAIN(setup, teardown,
    cmocka_unit_test(test_check_config_calibration_sizes),
    cmocka_unit_test(test_streams_n_frames),
    cmocka_unit_test(test_software_trigger_one_frame_each), cmocka_unit_test(test_bad_configs),
    cmocka_unit_test(test_reconnects_after_camera_restart),
    cmocka_unit_test(test_pairs_colour_and_range), cmocka_unit_test(test_pairs_at_register_size),
    cmocka_unit_test(test_pair_survives_camera_restart),
    cmocka_unit_test(test_pair_calibration_other_size))
