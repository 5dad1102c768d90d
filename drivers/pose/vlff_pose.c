/*
 * vlff-pose: the pose ring's producer for trackers that print TUM RGB-D
 * trajectory lines (ORB-SLAM3, OpenVINS, RTAB-Map, VIO SDK samples). It
 * reads lines from a file, a pipe or UDP datagrams, checks and converts
 * them (tum.h) and writes one pose record per accepted line. Refused lines
 * are counted per reason and reported with their line (or datagram)
 * number through the log's rate limiter (vlff_warn_limited: the first five
 * of each reason, then every 1000th), and in the summary at the end.
 *
 * UDP has no authentication: any process that can reach the address (on
 * loopback, any local user) can send lines. pose.udp_peer binds the source
 * to one sender address (and port); datagrams from others are refused and
 * counted.
 */
#include <arpa/inet.h>
#include <errno.h>
#include <getopt.h>
#include <math.h>
#include <netdb.h>
#include <poll.h>
#include <signal.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "cli.h"
#include "clock.h"
#include "config.h"
#include "log.h"
#include "service.h"
#include "tum.h"
#include "vlff/shm.h"
#include "vlff/escape.h"

#define TAG "pose"
#define LINE_MAX_BYTES VLFF_TUM_LINE_MAX /* a UDP datagram's size; TUM lines are far shorter */
/* How long the input loops wait for input before they pass their loop again:
 * they feed the service watchdog (Type=notify) while the tracker is quiet. */
#define WAIT_MS 200

static const struct vlff_cli cli = {
    "vlff-pose",
    "Usage: vlff-pose [OPTIONS] [FILE]\n"
    "Write camera poses into the pose ring (shm.pose_ring) from TUM RGB-D trajectory lines\n"
    "\"t tx ty tz qx qy qz qw\" read from FILE (\"-\": standard input), else UDP on pose.udp or\n"
    "--udp, else standard input.\n"
    "The config's pose.* keys set the defaults of the options below (docs/pose.md).\n"
    "\n"
    "  -c, --config FILE        the config; without it $VLFF_CONFIG, then\n"
    "                           " VLFF_SYSCONFDIR "/vlff/vlff.yaml; none found is an error\n"
    "                           (installed elsewhere: vlff/vlff.yaml in that install's sysconfdir)\n"
    "  -r, --ring NAME          pose ring segment name (default: shm.pose_ring)\n"
    "  -u, --udp ADDR:PORT      read datagrams of lines on this address (127.0.0.1:5600, [::]:5600)\n"
    "      --udp-peer ADDR[:PORT]\n"
    "                           take datagrams from this sender only (pose.udp_peer; UDP has no\n"
    "                           authentication: without it any local process can send poses)\n"
    "      --clock monotonic|realtime\n"
    "                           clock of the lines' stamps: the node's CLOCK_MONOTONIC, or UNIX\n"
    "                           time, converted to it (pose.clock)\n"
    "      --clock-offset S     seconds added to every line's stamp (pose.clock_offset_s)\n"
    "      --future-tolerance S refuse stamps more than S seconds ahead of the clock as a clock\n"
    "                           error (pose.future_tolerance_s, 0.05; 0: no check)\n"
    "      --out-of-order-reset N\n"
    "                           the Nth line in a row older than the last accepted one restarts\n"
    "                           the order (pose.out_of_order_reset, 10; 0: never)\n"
    "      --stamp-host         stamp each pose with its receipt time instead of its own\n"
    "      --latency S          with --stamp-host: seconds from the frame to its pose's receipt\n"
    "      --extrinsic \"tx ty tz qx qy qz qw\"\n"
    "                           the camera's pose in the tracker's body (IMU) frame (pose.extrinsic;\n"
    "                           identity: the lines are already the camera's poses)\n"
    "      --quat-tolerance X   quaternions with |norm - 1| <= X are normalised, others refused\n"
    "      --extra-fields       ignore numbers after the eighth (covariances), instead of refusing the line\n"
    "      --source-id N        written into every record\n"
    "  -q, --quiet              print only errors and refusals\n"
    "  -V, --version            print the version and exit\n"
    "  -h, --help               print this help and exit\n"
    "\n"
    "Examples:\n"
    "  vlff-pose -c /etc/vlff/vlff.yaml CameraTrajectory.txt\n"
    "  my_slam | vlff-pose -c /etc/vlff/vlff.yaml --clock realtime -\n"
    "  vlff-pose -c /etc/vlff/vlff.yaml --udp 127.0.0.1:5600 --extrinsic \"0.05 0 0 -0.5 0.5 -0.5 0.5\"\n"
    "Exit status: 0 at the end of the input or on SIGINT/SIGTERM (refused lines are counted and\n"
    "reported, not fatal), 1 when the config, the ring, the file or the socket cannot be opened,\n"
    "2 on usage errors.\n",
};

struct reporter {
  const char *name; /* file name, "stdin" or "udp" */
  uint64_t seen[VLFF_TUM_RESULTS]; /* vlff_warn_limited's count per reason */
  uint64_t resets;                 /* the same for the order's restarts */
};

static void report_refusal(struct reporter *rp, const char *where, int result, const char *why) {
  vlff_warn_limited(&rp->seen[result], TAG, "%s: refused, %s: %s%s", VLFF_Q(where), vlff_tum_result_name(result), why,
                    rp->seen[result] == 4 ? " (from here on every 1000th refusal for this reason is printed, all "
                                            "are counted)"
                                          : "");
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
  char resets[64] = "";
  if (f->resets) snprintf(resets, sizeof resets, ", order restarted %llu times", (unsigned long long)f->resets);
  vlff_log(vlff_tum_feed_refused(f) ? VLFF_LOG_WARN : VLFF_LOG_INFO, TAG,
           "%llu poses written to %s, %llu lines refused%s%s", (unsigned long long)f->accepted, ring,
           (unsigned long long)vlff_tum_feed_refused(f), line, resets);
}

/* One line of len bytes in (line[len] is a NUL); writes its record when
 * accepted. */
static void feed(struct vlff_tum_feed *f, struct vlff_ring *ring, struct reporter *rp, const char *where,
                 const char *line, size_t len) {
  struct vlff_pose_rec rec;
  char why[512];
  uint64_t resets = f->resets;
  int r = vlff_tum_feed_buf(f, line, len, vlff_now_ns(), &rec, why, sizeof why);
  if (f->resets != resets)
    vlff_warn_limited(&rp->resets, TAG,
                      "%s: %u lines in a row were older than the last accepted stamp %.9f: the tracker restarted "
                      "or a line got in ahead of it; the order restarts at this line's %.9f",
                      where, f->p.out_of_order_reset, (double)f->reset_from_t_ns * 1e-9,
                      (double)f->last_t_ns * 1e-9);
  if (r == VLFF_TUM_OK) {
    if (vlff_ring_write(ring, &rec, sizeof rec) != 0)
      VLFF_ERROR(TAG, "%s: pose ring write: %s", VLFF_Q(where), strerror(errno));
  } else if (r != VLFF_TUM_SKIP) {
    report_refusal(rp, where, r, why);
  }
}

/* Lines from a file or a pipe. poll(2) and read(2) rather than stdio's
 * blocking getline, so that the loop comes round while no input arrives and
 * feeds the watchdog; a line of LINE_MAX_BYTES or more is refused as a whole
 * and counted (it is no TUM line, and holding it would let a stream without
 * newlines take all memory). A line holding a NUL is refused (tum.h). */
static int read_stream(int fd, struct vlff_tum_feed *f, struct vlff_ring *ring, struct reporter *rp,
                       struct vlff_service *svc) {
  static char buf[LINE_MAX_BYTES + 1];
  size_t len = 0;
  unsigned long lineno = 0;
  bool eof = false, skipping = false;
  int bad = 0;
  while (!vlff_cli_stop && !eof) {
    if (vlff_service_watchdog_due(svc, vlff_now_ns())) vlff_service_watchdog();
    struct pollfd pfd = {.fd = fd, .events = POLLIN};
    int pr = poll(&pfd, 1, WAIT_MS);
    if (pr < 0 && errno != EINTR) {
      VLFF_ERROR(TAG, "%s: poll: %s", VLFF_Q(rp->name), strerror(errno));
      bad = 1;
      break;
    }
    if (pr <= 0) continue;
    ssize_t n = read(fd, buf + len, LINE_MAX_BYTES - len);
    if (n < 0) {
      if (errno == EINTR || errno == EAGAIN) continue;
      VLFF_ERROR(TAG, "%s: read error: %s", VLFF_Q(rp->name), strerror(errno));
      bad = 1;
      break;
    }
    if (n == 0) eof = true;
    len += (size_t)n;
    size_t start = 0;
    char *nl;
    while ((nl = memchr(buf + start, '\n', len - start))) {
      *nl = 0;
      lineno++;
      if (!skipping) {
        char where[300];
        snprintf(where, sizeof where, "%s:%lu", rp->name, lineno);
        feed(f, ring, rp, where, buf + start, (size_t)(nl - (buf + start)));
      }
      skipping = false;
      start = (size_t)(nl - buf) + 1;
    }
    if (eof && start < len && !skipping) { /* a last line without its newline */
      buf[len] = 0;
      char where[300];
      snprintf(where, sizeof where, "%s:%lu", rp->name, ++lineno);
      feed(f, ring, rp, where, buf + start, len - start);
      start = len;
    }
    memmove(buf, buf + start, len - start);
    len -= start;
    if (len == LINE_MAX_BYTES) {
      if (!skipping) { /* refused and counted once; the rest of it, up to its newline, is dropped */
        char where[300];
        snprintf(where, sizeof where, "%s:%lu", rp->name, lineno + 1);
        buf[len] = 0;
        feed(f, ring, rp, where, buf, len);
      }
      skipping = true;
      len = 0;
    }
  }
  return bad;
}

/* A port as written: decimal digits, 1..65535 (getaddrinfo takes 99999 and
 * binds it modulo 65536, while the log says 99999). */
static bool port_ok(const char *p) {
  if (!*p || strlen(p) > 5) return false;
  long v = 0;
  for (; *p; p++) {
    if (*p < '0' || *p > '9') return false;
    v = v * 10 + (*p - '0');
  }
  return v >= 1 && v <= 65535;
}

/* "host:port", "[v6]:port" or ":port" (every address). */
static int open_udp(const char *spec, char *err, size_t errlen) {
  char host[256];
  const char *colon = strrchr(spec, ':');
  if (!colon || !colon[1]) return snprintf(err, errlen, "udp '%.200s': expected ADDR:PORT", spec), -1;
  if (!port_ok(colon + 1)) return snprintf(err, errlen, "udp '%.200s': port '%.20s' is not 1..65535", spec, colon + 1), -1;
  size_t hl = (size_t)(colon - spec);
  if (hl >= sizeof host) return snprintf(err, errlen, "udp '%.200s': address too long", spec), -1;
  memcpy(host, spec, hl);
  host[hl] = 0;
  if (hl >= 2 && host[0] == '[' && host[hl - 1] == ']') {
    memmove(host, host + 1, hl - 2);
    host[hl - 2] = 0;
  }
  struct addrinfo hints = {.ai_family = AF_UNSPEC, .ai_socktype = SOCK_DGRAM, .ai_flags = AI_PASSIVE}, *res;
  int rc = getaddrinfo(host[0] ? host : NULL, colon + 1, &hints, &res);
  if (rc) return snprintf(err, errlen, "udp '%.200s': %s", spec, gai_strerror(rc)), -1;
  int s = -1;
  for (struct addrinfo *a = res; a; a = a->ai_next) {
    s = socket(a->ai_family, a->ai_socktype | SOCK_CLOEXEC, a->ai_protocol);
    if (s < 0) continue;
    if (bind(s, a->ai_addr, a->ai_addrlen) == 0) break;
    snprintf(err, errlen, "udp '%.200s': bind: %s", spec, strerror(errno));
    close(s);
    s = -1;
  }
  freeaddrinfo(res);
  return s;
}

/* The one sender a UDP source takes datagrams from (pose.udp_peer). */
struct peer {
  int set;
  int family;              /* AF_INET or AF_INET6 */
  unsigned char addr[16];  /* 4 or 16 bytes */
  int port;                /* 0: any port of that address */
  char text[80];
};

/* A sender's address as AF_INET for IPv4 (also when a dual-stack socket
 * reports it IPv4-mapped) or AF_INET6; its port; returns its family. */
static int sender_of(const struct sockaddr_storage *ss, unsigned char addr[16], int *port) {
  if (ss->ss_family == AF_INET) {
    const struct sockaddr_in *a = (const struct sockaddr_in *)ss;
    memcpy(addr, &a->sin_addr, 4);
    *port = ntohs(a->sin_port);
    return AF_INET;
  }
  if (ss->ss_family == AF_INET6) {
    const struct sockaddr_in6 *a = (const struct sockaddr_in6 *)ss;
    *port = ntohs(a->sin6_port);
    if (IN6_IS_ADDR_V4MAPPED(&a->sin6_addr)) {
      memcpy(addr, a->sin6_addr.s6_addr + 12, 4);
      return AF_INET;
    }
    memcpy(addr, &a->sin6_addr, 16);
    return AF_INET6;
  }
  return AF_UNSPEC;
}

/* "ADDR", "ADDR:PORT", "[V6]", "[V6]:PORT" or a bare IPv6 address, numeric
 * only (a name would be resolved once, and could change under us). */
static int parse_peer(const char *spec, struct peer *pr, char *err, size_t errlen) {
  char host[128] = "", port[16] = "";
  const char *colon = strchr(spec, ':');
  size_t hl;
  if (spec[0] == '[') {
    const char *close = strchr(spec, ']');
    if (!close || (close[1] && close[1] != ':')) return snprintf(err, errlen, "udp peer '%.200s': expected [ADDR]:PORT", spec), -1;
    hl = (size_t)(close - spec - 1);
    if (hl >= sizeof host) return snprintf(err, errlen, "udp peer '%.200s': address too long", spec), -1;
    memcpy(host, spec + 1, hl);
    if (close[1] == ':') snprintf(port, sizeof port, "%.15s", close + 2);
    if (close[1] == ':' && !port[0]) return snprintf(err, errlen, "udp peer '%.200s': empty port", spec), -1;
  } else if (colon && !strchr(colon + 1, ':')) { /* one colon: ADDR:PORT */
    hl = (size_t)(colon - spec);
    if (hl >= sizeof host || strlen(colon + 1) >= sizeof port)
      return snprintf(err, errlen, "udp peer '%.200s': too long", spec), -1;
    memcpy(host, spec, hl);
    strcpy(port, colon + 1);
    if (!port[0]) return snprintf(err, errlen, "udp peer '%.200s': empty port", spec), -1;
  } else { /* no colon, or a bare IPv6 address */
    if (strlen(spec) >= sizeof host) return snprintf(err, errlen, "udp peer '%.200s': address too long", spec), -1;
    strcpy(host, spec);
  }
  struct addrinfo hints = {.ai_family = AF_UNSPEC, .ai_socktype = SOCK_DGRAM,
                           .ai_flags = AI_NUMERICHOST | AI_NUMERICSERV}, *res;
  if (port[0] && !port_ok(port))
    return snprintf(err, errlen, "udp peer '%.200s': port '%s' is not 1..65535", spec, port), -1;
  int rc = getaddrinfo(host, port[0] ? port : NULL, &hints, &res);
  if (rc) return snprintf(err, errlen, "udp peer '%.200s': expected a numeric address, [:port]: %s", spec, gai_strerror(rc)), -1;
  struct sockaddr_storage ss = {0};
  memcpy(&ss, res->ai_addr, res->ai_addrlen < sizeof ss ? res->ai_addrlen : sizeof ss);
  freeaddrinfo(res);
  memset(pr, 0, sizeof *pr);
  pr->family = sender_of(&ss, pr->addr, &pr->port);
  if (pr->family == AF_UNSPEC) return snprintf(err, errlen, "udp peer '%.200s': not an IP address", spec), -1;
  if (port[0] && pr->port == 0) return snprintf(err, errlen, "udp peer '%.200s': port 0", spec), -1;
  pr->set = 1;
  snprintf(pr->text, sizeof pr->text, "%.79s", spec);
  return 0;
}

static int peer_matches(const struct peer *pr, const struct sockaddr_storage *ss, char *from, size_t fromlen) {
  unsigned char addr[16] = {0};
  int port = 0;
  int fam = sender_of(ss, addr, &port);
  char a[INET6_ADDRSTRLEN] = "?";
  if (fam != AF_UNSPEC) inet_ntop(fam, addr, a, sizeof a);
  snprintf(from, fromlen, fam == AF_INET6 ? "[%s]:%d" : "%s:%d", a, port);
  return fam == pr->family && !memcmp(addr, pr->addr, fam == AF_INET ? 4 : 16) && (!pr->port || port == pr->port);
}

static int read_udp(int sock, const struct peer *peer, struct vlff_tum_feed *f, struct vlff_ring *ring,
                    struct reporter *rp, struct vlff_service *svc) {
  static char buf[LINE_MAX_BYTES + 1];
  unsigned long dgram = 0;
  while (!vlff_cli_stop) {
    if (vlff_service_watchdog_due(svc, vlff_now_ns())) vlff_service_watchdog();
    struct pollfd pfd = {.fd = sock, .events = POLLIN};
    int pr = poll(&pfd, 1, WAIT_MS);
    if (pr < 0 && errno != EINTR) return VLFF_ERROR(TAG, "udp: poll: %s", strerror(errno)), 1;
    if (pr <= 0) continue;
    struct sockaddr_storage from;
    socklen_t fromlen = sizeof from;
    /* MSG_TRUNC: n is the datagram's whole size, so that one too big for
     * the buffer is refused, not read in part. */
    ssize_t n = recvfrom(sock, buf, LINE_MAX_BYTES, MSG_TRUNC, (struct sockaddr *)&from, &fromlen);
    if (n < 0) {
      if (errno == EINTR || errno == EAGAIN) continue;
      return VLFF_ERROR(TAG, "udp: recv: %s", strerror(errno)), 1;
    }
    dgram++;
    char where[160], sender[80];
    int ours = peer_matches(peer, &from, sender, sizeof sender);
    if (peer->set && !ours) {
      char why[160];
      snprintf(why, sizeof why, "the source takes datagrams from %s only (pose.udp_peer)", peer->text);
      snprintf(where, sizeof where, "udp datagram %lu from %s", dgram, sender);
      vlff_tum_feed_count(f, VLFF_TUM_FOREIGN);
      report_refusal(rp, where, VLFF_TUM_FOREIGN, why);
      continue;
    }
    if ((size_t)n >= LINE_MAX_BYTES) {
      snprintf(where, sizeof where, "udp datagram %lu", dgram);
      buf[LINE_MAX_BYTES] = 0;
      feed(f, ring, rp, where, buf, LINE_MAX_BYTES);
      continue;
    }
    buf[n] = 0;
    const char *nul = memchr(buf, 0, (size_t)n);
    if (nul) {
      /* Refused whole: the lines after the NUL would otherwise be lost
       * without a word, and a datagram is one message. */
      char why[96];
      snprintf(why, sizeof why, "a NUL byte at offset %zu of its %zd bytes (not text)", (size_t)(nul - buf), n);
      snprintf(where, sizeof where, "udp datagram %lu", dgram);
      vlff_tum_feed_count(f, VLFF_TUM_NUL);
      report_refusal(rp, where, VLFF_TUM_NUL, why);
      continue;
    }
    /* A datagram holds one line or several. */
    unsigned long lineno = 0;
    for (char *save = NULL, *l = strtok_r(buf, "\n", &save); l; l = strtok_r(NULL, "\n", &save)) {
      snprintf(where, sizeof where, "udp datagram %lu line %lu", dgram, ++lineno);
      feed(f, ring, rp, where, l, strlen(l));
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

/* Command-line values; each one set overrides its pose.* key. */
struct overrides {
  const char *ring, *udp, *udp_peer;
  int clock, stamp, extra_fields, quiet; /* -1 = from the config */
  double clock_offset_s, latency_s, quat_tolerance, source_id; /* NAN = from the config */
  double future_tolerance_s, out_of_order_reset;               /* NAN = from the config */
  int have_extrinsic;
  double extrinsic[7];
};

static int parse_options(int argc, char **argv, struct overrides *o, const char **config_path, int *status) {
  enum { OPT_CLOCK = 256, OPT_OFFSET, OPT_HOST, OPT_LATENCY, OPT_EXTRINSIC, OPT_QTOL, OPT_SOURCE, OPT_EXTRA,
         OPT_PEER, OPT_FUTURE, OPT_RESET };
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
      {"udp-peer", required_argument, NULL, OPT_PEER},
      {"future-tolerance", required_argument, NULL, OPT_FUTURE},
      {"out-of-order-reset", required_argument, NULL, OPT_RESET},
      {"quiet", no_argument, NULL, 'q'},
      VLFF_CLI_COMMON_OPTIONS,
  };
  int c;
  double v;
  while ((c = vlff_cli_next(&cli, argc, argv, "c:r:u:q", opts, status)) != -1) {
    switch (c) {
    case VLFF_CLI_EXIT: return -1;
    case 'c': *config_path = optarg; break;
    case 'r': o->ring = optarg; break;
    case 'u': o->udp = optarg; break;
    case 'q': o->quiet = 1; break;
    case OPT_HOST: o->stamp = VLFF_POSE_STAMP_HOST; break;
    case OPT_EXTRA: o->extra_fields = 1; break;
    case OPT_PEER: o->udp_peer = optarg; break;
    case OPT_FUTURE:
      if (parse_double(optarg, 0, 1e10, &o->future_tolerance_s))
        return *status = vlff_cli_usage_error(&cli, "--future-tolerance '%s': expected seconds, 0 for no check",
                                              optarg), -1;
      break;
    case OPT_RESET:
      if (parse_double(optarg, 0, 1000000, &v) || v != floor(v))
        return *status = vlff_cli_usage_error(&cli, "--out-of-order-reset '%s': expected lines in [0, 1000000]",
                                              optarg), -1;
      o->out_of_order_reset = v;
      break;
    case OPT_CLOCK:
      if (!strcmp(optarg, "monotonic")) o->clock = VLFF_POSE_CLOCK_MONOTONIC;
      else if (!strcmp(optarg, "realtime")) o->clock = VLFF_POSE_CLOCK_REALTIME;
      else return *status = vlff_cli_usage_error(&cli, "--clock '%s': expected monotonic or realtime", optarg), -1;
      break;
    case OPT_OFFSET:
      if (parse_double(optarg, -1e10, 1e10, &o->clock_offset_s))
        return *status = vlff_cli_usage_error(&cli, "--clock-offset '%s': expected seconds", optarg), -1;
      break;
    case OPT_LATENCY:
      if (parse_double(optarg, 0, 60, &o->latency_s))
        return *status = vlff_cli_usage_error(&cli, "--latency '%s': expected seconds in [0, 60]", optarg), -1;
      break;
    case OPT_QTOL:
      if (parse_double(optarg, 0, 0.5, &o->quat_tolerance))
        return *status = vlff_cli_usage_error(&cli, "--quat-tolerance '%s': expected a number in [0, 0.5]", optarg), -1;
      break;
    case OPT_SOURCE:
      if (parse_double(optarg, 0, 2147483647, &v) || v != floor(v))
        return *status = vlff_cli_usage_error(&cli, "--source-id '%s': expected a non-negative integer", optarg), -1;
      o->source_id = v;
      break;
    case OPT_EXTRINSIC: {
      struct vlff_tum_sample s;
      char line[512], why[256];
      snprintf(line, sizeof line, "0 %s", optarg);
      double n = 0;
      if (vlff_tum_parse(line, 0, &s, why, sizeof why) == VLFF_TUM_OK)
        n = sqrt(s.q[0] * s.q[0] + s.q[1] * s.q[1] + s.q[2] * s.q[2] + s.q[3] * s.q[3]);
      if (!(fabs(n - 1) <= 0.01))
        return *status = vlff_cli_usage_error(&cli, "--extrinsic '%s': expected \"tx ty tz qx qy qz qw\" with a unit "
                                              "quaternion", optarg), -1;
      /* the camera on the tracker's body: pose.extrinsic's bound */
      if (!(fabs(s.p[0]) <= 1e4 && fabs(s.p[1]) <= 1e4 && fabs(s.p[2]) <= 1e4))
        return *status = vlff_cli_usage_error(&cli, "--extrinsic '%s': translation beyond 1e4 m", optarg), -1;
      memcpy(o->extrinsic, s.p, 3 * sizeof(double));
      memcpy(o->extrinsic + 3, s.q, 4 * sizeof(double));
      o->have_extrinsic = 1;
      break;
    }
    default: return *status = vlff_cli_usage_error(&cli, "option '%s' not handled", argv[optind - 1]), -1;
    }
  }
  if (optind + 1 < argc || (o->udp && optind < argc))
    return *status = vlff_cli_usage_error(&cli, "unexpected argument '%s'", argv[o->udp ? optind : optind + 1]), -1;
  return 0;
}

int main(int argc, char **argv) {
  struct overrides o = {.clock = -1, .stamp = -1, .extra_fields = -1, .clock_offset_s = NAN, .latency_s = NAN,
                        .quat_tolerance = NAN, .source_id = NAN, .future_tolerance_s = NAN,
                        .out_of_order_reset = NAN};
  const char *config_path = NULL;
  int status = 0;
  if (parse_options(argc, argv, &o, &config_path, &status)) return status;
  const char *file = optind < argc ? argv[optind] : NULL;

  static struct vlff_config cfg;
  char err[1024];
  config_path = vlff_config_find(config_path, err, sizeof err);
  if (!config_path) return vlff_cli_error(&cli, "%s", err);
  if (vlff_config_load(config_path, &cfg, err, sizeof err)) return vlff_cli_config_error(err);
  /* The options override the config's pose.* keys. */
  const struct vlff_config *k = &cfg;
  const char *ring_name = o.ring ? o.ring : k->shm.pose_ring;
  /* A FILE operand ("-": standard input) wins over the config's pose.udp. */
  const char *udp = o.udp ? o.udp : !file && k->pose.udp[0] ? k->pose.udp : NULL;
  int realtime = (o.clock >= 0 ? o.clock : k->pose.clock) == VLFF_POSE_CLOCK_REALTIME;
  double offset_s = isnan(o.clock_offset_s) ? k->pose.clock_offset_s : o.clock_offset_s;
  double latency_s = isnan(o.latency_s) ? k->pose.latency_s : o.latency_s;
  const double *ext = o.have_extrinsic ? o.extrinsic : k->pose.extrinsic;
  struct vlff_tum_feed_params fp = {
      .stamp = (o.stamp >= 0 ? o.stamp : k->pose.stamp) == VLFF_POSE_STAMP_HOST ? VLFF_TUM_STAMP_HOST
                                                                                : VLFF_TUM_STAMP_SOURCE,
      .quat_tolerance = isnan(o.quat_tolerance) ? k->pose.quat_tolerance : o.quat_tolerance,
      .source_id = (uint32_t)(isnan(o.source_id) ? k->pose.source_id : o.source_id),
      .extra_fields = o.extra_fields >= 0 ? o.extra_fields : k->pose.extra_fields,
      .latency_ns = (int64_t)llround(latency_s * 1e9),
      .clock_offset_ns = (int64_t)llround(offset_s * 1e9),
      .future_tolerance_ns =
          (int64_t)llround((isnan(o.future_tolerance_s) ? k->pose.future_tolerance_s : o.future_tolerance_s) * 1e9),
      .out_of_order_reset =
          (uint32_t)(isnan(o.out_of_order_reset) ? k->pose.out_of_order_reset : o.out_of_order_reset),
  };
  const char *peer_spec = o.udp_peer ? o.udp_peer : k->pose.udp_peer;
  struct peer peer = {0};
  if (udp && peer_spec[0] && parse_peer(peer_spec, &peer, err, sizeof err)) return vlff_cli_error(&cli, "%s", err);
  vlff_log_set_level(o.quiet > 0 ? VLFF_LOG_WARN : (enum vlff_log_level)cfg.node.log_level);
  if (realtime) {
    /* UNIX-time stamps onto the node's clock. Read back to back once, a
     * preemption between the two reads (0.46 s in a loaded CI run) put
     * every later line that far ahead, refused as a clock error. */
    fp.clock_offset_ns += vlff_mono_minus_wall_ns();
  }
  /* Both ways in checked it: the option above, the config's cross-check. */
  double qn = sqrt(ext[3] * ext[3] + ext[4] * ext[4] + ext[5] * ext[5] + ext[6] * ext[6]);
  double q[4] = {ext[3] / qn, ext[4] / qn, ext[5] / qn, ext[6] / qn};
  vlff_tum_matrix(ext, q, fp.body_to_camera);
  struct vlff_tum_feed f;
  if (vlff_tum_feed_init(&f, &fp, err, sizeof err)) return vlff_cli_error(&cli, "%s", err);

  FILE *in = NULL;
  int sock = -1;
  if (udp) {
    sock = open_udp(udp, err, sizeof err);
    if (sock < 0) return vlff_cli_error(&cli, "%s", err);
  } else if (file && strcmp(file, "-")) {
    in = fopen(file, "r");
    if (!in) return vlff_cli_error(&cli, "%s: cannot open: %s", file, strerror(errno));
  } else {
    in = stdin;
  }
  struct vlff_ring_params rp = {.record_kind = VLFF_RECORD_POSE, .slots = (uint32_t)cfg.shm.pose_slots,
                                .slot_size = sizeof(struct vlff_pose_rec),
                                .perm = {.mode = (mode_t)cfg.shm.mode, .group = cfg.shm.group}};
  struct vlff_ring *ring = vlff_ring_create(ring_name, &rp);
  if (!ring) {
    int rc = vlff_cli_error(&cli, "pose ring %s: %s", ring_name, vlff_shm_last_message());
    if (in && in != stdin) fclose(in);
    if (sock >= 0) close(sock);
    return rc;
  }

  vlff_cli_catch_stop();

  struct reporter rep = {.name = udp ? "udp" : in == stdin ? "stdin" : file};
  char from[120] = "";
  if (udp)
    snprintf(from, sizeof from, peer.set ? " (from %s only)" : " (from any sender: UDP has no authentication, "
                                                                "pose.udp_peer binds one)%s",
             peer.set ? peer.text : "");
  VLFF_INFO(TAG, "vlff-pose %s: %s%s -> pose ring %s (%d slots), stamps %s%s", vlff_version(), udp ? udp : rep.name,
            from, ring_name, cfg.shm.pose_slots,
            fp.stamp == VLFF_TUM_STAMP_HOST ? "at receipt" : realtime ? "UNIX time" : "CLOCK_MONOTONIC",
            fp.stamp == VLFF_TUM_STAMP_HOST || offset_s == 0 ? "" : " plus the clock offset");
  /* Type=notify: ready once the ring exists (the node may attach; poses come
   * when the tracker sends them). The watchdog is fed from the input loop,
   * which comes round every WAIT_MS with or without input: only a hang stops
   * it. */
  struct vlff_service svc;
  vlff_service_ready(&svc);
  int rc = udp ? read_udp(sock, &peer, &f, ring, &rep, &svc) : read_stream(fileno(in), &f, ring, &rep, &svc);
  vlff_service_stopping();
  summary(&f, ring_name);
  if (in && in != stdin) fclose(in);
  if (sock >= 0) close(sock);
  vlff_ring_close(ring);
  return rc;
}
