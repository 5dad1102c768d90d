/*
 * vlff-camd end to end inside the test VM, against real kernel stacks:
 *
 *   vlff-camd-vmtest libcamera N
 *     vlff-camd with camera.kind libcamera streams the vimc virtual camera
 *     (formats set by tests/vm/cases/libcamera.sh) for N frames into a frame
 *     ring; checks size, format, frame ids, monotonic sensor timestamps on
 *     CLOCK_MONOTONIC, the sensor's colour bar pattern through libcamera's
 *     debayer and our RGB8 path, and a clean exit with its statistics.
 *     Then a second run is stopped by SIGTERM mid-stream: the camera was
 *     released by the first, and the second shuts down cleanly too.
 *
 *   vlff-camd-vmtest gpio-trigger CHIP SIMDIR
 *     vlff-camd with camera.trigger software and gpio.mode input on line 1
 *     of a gpio-sim chip, streaming Aravis' fake GigE camera (started by the
 *     case on 127.0.0.1): each edge driven through the sim's pull attribute
 *     gives exactly one frame, stamped with the edge's kernel timestamp
 *     (which lies inside our pull write), and falling edges give none.
 *   vlff-camd-vmtest gpio-pair CHIP SIMDIR
 *     the same edges fire two fake GigE cameras (127.0.0.1 colour, 127.0.0.2
 *     Mono16 range, started by the case): one paired record per edge.
 *   vlff-camd-vmtest lcam-pair CHIP SIMDIR
 *     a libcamera colour camera (vimc, free-running) paired with an Aravis
 *     range camera (the fake GigE camera on 127.0.0.1, started by the case):
 *     each edge stamps the next vimc frame and fires the range camera, one
 *     record per edge at a configured size.
 *
 * vlff-camd is run from PATH. Prints "ok: ..." lines; exits 1 on the first
 * failure with the reason.
 */
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
#include <vlff/shm.h>
#include "drvtest.h"

static char ring_name[64], cfg_path[128], out_path[128], err_path[128];
static pid_t camd_pid = -1;

static void cleanup(void) {
  if (camd_pid > 0) {
    kill(camd_pid, SIGKILL);
    waitpid(camd_pid, NULL, 0);
    camd_pid = -1;
  }
  vlff_shm_unlink(ring_name);
}

static void dump(const char *path) {
  FILE *f = fopen(path, "r");
  if (!f) return;
  char line[512];
  while (fgets(line, sizeof line, f)) fprintf(stderr, "  | %s", line);
  fclose(f);
}

static void failf(const char *fmt, ...) __attribute__((format(printf, 1, 2), noreturn));
static void failf(const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  fputs("FAIL: ", stderr);
  vfprintf(stderr, fmt, ap);
  fputc('\n', stderr);
  va_end(ap);
  /* SIGTERM first, so that its statistics line (triggers sent, edges seen,
   * frames stamped) is in the output below: what a failure needs read. */
  if (camd_pid > 0 && kill(camd_pid, SIGTERM) == 0) {
    for (int i = 0; i < 100; i++) {
      if (waitpid(camd_pid, NULL, WNOHANG) == camd_pid) {
        camd_pid = -1; /* reaped: cleanup() has nothing to kill */
        break;
      }
      struct timespec ts = {0, 50 * 1000 * 1000};
      nanosleep(&ts, NULL);
    }
  }
  fprintf(stderr, "vlff-camd stderr:\n");
  dump(err_path);
  fprintf(stderr, "vlff-camd stdout:\n");
  dump(out_path);
  cleanup();
  exit(1);
}
#define CHECK(c, ...) \
  do {                \
    if (!(c)) failf(__VA_ARGS__); \
  } while (0)

static void names(const char *what) {
  snprintf(ring_name, sizeof ring_name, "/vlff-vm-%s-%d", what, (int)getpid());
  snprintf(cfg_path, sizeof cfg_path, "/tmp/vlff-vm-%s-%d.yaml", what, (int)getpid());
  snprintf(out_path, sizeof out_path, "/tmp/vlff-vm-%s-%d.out", what, (int)getpid());
  snprintf(err_path, sizeof err_path, "/tmp/vlff-vm-%s-%d.err", what, (int)getpid());
}

static void write_file(const char *path, const char *text) {
  FILE *f = fopen(path, "w");
  CHECK(f && fputs(text, f) >= 0 && fclose(f) == 0, "cannot write %s", path);
}

static pid_t spawn_camd(const char *frames) {
  pid_t pid = fork();
  CHECK(pid >= 0, "fork: %s", strerror(errno));
  if (pid == 0) {
    int o = open(out_path, O_WRONLY | O_CREAT | O_TRUNC, 0644), e = open(err_path, O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (o < 0 || e < 0) _exit(127);
    dup2(o, 1), dup2(e, 2);
    if (frames)
      execlp("vlff-camd", "vlff-camd", "--config", cfg_path, "--frames", frames, (char *)NULL);
    else
      execlp("vlff-camd", "vlff-camd", "--config", cfg_path, (char *)NULL);
    _exit(127);
  }
  return pid;
}

/* Exit status, or -1 if it did not exit within timeout_s (then killed). */
static int wait_exit(pid_t pid, int timeout_s) {
  for (int i = 0; i < timeout_s * 20; i++) {
    int st;
    if (waitpid(pid, &st, WNOHANG) == pid) {
      camd_pid = -1;
      return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
    }
    sleep_ms(50);
  }
  return -1;
}

static struct vlff_ring *attach(int timeout_s) {
  for (int i = 0; i < timeout_s * 20; i++) {
    struct vlff_ring *r = vlff_ring_attach(ring_name, VLFF_RECORD_FRAME);
    if (r) return r;
    int st;
    CHECK(waitpid(camd_pid, &st, WNOHANG) != camd_pid, "vlff-camd exited before creating ring %s", ring_name);
    sleep_ms(50);
  }
  failf("ring %s never appeared: %s", ring_name, vlff_shm_last_message());
}

/* The end of a run that passed: nothing of it left behind. */
static void finish(struct vlff_ring *r, void *buf) {
  vlff_ring_close(r);
  free(buf);
  cleanup();
  unlink(cfg_path), unlink(out_path), unlink(err_path);
}

/* A key of vlff-camd's statistics line, UINT64_MAX if absent. */
static uint64_t stat_of(const char *key) { return stats_value(out_path, key); }

static int file_has(const char *path, const char *needle) {
  FILE *f = fopen(path, "r");
  if (!f) return 0;
  char line[1024];
  int found = 0;
  while (!found && fgets(line, sizeof line, f)) found = strstr(line, needle) != NULL;
  fclose(f);
  return found;
}

/* ------------------------------------------------------------ libcamera */

/* vimc's sensor draws v4l2-tpg's default pattern, 75 % colour bars: eight
 * equal-width vertical bars, white yellow cyan green magenta red blue black
 * at 75 % level (191). The case turns the sensor's text overlay off. Each
 * bar's middle third, averaged over every row, must have the bar's colour:
 * channels that are on > 150, channels that are off < 50 (the debayer and
 * scaler blur only the bar edges), and every row the same within 20. A
 * channel swap (RGB vs BGR), a wrong stride or a torn image fails this. */
static void check_bars(const struct vlff_frame_hdr *hd, const uint8_t *px) {
  static const char *name[8] = {"white", "yellow", "cyan", "green", "magenta", "red", "blue", "black"};
  static const uint8_t on[8][3] = {{1, 1, 1}, {1, 1, 0}, {0, 1, 1}, {0, 1, 0}, {1, 0, 1}, {1, 0, 0}, {0, 0, 1}, {0, 0, 0}};
  const struct vlff_plane *pl = &hd->plane[VLFF_PLANE_COLOR];
  unsigned bw = pl->width / 8;
  for (int b = 0; b < 8; b++) {
    double sum[3] = {0, 0, 0}, n = 0;
    double row_min = 1e9, row_max = -1;
    for (unsigned y = 0; y < pl->height; y++) {
      double rs = 0;
      for (unsigned x = b * bw + bw / 3; x < b * bw + 2 * bw / 3; x++) {
        const uint8_t *p = px + (size_t)y * pl->stride + (size_t)x * 3;
        for (int c = 0; c < 3; c++) sum[c] += p[c], rs += p[c];
        n++;
      }
      row_min = rs < row_min ? rs : row_min;
      row_max = rs > row_max ? rs : row_max;
    }
    double m[3] = {sum[0] / n, sum[1] / n, sum[2] / n};
    for (int c = 0; c < 3; c++)
      CHECK(on[b][c] ? m[c] > 150 : m[c] < 50, "frame %llu bar %d (%s): mean RGB %.0f %.0f %.0f",
            (unsigned long long)hd->frame_id, b, name[b], m[0], m[1], m[2]);
    /* Vertical bars: every row of the bar's middle is about the same. */
    double per_row = n / pl->height * 3; /* channel values summed per row */
    CHECK((row_max - row_min) / per_row < 20, "frame %llu bar %d (%s) varies down the image: row means %.0f..%.0f",
          (unsigned long long)hd->frame_id, b, name[b], row_min / per_row, row_max / per_row);
  }
}

/* vlff-camd's configuration at cfg_path: the node and shm sections every
 * run shares around its camera sections, and with a chip, gpio.mode input
 * on its line 1 with no debounce. */
static void write_config(int ring_slots, int max_w, int max_h, const char *cameras, const char *chip) {
  char cfg[2048], gpio[256] = "";
  if (chip)
    snprintf(gpio, sizeof gpio, "gpio:\n  mode: input\n  chip: %s\n  line: \"1\"\n  debounce_us: 0\n", chip);
  snprintf(cfg, sizeof cfg,
           "node:\n  log_level: info\n"
           "shm:\n  ring: %s\n  pose_ring: %s-poses\n  ring_slots: %d\n  max_width: %d\n  max_height: %d\n"
           "%s%s",
           ring_name, ring_name, ring_slots, max_w, max_h, cameras, gpio);
  write_file(cfg_path, cfg);
}

static void lcam_config(int w, int h) {
  char camera[512];
  snprintf(camera, sizeof camera,
           "camera:\n  kind: libcamera\n  device: \"0\"\n  pixel_format: RGB8\n  width: %d\n  height: %d\n"
           "  frame_rate: 30\n  reconnect_max_s: 1\n  intrinsics: [500, 500, %d, %d]\n",
           w, h, w / 2, h / 2);
  write_config(8, w, h, camera, NULL);
}

static int run_libcamera(int nframes) {
  /* vimc's pipeline handler scales by 3 with 2-pixel alignment: sizes are
   * multiples of 6 (checked below: 640 wide is refused with what it offers). */
  const int w = 480, h = 360;
  names("lcam");
  lcam_config(640, 480);
  camd_pid = spawn_camd("1");
  int rc = wait_exit(camd_pid, 40);
  CHECK(rc == 1, "640x480 (vimc offers 636x480): exit status %d, want 1 (configuration refused)", rc);
  CHECK(file_has(err_path, "camera.width") && file_has(err_path, "636x480"),
        "640x480: the error does not name camera.width and the offered 636x480");
  printf("ok: libcamera refuses 640x480 on vimc, naming camera.width and the offered 636x480\n");
  vlff_shm_unlink(ring_name);
  lcam_config(w, h);
  uint64_t t_start = now_ns();
  char nbuf[16];
  snprintf(nbuf, sizeof nbuf, "%d", nframes);
  camd_pid = spawn_camd(nbuf);
  struct vlff_ring *r = attach(30);
  vlff_ring_seek_oldest(r);
  size_t cap = vlff_ring_slot_size(r);
  uint8_t *buf = malloc(cap);
  CHECK(buf, "out of memory");
  uint64_t last_dev = 0, last_host = 0, last_id = 0, first_dev = 0;
  int n = 0, bars_checked = 0;
  while (n < nframes) {
    struct vlff_ring_view v;
    /* The first frame waits for libcamera, the IPA and vimc to start under TCG. */
    ssize_t len = vlff_ring_read_copy(r, buf, cap, &v, (n ? 10 : 40) * 1000000000ull);
    CHECK(len >= 0, "reading frame %d: %s", n, strerror(errno));
    CHECK(vlff_frame_validate(buf, (size_t)len) == 0, "frame %d does not validate", n);
    const struct vlff_frame_hdr *hd = (const void *)buf;
    const struct vlff_plane *pl = &hd->plane[VLFF_PLANE_COLOR];
    CHECK(pl->width == (uint32_t)w && pl->height == (uint32_t)h, "frame %d is %ux%u, want %dx%d", n, pl->width,
          pl->height, w, h);
    CHECK(pl->format == VLFF_PIX_RGB8 && hd->nplanes == 1, "frame %d format %s, %u planes", n,
          vlff_pixfmt_name(pl->format), hd->nplanes);
    CHECK((hd->flags & VLFF_FRAME_INTRINSICS_VALID) && hd->fx == 500 && hd->cx == w / 2 + 0.5, "frame %d intrinsics", n);
    /* Sensor timestamps: CLOCK_MONOTONIC (V4L2), inside this run, increasing. */
    uint64_t now = now_ns();
    CHECK(hd->t_device_ns > t_start && hd->t_device_ns <= now, "frame %d sensor time %llu outside [%llu, %llu]", n,
          (unsigned long long)hd->t_device_ns, (unsigned long long)t_start, (unsigned long long)now);
    CHECK(hd->t_host_ns >= hd->t_device_ns && hd->t_host_ns <= now, "frame %d host time %llu vs sensor %llu", n,
          (unsigned long long)hd->t_host_ns, (unsigned long long)hd->t_device_ns);
    if (n) {
      CHECK(hd->t_device_ns > last_dev, "frame %d sensor time not increasing", n);
      CHECK(hd->t_host_ns > last_host, "frame %d host time not increasing", n);
      CHECK(hd->frame_id > last_id, "frame %d id %llu after %llu", n, (unsigned long long)hd->frame_id,
            (unsigned long long)last_id);
    } else {
      first_dev = hd->t_device_ns;
    }
    /* Content: every other frame (the pattern is static; TCG is slow). */
    if (n % 2 == 0) {
      check_bars(hd, vlff_frame_plane(buf, VLFF_PLANE_COLOR));
      bars_checked++;
    }
    last_dev = hd->t_device_ns, last_host = hd->t_host_ns, last_id = hd->frame_id;
    n++;
  }
  rc = wait_exit(camd_pid, 20);
  CHECK(rc == 0, "vlff-camd --frames %d exited with %d", nframes, rc);
  CHECK(vlff_ring_head(r) == (uint64_t)nframes, "ring head %llu, want %d", (unsigned long long)vlff_ring_head(r),
        nframes);
  CHECK(vlff_ring_lost(r) == 0, "reader lost %llu frames", (unsigned long long)vlff_ring_lost(r));
  CHECK(stat_of("committed") == (uint64_t)nframes && stat_of("dropped") == 0 && stat_of("lost") == 0 &&
            stat_of("incomplete") == 0,
        "statistics line");
  CHECK(file_has(err_path, "streaming"), "no 'streaming' line from the libcamera backend");
  double span = (double)(last_dev - first_dev) * 1e-9;
  printf("ok: libcamera vimc %dx%d RGB8: %d frames, ids %llu.., sensor timestamps increasing over %.2f s, "
         "colour bars in %d frames, clean exit\n",
         w, h, n, (unsigned long long)last_id - (uint64_t)n + 1, span, bars_checked);
  vlff_ring_close(r);
  vlff_shm_unlink(ring_name);

  /* Second run: the camera was released; SIGTERM mid-stream exits cleanly. */
  camd_pid = spawn_camd(NULL);
  r = attach(30);
  uint64_t t0 = now_ns();
  while (vlff_ring_head(r) < 3 && now_ns() - t0 < 40000000000ull) sleep_ms(50);
  CHECK(vlff_ring_head(r) >= 3, "second run: %llu frames in 40 s (camera not released by the first?)",
        (unsigned long long)vlff_ring_head(r));
  kill(camd_pid, SIGTERM);
  rc = wait_exit(camd_pid, 20);
  CHECK(rc == 0, "second run: exit status %d after SIGTERM", rc);
  uint64_t committed = stat_of("committed");
  CHECK(committed >= 3 && committed == vlff_ring_head(r), "second run: committed=%llu, ring head %llu",
        (unsigned long long)committed, (unsigned long long)vlff_ring_head(r));
  printf("ok: second run reopened the camera, %llu frames, clean exit on SIGTERM\n", (unsigned long long)committed);
  finish(r, buf);
  return 0;
}

/* ---------------------------------------------------------- GPIO trigger */

static void write_pull(const char *path, const char *v) {
  int fd = open(path, O_WRONLY);
  CHECK(fd >= 0, "open %s: %s", path, strerror(errno));
  CHECK(write(fd, v, strlen(v)) == (ssize_t)strlen(v), "write %s: %s", path, strerror(errno));
  close(fd);
}

/* One GPIO-triggered run: line 1 of the gpio-sim chip, pulled down so that
 * the first edge is a rise, the ring vlff-camd writes and a buffer for one
 * of its slots. `what` names a ring entry in messages: frame or record. */
struct edges {
  char pull[512];
  const char *what;
  struct vlff_ring *r;
  uint8_t *buf;
  size_t cap;
  /* 0, or how long before the edge a free-running colour camera's frame
   * may have been taken and still be the record's: one that began just
   * before the edge but was delivered after it is nearer in time to the
   * triggered range frame than the next one, so it is paired and keeps its
   * own time (pair tolerance). */
  uint64_t own_time_before_ns;
};

static void edges_begin(struct edges *e, const char *sim, const char *run, const char *what) {
  snprintf(e->pull, sizeof e->pull, "%s/sim_gpio1/pull", sim);
  write_pull(e->pull, "pull-down");
  names(run);
  e->what = what;
  e->r = NULL, e->buf = NULL, e->cap = 0;
  e->own_time_before_ns = 0;
}

/* Once the cameras stream: nothing in the ring before the first edge. */
static void edges_ready(struct edges *e, const char *why) {
  CHECK(vlff_ring_head(e->r) == 0, "%llu %ss before any edge (%s)", (unsigned long long)vlff_ring_head(e->r), e->what,
        why);
  e->cap = vlff_ring_slot_size(e->r);
  e->buf = malloc(e->cap);
  CHECK(e->buf, "out of memory");
}

/* Edge i rises: its entry must come within timeout_ns, validate, and carry
 * the edge's kernel time, which lies inside our pull write. */
static const struct vlff_frame_hdr *edge_rise(struct edges *e, int i, uint64_t timeout_ns) {
  uint64_t before = now_ns();
  write_pull(e->pull, "pull-up"); /* the kernel stamps the edge inside this write */
  uint64_t after = now_ns();
  struct vlff_ring_view v;
  ssize_t len = vlff_ring_read_copy(e->r, e->buf, e->cap, &v, timeout_ns);
  CHECK(len >= 0, "edge %d: no %s within %llu s: %s", i, e->what, (unsigned long long)(timeout_ns / 1000000000ull),
        strerror(errno));
  CHECK(vlff_frame_validate(e->buf, (size_t)len) == 0, "edge %d: %s does not validate", i, e->what);
  const struct vlff_frame_hdr *hd = (const void *)e->buf;
  int own_time = e->own_time_before_ns && hd->t_host_ns == hd->t_device_ns && hd->t_host_ns < before &&
                 before - hd->t_host_ns <= e->own_time_before_ns;
  CHECK(own_time || (hd->t_host_ns >= before && hd->t_host_ns <= after),
        "edge %d: %s host time %lld us from the pull write [0, %lld us] (not the edge's timestamp)", i, e->what,
        (long long)(hd->t_host_ns - before) / 1000, (long long)(after - before) / 1000);
  return hd;
}

/* Edge i falls after settle_ms; another settle_ms later the ring holds
 * exactly i entries: one per rise, none for a fall (settle_ms spans
 * several of the fake camera's trigger ticks). */
static void edge_fall(struct edges *e, int i, int settle_ms) {
  sleep_ms(settle_ms);
  write_pull(e->pull, "pull-down");
  sleep_ms(settle_ms);
  CHECK(vlff_ring_head(e->r) == (uint64_t)i, "after %d edges the ring holds %llu %ss", i,
        (unsigned long long)vlff_ring_head(e->r), e->what);
}

/* SIGTERM ends vlff-camd cleanly; its statistics line is then in out_path. */
static void stop_camd(void) {
  kill(camd_pid, SIGTERM);
  int rc = wait_exit(camd_pid, 20);
  CHECK(rc == 0, "vlff-camd exit status %d after SIGTERM", rc);
}

/* An OpenCV stereo calibration file with no distortion and an identity
 * pose between the cameras: only the intrinsics K1 (range) and K2 (colour),
 * given as their nine values, and any extra lines differ. */
static void write_rig(const char *path, const char *k1, const char *k2, const char *extra) {
  char text[2048];
  snprintf(text, sizeof text,
           "%%YAML:1.0\n---\n"
           "K1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ %s ]\n"
           "D1: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
           "K2: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ %s ]\n"
           "D2: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
           "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]\n"
           "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ 0., 0., 0. ]\n%s",
           k1, k2, extra);
  write_file(path, text);
}

static int run_gpio_trigger(const char *chip, const char *sim) {
  const int edges = 6;
  struct edges e;
  edges_begin(&e, sim, "gtrig", "frame");
  write_config(16, 160, 120,
               "camera:\n  kind: aravis\n  device: 127.0.0.1\n  pixel_format: Mono8\n  width: 160\n  height: 120\n"
               "  frame_rate: 25\n  trigger: software\n  reconnect_max_s: 0.5\n",
               chip);
  camd_pid = spawn_camd(NULL);
  e.r = attach(30);
  /* Edges before the camera streams are void by design: wait until it does. */
  uint64_t t0 = now_ns();
  while (!file_has(err_path, "streaming") && now_ns() - t0 < 30000000000ull) sleep_ms(50);
  CHECK(file_has(err_path, "streaming"), "camera not streaming after 30 s");
  sleep_ms(500);
  edges_ready(&e, "software trigger mode");
  uint64_t last_host = 0;
  for (int i = 1; i <= edges; i++) {
    const struct vlff_frame_hdr *hd = edge_rise(&e, i, 5000000000ull);
    CHECK(hd->plane[0].width == 160 && hd->plane[0].height == 120 && hd->plane[0].format == VLFF_PIX_RGB8,
          "edge %d: frame %ux%u %s", i, hd->plane[0].width, hd->plane[0].height, vlff_pixfmt_name(hd->plane[0].format));
    CHECK(hd->t_host_ns > last_host, "edge %d: frame times out of order", i);
    last_host = hd->t_host_ns;
    /* Exactly one frame per edge, and the falling edge triggers nothing:
     * wait over several of the fake camera's 40 ms trigger ticks. */
    edge_fall(&e, i, 250);
  }
  stop_camd();
  CHECK(stat_of("edges") == (uint64_t)edges && stat_of("triggers") == (uint64_t)edges &&
            stat_of("committed") == (uint64_t)edges && stat_of("trigger_stamped") == (uint64_t)edges &&
            stat_of("trigger_failures") == 0,
        "statistics line");
  printf("ok: gpio-sim edges -> vlff-camd software triggers: %d edges, %d frames, each stamped with its edge's "
         "kernel time\n",
         edges, edges);
  finish(e.r, e.buf);
  return 0;
}

/* The GPIO-triggered RGB-D pair: two fake GigE cameras (colour on
 * 127.0.0.1, Mono16 range on 127.0.0.2, started by the case), both in
 * software trigger mode and fired by the same gpio-sim edge. Each edge must
 * give exactly one record holding both, stamped with the edge's kernel time
 * (the stamp both frames carry pairs them), and nothing unmatched. */
static int run_gpio_pair(const char *chip, const char *sim) {
  const int edges = 6;
  struct edges e;
  edges_begin(&e, sim, "gpair", "record");
  char rig[160], cameras[1024];
  snprintf(rig, sizeof rig, "/tmp/vlff-vm-gpair-%d-rig.yaml", (int)getpid());
  write_rig(rig, "150., 0., 79.5, 0., 150., 59.5, 0., 0., 1.", "150., 0., 79.5, 0., 150., 59.5, 0., 0., 1.", "");
  snprintf(cameras, sizeof cameras,
           "camera:\n  kind: aravis\n  device: 127.0.0.1\n  pixel_format: Mono8\n  width: 160\n  height: 120\n"
           "  frame_rate: 25\n  trigger: software\n  reconnect_max_s: 0.5\n  depth: stream\n  intrinsics: [0, 0, 0, 0]\n"
           "depth_camera:\n  kind: aravis\n  device: 127.0.0.2\n  pixel_format: Mono16\n  width: 160\n  height: 120\n"
           "  frame_rate: 25\n  trigger: software\n  scale_m: 0.001\n  calibration: %s\n  pair_tolerance_s: 0.015\n",
           rig);
  write_config(16, 160, 120, cameras, chip);
  camd_pid = spawn_camd(NULL);
  e.r = attach(30);
  uint64_t t0 = now_ns();
  while (!(file_has(err_path, "'127.0.0.1'") && file_has(err_path, "'127.0.0.2'") && file_has(err_path, "streaming")) &&
         now_ns() - t0 < 30000000000ull)
    sleep_ms(50);
  sleep_ms(1000); /* both cameras streaming (the second may log after the first) */
  edges_ready(&e, "software trigger mode");
  for (int i = 1; i <= edges; i++) {
    const struct vlff_frame_hdr *hd = edge_rise(&e, i, 5000000000ull);
    CHECK(hd->nplanes == 2 && hd->plane[VLFF_PLANE_COLOR].format == VLFF_PIX_RGB8 &&
              hd->plane[VLFF_PLANE_DEPTH].format == VLFF_PIX_DEPTH_U16_MM && hd->plane[VLFF_PLANE_DEPTH].width == 160,
          "edge %d: record of %u planes, not colour + registered range", i, hd->nplanes);
    /* The range plane is the fake range camera's image through the
     * identity rig: mostly non-zero (its ramp wraps through 0 rarely). */
    const uint16_t *dp = vlff_frame_plane(e.buf, VLFF_PLANE_DEPTH);
    int nz = 0;
    for (int k = 0; k < 160; k++) nz += dp[60 * (hd->plane[VLFF_PLANE_DEPTH].stride / 2) + k] != 0;
    CHECK(nz > 100, "edge %d: range plane row 60 has %d of 160 valid pixels", i, nz);
    edge_fall(&e, i, 250);
  }
  stop_camd();
  CHECK(stat_of("edges") == (uint64_t)edges && stat_of("triggers") == 2u * edges &&
            stat_of("committed") == (uint64_t)edges && stat_of("color_frames") == (uint64_t)edges &&
            stat_of("depth_frames") == (uint64_t)edges && stat_of("unmatched_color") == 0 &&
            stat_of("unmatched_depth") == 0 && stat_of("trigger_failures") == 0,
        "statistics line");
  printf("ok: gpio-sim edges -> both cameras of an RGB-D pair: %d edges, %d paired records, each stamped with its "
         "edge's kernel time\n",
         edges, edges);
  finish(e.r, e.buf);
  unlink(rig);
  return 0;
}

/* A libcamera colour camera and an Aravis range camera in one record: the
 * vimc virtual camera free-runs (libcamera cameras cannot be triggered),
 * the fake GigE camera on 127.0.0.1 streams Mono16 in software trigger
 * mode. Each gpio-sim edge (gpio.mode input) fires the range camera and
 * stamps the first vimc frame after it, as a colour camera's strobe output
 * wired to the GPIO line would on a rig: both frames carry the edge's
 * kernel time and pair on it. The record is registered at 240x180
 * (depth_camera.register_*): colour 480x360 averaged 2x2, range 160x120
 * registered 1.5x up through an identity rig (K1 = K2 / 3, its principal
 * point a tenth of a range pixel off, so that no output pixel centre falls
 * exactly on a boundary between two range pixels' footprints, where either
 * would be right). Each edge must
 * give one record, stamped with the edge's time (or, when vimc's frame began
 * within the pair tolerance before the edge and came after it, with that
 * frame's own time: the nearer partner), holding vimc's colour bars
 * and the range image; no range frame may go unmatched. vimc's frames
 * between edges find no partner and are counted. */
static int run_lcam_pair(const char *chip, const char *sim) {
  const int edges = 5;
  struct edges e;
  edges_begin(&e, sim, "lpair", "record");
  e.own_time_before_ns = 4000000; /* depth_camera.pair_tolerance_s below */
  char rig[160], cameras[1024];
  snprintf(rig, sizeof rig, "/tmp/vlff-vm-lpair-%d-rig.yaml", (int)getpid());
  write_rig(rig, "150., 0., 79.6, 0., 150., 59.4, 0., 0., 1.", "450., 0., 239.5, 0., 450., 179.5, 0., 0., 1.",
            "depth_width: 160\ndepth_height: 120\ncolor_width: 480\ncolor_height: 360\n");
  /* The range camera ticks at 100 Hz so that a triggered frame follows its
   * edge within a few vimc frames (the pairing holds eight of each). */
  snprintf(cameras, sizeof cameras,
           "camera:\n  kind: libcamera\n  device: \"0\"\n  pixel_format: RGB8\n  width: 480\n  height: 360\n"
           "  frame_rate: 30\n  reconnect_max_s: 1\n  depth: stream\n  intrinsics: [0, 0, 0, 0]\n"
           "depth_camera:\n  kind: aravis\n  device: 127.0.0.1\n  pixel_format: Mono16\n  width: 160\n  height: 120\n"
           "  frame_rate: 100\n  trigger: software\n  scale_m: 0.001\n  calibration: %s\n  pair_tolerance_s: 0.004\n"
           "  register_width: 240\n  register_height: 180\n",
           rig);
  write_config(16, 240, 180, cameras, chip);
  camd_pid = spawn_camd(NULL);
  e.r = attach(30);
  /* libcamera, the IPA and vimc start slowly under TCG */
  uint64_t t0 = now_ns();
  while (!(file_has(err_path, "libcamera: '") && file_has(err_path, "'127.0.0.1' (")) && now_ns() - t0 < 60000000000ull)
    sleep_ms(50);
  CHECK(file_has(err_path, "libcamera: '") && file_has(err_path, "'127.0.0.1' ("),
        "the two cameras are not both streaming after 60 s");
  sleep_ms(1000);
  edges_ready(&e, "the range camera waits for triggers");
  for (int i = 1; i <= edges; i++) {
    const struct vlff_frame_hdr *hd = edge_rise(&e, i, 10000000000ull);
    const struct vlff_plane *cp = &hd->plane[VLFF_PLANE_COLOR], *dpl = &hd->plane[VLFF_PLANE_DEPTH];
    CHECK(hd->nplanes == 2 && cp->format == VLFF_PIX_RGB8 && dpl->format == VLFF_PIX_DEPTH_U16_MM,
          "edge %d: record of %u planes, not colour + registered range", i, hd->nplanes);
    CHECK(cp->width == 240 && cp->height == 180 && dpl->width == 240 && dpl->height == 180,
          "edge %d: planes %ux%u and %ux%u, want both 240x180", i, cp->width, cp->height, dpl->width, dpl->height);
    /* K2 halved, in the record's pixel-centre convention */
    CHECK(hd->fx == 225 && hd->fy == 225 && hd->cx == 120 && hd->cy == 90, "edge %d: intrinsics %g %g %g %g", i,
          hd->fx, hd->fy, hd->cx, hd->cy);
    /* the colour frame is vimc's, stamped by the edge and taken after it, or
     * (edge_rise) taken within the pair tolerance before it and unstamped */
    CHECK(hd->t_device_ns >= hd->t_host_ns, "edge %d: vimc frame taken %lld us before its edge", i,
          (long long)(hd->t_host_ns - hd->t_device_ns) / 1000);
    check_bars(hd, vlff_frame_plane(e.buf, VLFF_PLANE_COLOR));
    /* The range image through the identity rig, 1.5x up: mostly valid, and
     * still the fake camera's ramp (+256 mm per range pixel in x and in y,
     * wrapping): each output pixel holds its nearest range pixel's value, so
     * neighbours differ by 0 or 256, and by 256 about every 1.5 pixels. */
    const uint8_t *dp = vlff_frame_plane(e.buf, VLFF_PLANE_DEPTH);
#define DV(x, y) (((const uint16_t *)(dp + (size_t)(y) * dpl->stride))[x])
    long nz = 0, steps = 0, rises = 0, bad = 0;
    char first_bad[96] = "";
    for (int y = 0; y < 180; y++)
      for (int x = 0; x < 240; x++) {
        nz += DV(x, y) != 0;
        for (int k = 0; k < 2; k++) {
          int nx = x + !k, ny = y + k;
          if (nx >= 240 || ny >= 180) continue;
          unsigned a = DV(x, y), b = DV(nx, ny);
          if (!a || !b || b < a) continue; /* invalid, or the ramp wrapped */
          steps++, rises += b == a + 256;
          if (b != a && b != a + 256 && !bad++)
            snprintf(first_bad, sizeof first_bad, "(%d,%d) %u -> (%d,%d) %u", x, y, a, nx, ny, b);
        }
      }
#undef DV
    CHECK(nz > 240 * 180 * 9 / 10, "edge %d: %ld of %d range pixels valid", i, nz, 240 * 180);
    CHECK(bad == 0 && rises > steps / 2 && rises < steps * 3 / 4,
          "edge %d: range neighbours: %ld of %ld steps neither 0 nor 256 mm (first %s), %ld rises (want about 2/3)", i,
          bad, steps, first_bad, rises);
    edge_fall(&e, i, 300);
  }
  stop_camd();
  /* vimc's frames before the first edge are start-up frames (the range
   * camera had sent none), those between edges unmatched */
  uint64_t colour = stat_of("color_frames"), unmatched = stat_of("unmatched_color"),
           startup = stat_of("startup_color");
  CHECK(stat_of("edges") == (uint64_t)edges && stat_of("triggers") == (uint64_t)edges &&
            stat_of("committed") == (uint64_t)edges && stat_of("depth_frames") == (uint64_t)edges &&
            stat_of("unmatched_depth") == 0 && stat_of("startup_depth") == 0 && stat_of("trigger_failures") == 0 &&
            colour > (uint64_t)edges && startup > 0 && unmatched > 0 && unmatched + startup <= colour - edges,
        "statistics line");
  printf("ok: vimc (libcamera) colour + fake GigE range camera, one GPIO edge each: %d edges, %d records at "
         "240x180 stamped with the edge's kernel time; %llu vimc frames, %llu before the first edge, %llu between "
         "edges without a partner\n",
         edges, edges, (unsigned long long)colour, (unsigned long long)startup, (unsigned long long)unmatched);
  finish(e.r, e.buf);
  unlink(rig);
  return 0;
}

int main(int argc, char **argv) {
  if (argc == 3 && !strcmp(argv[1], "libcamera")) return run_libcamera(atoi(argv[2]) > 0 ? atoi(argv[2]) : 10);
  if (argc == 4 && !strcmp(argv[1], "gpio-trigger")) return run_gpio_trigger(argv[2], argv[3]);
  if (argc == 4 && !strcmp(argv[1], "gpio-pair")) return run_gpio_pair(argv[2], argv[3]);
  if (argc == 4 && !strcmp(argv[1], "lcam-pair")) return run_lcam_pair(argv[2], argv[3]);
  fprintf(stderr,
          "usage: vlff-camd-vmtest libcamera N | gpio-trigger CHIP SIMDIR | gpio-pair CHIP SIMDIR | "
          "lcam-pair CHIP SIMDIR\n");
  return 2;
}
