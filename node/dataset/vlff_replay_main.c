/*
 * vlff-replay: a recorded scene directory played into the node's rings, the
 * way a camera, a pose source and a feature extractor would feed it live.
 *
 * Each frame becomes three records, in the order the live processes produce
 * them: the pose (pose ring, stamped with the frame's host time, so the
 * node's lookup finds it exactly), the frame (frame ring: RGB8 colour,
 * uint16 millimetre depth, intrinsics, no pose in the record), then its
 * features (feature ring, [D][h][w] float16, the frame's id and host time),
 * as an extractor publishes them after reading the frame. With --pose-in-frame
 * the pose travels in the frame record instead, as a camera with its own
 * tracker delivers it.
 *
 * Frames go out at the recording's own times: its stamps
 * (vlff_dataset_stamps: timestamps.txt, or a .sens file's), else 30 Hz;
 * --fps gives a uniform rate instead. The schedule runs at --rate times
 * that and never catches up after a late frame (a replay behind schedule
 * would otherwise burst). --backpressure instead waits before each frame
 * until the frame ring's reader has read everything, so a slow consumer
 * loses nothing. frame_id counts up across loops; t_device_ns is the
 * frame's place in the recording, loop * span + t[i] (span: the recording's
 * length plus one mean frame interval).
 *
 * An MCAP recording of the node's inputs (vlff-record's) is played by
 * replay_mcap.c instead: it holds the records themselves, poses at their own
 * stamps and feature maps, rather than a scene to read frames from.
 */
#include <errno.h>
#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "cli.h"
#include "clock.h"
#include "config.h"
#include "dataset.h"
#include "replay_rings.h"
#include "transpose.h"
#include "vlff/shm.h"
#include "vlff/escape.h"
#ifdef VLFF_HAVE_MCAP
#include "replay_mcap.h"
#endif

#define POSE_SLOTS 256

static const struct vlff_cli cli = {
    "vlff-replay",
    "Usage: vlff-replay [OPTIONS] SCENE\n"
    "Play a recorded scene (a directory, a ScanNet .sens file, or an MCAP recording of\n"
    "the node's inputs made by vlff-record) into the frame, pose and feature rings, as\n"
    "live cameras, a pose source and a feature extractor would.\n"
    "\n"
    "  -c, --config FILE      ring names, slots and permissions from FILE's shm section\n"
    "                         (else $VLFF_CONFIG, else the installed vlff.yaml, else\n"
    "                         built-in defaults, saying so on stderr)\n"
    "      --layout NAME      auto (default: an MCAP file by its magic, else a scene),\n"
    "                         reference, scannet, sens or mcap\n"
    "      --fps HZ           play at this uniform frame rate (default: the recording's\n"
    "                         stamps, timestamps.txt or a .sens file's; without any, 30;\n"
    "                         an MCAP recording keeps its pace scaled to HZ on average)\n"
    "  -r, --rate X           play at X times the recorded rate (default 1)\n"
    "  -b, --backpressure     as fast as the frame ring's reader takes the frames:\n"
    "                         wait before each frame until it has read everything\n"
    "      --wait-reader      hold the first frame until the frame ring has a reader,\n"
    "                         then keep the schedule (an evaluation's node sees every frame)\n"
    "  -l, --loop             start over after the last frame, until SIGINT/SIGTERM\n"
    "  -n, --count N          stop after N frames\n"
    "      --start I          begin at frame I of the scene\n"
    "      --pose-in-frame    put the pose into the frame record, not the pose ring\n"
    "                         (scenes only: an MCAP recording plays its poses as recorded)\n"
    "      --no-features      do not publish the scene's features (a recording without\n"
    "                         any plays as with this option, and says so)\n"
    "  -q, --quiet            no progress lines\n"
    "  -V, --version          print the version and exit\n"
    "  -h, --help             print this help and exit\n"
    "\n"
    "Exit status: 0 when every frame was published, 1 when a frame could not be\n"
    "read (it is skipped, named and counted), an MCAP recording is malformed or out\n"
    "of bounds (nothing is played; the error names the channel and the message) or a\n"
    "ring failed, 2 for a bad command line.\n"
    "\n"
    "Examples:\n"
    "  vlff-replay --config /etc/vlff/vlff.yaml /data/scannet/scene0000_00\n"
    "  vlff-replay -c node.yaml --rate 2 --loop /data/room3\n"
    "  vlff-replay -c node.yaml --backpressure --count 500 /data/room3\n"
    "  vlff-replay -c node.yaml --loop inputs.mcap\n",
};


struct replay {
  struct vlff_dataset ds;
  struct vlff_ring *frames, *poses, *feats;
  uint8_t *rgb;
  float *depth;
  uint16_t *hwc; /* features as stored, [h][w][D] */
  int pose_in_frame, backpressure, wait_reader, quiet;
  int skipped_before; /* the previous frame was unreadable: flag the next one */
  long long published, unreadable, late;
  long long featureless; /* frames the features do not hold, passed over */
};

static int open_rings(struct replay *r, const struct vlff_config *cfg, int features) {
  const struct vlff_dataset *ds = &r->ds;
  struct vlff_replay_rings rr = {0};
  int rc = vlff_replay_rings_open(&rr, cfg, (uint32_t)ds->width, (uint32_t)ds->height, VLFF_PIX_RGB8,
                                  VLFF_PIX_DEPTH_U16_MM, r->pose_in_frame ? 0 : POSE_SLOTS,
                                  features ? (uint32_t)ds->feature_dim : 0, (uint32_t)ds->feat_height,
                                  (uint32_t)ds->feat_width);
  r->frames = rr.frames, r->poses = rr.poses, r->feats = rr.feats;
  return rc;
}

/* Frame i of the scene as record number id. 0 published, 1 skipped (the
 * files could not be read: named on stderr), -1 a ring failed. */
static int publish(struct replay *r, int i, long long id, uint64_t t_device_ns) {
  const struct vlff_dataset *ds = &r->ds;
  const int W = ds->width, H = ds->height;
  char err[1024];
  if (vlff_dataset_read_frame(ds, i, r->rgb, r->depth, NULL, err, sizeof err) < 0 ||
      (r->feats && vlff_dataset_read_features(ds, i, r->hwc, err, sizeof err) < 0)) {
    fprintf(stderr, "vlff-replay: frame %d (%s) skipped: %s\n", i, VLFF_Q(ds->stem[i]), err);
    r->unreadable++;
    r->skipped_before = 1;
    return 1;
  }
  if (r->backpressure) {
    /* No reader yet (or a node restarting) holds the replay: frames nobody
     * reads would be lost, which is what this mode exists to prevent. */
    vlff_replay_wait_reader(r->frames, r->quiet);
    if (vlff_cli_stop) return 0;
  }
  const double *c2w = ds->c2w + (size_t)i * 16;
  uint64_t now = vlff_now_ns();
  if (r->poses) {
    struct vlff_pose_rec pr = {.t_ns = now, .flags = 0, .source_id = 0};
    memcpy(pr.pose, c2w, sizeof pr.pose);
    if (vlff_ring_write(r->poses, &pr, sizeof pr) < 0) return vlff_replay_ring_error("pose", "commit");
  }
  struct vlff_frame_hdr *h = vlff_ring_reserve(r->frames, NULL);
  uint64_t len = h ? vlff_frame_layout(h, vlff_ring_slot_size(r->frames), (uint32_t)W, (uint32_t)H, VLFF_PIX_RGB8,
                                       VLFF_PIX_DEPTH_U16_MM)
                   : 0;
  if (!len) return vlff_replay_ring_error("frame", "layout");
  h->frame_id = (uint64_t)id;
  h->t_host_ns = now;
  h->t_device_ns = t_device_ns;
  h->flags = VLFF_FRAME_INTRINSICS_VALID | (r->skipped_before ? VLFF_FRAME_DROPPED_BEFORE : 0u);
  r->skipped_before = 0;
  h->fx = ds->fx, h->fy = ds->fy, h->cx = ds->cx, h->cy = ds->cy;
  if (r->pose_in_frame) {
    h->flags |= VLFF_FRAME_POSE_VALID;
    memcpy(h->pose, c2w, sizeof h->pose);
    h->pose_t_ns = now;
  }
  uint8_t *rgb = (uint8_t *)h + h->plane[VLFF_PLANE_COLOR].offset;
  uint8_t *dep = (uint8_t *)h + h->plane[VLFF_PLANE_DEPTH].offset;
  for (int v = 0; v < H; v++) {
    memcpy(rgb + (size_t)v * h->plane[VLFF_PLANE_COLOR].stride, r->rgb + (size_t)v * W * 3, (size_t)W * 3);
    uint16_t *row = (uint16_t *)(dep + (size_t)v * h->plane[VLFF_PLANE_DEPTH].stride);
    for (int u = 0; u < W; u++) {
      /* The reader gives metres from millimetre PNGs: the round trip is exact. */
      float d = r->depth[(size_t)v * W + u];
      row[u] = isfinite(d) && d > 0 ? (uint16_t)fminf(lrintf(d * 1000.0f), 65535.0f) : 0;
    }
  }
  if (vlff_ring_commit(r->frames, len) < 0) return vlff_replay_ring_error("frame", "commit");
  if (r->feats) {
    struct vlff_feature_hdr *f = vlff_ring_reserve(r->feats, NULL);
    uint64_t flen = f ? vlff_feature_layout(f, vlff_ring_slot_size(r->feats), (uint32_t)ds->feature_dim,
                                            (uint32_t)ds->feat_height, (uint32_t)ds->feat_width)
                      : 0;
    if (!flen) return vlff_replay_ring_error("feature", "layout");
    f->frame_id = (uint64_t)id;
    f->t_host_ns = now;
    /* the scene stores [h][w][D]; the ring carries [D][h][w] */
    vlff_transpose_u16(r->hwc, (size_t)ds->feat_height * ds->feat_width, (size_t)ds->feature_dim,
                       (uint16_t *)((uint8_t *)f + f->data_offset));
    if (vlff_ring_commit(r->feats, flen) < 0) return vlff_replay_ring_error("feature", "commit");
  }
  r->published++;
  return 0;
}

/* t[i]: frame i's time in the recording (s, t[0] = 0); span: one loop's length. */
static int run(struct replay *r, const double *t, double span, double rate, int loop, long long count, int start) {
  const int n = r->ds.n;
  if (r->wait_reader && !r->backpressure) {
    /* The first frame waits for the node to attach, the rest keep the
     * schedule: an evaluation's node then sees every frame at the
     * recording's rate. */
    vlff_replay_wait_reader(r->frames, r->quiet);
  }
  uint64_t base = vlff_now_ns();
  long long id = 0;
  for (long long pass = 0; !vlff_cli_stop; pass++) {
    for (int i = pass ? 0 : start; i < n && !vlff_cli_stop && (count <= 0 || id < count); i++) {
      double rec = (double)pass * span + t[i]; /* seconds into the recording */
      if (!r->backpressure) {
        uint64_t off = (uint64_t)((rec - t[start]) / rate * 1e9), due = base + off, now = vlff_now_ns();
        if (now > due + 1000000ull) {
          r->late++; /* reading the scene is slower than the schedule: restart it from now */
          base = now - off;
        } else {
          vlff_replay_sleep_until(due);
        }
      }
      /* Features stored for some frames only (docs/datasets.md): the others
       * are passed over in their time, so the scene keeps its pace, and are
       * not records (no gap in frame_id, nothing reported dropped). */
      if (r->feats && r->ds.feat_row[i] < 0) {
        r->featureless++;
        continue;
      }
      if (publish(r, i, id++, (uint64_t)(rec * 1e9)) < 0) return -1;
      if (!r->quiet && r->published % 100 == 0)
        fprintf(stderr, "vlff-replay: %lld frames published (scene frame %d of %d, pass %lld)\n", r->published,
                i, n, pass + 1);
    }
    if (!loop || (count > 0 && id >= count)) break;
  }
  return 0;
}

static int parse_num(const char *opt, const char *v, double lo, double hi, double *out) {
  char *end;
  errno = 0;
  double x = strtod(v, &end);
  if (!*v || *end || errno || !(x >= lo && x <= hi))
    return vlff_cli_usage_error(&cli, "%s: expected a number in [%g, %g], got '%s'", opt, lo, hi, v);
  *out = x;
  return 0;
}

int main(int argc, char **argv) {
  enum { OPT_LAYOUT = 256, OPT_FPS, OPT_START, OPT_POSE_IN_FRAME, OPT_NO_FEATURES, OPT_WAIT_READER };
  static const struct option opts[] = {
      {"config", required_argument, NULL, 'c'},
      {"layout", required_argument, NULL, OPT_LAYOUT},
      {"fps", required_argument, NULL, OPT_FPS},
      {"rate", required_argument, NULL, 'r'},
      {"backpressure", no_argument, NULL, 'b'},
      {"wait-reader", no_argument, NULL, OPT_WAIT_READER},
      {"loop", no_argument, NULL, 'l'},
      {"count", required_argument, NULL, 'n'},
      {"start", required_argument, NULL, OPT_START},
      {"pose-in-frame", no_argument, NULL, OPT_POSE_IN_FRAME},
      {"no-features", no_argument, NULL, OPT_NO_FEATURES},
      {"quiet", no_argument, NULL, 'q'},
      VLFF_CLI_COMMON_OPTIONS,
  };
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  struct replay r;
  memset(&r, 0, sizeof r);
  int layout = VLFF_DS_AUTO, loop = 0, features = 1, mcap = 0, c;
  double fps = 0, rate = 1, x; /* fps 0: the recording's stamps */
  long long count = 0;
  int start = 0;
  char err[1024];
  const char *config = NULL;
  int cli_status;
  while ((c = vlff_cli_next(&cli, argc, argv, "c:r:bln:q", opts, &cli_status)) != -1) {
    switch (c) {
    case VLFF_CLI_EXIT: return cli_status;
    case 'c': config = optarg; break;
    case OPT_LAYOUT:
      mcap = 0;
      if (!strcmp(optarg, "auto")) layout = VLFF_DS_AUTO;
      else if (!strcmp(optarg, "reference")) layout = VLFF_DS_REFERENCE;
      else if (!strcmp(optarg, "scannet")) layout = VLFF_DS_SCANNET;
      else if (!strcmp(optarg, "sens")) layout = VLFF_DS_SENS;
      else if (!strcmp(optarg, "mcap")) mcap = 1;
      else return vlff_cli_usage_error(&cli, "--layout: expected auto, reference, scannet, sens or mcap, got '%s'",
                                       optarg);
      break;
    case OPT_FPS:
      if (parse_num("--fps", optarg, 0.01, 10000, &fps)) return 2;
      break;
    case 'r':
      if (parse_num("--rate", optarg, 0.001, 1000, &rate)) return 2;
      break;
    case 'b': r.backpressure = 1; break;
    case OPT_WAIT_READER: r.wait_reader = 1; break;
    case 'l': loop = 1; break;
    case 'n':
      if (parse_num("--count", optarg, 1, 1e15, &x)) return 2;
      if (x != floor(x)) return vlff_cli_usage_error(&cli, "--count: expected an integer, got '%s'", optarg);
      count = (long long)x;
      break;
    case OPT_START:
      if (parse_num("--start", optarg, 0, 1e9, &x)) return 2;
      if (x != floor(x)) return vlff_cli_usage_error(&cli, "--start: expected an integer, got '%s'", optarg);
      start = (int)x;
      break;
    case OPT_POSE_IN_FRAME: r.pose_in_frame = 1; break;
    case OPT_NO_FEATURES: features = 0; break;
    case 'q': r.quiet = 1; break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", argv[optind - 1]);
    }
  }
  if (optind >= argc) return vlff_cli_usage_error(&cli, "no SCENE given");
  if (optind < argc - 1) return vlff_cli_usage_error(&cli, "one SCENE only, got also '%s'", argv[optind + 1]);
  /* The node's config names the rings; without one anywhere on the search
   * path the built-in names are the node's defaults too, but a node run with
   * other names would wait on rings nobody fills: say which were taken. */
  char ferr[512];
  const char *path = vlff_config_find(config, ferr, sizeof ferr);
  if (path && vlff_config_load(path, &cfg, err, sizeof err) < 0) return vlff_cli_config_error(err);
  if (!path)
    fprintf(stderr, "vlff-replay: %s; using the default ring names (%s, %s, %s)\n", ferr, VLFF_Q(cfg.shm.ring),
            VLFF_Q(cfg.shm.pose_ring), VLFF_Q(cfg.shm.feature_ring));
#ifdef VLFF_HAVE_MCAP
  if (mcap || (layout == VLFF_DS_AUTO && vlff_replay_is_mcap(argv[optind]))) {
    if (r.pose_in_frame)
      return vlff_cli_usage_error(&cli, "--pose-in-frame: an MCAP recording plays its poses as recorded");
    struct vlff_replay_opts mo = {fps, rate, loop, r.backpressure, r.wait_reader, r.quiet, features, count, start,
                                  POSE_SLOTS};
    return vlff_replay_mcap(argv[optind], &cfg, &mo);
  }
#else
  if (mcap) return vlff_cli_error(&cli, "built without MCAP support (libzstd, zlib and json-c)");
#endif
  if (vlff_dataset_open(&r.ds, argv[optind], layout, err, sizeof err) < 0) return vlff_cli_error(&cli, "%s", err);
  int status = 1;
  double *times = NULL, span = 0;
  if (start >= r.ds.n) {
    fprintf(stderr, "vlff-replay: --start %d: the scene has %d frames\n", start, r.ds.n);
    goto out;
  }
  if (features && !r.ds.has_features) {
    if (!r.quiet) fprintf(stderr, "vlff-replay: %s has no features.hdf: no feature ring\n", VLFF_Q(r.ds.dir));
    features = 0;
  }
  const size_t px = (size_t)r.ds.width * r.ds.height;
  r.rgb = malloc(px * 3);
  r.depth = malloc(px * sizeof(float));
  r.hwc = features ? malloc((size_t)r.ds.feat_height * r.ds.feat_width * r.ds.feature_dim * sizeof(uint16_t)) : NULL;
  if (!r.rgb || !r.depth || (features && !r.hwc)) {
    fprintf(stderr, "vlff-replay: out of memory for %dx%d frames\n", r.ds.width, r.ds.height);
    goto out;
  }
  /* The recording's times: its stamps unless --fps gives a uniform rate. */
  times = malloc((size_t)r.ds.n * sizeof *times);
  if (!times) {
    fprintf(stderr, "vlff-replay: out of memory\n");
    goto out;
  }
  int stamped = fps > 0 ? 0 : vlff_dataset_stamps(&r.ds, times, err, sizeof err);
  if (stamped < 0) {
    fprintf(stderr, "vlff-replay: %s\n", err);
    goto out;
  }
  char pace[128];
  if (stamped && r.ds.n > 1 && times[r.ds.n - 1] > 0) {
    double mean = times[r.ds.n - 1] / (r.ds.n - 1);
    span = times[r.ds.n - 1] + mean;
    snprintf(pace, sizeof pace, "at the recording's stamps (%.2f Hz on average)", 1 / mean);
  } else {
    if (stamped) fprintf(stderr, "vlff-replay: the scene's stamps span no time; playing at 30 Hz\n");
    snprintf(pace, sizeof pace, "at %g Hz%s", fps > 0 ? fps : 30,
             fps > 0 ? " (--fps)" : " (the scene has no stamps; --fps sets the rate)");
    if (fps <= 0) fps = 30;
    for (int i = 0; i < r.ds.n; i++) times[i] = i / fps;
    span = r.ds.n / fps;
  }
  if (open_rings(&r, &cfg, features) < 0) goto out;
  vlff_cli_catch_stop();
  if (!r.quiet)
    fprintf(stderr, "vlff-replay: %s: %d frames %dx%d%s, %s\n", VLFF_Q(r.ds.dir), r.ds.n, r.ds.width, r.ds.height,
            features ? " with features" : "", r.backpressure ? "paced by the reader" : pace);
  if (!r.quiet && r.ds.skipped)
    fprintf(stderr, "vlff-replay: %s: %d more frames without a pose (lost tracking) skipped\n", VLFF_Q(r.ds.dir),
            r.ds.skipped);
  if (features && r.ds.feat_frames < r.ds.n)
    fprintf(stderr, "vlff-replay: %s: the features hold %d of the %d frames: the others are passed over "
                    "(--no-features plays them all)\n",
            VLFF_Q(r.ds.dir), r.ds.feat_frames, r.ds.n);
  if (run(&r, times, span, rate, loop, count, start) == 0) status = r.unreadable ? 1 : 0;
  if (!r.quiet || status)
    fprintf(stderr, "vlff-replay: %lld frames published, %lld unreadable skipped, %lld without features passed "
                    "over, %lld late\n",
            r.published, r.unreadable, r.featureless, r.late);
out:
  vlff_ring_close(r.frames);
  vlff_ring_close(r.poses);
  vlff_ring_close(r.feats);
  free(r.rgb);
  free(r.depth);
  free(r.hwc);
  free(times);
  vlff_dataset_close(&r.ds);
  return status;
}
