/*
 * CAN benchmark, run inside the test VM (tests/bench/can.sh boots it):
 *  1. heartbeat lateness against the ideal grid, idle and with every core
 *     busy (the learner's situation), from kernel receive timestamps;
 *  2. status frames/s capacity: the node's status path (encode the four
 *     frames from a snapshot, non-blocking send) against a baseline loop
 *     sending constant frames on the same socket.
 * Last line: RESULT hb_jitter_p99_ms=<x> status_fps=<x> ...
 */
#include <errno.h>
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "can_proto.h"
#include "config.h"
#include "hb_grid.h"
#include "vlff_can.h"

static atomic_bool quit;

static double mono(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void *burn(void *arg) {
  (void)arg;
  volatile double x = 1;
  while (!atomic_load(&quit)) x = x * 1.0000001 + 1e-9;
  return NULL;
}

static int bus_open(const char *iface) {
  int s = socket(PF_CAN, SOCK_RAW, CAN_RAW);
  int on = 1, buf = 4 << 20;
  setsockopt(s, SOL_SOCKET, SO_TIMESTAMPNS, &on, sizeof on);
  setsockopt(s, SOL_SOCKET, SO_RCVBUF, &buf, sizeof buf);
  struct sockaddr_can a = {.can_family = AF_CAN, .can_ifindex = (int)if_nametoindex(iface)};
  if (s < 0 || bind(s, (struct sockaddr *)&a, sizeof a) < 0) {
    perror("bench: bus socket");
    exit(1);
  }
  return s;
}

static double recv_ts(int s, struct can_frame *f) {
  char ctrl[CMSG_SPACE(sizeof(struct timespec))];
  struct iovec iov = {.iov_base = f, .iov_len = sizeof *f};
  struct msghdr m = {.msg_iov = &iov, .msg_iovlen = 1, .msg_control = ctrl, .msg_controllen = sizeof ctrl};
  if (recvmsg(s, &m, 0) < 0) return -1;
  for (struct cmsghdr *c = CMSG_FIRSTHDR(&m); c; c = CMSG_NXTHDR(&m, c))
    if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SCM_TIMESTAMPNS) {
      struct timespec ts;
      memcpy(&ts, CMSG_DATA(c), sizeof ts);
      return ts.tv_sec + ts.tv_nsec * 1e-9;
    }
  return -1;
}

/* n heartbeats at period_ms with `load` busy threads; fills g. */
static struct hb_grid heartbeat(const char *iface, int period_ms, int n, int load, struct vlff_can_stats *out) {
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  snprintf(cfg.can.interface, sizeof cfg.can.interface, "%s", iface);
  cfg.can.heartbeat_ms = period_ms;
  cfg.can.status_ms = 100;
  int bus = bus_open(iface);
  pthread_t th[8];
  atomic_store(&quit, false);
  for (int i = 0; i < load; i++) pthread_create(&th[i], NULL, burn, NULL);
  struct vlff_can *can = vlff_can_open(&cfg.can, cfg.prompts.set_count, NULL, NULL);
  double *t = calloc((size_t)n, sizeof *t), *lat = calloc((size_t)n, sizeof *lat), anchor = -1;
  int k = 0;
  const uint32_t hb = 0x700 + (uint32_t)cfg.can.node_id;
  while (k < n) {
    struct can_frame f;
    double ts = recv_ts(bus, &f);
    if (ts < 0 || f.can_id != hb) continue;
    if (f.data[0] == VLFF_NMT_BOOTUP) anchor = ts;
    else if (anchor > 0) t[k++] = ts;
  }
  vlff_can_get_stats(can, out);
  vlff_can_close(can);
  atomic_store(&quit, true);
  for (int i = 0; i < load; i++) pthread_join(th[i], NULL);
  struct hb_grid g = hb_grid_analyse(t, n, period_ms * 1e-3, anchor, lat);
  free(t);
  free(lat);
  close(bus);
  return g;
}

/* Baseline: what the VM's timers give any thread. A bare clock_nanosleep
 * TIMER_ABSTIME loop at the CAN thread's priority, lateness measured on wake. */
struct sleeper_arg {
  int period_ms, n;
  double *lat;
};

static void *sleeper(void *arg) {
  struct sleeper_arg *a = arg;
  struct sched_param sp = {.sched_priority = 10};
  pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
  struct timespec next;
  clock_gettime(CLOCK_MONOTONIC, &next);
  for (int i = 0; i < a->n; i++) {
    next.tv_nsec += a->period_ms * 1000000L;
    while (next.tv_nsec >= 1000000000L) {
      next.tv_nsec -= 1000000000L;
      next.tv_sec++;
    }
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    a->lat[i] = ((now.tv_sec - next.tv_sec) + (now.tv_nsec - next.tv_nsec) * 1e-9) * 1e3;
    /* Capped at a period, as the heartbeat analysis counts a skipped deadline. */
    if (a->lat[i] > a->period_ms) a->lat[i] = a->period_ms;
  }
  return NULL;
}

static void timer_baseline(int period_ms, int n, int load, double *p50, double *p99) {
  struct sleeper_arg a = {.period_ms = period_ms, .n = n, .lat = calloc((size_t)n, sizeof(double))};
  pthread_t th[8], t;
  atomic_store(&quit, false);
  for (int i = 0; i < load; i++) pthread_create(&th[i], NULL, burn, NULL);
  pthread_create(&t, NULL, sleeper, &a);
  pthread_join(t, NULL);
  atomic_store(&quit, true);
  for (int i = 0; i < load; i++) pthread_join(th[i], NULL);
  qsort(a.lat, (size_t)n, sizeof(double), hb_cmp);
  *p50 = a.lat[n / 2];
  *p99 = a.lat[(int)((n - 1) * 0.99)];
  free(a.lat);
}

/* Frames/s accepted by the kernel over seconds; encode = the status path. */
static double send_rate(const char *iface, double seconds, bool encode, uint64_t *drops) {
  int s = socket(PF_CAN, SOCK_RAW | SOCK_NONBLOCK, CAN_RAW);
  struct sockaddr_can a = {.can_family = AF_CAN, .can_ifindex = (int)if_nametoindex(iface)};
  bind(s, (struct sockaddr *)&a, sizeof a);
  struct vlff_can_status st = {.iteration = 1, .loss_total = 0.5f, .keyframes = 10, .fps_in = 30};
  struct vlff_canp_link link = {.nmt_state = VLFF_NMT_OPERATIONAL, .map_age_ms = 10};
  struct canfd_frame f;
  memset(&f, 0, sizeof f);
  f.len = 8;
  uint64_t sent = 0;
  *drops = 0;
  double t0 = mono(), t1;
  do {
    for (int i = 0; i < 64; i++) {
      f.can_id = 0x180 + (uint32_t)(i & 3);
      if (encode) {
        st.iteration++;
        vlff_canp_encode_status(i & 3, &st, &link, f.data);
      }
      if (send(s, &f, CAN_MTU, MSG_DONTWAIT) == (ssize_t)CAN_MTU) sent++;
      else (*drops)++;
    }
    t1 = mono();
  } while (t1 - t0 < seconds);
  close(s);
  return (double)sent / (t1 - t0);
}

int main(int argc, char **argv) {
  const char *iface = argc > 1 ? argv[1] : "vbench0";
  /* Half the default period: long enough that a loaded host's scheduling
   * slices show as lateness rather than as skipped deadlines. */
  const int period = 50;
  uint64_t d1, d2;
  struct vlff_can_stats si, sl;
  double b50_idle, b99_idle, b50_load, b99_load;
  timer_baseline(period, 150, 0, &b50_idle, &b99_idle);
  printf("timer baseline idle:      p50 %.3f ms p99 %.3f ms (bare clock_nanosleep loop, capped at a period)\n", b50_idle, b99_idle);
  timer_baseline(period, 300, 2, &b50_load, &b99_load);
  printf("timer baseline full load: p50 %.3f ms p99 %.3f ms\n", b50_load, b99_load);
  struct hb_grid idle = heartbeat(iface, period, 150, 0, &si);
  printf("heartbeat idle:      p50 %.3f ms p99 %.3f ms max %.3f ms, %llu deadlines skipped (node) / %d missed "
         "(receiver) of %d\n", idle.p50_ms, idle.p99_ms, idle.max_ms, (unsigned long long)si.tx_late, idle.missed,
         idle.n + idle.missed);
  struct hb_grid load = heartbeat(iface, period, 300, 2, &sl);
  printf("heartbeat full load: p50 %.3f ms p99 %.3f ms max %.3f ms, %llu deadlines skipped (node) / %d missed "
         "(receiver) of %d\n", load.p50_ms, load.p99_ms, load.max_ms, (unsigned long long)sl.tx_late, load.missed,
         load.n + load.missed);
  /* What punctuality costs: the CAN thread's spin before each heartbeat, as
   * a share of one core, and the wakes whose timer was later than the
   * learnt margin (those the spin could not save). */
  double spin_idle = si.hb_spin_ns * 1e-9 / (150 * period * 1e-3), spin_load = sl.hb_spin_ns * 1e-9 / (300 * period * 1e-3);
  printf("heartbeat spin: %.2f%% of a core idle, %.2f%% under load; timer past the deadline %llu / %llu times\n",
         100 * spin_idle, 100 * spin_load, (unsigned long long)si.hb_timer_late, (unsigned long long)sl.hb_timer_late);
  double raw = send_rate(iface, 2.0, false, &d1);
  double status = send_rate(iface, 2.0, true, &d2);
  printf("send capacity: constant frames %.0f/s, status frames %.0f/s (drops %llu / %llu)\n", raw, status,
         (unsigned long long)d1, (unsigned long long)d2);
  printf("RESULT hb_jitter_p99_ms=%.3f status_fps=%.0f hb_jitter_p50_ms=%.3f hb_p99_over_period=%.4f "
         "hb_idle_p99_ms=%.3f hb_late=%llu timer_p99_ms=%.3f hb_p99_over_timer_p99=%.2f raw_fps=%.0f "
         "status_vs_raw=%.3f spin_core_frac_load=%.4f\n",
         load.p99_ms, status, load.p50_ms, load.p99_ms / period, idle.p99_ms, (unsigned long long)sl.tx_late, b99_load,
         load.p99_ms / (b99_load > 1e-6 ? b99_load : 1e-6), raw, status / raw, spin_load);
  return 0;
}
