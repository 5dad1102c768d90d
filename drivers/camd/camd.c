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
#include "config.h"
#include "log.h"
#include "pipe.h"
#include "ringsink.h"
#include "stamps.h"
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
static struct vlff_stamps stamps;

static void on_stop(int sig) {
  (void)sig;
  stop_req = 1;
}
static void on_usr1(int sig) {
  (void)sig;
  atomic_fetch_add(&trigger_req, 1);
}

static uint64_t mono_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

static void sleep_ms(int ms) {
  struct timespec ts = {ms / 1000, (long)(ms % 1000) * 1000000L};
  nanosleep(&ts, NULL);
}

/* The camera backends behind one shape. */
struct backend {
  const char *name;
  void *(*open)(const struct vlff_config *cfg, char *err, size_t errlen);
  int (*grab)(void *cam, int timeout_ms, struct vlff_pipe *pipe, struct vlff_sink *sink,
              const struct vlff_pose_source *poses);
  int (*trigger)(void *cam, char *err, size_t errlen);
  void (*close)(void *cam);
  void (*counters)(void *cam, uint64_t *incomplete, uint64_t *timeouts);
};

#ifdef VLFF_HAVE_ARAVIS
static void *arv_open(const struct vlff_config *c, char *e, size_t l) { return vlff_arv_open(c, e, l); }
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
static void *lc_open(const struct vlff_config *c, char *e, size_t l) { return vlff_lcam_open(c, e, l); }
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
}
static void on_edge(void *ctx, uint64_t t, uint64_t n) {
  (void)ctx, (void)n;
  vlff_stamps_push(&stamps, t);
  if (trigger_on_edge) atomic_fetch_add(&trigger_req, 1);
}
#endif

static const struct vlff_cli cli = {
    "vlff-camd",
    "Usage: vlff-camd [--config FILE] [--frames N] [--seconds S]\n"
    "       vlff-camd --check-config FILE\n"
    "Streams one camera (camera.* keys) into the frame ring (shm.ring).\n"
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

int main(int argc, char **argv) {
  const char *path = NULL;
  long max_frames = 0;
  double max_seconds = 0;
  bool check_only = false;
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
    case 'c': path = optarg; break;
    case 'k': path = optarg, check_only = true; break;
    case 'n':
      max_frames = strtol(optarg, &end, 10);
      if (*end || max_frames < 1) return vlff_cli_usage_error(&cli, "--frames expects a positive integer");
      break;
    case 's':
      max_seconds = strtod(optarg, &end);
      if (*end || !(max_seconds > 0)) return vlff_cli_usage_error(&cli, "--seconds expects a positive number");
      break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", argv[optind - 1]);
    }
  }
  if (optind != argc) return vlff_cli_usage_error(&cli, "unexpected argument '%s'", argv[optind]);
  char ferr[512];
  path = vlff_config_find(path, ferr, sizeof ferr);
  if (!path) return vlff_cli_error(&cli, "%s", ferr);

  static struct vlff_config cfg;
  char err[1024];
  if (vlff_config_load(path, &cfg, err, sizeof err) || vlff_camcfg_check(&cfg, path, err, sizeof err)) {
    fprintf(stderr, "vlff-camd: %s\n", err);
    return 2;
  }
  vlff_log_set_level((enum vlff_log_level)cfg.node.log_level);
  const struct backend *be = NULL;
#ifdef VLFF_HAVE_ARAVIS
  if (cfg.camera.kind == VLFF_CAM_ARAVIS) be = &aravis_backend;
#endif
#ifdef VLFF_HAVE_LIBCAMERA
  if (cfg.camera.kind == VLFF_CAM_LIBCAMERA) be = &libcamera_backend;
#endif
  if (!be) {
    fprintf(stderr, "vlff-camd: %s: key 'camera.kind': this build has no %s support\n", path,
            cfg.camera.kind == VLFF_CAM_ARAVIS ? "Aravis" : "libcamera");
    return 2;
  }
  struct vlff_pipe *pipe = vlff_pipe_new(&cfg, err, sizeof err);
  if (!pipe) {
    fprintf(stderr, "vlff-camd: %s: %s\n", path, err);
    return 2;
  }
  if (check_only) {
    printf("%s: ok (%s camera '%s', %s)\n", path, be->name, cfg.camera.device, cfg.camera.pixel_format);
    vlff_pipe_free(pipe);
    return 0;
  }

  struct sigaction sa = {0};
  sa.sa_handler = on_stop;
  sigaction(SIGINT, &sa, NULL);
  sigaction(SIGTERM, &sa, NULL);
  sa.sa_handler = on_usr1;
  sa.sa_flags = SA_RESTART;
  sigaction(SIGUSR1, &sa, NULL);
  vlff_stamps_init(&stamps);

  int status = 0;
  struct vlff_ringsink *ring = vlff_ringsink_new(&cfg, err, sizeof err);
  if (!ring) {
    fprintf(stderr, "vlff-camd: %s\n", err);
    vlff_pipe_free(pipe);
    return 1;
  }

#ifdef VLFF_HAVE_GPIOD
  struct vlff_gpio_out *gout = NULL;
  struct vlff_gpio_in *gin = NULL;
  if (cfg.gpio.mode == VLFF_GPIO_OUTPUT) {
    gout = vlff_gpio_out_start(cfg.gpio.chip, cfg.gpio.line, cfg.gpio.rate_hz, cfg.gpio.pulse_us, cfg.gpio.active_low,
                               on_pulse, NULL, err, sizeof err);
    if (!gout) goto gpio_fail;
    /* A hardware-triggered frame belongs to the newest pulse before it. */
    if (cfg.camera.trigger == VLFF_TRIG_HARDWARE)
      vlff_pipe_set_stamps(pipe, &stamps, (uint64_t)(1e9 / cfg.gpio.rate_hz));
  } else if (cfg.gpio.mode == VLFF_GPIO_INPUT) {
    trigger_on_edge = cfg.camera.trigger == VLFF_TRIG_SOFTWARE;
    gin = vlff_gpio_in_start(cfg.gpio.chip, cfg.gpio.line, cfg.gpio.debounce_us, cfg.gpio.active_low, on_edge, NULL,
                             err, sizeof err);
    if (!gin) goto gpio_fail;
    /* A frame the edge triggered arrives after trigger latency, exposure,
     * readout and transfer, easily more than a frame period; it is still the
     * edge's frame. Stamping-only edges must fall within one period. */
    uint64_t period = (uint64_t)(1e9 / cfg.camera.frame_rate);
    vlff_pipe_set_stamps(pipe, &stamps, trigger_on_edge && period < 1000000000u ? 1000000000u : period);
  }
  if (0) {
  gpio_fail:
    fprintf(stderr, "vlff-camd: %s: %s\n", path, err);
    vlff_ringsink_free(ring);
    vlff_pipe_free(pipe);
    return 1;
  }
#else
  if (cfg.gpio.mode != VLFF_GPIO_OFF) {
    fprintf(stderr, "vlff-camd: %s: key 'gpio.mode': this build has no libgpiod support\n", path);
    vlff_ringsink_free(ring);
    vlff_pipe_free(pipe);
    return 2;
  }
#endif

  void *cam = NULL;
  uint64_t t0 = mono_ns(), next_try = t0, lost_at = 0;
  double backoff = 0.1;
  uint64_t lost = 0, reconnects = 0, open_failures = 0, incomplete = 0, timeouts = 0, triggers = 0, trig_fail = 0;
  bool ever_open = false;
  while (!stop_req) {
    if (max_seconds > 0 && (double)(mono_ns() - t0) * 1e-9 >= max_seconds) break;
    if (max_frames > 0 && vlff_pipe_get_stats(pipe)->committed >= (uint64_t)max_frames) break;
    if (!cam) {
      uint64_t now = mono_ns();
      if (now < next_try) {
        sleep_ms(20);
        continue;
      }
      cam = be->open(&cfg, err, sizeof err);
      if (!cam) {
        if (errno != ENODEV) { /* the camera refuses our configuration: retrying will not help */
          fprintf(stderr, "vlff-camd: %s: %s\n", path, err);
          status = 2;
          break;
        }
        open_failures++;
        if (open_failures == 1 || open_failures % 10 == 0)
          VLFF_WARN(TAG, "%s (attempt %llu, next in %.1f s)", err, (unsigned long long)open_failures, backoff);
        next_try = now + (uint64_t)(backoff * 1e9);
        backoff = backoff * 2 < cfg.camera.reconnect_max_s ? backoff * 2 : cfg.camera.reconnect_max_s;
        continue;
      }
      if (ever_open) {
        reconnects++;
        VLFF_INFO(TAG, "camera back after %.1f s (reconnect %llu)", (double)(mono_ns() - lost_at) * 1e-9,
                  (unsigned long long)reconnects);
      }
      ever_open = true;
      open_failures = 0;
      backoff = 0.1;
      atomic_store(&trigger_req, 0); /* triggers asked for while no camera was there are void */
    }
    uint64_t pend = atomic_exchange(&trigger_req, 0);
    for (; pend > 0 && be->trigger && cfg.camera.trigger == VLFF_TRIG_SOFTWARE; pend--) {
      if (be->trigger(cam, err, sizeof err)) {
        trig_fail++;
        VLFF_WARN(TAG, "%s", err);
      } else {
        triggers++;
      }
    }
    int rc = be->grab(cam, 20, pipe, vlff_ringsink_sink(ring), vlff_ringsink_poses(ring));
    if (rc < 0) {
      lost++;
      lost_at = mono_ns();
      uint64_t inc, to;
      be->counters(cam, &inc, &to);
      incomplete += inc, timeouts += to;
      be->close(cam);
      cam = NULL;
      VLFF_ERROR(TAG, "camera '%s' lost (%llu so far); ring %s stays up, reconnecting", cfg.camera.device,
                 (unsigned long long)lost, cfg.shm.ring);
      next_try = mono_ns() + (uint64_t)(backoff * 1e9);
    }
  }
  if (cam) {
    uint64_t inc, to;
    be->counters(cam, &inc, &to);
    incomplete += inc, timeouts += to;
    be->close(cam);
  }
  uint64_t pulses = 0, edges = 0;
#ifdef VLFF_HAVE_GPIOD
  if (gout) pulses = vlff_gpio_out_stats(gout).pulses;
  if (gin) edges = vlff_gpio_in_stats(gin).edges;
  vlff_gpio_out_stop(gout);
  vlff_gpio_in_stop(gin);
#endif
  const struct vlff_pipe_stats *st = vlff_pipe_get_stats(pipe);
  printf("vlff-camd: committed=%llu incomplete=%llu dropped=%llu timeouts=%llu lost=%llu reconnects=%llu "
         "triggers=%llu trigger_failures=%llu no_pose=%llu trigger_stamped=%llu pulses=%llu edges=%llu\n",
         (unsigned long long)st->committed, (unsigned long long)incomplete,
         (unsigned long long)(st->dropped_format + st->dropped_short + st->dropped_convert + st->dropped_sink),
         (unsigned long long)timeouts, (unsigned long long)lost, (unsigned long long)reconnects,
         (unsigned long long)triggers, (unsigned long long)trig_fail, (unsigned long long)st->no_pose,
         (unsigned long long)st->trigger_stamped, (unsigned long long)pulses, (unsigned long long)edges);
  fflush(stdout);
  vlff_ringsink_free(ring);
  vlff_pipe_free(pipe);
#ifdef VLFF_HAVE_ARAVIS
  vlff_arv_shutdown();
#endif
  return status;
}
