/*
 * vlff-scenecam: test infrastructure for the end-to-end rig test and bench.
 *
 * Serves the simulator's room as a real RGB-D rig would show it, through the
 * real stacks: two Aravis fake GigE Vision cameras on loopback (colour RGB8
 * on one address, 16-bit range in millimetres on the other) whose images
 * are the sim frame of the current tick, TUM trajectory lines of that frame
 * sent over UDP (for vlff-pose), and, for every frame record vlff-camd
 * writes into the frame ring, the sim's features of the frame it shows,
 * published into the feature ring under that record's frame id (what an
 * external feature extractor does).
 *
 * Which sim frame is shown: Aravis' fake camera exposes a frame at every
 * multiple of its frame period on the wall clock, so both cameras, set to
 * the same rate, fill at the same ticks; each fill renders sim frame
 * (tick - first tick) mod sim.frames, and its buffer carries the tick's
 * instant as the camera's timestamp. (The fake camera stamps the moment its
 * thread starts the fill, which on a busy host lags the tick by up to a
 * period while the image is the tick's; a real camera's clock stamps the
 * exposure, on its frame grid, however late the frame then arrives.) The
 * trajectory is held during a tick and sent as a tracker at POSE_HZ sends
 * it: each pose at its own stamp, on a grid of 1 / POSE_HZ on the wall
 * clock, holding the pose of the tick the stamp falls in, so a frame
 * stamped inside its tick (vlff-camd stamps arrival) finds the pose its
 * image was rendered from between two poses one pose period apart, and no
 * pose is ever ahead of the clock. The feature publisher maps a record to
 * its tick by the record's host stamp: the newest colour fill at or before
 * it.
 *
 * SIGUSR1 stops the range camera (its GigE Vision device goes away, as a
 * camera unplugged or powered off) and says on stderr, as
 * 'range camera stopped, last fill at T' (CLOCK_MONOTONIC seconds), when it
 * began its last frame.
 *
 * A fill that begins more than a period late (a busy host) leaves its
 * camera without a frame of a tick: the summary counts each camera's
 * skipped ticks and the range frames whose tick the colour camera skipped,
 * which no pairing can give a partner.
 *
 * Contract: runs until SIGINT/SIGTERM or --seconds; prints one summary line
 * on stderr at the end; exit 0, 1 on a setup error (a camera that cannot be
 * created, a config or socket error), 2 on a usage error.
 */
#include <arpa/inet.h>
#include <arv.h>
#include <errno.h>
#include <math.h>
#include <netinet/in.h>
#include <pthread.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "cli.h"
#include "config.h"
#include "sim.h"
#include "transpose.h"
#include "vlff/shm.h"

static const struct vlff_cli cli = {
    "vlff-scenecam",
    "Usage: vlff-scenecam --config FILE [OPTIONS]\n"
    "Serves the config's simulated room (sim.*) through two Aravis fake GigE\n"
    "cameras, TUM pose lines over UDP and the feature ring (test infrastructure).\n"
    "  -c, --config FILE     the config: sim.*, shm.ring, shm.feature_ring\n"
    "      --color ADDR      address of the colour camera (RGB8; 127.0.0.1)\n"
    "      --depth ADDR      address of the range camera (Mono16 mm; 127.0.0.2)\n"
    "      --poses ADDR:PORT send each tick's pose as TUM lines (realtime stamps)\n"
    "      --no-features     do not publish features\n"
    "      --seconds S       stop after S seconds (default: at SIGINT/SIGTERM)\n"
    "  -h, --help            this text\n"
    "  -V, --version         the version\n"};

static volatile sig_atomic_t stop, stop_depth;
static void on_signal(int sig) { (void)sig, stop = 1; }
static void on_usr1(int sig) { (void)sig, stop_depth = 1; }

#define POSE_HZ 30 /* the pose stream's rate: a common visual-inertial tracker's */

#define TICKS 256 /* colour fills remembered for the feature publisher */

struct scene {
  const struct vlff_config *cfg;
  struct vlff_sim *sim;
  uint64_t period_us;
  atomic_llong first_tick; /* -1 until the first fill or pose */
  int udp;
  struct sockaddr_in to;
  atomic_bool poses_done;  /* the pose thread's stop */
  pthread_mutex_t lock;
  uint64_t fill_mono[TICKS]; /* monotonic ns of colour fill i % TICKS */
  long long fill_idx[TICKS]; /* its sim frame */
  long long nfills;
  atomic_llong color_fills, depth_fills, bad_buffers, poses_sent;
  atomic_ullong last_depth_fill_ns; /* monotonic, when the range camera's latest fill began */
  ArvGvFakeCamera *gd;              /* the range camera, until SIGUSR1 */
};

struct cam {
  struct scene *sc;
  int depth;
  struct vlff_sim_frame *f;
  ArvFakeCamera *fake;
};

/* Which ticks (from the first) each camera, colour 0 and range 1, sent a
 * frame of: a fill that begins more than a period late leaves a tick
 * without a frame of that camera, and the other camera's frame of it
 * without a partner. Written by the fill threads, read at the end. */
#define SENT_TICKS 65536 /* 3.6 h at 5 Hz */
static atomic_uchar sent[2][SENT_TICKS];

static uint64_t mono_ns(void) { return vlff_shm_now_ns(); }

/* The sim frame of a tick (a multiple of the period on the wall clock):
 * the first tick asked for, by a fill or a pose, shows frame 0. */
static long long frame_of_tick(struct scene *sc, long long tick) {
  long long expected = -1;
  atomic_compare_exchange_strong(&sc->first_tick, &expected, tick);
  long long idx = (tick - atomic_load(&sc->first_tick)) % sc->cfg->sim.frames;
  return idx < 0 ? idx + sc->cfg->sim.frames : idx;
}

/* The sim frame of the tick now in progress on the fake cameras' clock. */
static long long tick_of_now(struct scene *sc, long long *tick) {
  *tick = (long long)((uint64_t)g_get_real_time() / sc->period_us);
  return frame_of_tick(sc, *tick);
}

/* Wall-clock ns of pose n of the POSE_HZ grid (n / POSE_HZ s; split so that
 * n * 1e9 does not overflow). */
static uint64_t pose_stamp_ns(uint64_t n) {
  return n / POSE_HZ * 1000000000ull + n % POSE_HZ * 1000000000ull / POSE_HZ;
}

/* The pose stream: each pose sent at its own stamp (never ahead of the
 * clock), late ones at once in order, as a tracker that fell behind sends
 * them; each holds the pose of the tick its stamp falls in. */
static void *send_poses(void *arg) {
  struct scene *sc = arg;
  struct timespec now;
  clock_gettime(CLOCK_REALTIME, &now);
  uint64_t n = (uint64_t)now.tv_sec * POSE_HZ + (uint64_t)now.tv_nsec * POSE_HZ / 1000000000ull + 1;
  while (!atomic_load(&sc->poses_done)) {
    const uint64_t t = pose_stamp_ns(n);
    const struct timespec at = {(time_t)(t / 1000000000ull), (long)(t % 1000000000ull)};
    if (clock_nanosleep(CLOCK_REALTIME, TIMER_ABSTIME, &at, NULL)) continue; /* a signal: sleep on */
    double c2w[16], wxyz[4];
    vlff_sim_pose(sc->sim, frame_of_tick(sc, (long long)(t / (sc->period_us * 1000))), c2w);
    vlff_pose_quaternion(c2w, wxyz);
    char msg[256];
    /* TUM order: t x y z qx qy qz qw */
    int len = snprintf(msg, sizeof msg, "%llu.%09llu %.9f %.9f %.9f %.9f %.9f %.9f %.9f\n",
                       (unsigned long long)(t / 1000000000ull), (unsigned long long)(t % 1000000000ull), c2w[3],
                       c2w[7], c2w[11], wxyz[1], wxyz[2], wxyz[3], wxyz[0]);
    if (sendto(sc->udp, msg, (size_t)len, 0, (struct sockaddr *)&sc->to, sizeof sc->to) == len)
      atomic_fetch_add(&sc->poses_sent, 1);
    n++;
  }
  return NULL;
}

static void fill(ArvBuffer *buffer, void *data, guint32 exposure_us, guint32 gain, ArvPixelFormat fmt) {
  (void)exposure_us, (void)gain;
  struct cam *c = data;
  struct scene *sc = c->sc;
  /* The buffer is being filled: its received size is not set yet, its
   * allocation is the camera's payload for the current registers. */
  uint8_t *px = (uint8_t *)arv_buffer_get_data(buffer, NULL);
  size_t size = c->fake ? arv_fake_camera_get_payload(c->fake) : 0;
  const int W = c->f->width, H = c->f->height;
  const ArvPixelFormat want = c->depth ? ARV_PIXEL_FORMAT_MONO_16 : ARV_PIXEL_FORMAT_RGB_8_PACKED;
  const size_t need = (size_t)W * H * (c->depth ? 2 : 3);
  if (!px || fmt != want || size != need) {
    /* A camera set to another format or size: left as the fake made it. */
    if (atomic_fetch_add(&sc->bad_buffers, 1) == 0)
      fprintf(stderr, "vlff-scenecam: %s camera: %zu bytes of format 0x%08x, expected %zu of 0x%08x (%dx%d)\n",
              c->depth ? "range" : "colour", size, (unsigned)fmt, need, (unsigned)want, W, H);
    return;
  }
  if (c->depth) atomic_store(&sc->last_depth_fill_ns, mono_ns());
  long long tick, idx = tick_of_now(sc, &tick);
  /* the camera's clock: the instant of the tick whose image this is (the
   * fake camera's own stamp is when this fill began) */
  arv_buffer_set_timestamp(buffer, (guint64)tick * sc->period_us * 1000u);
  const long long k = tick - atomic_load(&sc->first_tick);
  if (k >= 0 && k < SENT_TICKS) atomic_store(&sent[c->depth][k], 1);
  char err[256];
  if (vlff_sim_render(sc->sim, idx, VLFF_SIM_RGBD, c->f, err, sizeof err)) {
    fprintf(stderr, "vlff-scenecam: frame %lld: %s\n", idx, err);
    atomic_fetch_add(&sc->bad_buffers, 1);
    return;
  }
  if (c->depth) {
    memcpy(px, c->f->depth_mm, need);
    atomic_fetch_add(&sc->depth_fills, 1);
    return;
  }
  memcpy(px, c->f->rgb, need);
  pthread_mutex_lock(&sc->lock);
  sc->fill_mono[sc->nfills % TICKS] = mono_ns();
  sc->fill_idx[sc->nfills % TICKS] = idx;
  sc->nfills++;
  pthread_mutex_unlock(&sc->lock);
  atomic_fetch_add(&sc->color_fills, 1);
}

/* The sim frame the colour camera showed for a record stamped t (its
 * arrival): the newest fill at or before t; -1 when none is remembered. */
static long long frame_at(struct scene *sc, uint64_t t) {
  long long idx = -1;
  pthread_mutex_lock(&sc->lock);
  for (long long i = sc->nfills - 1; i >= 0 && i >= sc->nfills - TICKS; i--)
    if (sc->fill_mono[i % TICKS] <= t) {
      idx = sc->fill_idx[i % TICKS];
      break;
    }
  pthread_mutex_unlock(&sc->lock);
  return idx;
}

static ArvGvFakeCamera *camera_new(const char *addr, const char *serial, struct cam *c) {
  ArvGvFakeCamera *g = arv_gv_fake_camera_new(addr, serial);
  if (!g) return NULL;
  for (int i = 0; i < 100 && !arv_gv_fake_camera_is_running(g); i++) g_usleep(10000);
  if (!arv_gv_fake_camera_is_running(g)) {
    g_object_unref(g);
    return NULL;
  }
  c->fake = arv_gv_fake_camera_get_fake_camera(g);
  arv_fake_camera_set_fill_pattern(c->fake, fill, c);
  return g;
}

/* SIGUSR1: the range camera goes away. */
static void maybe_stop_depth(struct scene *sc) {
  if (!stop_depth || !sc->gd) return;
  /* Its acquisition off first: the fake camera's thread, cancelled, sends
   * one more frame at once, off its period's grid (a second frame of the
   * tick it last sent), which a camera unplugged does not. */
  arv_fake_camera_write_register(arv_gv_fake_camera_get_fake_camera(sc->gd), ARV_FAKE_CAMERA_REGISTER_ACQUISITION,
                                 0);
  g_object_unref(sc->gd);
  sc->gd = NULL;
  fprintf(stderr, "vlff-scenecam: range camera stopped, last fill at %.6f\n",
          (double)atomic_load(&sc->last_depth_fill_ns) * 1e-9);
}

/* The ticks each camera skipped between its first and last frame, and the
 * range frames of ticks the colour camera skipped while streaming (no
 * colour frame was ever sent for them to pair with). */
static void count_skipped(long long skipped[2], long long *orphans) {
  long long first[2] = {-1, -1}, last[2] = {-1, -1};
  for (int c = 0; c < 2; c++)
    for (long long k = 0; k < SENT_TICKS; k++)
      if (atomic_load(&sent[c][k])) {
        if (first[c] < 0) first[c] = k;
        last[c] = k;
      }
  *orphans = 0;
  for (int c = 0; c < 2; c++) {
    skipped[c] = 0;
    for (long long k = first[c] + 1; first[c] >= 0 && k < last[c]; k++) {
      const bool none = !atomic_load(&sent[c][k]);
      skipped[c] += none;
      if (c == 0 && none && atomic_load(&sent[1][k])) (*orphans)++;
    }
  }
}

/* Features for every record of the frame ring, until stopped. */
static int publish_features(struct scene *sc, long long *published, long long *unknown) {
  const struct vlff_config *cfg = sc->cfg;
  int W, H, fw, fh, D;
  vlff_sim_size(sc->sim, &W, &H, &fw, &fh, &D);
  struct vlff_ring_params fp = {VLFF_RECORD_FEATURE, (uint32_t)cfg->shm.ring_slots,
                                vlff_feature_slot_size((uint32_t)D, (uint32_t)fh, (uint32_t)fw),
                                {(mode_t)cfg->shm.mode, cfg->shm.group}};
  struct vlff_ring *fring = vlff_ring_create(cfg->shm.feature_ring, &fp);
  if (!fring) {
    fprintf(stderr, "vlff-scenecam: feature ring %s: %s\n", cfg->shm.feature_ring, vlff_shm_last_message());
    return 1;
  }
  struct vlff_sim_frame *f = vlff_sim_frame_new(sc->sim);
  struct vlff_ring *ring = NULL;
  void *buf = NULL;
  size_t cap = 0;
  int status = 0;
  while (!stop && f) {
    maybe_stop_depth(sc);
    if (!ring) {
      ring = vlff_ring_attach(cfg->shm.ring, VLFF_RECORD_FRAME);
      if (!ring) {
        g_usleep(20000);
        continue;
      }
      cap = vlff_ring_slot_size(ring);
      buf = malloc(cap);
      if (!buf) break;
    }
    struct vlff_ring_view v;
    ssize_t len = vlff_ring_read_copy(ring, buf, cap, &v, 200ull * 1000 * 1000);
    if (len < 0) continue; /* timeout, or overrun (the cursor moved on) */
    if (vlff_frame_validate(buf, (size_t)len)) continue;
    const struct vlff_frame_hdr *h = buf;
    long long idx = frame_at(sc, h->t_host_ns);
    if (idx < 0) {
      (*unknown)++;
      continue;
    }
    char err[256];
    if (vlff_sim_render(sc->sim, idx, VLFF_SIM_FEATURES, f, err, sizeof err)) {
      fprintf(stderr, "vlff-scenecam: features of frame %lld: %s\n", idx, err);
      status = 1;
      break;
    }
    struct vlff_feature_hdr *fhd = vlff_ring_reserve(fring, NULL);
    uint64_t flen = vlff_feature_layout(fhd, vlff_ring_slot_size(fring), (uint32_t)D, (uint32_t)fh, (uint32_t)fw);
    if (!flen) {
      fprintf(stderr, "vlff-scenecam: features do not fit the ring slot\n");
      status = 1;
      break;
    }
    fhd->frame_id = h->frame_id, fhd->t_host_ns = h->t_host_ns, fhd->sensor_id = h->sensor_id;
    vlff_transpose_u16(f->features, (size_t)fw * fh, (size_t)D, (uint16_t *)((uint8_t *)fhd + fhd->data_offset));
    if (vlff_ring_commit(fring, flen) < 0) {
      fprintf(stderr, "vlff-scenecam: feature commit: %s\n", strerror(errno));
      status = 1;
      break;
    }
    (*published)++;
  }
  free(buf);
  vlff_sim_frame_free(f);
  vlff_ring_close(ring);
  vlff_ring_close(fring);
  return status;
}

static int parse_addr(const char *s, struct sockaddr_in *a) {
  char host[64];
  const char *colon = strrchr(s, ':');
  if (!colon || colon == s || (size_t)(colon - s) >= sizeof host) return -1;
  memcpy(host, s, (size_t)(colon - s));
  host[colon - s] = 0;
  char *end;
  long port = strtol(colon + 1, &end, 10);
  if (*end || port < 1 || port > 65535) return -1;
  memset(a, 0, sizeof *a);
  a->sin_family = AF_INET;
  a->sin_port = htons((uint16_t)port);
  return inet_pton(AF_INET, host, &a->sin_addr) == 1 ? 0 : -1;
}

int main(int argc, char **argv) {
  const char *config = NULL, *color = "127.0.0.1", *depth = "127.0.0.2", *poses = NULL;
  double seconds = 0;
  int features = 1;
  enum { O_COLOR = 256, O_DEPTH, O_POSES, O_NOFEAT, O_SECONDS };
  static const struct option longopts[] = {
      {"config", required_argument, NULL, 'c'},  {"color", required_argument, NULL, O_COLOR},
      {"depth", required_argument, NULL, O_DEPTH}, {"poses", required_argument, NULL, O_POSES},
      {"no-features", no_argument, NULL, O_NOFEAT}, {"seconds", required_argument, NULL, O_SECONDS},
      VLFF_CLI_COMMON_OPTIONS,
  };
  int c, status;
  char *end;
  while ((c = vlff_cli_next(&cli, argc, argv, "c:", longopts, &status)) != -1) {
    switch (c) {
    case VLFF_CLI_EXIT: return status;
    case 'c': config = optarg; break;
    case O_COLOR: color = optarg; break;
    case O_DEPTH: depth = optarg; break;
    case O_POSES: poses = optarg; break;
    case O_NOFEAT: features = 0; break;
    case O_SECONDS:
      seconds = strtod(optarg, &end);
      if (*end || !(seconds > 0 && seconds < 1e6))
        return vlff_cli_usage_error(&cli, "--seconds: expected a number in (0, 1e6), got '%s'", optarg);
      break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", argv[optind - 1]);
    }
  }
  if (optind < argc) return vlff_cli_usage_error(&cli, "unexpected argument '%s'", argv[optind]);
  if (!config) return vlff_cli_usage_error(&cli, "no --config given");
  struct vlff_config cfg;
  char err[1024];
  if (vlff_config_load(config, &cfg, err, sizeof err) < 0) {
    fprintf(stderr, "%s\n", err);
    return 1;
  }
  struct scene sc = {.cfg = &cfg, .udp = -1, .lock = PTHREAD_MUTEX_INITIALIZER};
  atomic_init(&sc.first_tick, -1);
  atomic_init(&sc.poses_done, false);
  sc.period_us = (uint64_t)llround(1e6 / cfg.sim.rate_hz);
  if (poses) {
    if (parse_addr(poses, &sc.to)) return vlff_cli_usage_error(&cli, "--poses: expected IPv4:PORT, got '%s'", poses);
    sc.udp = socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    if (sc.udp < 0) return vlff_cli_error(&cli, "socket: %s", strerror(errno));
  }
  sc.sim = vlff_sim_create(&cfg.sim, &cfg.field, err, sizeof err);
  if (!sc.sim) return vlff_cli_error(&cli, "%s", err);
  struct cam cc = {&sc, 0, vlff_sim_frame_new(sc.sim), NULL}, cd = {&sc, 1, vlff_sim_frame_new(sc.sim), NULL};
  ArvGvFakeCamera *gc = cc.f && cd.f ? camera_new(color, "SCENE-RGB", &cc) : NULL;
  ArvGvFakeCamera *gd = gc ? camera_new(depth, "SCENE-DEPTH", &cd) : NULL;
  int rc = 0;
  if (!gc || !gd) {
    rc = vlff_cli_error(&cli, "cannot start the fake GigE camera on %s", gc ? depth : color);
  } else {
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    if (seconds > 0) alarm((unsigned)ceil(seconds)), sigaction(SIGALRM, &sa, NULL);
    sc.gd = gd;
    sa.sa_handler = on_usr1;
    sigaction(SIGUSR1, &sa, NULL);
    /* the pose thread takes no signal: this one sees them all */
    pthread_t poser;
    sigset_t all, old;
    sigfillset(&all);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    bool posing = sc.udp >= 0 && pthread_create(&poser, NULL, send_poses, &sc) == 0;
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (sc.udp >= 0 && !posing) rc = vlff_cli_error(&cli, "cannot start the pose thread");
    long long published = 0, unknown = 0;
    if (rc == 0 && features)
      rc = publish_features(&sc, &published, &unknown);
    else
      while (rc == 0 && !stop) maybe_stop_depth(&sc), g_usleep(50000);
    atomic_store(&sc.poses_done, true);
    if (posing) pthread_join(poser, NULL);
    long long skipped[2], orphans;
    count_skipped(skipped, &orphans);
    fprintf(stderr,
            "vlff-scenecam: %lld colour fills, %lld range fills, %lld wrong buffers, %lld poses sent, "
            "%lld feature records, %lld records of no known fill, ticks skipped: %lld colour %lld range, "
            "range frames of a skipped colour tick: %lld\n",
            (long long)atomic_load(&sc.color_fills), (long long)atomic_load(&sc.depth_fills),
            (long long)atomic_load(&sc.bad_buffers), (long long)atomic_load(&sc.poses_sent), published, unknown,
            skipped[0], skipped[1], orphans);
  }
  if (sc.gd) g_object_unref(sc.gd); /* unless SIGUSR1 stopped it */
  if (gc) g_object_unref(gc);
  vlff_sim_frame_free(cc.f);
  vlff_sim_frame_free(cd.f);
  vlff_sim_destroy(sc.sim);
  if (sc.udp >= 0) close(sc.udp);
  return rc;
}
