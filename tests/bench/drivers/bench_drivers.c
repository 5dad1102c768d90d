/*
 * Drivers benchmark: Aravis' fake GigE camera at 1920x1080 BayerRG8,
 * through vlff-camd (demosaic into the shm ring) against a bare Aravis grab
 * loop of the same camera in the same run. The fake camera's pattern
 * generation is the ceiling for both, so the ratio says how much of the
 * camera's rate the driver keeps. Runs alternate bare/camd twice to spread
 * machine noise over both. GPIO pulse jitter needs a GPIO chip: measured
 * here when one is given (VLFF_BENCH_GPIO_CHIP/LINE); else taken from
 * VLFF_BENCH_GPIO_JITTER_VM_US, which tests/bench/drivers.sh measures by
 * running "bench_drivers --gpio-jitter CHIP LINE" on a gpio-sim line inside
 * the qemu VM (TCG emulation: an upper bound, not real hardware); else NA.
 */
#include <arv.h>
#include <errno.h>
#include <math.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
#include <vlff/shm.h>

#include "fakecam.h"
#ifdef VLFF_HAVE_GPIOD
#include "gpio.h"
#endif

#define SECONDS 4.0

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static double cpu_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void sleep_s(double s) {
  struct timespec ts = {(time_t)s, (long)((s - (time_t)s) * 1e9)};
  while (nanosleep(&ts, &ts) && errno == EINTR) {}
}

/* Bare loop: what any Aravis application does at minimum. */
static double bare(double *cpu_ms_per_frame) {
  GError *e = NULL;
  ArvCamera *c = arv_camera_new("127.0.0.1", &e);
  if (!c) return fprintf(stderr, "bare: %s\n", e->message), -1;
  arv_camera_set_pixel_format_from_string(c, "BayerRG8", NULL);
  arv_camera_set_region(c, 0, 0, 1920, 1080, NULL);
  arv_camera_set_frame_rate(c, 1000, NULL);
  arv_camera_clear_triggers(c, NULL);
  arv_camera_gv_auto_packet_size(c, NULL);
  ArvStream *s = arv_camera_create_stream(c, NULL, NULL, NULL);
  size_t payload = (size_t)arv_camera_get_payload(c, NULL);
  for (int i = 0; i < 8; i++) arv_stream_push_buffer(s, arv_buffer_new(payload, NULL));
  arv_camera_start_acquisition(c, NULL);
  /* Warm up, then count complete buffers over the window. */
  for (double t = now_s(); now_s() - t < 0.5;) {
    ArvBuffer *b = arv_stream_timeout_pop_buffer(s, 100000);
    if (b) arv_stream_push_buffer(s, b);
  }
  long n = 0;
  double t0 = now_s(), c0 = cpu_s();
  while (now_s() - t0 < SECONDS) {
    ArvBuffer *b = arv_stream_timeout_pop_buffer(s, 100000);
    if (!b) continue;
    n += arv_buffer_get_status(b) == ARV_BUFFER_STATUS_SUCCESS;
    arv_stream_push_buffer(s, b);
  }
  double dt = now_s() - t0;
  *cpu_ms_per_frame = n ? (cpu_s() - c0) * 1e3 / n : 0;
  arv_camera_stop_acquisition(c, NULL);
  g_object_unref(s);
  g_object_unref(c);
  return n / dt;
}

static double camd(double *cpu_ms_per_frame) {
  char ring[64], cfg[128];
  snprintf(ring, sizeof ring, "/vlff-bench-drivers-%d", (int)getpid());
  snprintf(cfg, sizeof cfg, "/tmp/vlff-bench-drivers-%d.yaml", (int)getpid());
  FILE *f = fopen(cfg, "w");
  if (!f) return -1;
  fprintf(f,
          "node:\n  log_level: warn\nshm:\n  ring: %s\n  ring_slots: 16\n  max_width: 1920\n  max_height: 1080\n"
          "camera:\n  kind: aravis\n  device: 127.0.0.1\n  pixel_format: BayerRG8\n  width: 1920\n  height: 1080\n"
          "  frame_rate: 1000\n",
          ring);
  fclose(f);
  pid_t pid = fork();
  if (pid == 0) {
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    int null = open("/dev/null", O_WRONLY);
    dup2(null, 1);
    execl(VLFF_CAMD, VLFF_CAMD, "--config", cfg, (char *)NULL);
    _exit(127);
  }
  struct vlff_ring *r = NULL;
  for (int i = 0; i < 100 && !r; i++) {
    sleep_s(0.05);
    r = vlff_ring_attach(ring, VLFF_RECORD_FRAME);
  }
  double fps = -1;
  if (r) {
    double t = now_s();
    while (vlff_ring_head(r) == 0 && now_s() - t < 5) sleep_s(0.01);
    sleep_s(0.5);
    uint64_t h0 = vlff_ring_head(r);
    double t0 = now_s();
    sleep_s(SECONDS);
    uint64_t h1 = vlff_ring_head(r);
    fps = (h1 - h0) / (now_s() - t0);
  }
  kill(pid, SIGTERM);
  int st;
  struct rusage ru;
  wait4(pid, &st, 0, &ru);
  double cpu = ru.ru_utime.tv_sec + ru.ru_utime.tv_usec * 1e-6 + ru.ru_stime.tv_sec + ru.ru_stime.tv_usec * 1e-6;
  uint64_t total = r ? vlff_ring_head(r) : 0;
  *cpu_ms_per_frame = total ? cpu * 1e3 / total : 0;
  vlff_ring_close(r);
  vlff_shm_unlink(ring);
  unlink(cfg);
  return fps;
}

#ifdef VLFF_HAVE_GPIOD
#define NP 400
static uint64_t pt[NP];
static int np;
static void on_pulse(void *ctx, uint64_t t, uint64_t n) {
  (void)ctx, (void)n;
  if (np < NP) pt[np++] = t;
}
static int cmp_d(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return x < y ? -1 : x > y;
}
#endif

/* p99 of |interval - period| over 2 s of 100 Hz pulses, us; -1 = no chip. */
static double gpio_jitter(const char *chip, const char *line) {
#ifdef VLFF_HAVE_GPIOD
  if (!chip) return -1;
  char err[256];
  struct vlff_gpio_out *g = vlff_gpio_out_start(chip, line ? line : "0", 100, 1000, false, on_pulse, NULL, err, sizeof err);
  if (!g) return fprintf(stderr, "gpio: %s\n", err), -1;
  sleep_s(2.05);
  vlff_gpio_out_stop(g);
  if (np < 10) return fprintf(stderr, "gpio: only %d pulses in 2 s at 100 Hz\n", np), -1;
  printf("gpio: %d pulses at 100 Hz on %s line %s\n", np, chip, line);
  double d[NP];
  for (int i = 1; i < np; i++) d[i - 1] = fabs((double)(pt[i] - pt[i - 1]) / 1e3 - 10000.0);
  qsort(d, (size_t)np - 1, sizeof d[0], cmp_d);
  return d[(np - 1) * 99 / 100];
#else
  (void)chip, (void)line;
  return -1;
#endif
}

int main(int argc, char **argv) {
  if (argc == 4 && !strcmp(argv[1], "--gpio-jitter")) {
    double j = gpio_jitter(argv[2], argv[3]);
    if (j < 0) return 1;
    printf("RESULT gpio_pulse_jitter_us_p99=%.1f\n", j);
    return 0;
  }
  if (argc != 1) {
    fprintf(stderr, "usage: bench_drivers [--gpio-jitter CHIP LINE]\n");
    return 2;
  }
  pid_t cam = fakecam_start(0);
  if (cam <= 0) {
    fprintf(stderr, "bench drivers: cannot start arv-fake-gv-camera-0.8\n");
    return 1;
  }
  double fb = 0, fc = 0, cb = 0, cc = 0;
  for (int round = 0; round < 2; round++) {
    double cpu_b = 0, cpu_c = 0;
    double b = bare(&cpu_b), c = camd(&cpu_c);
    printf("round %d: bare %.1f fps (%.2f ms CPU/frame), vlff-camd %.1f fps (%.2f ms CPU/frame)\n", round, b, cpu_b, c,
           cpu_c);
    if (b <= 0 || c < 0) {
      fakecam_stop(cam);
      return 1;
    }
    fb += b, fc += c, cb += cpu_b, cc += cpu_c;
  }
  fakecam_stop(cam);
  arv_shutdown();
  double j = gpio_jitter(getenv("VLFF_BENCH_GPIO_CHIP"), getenv("VLFF_BENCH_GPIO_LINE") ? getenv("VLFF_BENCH_GPIO_LINE") : "0");
  const char *where = "host";
  const char *vm = getenv("VLFF_BENCH_GPIO_JITTER_VM_US");
  if (j < 0 && vm && *vm) {
    char *end;
    double v = strtod(vm, &end);
    if (!*end && v >= 0) j = v, where = "qemu_tcg";
  }
  printf("1920x1080 BayerRG8 over loopback: bare %.1f fps, vlff-camd (demosaic into the ring) %.1f fps\n", fb / 2,
         fc / 2);
  printf("CPU per frame: bare grab %.2f ms, vlff-camd %.2f ms (demosaic + copy into the slot)\n", cb / 2, cc / 2);
  if (j < 0)
    printf("gpio: no GPIO chip on this host and no VM measurement (set VLFF_BENCH_GPIO_CHIP/LINE where one "
           "exists; scripts/bench drivers measures it in the qemu VM)\n");
  else if (!strcmp(where, "qemu_tcg"))
    printf("gpio: pulse jitter p99 %.1f us was MEASURED INSIDE THE QEMU VM UNDER TCG EMULATION (gpio-sim, "
           "software-emulated CPU and timers): an upper bound, not what real hardware does\n",
           j);
  else
    printf("gpio: pulse jitter p99 %.1f us on this host\n", j);
  char js[32];
  if (j < 0)
    snprintf(js, sizeof js, "NA");
  else
    snprintf(js, sizeof js, "%.1f", j);
  printf("RESULT camd_vs_bare_fps=%.3f cpu_ms_per_frame=%.2f gpio_pulse_jitter_us_p99=%s gpio_jitter_measured_on=%s\n",
         fc / fb, cc / 2, js, j < 0 ? "none" : where);
  return 0;
}
