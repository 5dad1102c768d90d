/*
 * vlff-camd: one camera -> the frame ring.
 *
 * A separate process per camera so that a driver crash (or a camera SDK
 * misbehaving) never takes the learner down. The loop owns the camera; the
 * ring outlives any number of camera losses: on loss the camera is closed
 * and reopened with exponential backoff up to camera.reconnect_max_s, while
 * the ring stays created and consumers just see a gap.
 *
 * Software triggers come from SIGUSR1 (one per signal, for tests and simple
 * integrations) or from GPIO input edges; they are sent from this loop so
 * that the camera object is only ever touched by one thread.
 *
 * With camera.depth: stream the process drives two cameras, the colour
 * camera and a range camera (depth_camera.*), each with its own pipeline
 * and reconnect state; their frames meet in the pairing (pair.h), which
 * writes one record per matched pair.
 */
#include <errno.h>
#include <getopt.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "cli.h"
#include "clock.h"
#include "config.h"
#include "log.h"
#include "pair.h"
#include "pipe.h"
#include "ringsink.h"
#include "service.h"
#include "stamps.h"
#include "vlff/escape.h"
#ifdef VLFF_HAVE_ARAVIS
#include "aravis.h"
#endif
#ifdef VLFF_HAVE_LIBCAMERA
#include "lcam.h"
#endif
#ifdef VLFF_HAVE_GPIOD
#include "gpio.h"
#endif

#define TAG "camd"

static volatile sig_atomic_t stop_req;
static atomic_uint_fast64_t trigger_req; /* signal handler and GPIO thread add, loop consumes */
static struct vlff_stamps stamps, depth_stamps; /* one consumer each: the two pipelines */

static void on_stop(int sig) {
  (void)sig;
  stop_req = 1;
}
static void on_usr1(int sig) {
  (void)sig;
  atomic_fetch_add(&trigger_req, 1);
}

static void sleep_ms(int ms) {
  struct timespec ts = {ms / 1000, (long)(ms % 1000) * 1000000L};
  nanosleep(&ts, NULL);
}

/* The camera backends behind one shape. */
struct backend {
  const char *name;
  void *(*open)(const struct vlff_cfg_camera *cfg, char *err, size_t errlen);
  int (*grab)(void *cam, int timeout_ms, struct vlff_pipe *pipe, struct vlff_sink *sink,
              const struct vlff_pose_source *poses);
  int (*trigger)(void *cam, char *err, size_t errlen);
  void (*close)(void *cam);
  void (*counters)(void *cam, uint64_t *incomplete, uint64_t *timeouts);
};

#ifdef VLFF_HAVE_ARAVIS
static void *arv_open(const struct vlff_cfg_camera *c, char *e, size_t l) { return vlff_arv_open(c, e, l); }
static int arv_grab(void *cam, int t, struct vlff_pipe *p, struct vlff_sink *s, const struct vlff_pose_source *ps) {
  return vlff_arv_grab(cam, t, p, s, ps);
}
static int arv_trig(void *cam, char *e, size_t l) { return vlff_arv_software_trigger(cam, e, l); }
static void arv_close(void *cam) { vlff_arv_close(cam); }
static void arv_counters(void *cam, uint64_t *inc, uint64_t *to) {
  const struct vlff_arv_stats *st = vlff_arv_stats(cam);
  *inc = st->incomplete;
  *to = st->timeouts;
}
static const struct backend aravis_backend = {"aravis", arv_open, arv_grab, arv_trig, arv_close, arv_counters};
#endif

#ifdef VLFF_HAVE_LIBCAMERA
static void *lc_open(const struct vlff_cfg_camera *c, char *e, size_t l) { return vlff_lcam_open(c, e, l); }
static int lc_grab(void *cam, int t, struct vlff_pipe *p, struct vlff_sink *s, const struct vlff_pose_source *ps) {
  return vlff_lcam_grab(cam, t, p, s, ps);
}
static void lc_close(void *cam) { vlff_lcam_close(cam); }
static void lc_counters(void *cam, uint64_t *inc, uint64_t *to) { vlff_lcam_counters(cam, inc, to); }
static const struct backend libcamera_backend = {"libcamera", lc_open, lc_grab, NULL, lc_close, lc_counters};
#endif

#ifdef VLFF_HAVE_GPIOD
static int trigger_on_edge;
static void on_pulse(void *ctx, uint64_t t, uint64_t n) {
  (void)ctx, (void)n;
  vlff_stamps_push(&stamps, t);
  vlff_stamps_push(&depth_stamps, t);
}
static void on_edge(void *ctx, uint64_t t, uint64_t n) {
  (void)ctx, (void)n;
  vlff_stamps_push(&stamps, t);
  vlff_stamps_push(&depth_stamps, t);
  if (trigger_on_edge) atomic_fetch_add(&trigger_req, 1);
}
#endif

/* One camera of the process, its pipeline and its reconnect state. */
struct slot {
  const char *what; /* "camera" or "depth camera", for messages */
  const struct backend *be;
  struct vlff_cfg_camera camera; /* this camera's section (the range camera's: vlff_depth_camera_config) */
  struct vlff_pipe *pipe;
  struct vlff_sink *sink;
  const struct vlff_pose_source *poses;
  void *cam;
  uint64_t next_try, lost_at;
  double backoff;
  uint64_t lost, reconnects, open_failures, incomplete, timeouts, triggers, trig_fail;
  bool ever_open;
  uint64_t seen;          /* frames its pipeline took (committed or dropped) */
  uint64_t last_frame_ns; /* when seen last grew, or the camera opened */
  bool silent;            /* its silence was logged */
};

/* Frames the slot's pipeline has taken so far, kept or not. */
static uint64_t slot_frames(const struct slot *s) {
  const struct vlff_pipe_stats *ps = vlff_pipe_get_stats(s->pipe);
  return ps->committed + ps->dropped_format + ps->dropped_short + ps->dropped_convert + ps->dropped_sink;
}

/* The range camera's settings travel as camera.* keys into the backend:
 * its messages name them as the user wrote them, depth_camera.*. */
static void name_depth_keys(char *msg, size_t len) {
  char out[1024];
  size_t k = 0;
  for (const char *p = msg; *p && k + 1 < sizeof out;) {
    if (!strncmp(p, "'camera.", 8) && k + 15 < sizeof out) {
      memcpy(out + k, "'depth_camera.", 14);
      k += 14, p += 8;
    } else {
      out[k++] = *p++;
    }
  }
  out[k] = 0;
  snprintf(msg, len, "%s", out);
}

/* Opens the camera when it is due; 1 open, 0 not (yet), -1 the camera
 * refuses its configuration (retrying will not help). */
static int slot_open(struct slot *s, const char *path) {
  if (s->cam) return 1;
  char err[1024];
  uint64_t now = vlff_now_ns();
  if (now < s->next_try) return 0;
  s->cam = s->be->open(&s->camera, err, sizeof err);
  if (!s->cam && strcmp(s->what, "camera")) name_depth_keys(err, sizeof err);
  if (!s->cam) {
    if (errno != ENODEV) {
      fprintf(stderr, "%s: %s\n", path, err);
      return -1;
    }
    s->open_failures++;
    if (s->open_failures == 1 || s->open_failures % 10 == 0)
      VLFF_WARN(TAG, "%s: %s (attempt %llu, next in %.1f s)", s->what, err, (unsigned long long)s->open_failures,
                s->backoff);
    s->next_try = now + (uint64_t)(s->backoff * 1e9);
    s->backoff = s->backoff * 2 < s->camera.reconnect_max_s ? s->backoff * 2 : s->camera.reconnect_max_s;
    return 0;
  }
  if (s->ever_open) {
    s->reconnects++;
    VLFF_INFO(TAG, "%s back after %.1f s (reconnect %llu)", s->what, (double)(vlff_now_ns() - s->lost_at) * 1e-9,
              (unsigned long long)s->reconnects);
  }
  s->ever_open = true;
  s->last_frame_ns = vlff_now_ns();
  s->open_failures = 0;
  s->backoff = 0.1;
  return 1;
}

static void slot_close(struct slot *s) {
  if (!s->cam) return;
  uint64_t inc, to;
  s->be->counters(s->cam, &inc, &to);
  s->incomplete += inc, s->timeouts += to;
  s->be->close(s->cam);
  s->cam = NULL;
}

static void slot_trigger(struct slot *s, uint64_t n) {
  char err[512];
  for (; n > 0 && s->cam && s->be->trigger && s->camera.trigger == VLFF_TRIG_SOFTWARE; n--) {
    if (s->be->trigger(s->cam, err, sizeof err)) {
      s->trig_fail++;
      VLFF_WARN(TAG, "%s: %s", s->what, err);
    } else {
      s->triggers++;
    }
  }
}

static void slot_grab(struct slot *s, int timeout_ms, const char *ring) {
  if (!s->cam) return;
  if (s->be->grab(s->cam, timeout_ms, s->pipe, s->sink, s->poses) >= 0) return;
  s->lost++;
  s->lost_at = vlff_now_ns();
  /* said before closing: releasing a camera that is gone can take seconds */
  VLFF_ERROR(TAG, "%s '%s' lost (%llu so far); ring %s stays up, reconnecting", s->what, VLFF_Q(s->camera.device),
             (unsigned long long)s->lost, ring);
  slot_close(s);
  s->next_try = vlff_now_ns() + (uint64_t)(s->backoff * 1e9);
}

/* A free-running camera that is open but sends nothing is said at once
 * (the loss itself takes the control channel's timeouts to show, and the
 * backend asks it after a second): after half a second, or three frame
 * periods when longer, without a frame. With two cameras no pair forms
 * meanwhile, and the node sees no frame either. */
static void slot_watch(struct slot *s, const struct slot *other, uint64_t now, bool stalled) {
  uint64_t seen = slot_frames(s);
  /* stalled: this loop was held up (a lost camera's release or reopen
   * blocks it for seconds), so the other camera's silence is camd's own */
  if (stalled && seen == s->seen && s->cam) {
    if (!s->silent) s->last_frame_ns = now;
    return;
  }
  if (seen != s->seen || !s->cam) {
    if (s->silent && s->cam)
      VLFF_INFO(TAG, "%s '%s': frames again after %.1f s", s->what, VLFF_Q(s->camera.device),
                (double)(now - s->last_frame_ns) * 1e-9);
    s->seen = seen, s->silent = false;
    if (s->cam) s->last_frame_ns = now;
    return;
  }
  const double rate = s->camera.frame_rate, quiet = rate > 0 && 3 / rate > 0.5 ? 3 / rate : 0.5;
  if (s->silent || s->camera.trigger != VLFF_TRIG_FREERUN || (double)(now - s->last_frame_ns) * 1e-9 < quiet)
    return;
  s->silent = true;
  VLFF_WARN(TAG, "%s '%s': no frame for %.1f s although open%s", s->what, VLFF_Q(s->camera.device),
             (double)(now - s->last_frame_ns) * 1e-9,
             other ? (other->cam ? ": no pairs until it is back (the other camera streams)" : ": no pairs") : "");
}

/* The pairing's counts over the last report period, said when frames found
 * no partner or pairs were lost (and once at the start): the exit line
 * alone would hide a tolerance or a calibration that fails every pair. At
 * exit (final) the part-period since the last report is said if it had
 * trouble: a short run would otherwise end with the reason unsaid. */
#define PAIR_REPORT_S 10
#define PAIR_FIRST_S 3
struct pair_report {
  uint64_t t_ns;
  struct vlff_pair_stats last;
  uint64_t color, depth;
  bool first_done;
};

static void pair_report(struct pair_report *r, const struct vlff_pair *pair, const struct slot *slots,
                        double pair_tolerance_s, uint64_t now, bool final) {
  if (!r->t_ns) r->t_ns = now;
  /* the first soon after the start: a pairing that fails every pair is
   * said within seconds */
  if (!final && now - r->t_ns < (r->first_done ? PAIR_REPORT_S : PAIR_FIRST_S) * 1000000000ull) return;
  const struct vlff_pair_stats *st = vlff_pair_get_stats(pair), *o = &r->last;
  uint64_t c = vlff_pipe_get_stats(slots[0].pipe)->committed, d = vlff_pipe_get_stats(slots[1].pipe)->committed;
  uint64_t pairs = st->pairs - o->pairs, um_c = st->unmatched_color - o->unmatched_color,
           um_d = st->unmatched_depth - o->unmatched_depth, drop = st->dropped - o->dropped,
           nc = c - r->color, nd = d - r->depth;
  double secs = (double)(now - r->t_ns) * 1e-9;
  double skew = pairs ? (double)(st->skew_sum_ns - o->skew_sum_ns) / (double)pairs * 1e-6 : 0;
  bool bad = um_c + um_d + drop > 0 || (!pairs && nc && nd);
  if (bad || (!r->first_done && !final)) {
    enum vlff_log_level lv = !pairs && (nc || nd) ? VLFF_LOG_ERROR : bad ? VLFF_LOG_WARN : VLFF_LOG_INFO;
    const char *why = vlff_pair_last_error(pair);
    vlff_log(lv, TAG,
             "pairing, last %.0f s: %llu pairs of %llu colour and %llu range frames, without a partner %llu colour "
             "%llu range, %llu pairs dropped%s%s; skew mean %.1f ms, max so far %.1f ms (depth_camera.pair_tolerance_s "
             "%g s holds trigger-stamped pairs, free-running ones pair within half a frame period)",
             secs, (unsigned long long)pairs, (unsigned long long)nc, (unsigned long long)nd,
             (unsigned long long)um_c, (unsigned long long)um_d, (unsigned long long)drop,
             drop && why[0] ? ": " : "", drop ? why : "", skew, (double)st->skew_max_ns * 1e-6,
             pair_tolerance_s);
  }
  r->first_done = true;
  r->last = *st, r->color = c, r->depth = d, r->t_ns = now;
}

static const struct vlff_cli cli = {
    "vlff-camd",
    "Usage: vlff-camd [--config FILE] [--frames N] [--seconds S]\n"
    "       vlff-camd --check-config FILE\n"
    "Streams one camera (camera.* keys) into the frame ring (shm.ring), or with\n"
    "camera.depth: stream a colour camera and a range camera (depth_camera.*) as\n"
    "one record per pair, the range image registered into the colour camera.\n"
    "  -c, --config FILE  the config; without it $VLFF_CONFIG, then the installed\n"
    "                     vlff.yaml (vlff-node --help names it); none found is an error\n"
    "  --check-config FILE  check FILE's camera keys and exit 0/1\n"
    "  --frames N     exit after N frames were committed\n"
    "  --seconds S    exit after S seconds\n"
    "  -V, --version  print the version and exit\n"
    "  -h, --help     print this help and exit\n"
    "  SIGUSR1        one software trigger (camera.trigger: software)\n"
    "  SIGINT/SIGTERM stop; a statistics line is printed on exit\n"
    "Examples:\n"
    "  vlff-camd --config /etc/vlff/aravis-gige.yaml\n"
    "  vlff-camd --check-config my-camera.yaml\n",
};

/* The process: its options, its cameras and where their frames go. */
struct camd {
  const char *path;
  long max_frames;
  double max_seconds;
  bool check_only;
  struct vlff_config cfg;
  struct slot slots[2];
  int nslots;
  struct vlff_ringsink *ring;
  struct vlff_pair *pair;
#ifdef VLFF_HAVE_GPIOD
  struct vlff_gpio_out *gout;
  struct vlff_gpio_in *gin;
#endif
};

/* -1 to go on, else the exit status. */
static int parse_args(struct camd *d, int argc, char **argv) {
  static const struct option opts[] = {{"config", required_argument, 0, 'c'},
                                       {"check-config", required_argument, 0, 'k'},
                                       {"frames", required_argument, 0, 'n'},
                                       {"seconds", required_argument, 0, 's'},
                                       VLFF_CLI_COMMON_OPTIONS};
  int o, exit_status;
  while ((o = vlff_cli_next(&cli, argc, argv, "c:", opts, &exit_status)) != -1) {
    char *end;
    switch (o) {
    case VLFF_CLI_EXIT: return exit_status;
    case 'c': d->path = optarg; break;
    case 'k': d->path = optarg, d->check_only = true; break;
    case 'n':
      d->max_frames = strtol(optarg, &end, 10);
      if (*end || d->max_frames < 1) return vlff_cli_usage_error(&cli, "--frames expects a positive integer");
      break;
    case 's':
      d->max_seconds = strtod(optarg, &end);
      if (end == optarg || *end || !(d->max_seconds > 0 && d->max_seconds <= 1e9))
        return vlff_cli_usage_error(&cli, "--seconds expects a number of seconds in (0, 1e9]");
      break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", VLFF_Q(argv[optind - 1]));
    }
  }
  if (optind != argc) return vlff_cli_usage_error(&cli, "unexpected argument '%s'", VLFF_Q(argv[optind]));
  char ferr[512];
  d->path = vlff_config_find(d->path, ferr, sizeof ferr);
  if (!d->path) return vlff_cli_error(&cli, "%s", ferr);
  return -1;
}

/* The config, the backend and each camera's pipeline: 0, or 1 (the
 * configuration cannot run), said on stderr. */
static int setup_cameras(struct camd *d) {
  char err[1024];
  struct vlff_config *cfg = &d->cfg;
  if (vlff_config_load(d->path, cfg, err, sizeof err) || vlff_camcfg_check(cfg, d->path, err, sizeof err))
    return vlff_cli_config_error(err);
  vlff_log_set_level((enum vlff_log_level)cfg->node.log_level);
  const struct backend *be = NULL;
#ifdef VLFF_HAVE_ARAVIS
  if (cfg->camera.kind == VLFF_CAM_ARAVIS) be = &aravis_backend;
#endif
#ifdef VLFF_HAVE_LIBCAMERA
  if (cfg->camera.kind == VLFF_CAM_LIBCAMERA) be = &libcamera_backend;
#endif
  if (!be) {
    fprintf(stderr, "%s: key 'camera.kind': this build has no %s support\n", d->path,
            cfg->camera.kind == VLFF_CAM_ARAVIS ? "Aravis" : "libcamera");
    return 1;
  }
  const bool paired = cfg->camera.depth == VLFF_DEPTH_STREAM;
  d->nslots = paired ? 2 : 1;
  struct slot *color = &d->slots[0], *range = paired ? &d->slots[1] : NULL;
  color->what = "camera", color->be = be, color->camera = cfg->camera, color->backoff = 0.1;
  color->pipe = vlff_pipe_new(cfg, err, sizeof err);
  if (!color->pipe) {
    fprintf(stderr, "%s: %s\n", d->path, err);
    return 1;
  }
  if (range) {
#ifdef VLFF_HAVE_ARAVIS
    range->what = "depth camera", range->be = &aravis_backend, range->backoff = 0.1;
    vlff_depth_camera_config(cfg, &range->camera);
    range->pipe = vlff_pipe_new_depth(cfg, err, sizeof err);
#else
    snprintf(err, sizeof err, "key 'depth_camera.kind': this build has no Aravis support");
#endif
    if (!range->pipe) {
      fprintf(stderr, "%s: %s\n", d->path, err);
      return 1;
    }
  }
  if (d->check_only) {
    /* the calibration is read by the pairing: check it here too */
    if (paired && !(d->pair = vlff_pair_new(&cfg->depth_camera, &cfg->camera, NULL, err, sizeof err))) {
      fprintf(stderr, "%s: %s\n", d->path, err);
      return 1;
    }
    printf("%s: ok (%s camera '%s', %s%s%s)\n", VLFF_Q(d->path), be->name, VLFF_Q(cfg->camera.device),
                                                                                  cfg->camera.pixel_format,
           paired ? ", range camera " : "", paired ? cfg->depth_camera.device : "");
  }
  return 0;
}

/* The frame ring, and the pairing between the cameras and it: 0, 1 (the
 * ring, or the pairing's calibration). */
static int setup_ring(struct camd *d) {
  char err[1024];
  d->ring = vlff_ringsink_new(&d->cfg.shm, &d->cfg.camera, err, sizeof err);
  if (!d->ring) {
    fprintf(stderr, "vlff-camd: %s\n", err);
    return 1;
  }
  struct slot *color = &d->slots[0];
  color->poses = vlff_ringsink_poses(d->ring);
  color->sink = vlff_ringsink_sink(d->ring);
  if (d->nslots == 2) {
    d->pair = vlff_pair_new(&d->cfg.depth_camera, &d->cfg.camera, vlff_ringsink_sink(d->ring), err, sizeof err);
    if (!d->pair) {
      fprintf(stderr, "%s: %s\n", d->path, err);
      return 1;
    }
    color->sink = vlff_pair_color_sink(d->pair);
    d->slots[1].sink = vlff_pair_depth_sink(d->pair);
  }
  return 0;
}

/* The GPIO line, driving the trigger or stamping its edges: 0, 1 (the line
 * failed, or no libgpiod in this build). */
static int setup_gpio(struct camd *d) {
  const struct vlff_config *cfg = &d->cfg;
#ifdef VLFF_HAVE_GPIOD
  char err[1024];
  struct slot *color = &d->slots[0], *range = d->nslots == 2 ? &d->slots[1] : NULL;
  if (cfg->gpio.mode == VLFF_GPIO_OUTPUT) {
    d->gout = vlff_gpio_out_start(cfg->gpio.chip, cfg->gpio.line, cfg->gpio.rate_hz, cfg->gpio.pulse_us,
                                  cfg->gpio.active_low, on_pulse, NULL, err, sizeof err);
    if (!d->gout) {
      fprintf(stderr, "vlff-camd: %s: %s\n", d->path, err);
      return 1;
    }
    /* A hardware-triggered frame belongs to the newest pulse before it; a
     * pair fired by one pulse carries that pulse's stamp on both sides. */
    if (cfg->camera.trigger == VLFF_TRIG_HARDWARE)
      vlff_pipe_set_stamps(color->pipe, &stamps, (uint64_t)(1e9 / cfg->gpio.rate_hz));
    if (range && cfg->depth_camera.trigger == VLFF_TRIG_HARDWARE)
      vlff_pipe_set_stamps(range->pipe, &depth_stamps, (uint64_t)(1e9 / cfg->gpio.rate_hz));
  } else if (cfg->gpio.mode == VLFF_GPIO_INPUT) {
    trigger_on_edge = cfg->camera.trigger == VLFF_TRIG_SOFTWARE ||
                      (range && cfg->depth_camera.trigger == VLFF_TRIG_SOFTWARE);
    d->gin = vlff_gpio_in_start(cfg->gpio.chip, cfg->gpio.line, cfg->gpio.debounce_us, cfg->gpio.active_low,
                                on_edge, NULL, err, sizeof err);
    if (!d->gin) {
      fprintf(stderr, "vlff-camd: %s: %s\n", d->path, err);
      return 1;
    }
    /* A frame the edge triggered arrives after trigger latency, exposure,
     * readout and transfer, easily more than a frame period; it is still the
     * edge's frame. Stamping-only edges must fall within one period. */
    for (int i = 0; i < d->nslots; i++) {
      uint64_t period = (uint64_t)(1e9 / d->slots[i].camera.frame_rate);
      vlff_pipe_set_stamps(d->slots[i].pipe, i ? &depth_stamps : &stamps,
                           trigger_on_edge && period < 1000000000u ? 1000000000u : period);
    }
  }
#else
  if (cfg->gpio.mode != VLFF_GPIO_OFF) {
    fprintf(stderr, "%s: key 'gpio.mode': this build has no libgpiod support\n", d->path);
    return 1;
  }
#endif
  return 0;
}

static bool frames_done(const struct camd *d) {
  uint64_t committed =
      d->pair ? vlff_pair_get_stats(d->pair)->pairs : vlff_pipe_get_stats(d->slots[0].pipe)->committed;
  return d->max_frames > 0 && committed >= (uint64_t)d->max_frames;
}

/* Grabs until a signal, --frames or --seconds: 0, or 1 when a camera
 * refuses its configuration. */
static int run(struct camd *d) {
  int status = 0;
  /* Type=notify: ready once the ring exists (consumers may attach; the camera
   * may come later). The watchdog is fed from this loop, which passes every
   * grab timeout whether a camera is there or not: only a hang stops it. */
  struct vlff_service svc;
  vlff_service_ready(&svc);
  uint64_t t0 = vlff_now_ns();
  struct pair_report report = {0};
  uint64_t last_pass = vlff_now_ns();
  while (!stop_req) {
    if (vlff_service_watchdog_due(&svc, vlff_now_ns())) vlff_service_watchdog();
    if (d->max_seconds > 0 && (double)(vlff_now_ns() - t0) * 1e-9 >= d->max_seconds) break;
    if (frames_done(d)) break;
    int open = 0, refused = 0;
    for (int i = 0; i < d->nslots; i++) {
      bool was = d->slots[i].cam != NULL;
      int r = slot_open(&d->slots[i], d->path);
      refused |= r < 0;
      open += r > 0;
      /* triggers asked for while no camera was there are void */
      if (r > 0 && !was && d->nslots == 1) atomic_store(&trigger_req, 0);
    }
    if (refused) {
      status = 1;
      break;
    }
    if (!open) {
      sleep_ms(20);
      continue;
    }
    uint64_t pend = atomic_exchange(&trigger_req, 0);
    for (int i = 0; i < d->nslots; i++) slot_trigger(&d->slots[i], pend);
    /* Each camera's stream fills its buffers in the background: a short
     * wait per camera keeps both drained. */
    /* --frames is checked after each camera's grab too: with two cameras
     * either grab can complete a pair, and one pass could pass the count. */
    for (int i = 0; i < d->nslots && !frames_done(d); i++) slot_grab(&d->slots[i], 20 / d->nslots, d->cfg.shm.ring);
    uint64_t now = vlff_now_ns();
    const bool stalled = now - last_pass > 250000000u;
    last_pass = now;
    for (int i = 0; i < d->nslots; i++)
      slot_watch(&d->slots[i], d->nslots == 2 ? &d->slots[1 - i] : NULL, now, stalled);
    if (d->pair) pair_report(&report, d->pair, d->slots, d->cfg.depth_camera.pair_tolerance_s, now, false);
  }
  if (d->pair && report.t_ns)
    pair_report(&report, d->pair, d->slots, d->cfg.depth_camera.pair_tolerance_s, vlff_now_ns(), true);
  vlff_service_stopping();
  for (int i = 0; i < d->nslots; i++) slot_close(&d->slots[i]);
  return status;
}

/* The one statistics line at exit (scripts parse it). */
static void print_stats(const struct camd *d) {
  uint64_t pulses = 0, edges = 0;
#ifdef VLFF_HAVE_GPIOD
  if (d->gout) pulses = vlff_gpio_out_stats(d->gout).pulses;
  if (d->gin) edges = vlff_gpio_in_stats(d->gin).edges;
#endif
  const struct vlff_pipe_stats *st = vlff_pipe_get_stats(d->slots[0].pipe);
  uint64_t dropped = 0, incomplete = 0, timeouts = 0, lost = 0, reconnects = 0, triggers = 0, trig_fail = 0;
  for (int i = 0; i < d->nslots; i++) {
    const struct slot *s = &d->slots[i];
    const struct vlff_pipe_stats *ps = vlff_pipe_get_stats(s->pipe);
    dropped += ps->dropped_format + ps->dropped_short + ps->dropped_convert + ps->dropped_sink;
    incomplete += s->incomplete, timeouts += s->timeouts, lost += s->lost;
    reconnects += s->reconnects, triggers += s->triggers, trig_fail += s->trig_fail;
  }
  const struct vlff_pair_stats *ps = d->pair ? vlff_pair_get_stats(d->pair) : NULL;
  printf("vlff-camd: committed=%llu incomplete=%llu dropped=%llu timeouts=%llu lost=%llu reconnects=%llu "
         "triggers=%llu trigger_failures=%llu no_pose=%llu trigger_stamped=%llu pulses=%llu edges=%llu",
         (unsigned long long)(ps ? ps->pairs : st->committed), (unsigned long long)incomplete,
         (unsigned long long)(dropped + (ps ? ps->dropped : 0)), (unsigned long long)timeouts,
         (unsigned long long)lost, (unsigned long long)reconnects, (unsigned long long)triggers,
         (unsigned long long)trig_fail, (unsigned long long)st->no_pose, (unsigned long long)st->trigger_stamped,
         (unsigned long long)pulses, (unsigned long long)edges);
  if (ps)
    printf(" color_frames=%llu depth_frames=%llu unmatched_color=%llu unmatched_depth=%llu startup_color=%llu "
           "startup_depth=%llu",
           (unsigned long long)st->committed, (unsigned long long)vlff_pipe_get_stats(d->slots[1].pipe)->committed,
           (unsigned long long)ps->unmatched_color, (unsigned long long)ps->unmatched_depth,
           (unsigned long long)ps->startup_color, (unsigned long long)ps->startup_depth);
  printf("\n");
  fflush(stdout);
}

int main(int argc, char **argv) {
  static struct camd d; /* large (two configs): not on the stack */
  int status = parse_args(&d, argc, argv);
  if (status >= 0) return status;
  status = setup_cameras(&d);
  if (status == 0 && !d.check_only) {
    struct sigaction sa = {0};
    sa.sa_handler = on_stop;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    sa.sa_handler = on_usr1;
    sa.sa_flags = SA_RESTART;
    sigaction(SIGUSR1, &sa, NULL);
    vlff_stamps_init(&stamps);
    vlff_stamps_init(&depth_stamps);
    status = setup_ring(&d);
    if (status == 0) status = setup_gpio(&d);
    if (status == 0) {
      status = run(&d);
      print_stats(&d);
    }
  }
#ifdef VLFF_HAVE_GPIOD
  vlff_gpio_out_stop(d.gout);
  vlff_gpio_in_stop(d.gin);
#endif
  vlff_pair_free(d.pair);
  vlff_ringsink_free(d.ring);
  for (int i = 0; i < d.nslots; i++) vlff_pipe_free(d.slots[i].pipe);
#ifdef VLFF_HAVE_ARAVIS
  if (!d.check_only) vlff_arv_shutdown();
#endif
  return status;
}
