/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * vlff-record: the node's inputs (every record of the frame, pose and feature
 * rings) written losslessly to an MCAP file (inputs.h's channels), which
 * vlff-replay plays back into the rings.
 *
 * A program of its own rather than a mode of vlff-view: the viewer decimates
 * and compresses what it shows, and a recorder of everything must not share a
 * process (or a stall) with it. It is one more ring reader: readers are
 * lock-free and invisible to the producers, so recording never slows or blocks
 * a camera, the pose source, the extractor or the node. A recorder that falls
 * behind (a slow disk) is lapped by the producer: the records it missed are
 * counted by the ring (vlff_ring_lost), logged as they happen and reported at
 * the end; what it did read is written whole.
 *
 * Each ring is attached when it appears (a producer started after the
 * recorder), from its oldest record still held, and again when its producer
 * replaces it; a pose or feature ring not attached yet is looked for again as
 * soon as the frame ring's first frame is read, since a producer makes its
 * rings before its first frame (a feature ring found 100 ms late had lost the
 * maps of the first frames a fast replay wrote), and every 100 ms after. Each
 * frame is written after the poses committed before it was
 * read and before the feature maps committed after, the order in which the
 * live processes produce a frame's records, so the file's order is the order
 * the node saw them in.
 */
#include <errno.h>
#include <getopt.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>

#include "cli.h"
#include "clock.h"
#include "config.h"
#include "inputs.h"
#include "mcap.h"
#include "vlff/escape.h"
#include "vlff/shm.h"

static const struct vlff_cli cli = {
    "vlff-record",
    "Usage: vlff-record [OPTIONS] FILE.mcap\n"
    "Record the node's inputs, every record of the frame, pose and feature rings, to\n"
    "an MCAP file that vlff-replay plays back into the rings (docs/replay.md).\n"
    "\n"
    "  -c, --config FILE      ring names from FILE's shm section (else $VLFF_CONFIG,\n"
    "                         else the installed vlff.yaml, else built-in defaults)\n"
    "  -f, --force            replace FILE if it exists\n"
    "      --no-features      do not record the feature ring\n"
    "      --no-poses         do not record the pose ring\n"
    "  -n, --count N          stop after N frames\n"
    "      --zstd LEVEL       chunk compression, 0 (none) to 19 (default 1)\n"
    "  -q, --quiet            no progress lines\n"
    "  -V, --version          print the version and exit\n"
    "  -h, --help             print this help and exit\n"
    "\n"
    "Stops on SIGINT or SIGTERM (reading what the rings still hold first), or after\n"
    "--count frames, and closes the file with its index and summary.\n"
    "\n"
    "Exit status: 0 when the file was written (records the recorder missed are\n"
    "reported on stderr), 1 when it could not be, 2 for a bad command line.\n"
    "\n"
    "Examples:\n"
    "  vlff-record -c /etc/vlff/vlff.yaml /data/run1.mcap\n"
    "  vlff-record -c node.yaml --count 300 --no-features poses-and-frames.mcap\n",
};

enum { R_POSE, R_FRAME, R_FEAT, R_COUNT };
static const char *const ring_what[R_COUNT] = {"pose", "frame", "feature"};
static const uint32_t ring_kind[R_COUNT] = {VLFF_RECORD_POSE, VLFF_RECORD_FRAME, VLFF_RECORD_FEATURE};

struct src {
  const char *name;
  int wanted;
  struct vlff_ring *ring;
  void *buf;
  size_t cap;
  uint64_t records, lost_said, bad, last_try;
};

struct rec {
  struct vlff_mcap_writer *w;
  struct src s[R_COUNT];
  char *scratch;
  size_t scratch_cap;
  int quiet;
  uint64_t lost_prev; /* rings replaced: what their old handles had lost */
  size_t held_len;    /* a feature map read and kept for after its frame (in the ring's buffer) */
  uint64_t held_seq;
  int looked_at_first; /* the pose and feature rings were looked for at the frame ring's first frame */
};

/* Attaches ring i when it exists, trying at most every 100 ms unless forced. */
static void attach(struct rec *r, int i, uint64_t now, int force) {
  struct src *s = &r->s[i];
  if (!s->wanted || s->ring || (!force && s->last_try && now - s->last_try < 100000000ull)) return;
  s->last_try = now;
  s->ring = vlff_ring_attach(s->name, ring_kind[i]);
  if (!s->ring) return;
  vlff_ring_seek_oldest(s->ring); /* what the producer wrote before the recorder came */
  size_t cap = vlff_ring_slot_size(s->ring);
  if (cap > s->cap) {
    void *b = realloc(s->buf, cap);
    if (!b) {
      fprintf(stderr, "vlff-record: out of memory for %s ring records of %zu bytes\n", ring_what[i], cap);
      vlff_ring_close(s->ring);
      s->ring = NULL;
      return;
    }
    s->buf = b, s->cap = cap;
  }
  if (i == R_FRAME) r->looked_at_first = 0; /* a new frame ring: its first frame is to come */
  if (!r->quiet) fprintf(stderr, "vlff-record: recording the %s ring %s\n", ring_what[i], VLFF_Q(s->name));
}

/* The next record of ring i into its buffer, waiting up to timeout_ns: its
 * length, or 0 when there is none (the ring replaced: attached again later). */
static ssize_t read_one(struct rec *r, int i, uint64_t timeout_ns, uint64_t *seq) {
  struct src *s = &r->s[i];
  if (!s->ring) return 0;
  struct vlff_ring_view v;
  ssize_t n = vlff_ring_read_copy(s->ring, s->buf, s->cap, &v, timeout_ns);
  uint64_t lost = vlff_ring_lost(s->ring);
  if (lost > s->lost_said) {
    fprintf(stderr, "vlff-record: fell behind the %s ring: %llu records missed so far\n", ring_what[i],
            (unsigned long long)lost);
    s->lost_said = lost;
  }
  if (n < 0) {
    if (errno == EPIPE) { /* the producer replaced the ring: attach the new one */
      fprintf(stderr, "vlff-record: the %s ring %s was replaced: attaching again\n", ring_what[i], VLFF_Q(s->name));
      r->lost_prev += vlff_ring_lost(s->ring);
      vlff_ring_close(s->ring);
      s->ring = NULL;
      s->lost_said = 0;
      s->last_try = 0;
    }
    return 0; /* EAGAIN, ETIMEDOUT, EINTR */
  }
  *seq = v.seq;
  return n;
}

/* Writes the record of ring i read into its buffer. -1 when the file cannot be
 * written; a record its producer got wrong is named and counted. */
static int write_one(struct rec *r, int i, size_t n, uint64_t seq) {
  struct src *s = &r->s[i];
  char why[512];
  int rc;
  if (i == R_POSE) {
    const struct vlff_pose_rec *p = s->buf;
    rc = n >= sizeof *p ? vlff_in_write_pose(r->w, p->t_ns, p->pose, why, sizeof why)
                        : (snprintf(why, sizeof why, "a pose record of %zu bytes", n), -1);
  } else if (i == R_FRAME) {
    rc = vlff_in_write_frame(r->w, s->buf, n, &r->scratch, &r->scratch_cap, why, sizeof why);
  } else {
    rc = vlff_in_write_features(r->w, s->buf, n, &r->scratch, &r->scratch_cap, why, sizeof why);
  }
  if (rc < 0) {
    if (vlff_mcap_writer_error(r->w)) {
      fprintf(stderr, "vlff-record: %s\n", why);
      return -1;
    }
    s->bad++; /* a record its producer got wrong: the node refuses it too */
    fprintf(stderr, "vlff-record: %s ring record %llu not recorded: %s\n", ring_what[i], (unsigned long long)seq,
            why);
    return 0;
  }
  s->records++;
  return 0;
}

/* Writes every record ring i holds now. */
static int drain(struct rec *r, int i) {
  uint64_t seq;
  ssize_t n;
  while ((n = read_one(r, i, 0, &seq)) > 0)
    if (write_one(r, i, (size_t)n, seq) < 0) return -1;
  return 0;
}

/* Writes the feature maps the ring holds now (all), or only those of frames
 * stamped before limit_ns, the first later one kept for after its frame. */
static int drain_features(struct rec *r, int all, uint64_t limit_ns) {
  struct src *s = &r->s[R_FEAT];
  if (r->held_len) {
    if (!all && ((const struct vlff_feature_hdr *)s->buf)->t_host_ns >= limit_ns) return 0;
    size_t n = r->held_len;
    r->held_len = 0;
    if (write_one(r, R_FEAT, n, r->held_seq) < 0) return -1;
  }
  uint64_t seq;
  ssize_t n;
  while ((n = read_one(r, R_FEAT, 0, &seq)) > 0) {
    if (!all && (size_t)n >= sizeof(struct vlff_feature_hdr) &&
        ((const struct vlff_feature_hdr *)s->buf)->t_host_ns >= limit_ns) {
      r->held_len = (size_t)n, r->held_seq = seq; /* its frame is the one being written, or a later one */
      return 0;
    }
    if (write_one(r, R_FEAT, (size_t)n, seq) < 0) return -1;
  }
  return 0;
}

/* The frames, waiting up to timeout_ns for the first. Each is written after
 * the feature maps of earlier frames and the poses committed before it was
 * read, and before its own feature map: the order in which a pose source, a
 * camera and an extractor commit a frame's records, which the node's pose
 * lookup relies on when the recording is played. Stops at count frames (0: no
 * limit). */
static int frames_step(struct rec *r, uint64_t timeout_ns, long long *frames, long long count) {
  for (;;) {
    if (count > 0 && *frames >= count) return 0;
    uint64_t seq;
    ssize_t n = read_one(r, R_FRAME, timeout_ns, &seq);
    timeout_ns = 0;
    int framed = n >= (ssize_t)sizeof(struct vlff_frame_hdr);
    uint64_t t = framed ? ((const struct vlff_frame_hdr *)r->s[R_FRAME].buf)->t_host_ns : 0;
    /* the maps of earlier frames, then the poses, the frame, its own map */
    if (framed && !r->looked_at_first) {
      /* A producer makes its rings before it writes its first frame: one not
       * attached yet exists now, and what it holds of this frame is kept.
       * Once per frame ring: a recording without an extractor would
       * otherwise look for its feature ring at every frame. */
      uint64_t now = vlff_now_ns();
      attach(r, R_POSE, now, 1);
      attach(r, R_FEAT, now, 1);
      r->looked_at_first = 1;
    }
    if (drain_features(r, !framed, t) < 0 || drain(r, R_POSE) < 0) return -1;
    if (n > 0) {
      uint64_t before = r->s[R_FRAME].records;
      if (write_one(r, R_FRAME, (size_t)n, seq) < 0) return -1;
      if (r->s[R_FRAME].records > before) {
        ++*frames;
        if (!r->quiet && *frames % 300 == 0)
          fprintf(stderr, "vlff-record: %lld frames, %llu bytes\n", *frames,
                  (unsigned long long)vlff_mcap_writer_bytes(r->w));
      }
    }
    /* with no frame left to read, every map's frame has been read (an extractor
     * reads a frame before it publishes the frame's map) */
    if (framed ? drain_features(r, t == UINT64_MAX, t + 1) < 0 : drain_features(r, 1, 0) < 0) return -1;
    if (n <= 0) return 0;
  }
}

static int parse_count(const char *opt, const char *v, long long lo, long long hi, long long *out) {
  char *end;
  errno = 0;
  long long x = strtoll(v, &end, 10);
  if (!*v || *end || errno || x < lo || x > hi)
    return vlff_cli_usage_error(&cli, "%s: expected an integer in [%lld, %lld], got '%s'", opt, lo, hi, v);
  *out = x;
  return 0;
}

int main(int argc, char **argv) {
  enum { OPT_NO_FEATURES = 256, OPT_NO_POSES, OPT_ZSTD };
  static const struct option opts[] = {
      {"config", required_argument, NULL, 'c'}, {"force", no_argument, NULL, 'f'},
      {"no-features", no_argument, NULL, OPT_NO_FEATURES}, {"no-poses", no_argument, NULL, OPT_NO_POSES},
      {"count", required_argument, NULL, 'n'}, {"zstd", required_argument, NULL, OPT_ZSTD},
      {"quiet", no_argument, NULL, 'q'}, VLFF_CLI_COMMON_OPTIONS,
  };
  struct rec r;
  memset(&r, 0, sizeof r);
  const char *config = NULL;
  int force = 0, features = 1, poses = 1, c, cli_status;
  long long count = 0, zstd = 1;
  while ((c = vlff_cli_next(&cli, argc, argv, "c:fn:q", opts, &cli_status)) != -1) {
    switch (c) {
    case VLFF_CLI_EXIT: return cli_status;
    case 'c': config = optarg; break;
    case 'f': force = 1; break;
    case OPT_NO_FEATURES: features = 0; break;
    case OPT_NO_POSES: poses = 0; break;
    case 'n':
      if (parse_count("--count", optarg, 1, (long long)1e15, &count)) return 2;
      break;
    case OPT_ZSTD:
      if (parse_count("--zstd", optarg, 0, 19, &zstd)) return 2;
      break;
    case 'q': r.quiet = 1; break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", argv[optind - 1]);
    }
  }
  if (optind >= argc) return vlff_cli_usage_error(&cli, "no FILE given");
  if (optind < argc - 1) return vlff_cli_usage_error(&cli, "one FILE only, got also '%s'", argv[optind + 1]);
  const char *path = argv[optind];
  struct stat st;
  if (!force && lstat(path, &st) == 0)
    return vlff_cli_error(&cli, "%s exists (--force replaces it)", VLFF_Q(path));
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  char err[1024], ferr[512];
  const char *cpath = vlff_config_find(config, ferr, sizeof ferr);
  if (cpath && vlff_config_load(cpath, &cfg, err, sizeof err) < 0) return vlff_cli_config_error(err);
  if (!cpath)
    fprintf(stderr, "vlff-record: %s; using the default ring names (%s, %s, %s)\n", ferr, VLFF_Q(cfg.shm.ring),
            VLFF_Q(cfg.shm.pose_ring), VLFF_Q(cfg.shm.feature_ring));
  r.s[R_POSE] = (struct src){.name = cfg.shm.pose_ring, .wanted = poses};
  r.s[R_FRAME] = (struct src){.name = cfg.shm.ring, .wanted = 1};
  r.s[R_FEAT] = (struct src){.name = cfg.shm.feature_ring, .wanted = features};
  char lib[64];
  snprintf(lib, sizeof lib, "vlff-record %s", vlff_version());
  struct vlff_mcap_writer_params wp = {lib, 0, 0, (int)zstd};
  r.w = vlff_mcap_writer_open(path, &wp, err, sizeof err);
  if (!r.w) return vlff_cli_error(&cli, "%s", err);
  int status = 1;
  if (vlff_in_declare(r.w, err, sizeof err) < 0) {
    fprintf(stderr, "vlff-record: %s\n", err);
    goto out;
  }
  vlff_cli_catch_stop();
  long long frames = 0;
  int said_wait = 0, failed = 0;
  while (!failed) {
    int stopping = vlff_cli_stop || (count > 0 && frames >= count);
    uint64_t now = vlff_now_ns();
    for (int i = 0; i < R_COUNT; i++) attach(&r, i, now, 0);
    if (!r.s[R_FRAME].ring && !said_wait && !r.quiet && !stopping) {
      fprintf(stderr, "vlff-record: waiting for the frame ring %s\n", VLFF_Q(r.s[R_FRAME].name));
      said_wait = 1;
    }
    /* the frame ring paces the loop: its reader sleeps there between frames */
    if (frames_step(&r, stopping || !r.s[R_FRAME].ring ? 0 : 20000000ull, &frames, count) < 0 ||
        drain(&r, R_POSE) < 0 || drain_features(&r, 1, 0) < 0 || vlff_mcap_writer_tick(r.w, vlff_now_ns()) < 0)
      failed = 1;
    if (stopping) break; /* the rings drained once more after the stop */
    if (!r.s[R_FRAME].ring) {
      struct timespec ts = {0, 20000000};
      nanosleep(&ts, NULL);
    }
  }
  if (!failed) status = 0;
  uint64_t lost = r.lost_prev;
  for (int i = 0; i < R_COUNT; i++)
    if (r.s[i].ring) lost += vlff_ring_lost(r.s[i].ring);
  fprintf(stderr,
          "vlff-record: %s: %llu frames, %llu poses, %llu feature maps recorded; %llu records missed, %llu "
          "malformed refused\n",
          VLFF_Q(path), (unsigned long long)r.s[R_FRAME].records, (unsigned long long)r.s[R_POSE].records,
          (unsigned long long)r.s[R_FEAT].records, (unsigned long long)lost,
          (unsigned long long)(r.s[R_POSE].bad + r.s[R_FRAME].bad + r.s[R_FEAT].bad));
out:
  if (vlff_mcap_writer_close(r.w, err, sizeof err) < 0) {
    fprintf(stderr, "vlff-record: %s\n", err);
    status = 1;
  }
  for (int i = 0; i < R_COUNT; i++) {
    vlff_ring_close(r.s[i].ring);
    free(r.s[i].buf);
  }
  free(r.scratch);
  return status;
}
