/*
 * vlff-sim: the synthetic room as a live camera, or as a dataset on disk.
 *
 * Live: frames (RGB8 + uint16 mm depth, intrinsics, camera-to-world pose)
 * go into the frame ring shm.ring at sim.rate_hz, and the simulated features
 * of the same frame into shm.feature_ring ([D][h][w] float16, same frame_id).
 * frame_id counts up from 0; the scene index rendered is frame_id modulo
 * sim.frames, so the trajectory loops like a recorded sequence. A consumer
 * that prefers not to read the feature ring can regenerate any frame's
 * features from (config, frame_id % sim.frames) with vlff_sim_render: the
 * sim is a pure function of both. Frames with a corrupted pose
 * (sim.bad_pose_frac) are deliberately NOT flagged: catching them is the
 * learner's job.
 *
 * Dataset: --write-dataset DIR writes sim.frames frames in the reference
 * layout (see node/dataset/dataset.h), the labelled point set points.ply and
 * prompt_embeddings.txt (vlff-embeddings format, the same file the node
 * reads as prompts.embeddings) for the active prompt set.
 */
#include <errno.h>
#include <signal.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "clock.h"
#include "config.h"
#include "dataset.h"
#include "embeddings.h"
#include "cli.h"
#include "log.h"
#include "sim.h"
#include "transpose.h"
#include "vlff/shm.h"
#include "vlff/escape.h"

#define TAG "sim"

static const struct vlff_cli cli = {
    "vlff-sim",
    "Usage: vlff-sim [-c FILE] [--seed N] [--frames N] [--rate HZ] [--count N]\n"
    "                [--range A..B] [--no-features] [--write-dataset DIR] [--quiet]\n"
    "Publish the synthetic room into the frame ring (and its features into the\n"
    "feature ring) at sim.rate_hz, or write it as a scene directory.\n"
    "\n"
    "  -c, --config FILE    vlff YAML config (default: built-in defaults)\n"
    "  --seed N             sim.seed\n"
    "  --frames N           sim.frames\n"
    "  --rate HZ            sim.rate_hz\n"
    "  --count N            stop after N frames (default: until SIGINT/SIGTERM)\n"
    "  --range A..B         walk only scene frames A to B (of sim.frames), repeated\n"
    "                       (sim.range_first, sim.range_count)\n"
    "  --no-features        do not publish features (consumers regenerate them)\n"
    "  --write-dataset DIR  write sim.frames frames to DIR and exit\n"
    "  --quiet              no progress output\n"
    "  -V, --version        print the version and exit\n"
    "  -h, --help           print this help and exit\n"
    "\n"
    "Examples:\n"
    "  vlff-sim --config configs/default.yaml --rate 10\n"
    "  vlff-sim --seed 3 --frames 200 --write-dataset /tmp/room3\n",
};

/* A finite number and nothing else: "nan" passed a range test written as
 * x < lo || x > hi, and --rate nan then slept for ever. */
static int parse_num(const char *s, double *x) {
  char *end;
  *x = strtod(s, &end);
  return *s && !*end && isfinite(*x);
}


static int write_dataset(const struct vlff_config *cfg, struct vlff_sim *s, const char *dir, int quiet) {
  char err[1024];
  int W, H, fw, fh, D;
  double fx, fy, cx, cy, lo[3], hi[3];
  vlff_sim_size(s, &W, &H, &fw, &fh, &D);
  vlff_sim_intrinsics(s, &fx, &fy, &cx, &cy);
  vlff_config_sim_box(&cfg->sim, &cfg->field, lo, hi);
  int n = cfg->sim.frames;
  struct vlff_dataset_writer *w =
      vlff_dataset_writer_open(dir, n, W, H, fx, fy, cx, cy, lo, hi, "sim", fw, fh, D, err, sizeof err);
  if (!w) {
    fprintf(stderr, "vlff-sim: %s\n", err);
    return 1;
  }
  struct vlff_sim_frame *f = vlff_sim_frame_new(s);
  if (!f) {
    vlff_dataset_writer_abort(w);
    fprintf(stderr, "vlff-sim: out of memory\n");
    return 1;
  }
  for (int i = 0; i < n; i++) {
    if (vlff_sim_render(s, i, VLFF_SIM_ALL, f, err, sizeof err) < 0 ||
        vlff_dataset_writer_add(w, i, f->rgb, f->depth_mm, f->label, f->c2w, f->features, err, sizeof err) < 0) {
      fprintf(stderr, "vlff-sim: %s\n", err);
      vlff_sim_frame_free(f);
      vlff_dataset_writer_abort(w);
      return 1;
    }
    if (!quiet && (i + 1) % 25 == 0) fprintf(stderr, "vlff-sim: %d/%d frames\n", i + 1, n);
  }
  vlff_sim_frame_free(f);
  if (vlff_dataset_writer_close(w, err, sizeof err) < 0) {
    fprintf(stderr, "vlff-sim: %s\n", err);
    return 1;
  }
  /* The frames' times at sim.rate_hz, so a replay plays them at the rate they were made. */
  double *t = malloc((size_t)n * sizeof *t);
  if (!t) {
    fprintf(stderr, "vlff-sim: out of memory\n");
    return 1;
  }
  for (int i = 0; i < n; i++) t[i] = i / cfg->sim.rate_hz;
  int trc = vlff_dataset_write_stamps(dir, n, t, err, sizeof err);
  free(t);
  if (trc < 0) {
    fprintf(stderr, "vlff-sim: %s\n", err);
    return 1;
  }
  char p[4200];
  struct vlff_sim_points pts;
  if (vlff_sim_points(s, n, 2, 0.04, &pts, err, sizeof err) < 0) {
    fprintf(stderr, "vlff-sim: %s\n", err);
    return 1;
  }
  if (pts.n == 0) { /* a dataset without one would be refused when read */
    fprintf(stderr, "vlff-sim: no labelled point: no ray of the %d frames met a surface within sim.depth_max_m %g m\n",
            n, cfg->sim.depth_max_m);
    vlff_sim_points_free(&pts);
    return 1;
  }
  snprintf(p, sizeof p, "%s/points.ply", dir);
  int rc = vlff_ply_write(p, pts.xyz, NULL, pts.label, pts.n, err, sizeof err);
  vlff_sim_points_free(&pts);
  if (rc < 0) {
    fprintf(stderr, "vlff-sim: %s\n", err);
    return 1;
  }
  const struct vlff_prompt_set *set = &cfg->prompts.sets[cfg->prompts.active];
  float *emb = calloc((size_t)set->count * D, sizeof(float));
  const char *names[VLFF_MAX_PROMPTS];
  if (!emb) return 1;
  for (int k = 0; k < set->count; k++) {
    names[k] = set->text[k];
    vlff_sim_text_embedding(s, set->text[k], emb + (size_t)k * D);
  }
  snprintf(p, sizeof p, "%s/prompt_embeddings.txt", dir);
  rc = vlff_embeddings_save(p, D, set->count, names, emb, err, sizeof err);
  free(emb);
  if (rc < 0) {
    fprintf(stderr, "vlff-sim: %s\n", err);
    return 1;
  }
  if (!quiet) fprintf(stderr, "vlff-sim: wrote %d frames to %s\n", n, VLFF_Q(dir));
  return 0;
}

/* Commits a record of len bytes to ring; what names the ring. A truncated
 * ring (EPIPE) is logged and the stream goes on (the library replaces the
 * segment); any other failure ends it: -1. */
static int commit(struct vlff_ring *ring, uint64_t len, const char *what, uint64_t *warned) {
  if (vlff_ring_commit(ring, len) == 0) return 0;
  if (errno != EPIPE) {
    fprintf(stderr, "vlff-sim: %s commit: %s\n", what, strerror(errno));
    return -1;
  }
  vlff_warn_limited(warned, TAG, "%s ring: %s", what, vlff_shm_last_message());
  return 0;
}

static int live(const struct vlff_config *cfg, struct vlff_sim *s, long long count, int features, int quiet) {
  char err[512];
  int W, H, fw, fh, D;
  vlff_sim_size(s, &W, &H, &fw, &fh, &D);
  struct vlff_ring_params rp = {VLFF_RECORD_FRAME, (uint32_t)cfg->shm.ring_slots,
                                vlff_frame_slot_size((uint32_t)W, (uint32_t)H, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM),
                                {(mode_t)cfg->shm.mode, cfg->shm.group}};
  struct vlff_ring *ring = vlff_ring_create(cfg->shm.ring, &rp);
  if (!ring) {
    fprintf(stderr, "vlff-sim: frame ring %s: %s\n", VLFF_Q(cfg->shm.ring), vlff_shm_last_message());
    return 1;
  }
  struct vlff_ring *fring = NULL;
  if (features) {
    struct vlff_ring_params fp = {VLFF_RECORD_FEATURE, (uint32_t)cfg->shm.ring_slots,
                                  vlff_feature_slot_size((uint32_t)D, (uint32_t)fh, (uint32_t)fw),
                                  {(mode_t)cfg->shm.mode, cfg->shm.group}};
    fring = vlff_ring_create(cfg->shm.feature_ring, &fp);
    if (!fring) {
      fprintf(stderr, "vlff-sim: feature ring %s: %s\n", VLFF_Q(cfg->shm.feature_ring), vlff_shm_last_message());
      vlff_ring_close(ring);
      return 1;
    }
  }
  struct vlff_sim_frame *f = vlff_sim_frame_new(s);
  if (!f) {
    vlff_ring_close(ring), vlff_ring_close(fring);
    return 1;
  }
  const uint64_t period = (uint64_t)(1e9 / cfg->sim.rate_hz);
  struct timespec next;
  clock_gettime(CLOCK_MONOTONIC, &next);
  long long late = 0;
  int status = 0;
  uint64_t ring_warned = 0, fring_warned = 0; /* vlff_warn_limited's */
  for (long long id = 0; !vlff_cli_stop && (count <= 0 || id < count); id++) {
    long long idx = vlff_sim_stream_frame(s, id);
    if (vlff_sim_render(s, idx, features ? VLFF_SIM_ALL : VLFF_SIM_RGBD, f, err, sizeof err) < 0) {
      fprintf(stderr, "vlff-sim: %s\n", err);
      status = 1;
      break;
    }
    uint64_t seq;
    struct vlff_frame_hdr *h = vlff_ring_reserve(ring, &seq);
    if (!h && errno == EPIPE) {
      /* The ring's file was truncated under us; the library has replaced it, or
       * could not (no space left in /dev/shm) and tries again after a growing
       * delay. This frame is skipped, at the frame rate: no spinning. */
      vlff_warn_limited(&ring_warned, TAG, "frame ring: %s", vlff_shm_last_message());
      goto pace;
    }
    if (!h) {
      fprintf(stderr, "vlff-sim: frame ring: %s\n", vlff_shm_last_message());
      status = 1;
      break;
    }
    uint64_t len = vlff_frame_layout(h, vlff_ring_slot_size(ring), (uint32_t)W, (uint32_t)H, VLFF_PIX_RGB8,
                                     VLFF_PIX_DEPTH_U16_MM);
    if (!len) {
      fprintf(stderr, "vlff-sim: frame does not fit the ring slot\n");
      status = 1;
      break;
    }
    uint64_t now = vlff_now_ns();
    h->frame_id = (uint64_t)id;
    h->t_host_ns = now;
    h->t_device_ns = (uint64_t)(f->time_s * 1e9);
    h->flags = VLFF_FRAME_POSE_VALID | VLFF_FRAME_INTRINSICS_VALID;
    h->fx = f->fx, h->fy = f->fy, h->cx = f->cx, h->cy = f->cy;
    memcpy(h->pose, f->c2w, sizeof h->pose);
    h->pose_t_ns = now;
    uint8_t *rgb = (uint8_t *)h + h->plane[VLFF_PLANE_COLOR].offset;
    uint8_t *dep = (uint8_t *)h + h->plane[VLFF_PLANE_DEPTH].offset;
    for (int v = 0; v < H; v++) {
      memcpy(rgb + (size_t)v * h->plane[VLFF_PLANE_COLOR].stride, f->rgb + (size_t)v * W * 3, (size_t)W * 3);
      memcpy(dep + (size_t)v * h->plane[VLFF_PLANE_DEPTH].stride, f->depth_mm + (size_t)v * W, (size_t)W * 2);
    }
    if (commit(ring, len, "frame", &ring_warned) < 0) {
      status = 1;
      break;
    }
    if (fring) {
      struct vlff_feature_hdr *fhd = vlff_ring_reserve(fring, NULL);
      if (!fhd && errno == EPIPE) {
        vlff_warn_limited(&fring_warned, TAG, "feature ring: %s", vlff_shm_last_message());
        goto pace;
      }
      if (!fhd) {
        fprintf(stderr, "vlff-sim: feature ring: %s\n", vlff_shm_last_message());
        status = 1;
        break;
      }
      uint64_t flen = vlff_feature_layout(fhd, vlff_ring_slot_size(fring), (uint32_t)D, (uint32_t)fh, (uint32_t)fw);
      if (!flen) {
        fprintf(stderr, "vlff-sim: features do not fit the ring slot\n");
        status = 1;
        break;
      }
      fhd->frame_id = (uint64_t)id, fhd->t_host_ns = now;
      /* the ring carries [D][h][w]; the sim makes [h][w][D] */
      uint16_t *out = (uint16_t *)((uint8_t *)fhd + fhd->data_offset);
      vlff_transpose_u16(f->features, (size_t)fw * fh, (size_t)D, out);
      if (commit(fring, flen, "feature", &fring_warned) < 0) {
        status = 1;
        break;
      }
    }
    if (!quiet && id % 50 == 0) VLFF_INFO(TAG, "frame %lld (scene frame %lld) published, %lld late", id, idx, late);
  pace:
    next.tv_nsec += (long)(period % 1000000000ull);
    next.tv_sec += (time_t)(period / 1000000000ull);
    if (next.tv_nsec >= 1000000000L) next.tv_nsec -= 1000000000L, next.tv_sec++;
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    if (t.tv_sec > next.tv_sec || (t.tv_sec == next.tv_sec && t.tv_nsec > next.tv_nsec)) {
      late++; /* rendering slower than the rate: do not try to catch up */
      next = t;
    } else {
      while (!vlff_cli_stop && clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL) == EINTR) {
      }
    }
  }
  vlff_sim_frame_free(f);
  vlff_ring_close(ring);
  vlff_ring_close(fring);
  return status;
}

int main(int argc, char **argv) {
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  const char *config = NULL, *dataset = NULL;
  long long count = 0;
  int features = 1, quiet = 0;
  char err[1024];
  enum { O_SEED = 256, O_FRAMES, O_RATE, O_COUNT, O_NOFEAT, O_DATASET, O_QUIET, O_RANGE };
  static const struct option longopts[] = {
      {"config", required_argument, NULL, 'c'}, {"seed", required_argument, NULL, O_SEED},
      {"frames", required_argument, NULL, O_FRAMES}, {"rate", required_argument, NULL, O_RATE},
      {"count", required_argument, NULL, O_COUNT},   {"no-features", no_argument, NULL, O_NOFEAT},
      {"write-dataset", required_argument, NULL, O_DATASET}, {"quiet", no_argument, NULL, O_QUIET},
      {"range", required_argument, NULL, O_RANGE},
      VLFF_CLI_COMMON_OPTIONS,
  };
  /* Values are applied after the options end, so that --seed before --config
   * is not overwritten by the file. */
  const char *seed = NULL, *frames = NULL, *rate = NULL, *cnt = NULL, *range = NULL;
  int c, status;
  while ((c = vlff_cli_next(&cli, argc, argv, "c:", longopts, &status)) != -1) {
    switch (c) {
    case VLFF_CLI_EXIT: return status;
    case 'c': config = optarg; break;
    case O_SEED: seed = optarg; break;
    case O_FRAMES: frames = optarg; break;
    case O_RATE: rate = optarg; break;
    case O_COUNT: cnt = optarg; break;
    case O_NOFEAT: features = 0; break;
    case O_DATASET: dataset = optarg; break;
    case O_QUIET: quiet = 1; break;
    case O_RANGE: range = optarg; break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", argv[optind - 1]);
    }
  }
  if (optind < argc) return vlff_cli_usage_error(&cli, "unexpected argument '%s'", argv[optind]);
  if (config && vlff_config_load(config, &cfg, err, sizeof err) < 0) return vlff_cli_config_error(err);
  double x;
  if (seed && (!parse_num(seed, &x) || x < 0 || x > 2147483647 || x != (int)x))
    return vlff_cli_usage_error(&cli, "--seed: expected an integer in 0..2147483647, got '%s'", seed);
  if (seed) cfg.sim.seed = (int)x;
  if (frames && (!parse_num(frames, &x) || x < 1 || x > 1000000 || x != (int)x))
    return vlff_cli_usage_error(&cli, "--frames: expected an integer in 1..1000000, got '%s'", frames);
  if (frames) cfg.sim.frames = (int)x;
  if (rate && (!parse_num(rate, &x) || x < 0.1 || x > 1000))
    return vlff_cli_usage_error(&cli, "--rate: expected a number in 0.1..1000, got '%s'", rate);
  if (rate) cfg.sim.rate_hz = x;
  if (cnt && (!parse_num(cnt, &x) || x < 1 || x > 1e15 || x != (long long)x))
    return vlff_cli_usage_error(&cli, "--count: expected a positive integer, got '%s'", cnt);
  if (cnt) count = (long long)x;
  if (range) {
    long a, b;
    char tail;
    if (sscanf(range, "%ld..%ld%c", &a, &b, &tail) != 2 || a < 0 || b < a || b >= cfg.sim.frames)
      return vlff_cli_usage_error(&cli, "--range: expected A..B with 0 <= A <= B < sim.frames (%d), got '%s'",
                                  cfg.sim.frames, VLFF_Q(range));
    if (cfg.sim.change_count)
      return vlff_cli_usage_error(&cli, "--range: a scene with sim.changes is streamed whole");
    cfg.sim.range_first = (int)a, cfg.sim.range_count = (int)(b - a + 1);
  }
  vlff_log_set_level((enum vlff_log_level)cfg.node.log_level);
  struct vlff_sim *s = vlff_sim_create(&cfg.sim, &cfg.field, err, sizeof err);
  if (!s) {
    fprintf(stderr, "vlff-sim: %s\n", err);
    return 1;
  }
  int rc;
  if (dataset) {
    rc = write_dataset(&cfg, s, dataset, quiet);
  } else {
    vlff_cli_catch_stop();
    if (cfg.node.run_seconds > 0 && count == 0) count = (long long)(cfg.node.run_seconds * cfg.sim.rate_hz + 0.5);
    rc = live(&cfg, s, count, features, quiet);
  }
  vlff_sim_destroy(s);
  return rc;
}
