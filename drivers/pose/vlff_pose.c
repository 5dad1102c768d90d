/*
 * vlff-pose: the pose ring's producer for trackers that print TUM RGB-D
 * trajectory lines (ORB-SLAM3, OpenVINS, RTAB-Map, VIO SDK samples). It
 * reads lines from a file, a pipe or UDP datagrams, checks and converts
 * them (tum.h) and writes one pose record per accepted line. Refused lines
 * are counted per reason and reported with their line (or datagram)
 * number; the first few of each reason are printed, then a summary.
 */
#include <arpa/inet.h>
#include <errno.h>
#include <getopt.h>
#include <math.h>
#include <netdb.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "config.h"
#include "log.h"
#include "tum.h"
#include "vlff/shm.h"

#ifndef VLFF_VERSION
#define VLFF_VERSION "unknown"
#endif

#define TAG "pose"
#define REPORT_EACH 5 /* refusals of one reason printed one by one, the rest summarised */

static volatile sig_atomic_t stop_requested;

static void on_signal(int sig) { stop_requested = sig; }

static void usage(FILE *out) {
  fputs("Usage: vlff-pose [OPTIONS] [FILE]\n"
        "Write camera poses into the pose ring (shm.pose_ring) from TUM RGB-D trajectory lines\n"
        "\"t tx ty tz qx qy qz qw\" read from FILE, standard input (no FILE or \"-\") or UDP.\n"
        "\n"
        "  -c, --config FILE        take shm.pose_ring, shm.pose_slots, shm.mode, shm.group from FILE\n"
        "  -r, --ring NAME          pose ring segment name (default: shm.pose_ring, /vlff-poses)\n"
        "  -u, --udp ADDR:PORT      read datagrams of lines on this address (127.0.0.1:5600, [::]:5600)\n"
        "      --clock monotonic|realtime\n"
        "                           clock of the line's stamps: the node's CLOCK_MONOTONIC (default),\n"
        "                           or UNIX time, converted to it\n"
        "      --clock-offset S     seconds added to every line's stamp\n"
        "      --stamp-host         stamp each pose with the host's receipt time instead of its own\n"
        "      --latency S          with --stamp-host: seconds from the frame to its pose's receipt\n"
        "      --extrinsic \"tx ty tz qx qy qz qw\"\n"
        "                           the camera's pose in the tracker's body (IMU) frame; default identity\n"
        "                           (the lines are already the camera's poses)\n"
        "      --quat-tolerance X   quaternions with |norm - 1| <= X are normalised, others refused (0.01)\n"
        "      --extra-fields       ignore numbers after the eighth (covariances), instead of refusing the line\n"
        "      --source-id N        written into every record (0)\n"
        "  -q, --quiet              print only errors and refusals\n"
        "  -V, --version            print the version and exit\n"
        "  -h, --help               print this help and exit\n"
        "\n"
        "Examples:\n"
        "  vlff-pose -c /etc/vlff/default.yaml CameraTrajectory.txt\n"
        "  my_slam | vlff-pose -c /etc/vlff/default.yaml --clock realtime\n"
        "  vlff-pose -c /etc/vlff/default.yaml --udp 127.0.0.1:5600 --extrinsic \"0.05 0 0 -0.5 0.5 -0.5 0.5\"\n"
        "Exit status: 0 at the end of the input or on SIGINT/SIGTERM (refused lines are counted and\n"
        "reported, not fatal), 1 when the ring, the file or the socket cannot be opened, 2 on usage errors.\n",
        out);
}

struct reporter {
  const char *name; /* file name, "stdin" or "udp" */
  unsigned long printed[VLFF_TUM_RESULTS];
};

static void report_refusal(struct reporter *rp, const char *where, int result, const char *why) {
  if (rp->printed[result]++ < REPORT_EACH) {
    VLFF_WARN(TAG, "%s: refused, %s: %s%s", where, vlff_tum_result_name(result), why,
              rp->printed[result] == REPORT_EACH ? " (further lines refused for this reason are only counted)" : "");
  }
}

static void summary(const struct vlff_tum_feed *f, const char *ring) {
  char line[512];
  size_t k = 0;
  line[0] = 0;
  for (int r = VLFF_TUM_MALFORMED; r < VLFF_TUM_RESULTS && k < sizeof line; r++)
    if (f->refused[r])
      k += (size_t)snprintf(line + k, sizeof line - k, "%s%s %llu", k ? ", " : " (", vlff_tum_result_name(r),
                            (unsigned long long)f->refused[r]);
  if (k && k < sizeof line) snprintf(line + k, sizeof line - k, ")");
  vlff_log(vlff_tum_feed_refused(f) ? VLFF_LOG_WARN : VLFF_LOG_INFO, TAG, "%llu poses written to %s, %llu lines refused%s",
           (unsigned long long)f->accepted, ring, (unsigned long long)vlff_tum_feed_refused(f), line);
}

/* One line in; writes its record when accepted. */
static void feed(struct vlff_tum_feed *f, struct vlff_ring *ring, struct reporter *rp, const char *where,
                 const char *line) {
  struct vlff_pose_rec rec;
  char why[256];
  int r = vlff_tum_feed_line(f, line, vlff_shm_now_ns(), &rec, why, sizeof why);
  if (r == VLFF_TUM_OK) {
    if (vlff_ring_write(ring, &rec, sizeof rec) != 0) VLFF_ERROR(TAG, "%s: pose ring write: %s", where, strerror(errno));
  } else if (r != VLFF_TUM_SKIP) {
    report_refusal(rp, where, r, why);
  }
}

static int read_stream(FILE *in, struct vlff_tum_feed *f, struct vlff_ring *ring, struct reporter *rp) {
  char *line = NULL;
  size_t cap = 0;
  unsigned long lineno = 0;
  while (!stop_requested) {
    errno = 0;
    ssize_t n = getline(&line, &cap, in);
    if (n < 0) {
      if (errno == EINTR && !stop_requested) {
        clearerr(in);
        continue;
      }
      break;
    }
    lineno++;
    char where[300];
    snprintf(where, sizeof where, "%s:%lu", rp->name, lineno);
    feed(f, ring, rp, where, line);
  }
  int bad = ferror(in) && !stop_requested;
  if (bad) VLFF_ERROR(TAG, "%s: read error: %s", rp->name, strerror(errno));
  free(line);
  return bad ? 1 : 0;
}

/* "host:port", "[v6]:port" or ":port" (every address). */
static int open_udp(const char *spec, char *err, size_t errlen) {
  char host[256];
  const char *colon = strrchr(spec, ':');
  if (!colon || !colon[1]) return snprintf(err, errlen, "--udp '%s': expected ADDR:PORT", spec), -1;
  size_t hl = (size_t)(colon - spec);
  if (hl >= sizeof host) return snprintf(err, errlen, "--udp '%s': address too long", spec), -1;
  memcpy(host, spec, hl);
  host[hl] = 0;
  if (hl >= 2 && host[0] == '[' && host[hl - 1] == ']') {
    memmove(host, host + 1, hl - 2);
    host[hl - 2] = 0;
  }
  struct addrinfo hints = {.ai_family = AF_UNSPEC, .ai_socktype = SOCK_DGRAM, .ai_flags = AI_PASSIVE}, *res;
  int rc = getaddrinfo(host[0] ? host : NULL, colon + 1, &hints, &res);
  if (rc) return snprintf(err, errlen, "--udp '%s': %s", spec, gai_strerror(rc)), -1;
  int s = -1;
  for (struct addrinfo *a = res; a; a = a->ai_next) {
    s = socket(a->ai_family, a->ai_socktype | SOCK_CLOEXEC, a->ai_protocol);
    if (s < 0) continue;
    if (bind(s, a->ai_addr, a->ai_addrlen) == 0) break;
    snprintf(err, errlen, "--udp '%s': bind: %s", spec, strerror(errno));
    close(s);
    s = -1;
  }
  freeaddrinfo(res);
  return s;
}

static int read_udp(int sock, struct vlff_tum_feed *f, struct vlff_ring *ring, struct reporter *rp) {
  static char buf[65536];
  unsigned long dgram = 0;
  while (!stop_requested) {
    struct pollfd pfd = {.fd = sock, .events = POLLIN};
    int pr = poll(&pfd, 1, 200);
    if (pr < 0 && errno != EINTR) return VLFF_ERROR(TAG, "udp: poll: %s", strerror(errno)), 1;
    if (pr <= 0) continue;
    ssize_t n = recv(sock, buf, sizeof buf - 1, 0);
    if (n < 0) {
      if (errno == EINTR || errno == EAGAIN) continue;
      return VLFF_ERROR(TAG, "udp: recv: %s", strerror(errno)), 1;
    }
    buf[n] = 0;
    dgram++;
    /* A datagram holds one line or several. */
    unsigned long lineno = 0;
    for (char *save = NULL, *l = strtok_r(buf, "\n", &save); l; l = strtok_r(NULL, "\n", &save)) {
      char where[96];
      snprintf(where, sizeof where, "udp datagram %lu line %lu", dgram, ++lineno);
      feed(f, ring, rp, where, l);
    }
  }
  return 0;
}

static int parse_double(const char *s, double lo, double hi, double *out) {
  char *end;
  errno = 0;
  double v = strtod(s, &end);
  if (end == s || *end || errno || !isfinite(v) || v < lo || v > hi) return -1;
  *out = v;
  return 0;
}

int main(int argc, char **argv) {
  enum { OPT_CLOCK = 256, OPT_OFFSET, OPT_HOST, OPT_LATENCY, OPT_EXTRINSIC, OPT_QTOL, OPT_SOURCE, OPT_EXTRA };
  static const struct option opts[] = {
      {"config", required_argument, NULL, 'c'},
      {"ring", required_argument, NULL, 'r'},
      {"udp", required_argument, NULL, 'u'},
      {"clock", required_argument, NULL, OPT_CLOCK},
      {"clock-offset", required_argument, NULL, OPT_OFFSET},
      {"stamp-host", no_argument, NULL, OPT_HOST},
      {"latency", required_argument, NULL, OPT_LATENCY},
      {"extrinsic", required_argument, NULL, OPT_EXTRINSIC},
      {"quat-tolerance", required_argument, NULL, OPT_QTOL},
      {"source-id", required_argument, NULL, OPT_SOURCE},
      {"extra-fields", no_argument, NULL, OPT_EXTRA},
      {"quiet", no_argument, NULL, 'q'},
      {"version", no_argument, NULL, 'V'},
      {"help", no_argument, NULL, 'h'},
      {NULL, 0, NULL, 0},
  };
  const char *config_path = NULL, *ring_name = NULL, *udp = NULL;
  int realtime = 0, quiet = 0, c;
  double offset_s = 0, latency_s = 0, v;
  struct vlff_tum_feed_params fp = {.stamp = VLFF_TUM_STAMP_SOURCE, .quat_tolerance = 0.01};
  double ext_p[3] = {0, 0, 0}, ext_q[4] = {0, 0, 0, 1};
  while ((c = getopt_long(argc, argv, "c:r:u:qVh", opts, NULL)) != -1) {
    switch (c) {
    case 'c': config_path = optarg; break;
    case 'r': ring_name = optarg; break;
    case 'u': udp = optarg; break;
    case 'q': quiet = 1; break;
    case OPT_HOST: fp.stamp = VLFF_TUM_STAMP_HOST; break;
    case OPT_EXTRA: fp.extra_fields = 1; break;
    case OPT_CLOCK:
      if (!strcmp(optarg, "monotonic")) realtime = 0;
      else if (!strcmp(optarg, "realtime")) realtime = 1;
      else {
        fprintf(stderr, "vlff-pose: --clock '%s': expected monotonic or realtime\n", optarg);
        usage(stderr);
        return 2;
      }
      break;
    case OPT_OFFSET:
    case OPT_LATENCY:
    case OPT_QTOL:
    case OPT_SOURCE: {
      const char *name = c == OPT_OFFSET ? "--clock-offset" : c == OPT_LATENCY ? "--latency"
                         : c == OPT_QTOL ? "--quat-tolerance" : "--source-id";
      double lo = c == OPT_OFFSET ? -1e10 : 0, hi = c == OPT_OFFSET ? 1e10 : c == OPT_LATENCY ? 60
                                                : c == OPT_QTOL ? 0.5 : 4294967295.0;
      if (parse_double(optarg, lo, hi, &v) || (c == OPT_SOURCE && v != floor(v))) {
        fprintf(stderr, "vlff-pose: %s '%s': expected a number in [%g, %g]\n", name, optarg, lo, hi);
        usage(stderr);
        return 2;
      }
      if (c == OPT_OFFSET) offset_s = v;
      else if (c == OPT_LATENCY) latency_s = v;
      else if (c == OPT_QTOL) fp.quat_tolerance = v;
      else fp.source_id = (uint32_t)v;
      break;
    }
    case OPT_EXTRINSIC: {
      struct vlff_tum_sample s;
      char line[512], why[256];
      snprintf(line, sizeof line, "0 %s", optarg);
      double n = 0;
      if (vlff_tum_parse(line, 0, &s, why, sizeof why) == VLFF_TUM_OK)
        n = sqrt(s.q[0] * s.q[0] + s.q[1] * s.q[1] + s.q[2] * s.q[2] + s.q[3] * s.q[3]);
      if (!(fabs(n - 1) <= 0.01)) {
        fprintf(stderr, "vlff-pose: --extrinsic '%s': expected \"tx ty tz qx qy qz qw\" with a unit quaternion\n",
                optarg);
        usage(stderr);
        return 2;
      }
      memcpy(ext_p, s.p, sizeof ext_p);
      for (int i = 0; i < 4; i++) ext_q[i] = s.q[i] / n;
      break;
    }
    case 'V': printf("vlff-pose %s\n", VLFF_VERSION); return 0;
    case 'h': usage(stdout); return 0;
    default: usage(stderr); return 2;
    }
  }
  if (optind + 1 < argc || (udp && optind < argc)) {
    fprintf(stderr, "vlff-pose: unexpected argument '%s'\n", argv[udp ? optind : optind + 1]);
    usage(stderr);
    return 2;
  }
  const char *file = optind < argc ? argv[optind] : NULL;

  struct vlff_config cfg;
  char err[512];
  if (config_path) {
    if (vlff_config_load(config_path, &cfg, err, sizeof err)) {
      fprintf(stderr, "vlff-pose: %s\n", err);
      return 1;
    }
  } else {
    vlff_config_defaults(&cfg);
  }
  vlff_log_set_level(quiet ? VLFF_LOG_WARN : (enum vlff_log_level)cfg.node.log_level);
  if (!ring_name) ring_name = cfg.shm.pose_ring;

  fp.latency_ns = (int64_t)llround(latency_s * 1e9);
  fp.clock_offset_ns = (int64_t)llround(offset_s * 1e9);
  if (realtime) {
    /* UNIX-time stamps onto the node's clock: both clocks read back to back. */
    struct timespec rt, mt;
    clock_gettime(CLOCK_REALTIME, &rt);
    clock_gettime(CLOCK_MONOTONIC, &mt);
    fp.clock_offset_ns += ((int64_t)mt.tv_sec - rt.tv_sec) * 1000000000 + (mt.tv_nsec - rt.tv_nsec);
  }
  vlff_tum_matrix(ext_p, ext_q, fp.body_to_camera);
  struct vlff_tum_feed f;
  if (vlff_tum_feed_init(&f, &fp, err, sizeof err)) {
    fprintf(stderr, "vlff-pose: %s\n", err);
    return 2;
  }

  FILE *in = NULL;
  int sock = -1;
  if (udp) {
    sock = open_udp(udp, err, sizeof err);
    if (sock < 0) return VLFF_ERROR(TAG, "%s", err), 1;
  } else if (file && strcmp(file, "-")) {
    in = fopen(file, "r");
    if (!in) return VLFF_ERROR(TAG, "%s: cannot open: %s", file, strerror(errno)), 1;
  } else {
    in = stdin;
  }
  struct vlff_ring_params rp = {.record_kind = VLFF_RECORD_POSE, .slots = (uint32_t)cfg.shm.pose_slots,
                                .slot_size = sizeof(struct vlff_pose_rec),
                                .perm = {.mode = (mode_t)cfg.shm.mode, .group = cfg.shm.group}};
  struct vlff_ring *ring = vlff_ring_create(ring_name, &rp);
  if (!ring) {
    VLFF_ERROR(TAG, "pose ring %s: %s", ring_name, vlff_shm_last_message());
    if (in && in != stdin) fclose(in);
    if (sock >= 0) close(sock);
    return 1;
  }

  struct sigaction sa;
  memset(&sa, 0, sizeof sa);
  sa.sa_handler = on_signal; /* no SA_RESTART: a blocked read returns */
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, NULL);
  sigaction(SIGTERM, &sa, NULL);

  struct reporter rep = {.name = udp ? "udp" : in == stdin ? "stdin" : file};
  VLFF_INFO(TAG, "vlff-pose %s: %s -> pose ring %s (%d slots), stamps %s%s", VLFF_VERSION,
            udp ? udp : rep.name, ring_name, cfg.shm.pose_slots,
            fp.stamp == VLFF_TUM_STAMP_HOST ? "at receipt" : realtime ? "UNIX time" : "CLOCK_MONOTONIC",
            fp.stamp == VLFF_TUM_STAMP_HOST || offset_s == 0 ? "" : " plus the clock offset");
  int rc = udp ? read_udp(sock, &f, ring, &rep) : read_stream(in, &f, ring, &rep);
  summary(&f, ring_name);
  if (in && in != stdin) fclose(in);
  if (sock >= 0) close(sock);
  vlff_ring_close(ring);
  return rc;
}
