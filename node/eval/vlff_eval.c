/*
 * vlff-eval: fit a scene offline and measure it (the paper's Table I, here).
 *
 * A scene (a synthetic room from the sim, or a scene directory) is split into
 * training frames and held-out frames (every --holdout'th). The field is fit
 * on the training frames (a dataset's: those of them keyframes.memory_mb
 * holds, spread over the scene; every other pass reads a dataset one frame
 * at a time, so a scene of any length fits) for --iters steps; then
 *   2D: the held-out frames are rendered at the feature-map resolution and
 *       segmented with the prompts, cells on measured surfaces as the node's
 *       label image reads them (field and evidence); the raw per-frame
 *       features of the same frames are the baseline;
 *   3D: the labelled points are queried; OpenScene-style multi-view fusion of
 *       the training frames' features is the baseline.
 * Both protocols (metrics.h) are reported. Output: report.md, report.json,
 * overlay_<frame>.png (image | prediction | ground truth), prediction.ply, a
 * per-class table (3D IoU of the field beside fusion's, 2D beside the raw
 * features') and a last line "RESULT miou3d=... miou3d_fusion=... miou2d=...
 * miou2d_raw=... macc2d=... macc2d_raw=... worst_class_vs_fusion=...
 * fit_seconds=... steps=... miou3d_field_alone=... miou2d_field_alone=...
 * macc2d_field_alone=..." (standard protocol, percent).
 */
#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "config.h"
#include "clock.h"
#include "dataset.h"
#include "embeddings.h"
#include "evidence.h"
#include <json-c/json.h>

#include "cli.h"
#include "field.h"
#include "log.h"
#include "metrics.h"
#include "online.h"
#include "palette.h"
#include "regions.h"
#include "rng.h"
#include "select.h"
#include "sim.h"
#include "vlff/escape.h"

#define TAG "eval"
#define MAXK VLFF_FIELD_MAX_PROMPTS

static const struct vlff_cli cli = {
    "vlff-eval",
    "Usage: vlff-eval [OPTIONS]\n"
    "Fit a feature field to a scene, then evaluate 2D (held-out frames) and 3D\n"
    "(labelled points) segmentation against ground truth and two baselines.\n"
    "\n"
    "  -c, --config FILE   vlff YAML config (default: built-in defaults)\n"
    "  --dataset DIR       scene directory (reference or ScanNet layout);\n"
    "                      default: the synthetic room of sim.*\n"
    "  --seed N            sim.seed\n"
    "  --frames N          frames of the synthetic trajectory (sim.frames)\n"
    "  --difficulty X      sim.difficulty\n"
    "  --feature-dim D     field.feature_dim (the simulator renders that many)\n"
    "  --iters N           training steps (default 1500; 0 = baselines only)\n"
    "  --fit-seconds S     fit for S seconds of wall clock instead of --iters steps\n"
    "  --holdout K         every K-th frame is held out for 2D evaluation (default 8)\n"
    "  --stride N          dataset: the frames whose number is a multiple of N\n"
    "                      (default 1); read one at a time, the field fitting on as\n"
    "                      many as keyframes.memory_mb holds, spread over the scene\n"
    "  --label-set SET     ScanNet labels as scannet20 (default) or nyu40 classes\n"
    "  --label-tsv FILE    ScanNet's scannetv2-labels.combined.tsv (default: looked\n"
    "                      for in the scene directory and its two parents)\n"
    "  --threads N         node.threads\n"
    "  --out DIR           report directory (default eval-out)\n"
    "  --overlays N        overlay images to write (default 3)\n"
    "  --online            then play --dataset through vlff-replay into a vlff-node and\n"
    "                      score its published map over time (docs/eval.md)\n"
    "  --online-interval S seconds between the map's samples (default 10)\n"
    "  --online-after S    keep sampling this long after the replay ends (default 60)\n"
    "  --node FILE, --replay FILE  the programs --online runs (default: beside vlff-eval)\n"
    "  --quiet             no progress bar\n"
    "  -V, --version       print the version and exit\n"
    "  -h, --help          print this help and exit\n"
    "\n"
    "examples:\n"
    "  vlff-eval --seed 3 --iters 2000 --out /tmp/eval3\n"
    "  vlff-eval --dataset scans/scene0000_00 --config my.yaml --iters 20000\n"
    "  vlff-eval --dataset scans/scene0000_00/scene0000_00.sens --stride 10 --label-set nyu40\n",
};

struct opts {
  const char *config, *dataset, *out, *label_tsv, *node_bin, *replay_bin;
  int online;
  double online_interval, online_after;
  int seed, frames, dim, iters, holdout, threads, overlays, quiet, stride, label_set;
  double difficulty, fit_seconds;
};

/* One scene frame. The synthetic room's frames are rendered into memory
 * and stay there; a dataset's are read when a pass needs them (frame_data),
 * and only the field's keyframes keep their training copies resident. */
struct frame {
  int index;
  double c2w[16];
  uint8_t *rgb, *label;
  float *depth;
  uint16_t *feat;
  int key;         /* a training frame the field fits on */
  /* a keyframe's training copies at train.image_scale, and (dataset) its
   * features */
  uint8_t *trgb;
  float *tdepth;
  uint16_t *kfeat;
};

struct scene {
  int n, W, H, fw, fh, D;
  double fx, fy, cx, cy;
  struct frame *f;
  int K;
  char names[MAXK][VLFF_PROMPT_LEN];
  float emb[MAXK * 1024];  /* unit rows, K x D (D <= 1024) */
  struct vlff_points pts;
  int tw, th;              /* training image size */
  int holdout;             /* frame i is held out when i % holdout == holdout / 2 */
  /* dataset: every frame's images, labels and features are read when a
   * pass needs them, into these scratch buffers */
  struct vlff_dataset ds;
  int streaming;
  uint8_t *srgb, *slabel;
  uint16_t *sfeat;
  float *sdepth;
  int stride;              /* dataset: --stride */
  int nkey;                /* keyframes: the training frames the field fits on */
  double key_mib;          /* what one keyframe holds resident */
  const char *key_why;     /* why nkey is fewer than the training frames (NULL: it is not) */
  const char *box_from;    /* where field.scene_min/max came from */
  size_t pts_outside;      /* labelled points outside that box */
};


static void die(const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  fprintf(stderr, "vlff-eval: ");
  vfprintf(stderr, fmt, ap);
  fputc('\n', stderr);
  va_end(ap);
  exit(1);
}

static void *xcalloc(size_t n, size_t s) {
  void *p = calloc(n ? n : 1, s);
  if (!p) die("out of memory (%zu x %zu bytes)", n, s);
  return p;
}

/* A bad value is a usage error like an unknown option: one line, the usage, 2. */
static int parse_int(const char *s, const char *opt, int lo, int hi) {
  char *e;
  errno = 0;
  long v = strtol(s, &e, 10);
  if (!*s || *e || errno || v < lo || v > hi)
    exit(vlff_cli_usage_error(&cli, "%s: expected an integer in %d..%d, got '%s'", opt, lo, hi, s));
  return (int)v;
}

static double parse_dbl(const char *s, const char *opt, double lo, double hi) {
  char *e;
  double v = strtod(s, &e);
  if (!*s || *e || !(v >= lo && v <= hi))
    exit(vlff_cli_usage_error(&cli, "%s: expected a number in %g..%g, got '%s'", opt, lo, hi, s));
  return v;
}

static void parse_args(int argc, char **argv, struct opts *o) {
  enum { O_DATASET = 256, O_OUT, O_SEED, O_FRAMES, O_DIM, O_ITERS, O_HOLDOUT, O_THREADS, O_OVERLAYS,
         O_DIFFICULTY, O_QUIET, O_STRIDE, O_LABEL_SET, O_LABEL_TSV, O_FIT_SECONDS, O_ONLINE, O_ONLINE_INTERVAL,
         O_ONLINE_AFTER, O_NODE, O_REPLAY };
  static const struct option longopts[] = {
      {"config", required_argument, NULL, 'c'},          {"dataset", required_argument, NULL, O_DATASET},
      {"out", required_argument, NULL, O_OUT},           {"seed", required_argument, NULL, O_SEED},
      {"frames", required_argument, NULL, O_FRAMES},     {"feature-dim", required_argument, NULL, O_DIM},
      {"iters", required_argument, NULL, O_ITERS},       {"holdout", required_argument, NULL, O_HOLDOUT},
      {"threads", required_argument, NULL, O_THREADS},   {"overlays", required_argument, NULL, O_OVERLAYS},
      {"difficulty", required_argument, NULL, O_DIFFICULTY}, {"quiet", no_argument, NULL, O_QUIET},
      {"stride", required_argument, NULL, O_STRIDE},     {"label-set", required_argument, NULL, O_LABEL_SET},
      {"label-tsv", required_argument, NULL, O_LABEL_TSV},
      {"fit-seconds", required_argument, NULL, O_FIT_SECONDS},
      {"online", no_argument, NULL, O_ONLINE},           {"online-interval", required_argument, NULL, O_ONLINE_INTERVAL},
      {"online-after", required_argument, NULL, O_ONLINE_AFTER},
      {"node", required_argument, NULL, O_NODE},         {"replay", required_argument, NULL, O_REPLAY},
      VLFF_CLI_COMMON_OPTIONS,
  };
  memset(o, 0, sizeof *o);
  o->seed = o->frames = o->dim = o->threads = -1;
  o->difficulty = -1;
  o->iters = 1500, o->holdout = 8, o->overlays = 3, o->out = "eval-out", o->stride = 1;
  o->label_set = VLFF_LABELS_SCANNET20;
  o->online_interval = 10, o->online_after = 60;
  int c, status;
  while ((c = vlff_cli_next(&cli, argc, argv, "c:", longopts, &status)) != -1) {
    /* the option's name for messages: argv[optind - 1] is its value when
     * given apart ("--frames 1" said "1: expected ...") */
    char a[48] = "-c";
    for (const struct option *lo = longopts; lo->name; lo++)
      if (lo->val == c) snprintf(a, sizeof a, "--%s", lo->name);
    const char *v = optarg;
    switch (c) {
    case VLFF_CLI_EXIT: exit(status);
    case O_QUIET: o->quiet = 1; break;
    case 'c': o->config = v; break;
    case O_DATASET: o->dataset = v; break;
    case O_OUT: o->out = v; break;
    case O_SEED: o->seed = parse_int(v, a, 0, 2147483647); break;
    case O_FRAMES: o->frames = parse_int(v, a, 2, 100000); break;
    case O_DIM: o->dim = parse_int(v, a, 8, 1024); break;
    case O_ITERS: o->iters = parse_int(v, a, 0, 100000000); break;
    case O_HOLDOUT: o->holdout = parse_int(v, a, 2, 1000); break;
    case O_THREADS: o->threads = parse_int(v, a, 0, 256); break;
    case O_OVERLAYS: o->overlays = parse_int(v, a, 0, 1000); break;
    case O_DIFFICULTY: o->difficulty = parse_dbl(v, a, 0, 1); break;
    case O_FIT_SECONDS: o->fit_seconds = parse_dbl(v, a, 0.001, 1e7); break;
    case O_STRIDE: o->stride = parse_int(v, a, 1, 100000); break;
    case O_LABEL_TSV: o->label_tsv = v; break;
    case O_ONLINE: o->online = 1; break;
    case O_ONLINE_INTERVAL: o->online_interval = parse_dbl(v, a, 0.1, 3600); break;
    case O_ONLINE_AFTER: o->online_after = parse_dbl(v, a, 0, 86400); break;
    case O_NODE: o->node_bin = v; break;
    case O_REPLAY: o->replay_bin = v; break;
    case O_LABEL_SET:
      if (!strcmp(v, "scannet20")) o->label_set = VLFF_LABELS_SCANNET20;
      else if (!strcmp(v, "nyu40")) o->label_set = VLFF_LABELS_NYU40;
      else exit(vlff_cli_usage_error(&cli, "%s: expected scannet20 or nyu40, got '%s'", a, v));
      break;
    default: exit(vlff_cli_usage_error(&cli, "option '%s' not handled", a));
    }
  }
  if (optind < argc) exit(vlff_cli_usage_error(&cli, "unexpected argument '%s'", argv[optind]));
  if (o->online && !o->dataset)
    exit(vlff_cli_usage_error(&cli, "--online plays a recorded scene: give it with --dataset"));
  /* what describes the synthetic scene means nothing for a recorded one:
   * said, not ignored */
  if (o->dataset && (o->seed >= 0 || o->frames > 0 || o->difficulty >= 0 || o->dim > 0))
    exit(vlff_cli_usage_error(&cli, "--seed, --frames, --difficulty and --feature-dim describe the synthetic scene; "
                                    "a --dataset has its own"));
  if (!o->dataset && (o->label_tsv || o->stride != 1))
    exit(vlff_cli_usage_error(&cli, "--label-tsv and --stride apply to a --dataset"));
}

/* ---- scene loading ------------------------------------------------------ */

static void load_sim(struct scene *sc, const struct vlff_config *cfg) {
  char err[512];
  struct vlff_sim *s = vlff_sim_create(&cfg->sim, &cfg->field, err, sizeof err);
  if (!s) die("%s", err);
  vlff_sim_size(s, &sc->W, &sc->H, &sc->fw, &sc->fh, &sc->D);
  vlff_sim_intrinsics(s, &sc->fx, &sc->fy, &sc->cx, &sc->cy);
  sc->n = cfg->sim.frames;
  sc->box_from = "config"; /* the simulator renders inside the field's box */
  sc->f = xcalloc((size_t)sc->n, sizeof *sc->f);
  struct vlff_sim_frame *fr = vlff_sim_frame_new(s);
  if (!fr) die("out of memory");
  size_t npx = (size_t)sc->W * sc->H, nf = (size_t)sc->fw * sc->fh * sc->D;
  for (int i = 0; i < sc->n; i++) {
    if (vlff_sim_render(s, i, VLFF_SIM_ALL, fr, err, sizeof err) < 0) die("%s", err);
    struct frame *f = &sc->f[i];
    f->index = i;
    memcpy(f->c2w, fr->c2w, sizeof f->c2w);
    f->rgb = xcalloc(npx, 3), f->label = xcalloc(npx, 1), f->depth = xcalloc(npx, sizeof(float));
    f->feat = xcalloc(nf, sizeof(uint16_t));
    memcpy(f->rgb, fr->rgb, npx * 3);
    memcpy(f->label, fr->label, npx);
    memcpy(f->depth, fr->depth, npx * sizeof(float));
    memcpy(f->feat, fr->features, nf * sizeof(uint16_t));
  }
  vlff_sim_frame_free(fr);
  /* 3D ground truth from every other frame's exact depth, 4 cm voxels */
  struct vlff_sim_points p;
  if (vlff_sim_points(s, sc->n, 2, 0.04, &p, err, sizeof err) < 0) die("%s", err);
  sc->pts.n = p.n, sc->pts.xyz = p.xyz, sc->pts.label = p.label;
  const struct vlff_prompt_set *set = &cfg->prompts.sets[cfg->prompts.active];
  sc->K = set->count;
  float *e = xcalloc((size_t)sc->D, sizeof(float));
  for (int k = 0; k < sc->K; k++) {
    snprintf(sc->names[k], VLFF_PROMPT_LEN, "%s", set->text[k]);
    vlff_sim_text_embedding(s, set->text[k], e);
    memcpy(sc->emb + (size_t)k * sc->D, e, (size_t)sc->D * sizeof(float));
  }
  free(e);
  vlff_sim_destroy(s);
}

static int held_out(int i, int holdout) { return i % holdout == holdout / 2; }

enum { FD_RGB = 1, FD_DEPTH = 2, FD_FEAT = 4, FD_LABEL = 8 };

/* Frame i's parts asked for (FD_*): the synthetic room's are in memory; a
 * dataset's are read into the scene's scratch buffers, valid until the next
 * call, and the parts not asked for are NULL (a keyframe's features come
 * from memory). A dataset of any length thus holds one frame's images at a
 * time besides the keyframes, as the node's keyframe store bounds it. */
static struct frame *frame_data(struct scene *sc, int i, unsigned parts) {
  struct frame *f = &sc->f[i];
  if (!sc->streaming) return f;
  char err[1024];
  f->rgb = parts & FD_RGB ? sc->srgb : NULL;
  f->depth = parts & FD_DEPTH ? sc->sdepth : NULL;
  f->label = parts & FD_LABEL ? sc->slabel : NULL;
  f->feat = parts & FD_FEAT ? (f->kfeat ? f->kfeat : sc->sfeat) : NULL;
  if (((parts & (FD_RGB | FD_DEPTH | FD_LABEL)) &&
       vlff_dataset_read_frame(&sc->ds, f->index, f->rgb, f->depth, f->label, err, sizeof err) < 0) ||
      (f->feat == sc->sfeat && vlff_dataset_read_features(&sc->ds, f->index, f->feat, err, sizeof err) < 0))
    die("%s", err);
  return f;
}

static int cmp_float(const void *a, const void *b) {
  float x = *(const float *)a, y = *(const float *)b;
  return (x > y) - (x < y);
}

/* The box the training frames measured: their depth's surface points
 * (a pixel grid of about a million in all) and the cameras, each axis from
 * its 0.2nd to its 99.8th percentile (a stereo sensor's noise at a far wall,
 * or a few spikes through a window, must not stretch the box by metres),
 * widened by 5 % of its extent and 10 cm each side (a box a little too
 * large costs a little resolution; one too small loses what it cuts). Sets
 * *inside to the share of those points within the config's box. 0, or -1
 * when the frames measured too little to bound anything. */
static int measured_box(struct scene *sc, const struct vlff_cfg_field *fc, double lo[3], double hi[3],
                        double *inside) {
  size_t nd = 0; /* the training frames: their depth is read one at a time */
  for (int i = 0; i < sc->n; i++) nd += !held_out(i, sc->holdout);
  int step = 1;
  while (nd * sc->W * sc->H / ((size_t)step * step) > (1u << 20)) step++;
  /* pixels sampled per frame (from step / 2 on, every step-th), exactly:
   * rounding up on both axes can exceed W H / step^2 */
  const size_t nu = sc->W > step / 2 ? (size_t)((sc->W - 1 - step / 2) / step + 1) : 0;
  const size_t nv = sc->H > step / 2 ? (size_t)((sc->H - 1 - step / 2) / step + 1) : 0;
  size_t cap = nd * nu * nv + (size_t)sc->n, m = 0, in = 0;
  float *ax[3];
  for (int a = 0; a < 3; a++) ax[a] = xcalloc(cap, sizeof(float));
  for (int i = 0; i < sc->n; i++) {
    if (held_out(i, sc->holdout)) continue;
    const struct frame *f = frame_data(sc, i, FD_DEPTH);
    double x[3];
    for (int v = step / 2; v < sc->H; v += step)
      for (int u = step / 2; u < sc->W; u += step) {
        float d = f->depth[(size_t)v * sc->W + u];
        if (!(d > 0) || !isfinite(d)) continue;
        vlff_unproject(f->c2w, sc->fx, sc->fy, sc->cx, sc->cy, u + 0.5, v + 0.5, d, x);
        int ok = 1;
        for (int a = 0; a < 3; a++) ax[a][m] = (float)x[a], ok &= x[a] >= fc->scene_min[a] && x[a] <= fc->scene_max[a];
        in += ok, m++;
      }
    for (int a = 0; a < 3; a++) ax[a][m] = (float)f->c2w[4 * a + 3];
    m++;
  }
  int rc = -1;
  if (m >= 1000) {
    rc = 0;
    for (int a = 0; a < 3; a++) {
      qsort(ax[a], m, sizeof(float), cmp_float);
      double l = ax[a][(size_t)(0.002 * (double)(m - 1))], h = ax[a][(size_t)(0.998 * (double)(m - 1))];
      double pad = 0.05 * (h - l) + 0.1;
      lo[a] = l - pad, hi[a] = h + pad;
      if (!(hi[a] - lo[a] < 2e4) || !(lo[a] >= -1e4) || !(hi[a] <= 1e4)) rc = -1;
    }
    *inside = (double)in / (double)m;
  }
  for (int a = 0; a < 3; a++) free(ax[a]);
  return rc;
}

/* The field's box for a recorded scene: its bbox.txt when it has one; else
 * the config's field.scene_min/max when they hold 90 % of what the frames
 * measured (the rest: far depth's noise); else the measured box, said on
 * stderr. A default box silently cutting a ScanNet room (whose coordinates
 * run from 0 to several metres) in half would score every point outside it
 * as a miss. */
static void dataset_box(struct scene *sc, const struct vlff_dataset *ds, struct vlff_config *cfg) {
  struct vlff_cfg_field *fc = &cfg->field;
  if (ds->has_bbox) {
    memcpy(fc->scene_min, ds->bbox_lo, sizeof ds->bbox_lo);
    memcpy(fc->scene_max, ds->bbox_hi, sizeof ds->bbox_hi);
    sc->box_from = "bbox.txt";
  } else {
    double lo[3], hi[3], inside = 0;
    if (measured_box(sc, fc, lo, hi, &inside) < 0)
      die("%s: no bbox.txt, and the training frames' depth is too sparse to bound the scene: add bbox.txt "
          "(min xyz, max xyz) or set field.scene_min/max",
          ds->dir);
    if (inside >= 0.9) {
      sc->box_from = "config";
    } else {
      fprintf(stderr,
              "vlff-eval: %s has no bbox.txt and field.scene_min/max [%g %g %g]..[%g %g %g] hold %.0f %% of what "
              "its frames measured: the scene box is the measured one, [%.2f %.2f %.2f]..[%.2f %.2f %.2f]\n",
              ds->dir, fc->scene_min[0], fc->scene_min[1], fc->scene_min[2], fc->scene_max[0], fc->scene_max[1],
              fc->scene_max[2], 100 * inside, lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]);
      memcpy(fc->scene_min, lo, sizeof lo);
      memcpy(fc->scene_max, hi, sizeof hi);
      sc->box_from = "measured";
    }
  }
}

/* Labelled points outside the field's box are counted and said: the field
 * cannot label them. */
static void count_outside(struct scene *sc, const struct vlff_cfg_field *fc) {
  size_t labelled = 0;
  for (size_t j = 0; j < sc->pts.n; j++) {
    if (sc->pts.label[j] == 255) continue;
    labelled++;
    const float *x = sc->pts.xyz + 3 * j;
    for (int a = 0; a < 3; a++)
      if (!(x[a] >= fc->scene_min[a] && x[a] <= fc->scene_max[a])) {
        sc->pts_outside++;
        break;
      }
  }
  if (sc->pts_outside)
    fprintf(stderr,
            "vlff-eval: %zu of %zu labelled points (%.1f %%) lie outside the scene box (%s): the field cannot "
            "label them, and they count as misses\n",
            sc->pts_outside, labelled, 100.0 * (double)sc->pts_outside / (double)(labelled ? labelled : 1),
            sc->box_from);
}

/* The frames --stride N takes: those whose number (a ScanNet scene's frame
 * number) is a multiple of N, lost ones left out. Fills idx (when not
 * NULL) and returns how many; *ntrain counts those not held out. */
static int stride_frames(const struct vlff_dataset *ds, int stride, int holdout, int *idx, int *ntrain) {
  int n = 0;
  *ntrain = 0;
  for (int i = 0; i < ds->n; i++)
    if (ds->number[i] % stride == 0) {
      if (idx) idx[n] = i;
      *ntrain += !held_out(n, holdout);
      n++;
    }
  return n;
}

/* The field's keyframes among the training frames. Every training frame
 * feeds fusion and the evidence, read one at a time; the field samples its
 * rays from all of its keyframes at every step, so their training copies
 * and features stay in memory, within keyframes.memory_mb as the node's
 * keyframe store. When the training frames need more, as many as fit are
 * taken spread evenly over the whole scene (the k-th of m from the middle
 * of its share of the training frames), so the field sees every part of a
 * recording, not only its start; said on stderr and in the report. */
static void choose_keyframes(struct scene *sc, const struct vlff_config *cfg, int fit) {
  int ntrain = 0;
  for (int i = 0; i < sc->n; i++) ntrain += !held_out(i, sc->holdout);
  const size_t nf = (size_t)sc->fw * sc->fh * sc->D;
  sc->key_mib = (double)((size_t)sc->tw * sc->th * (3 + sizeof(float)) + (sc->streaming ? nf * sizeof(uint16_t) : 0)) /
                (1 << 20);
  const double budget = cfg->keyframes.memory_mb;
  long m = ntrain;
  /* the synthetic room is rendered into memory whole; a run that fits
   * nothing keeps no keyframes */
  if (!fit) m = 0;
  else if (sc->streaming && ntrain * sc->key_mib > budget) {
    m = (long)(budget / sc->key_mib);
    if (m < 1)
      die("%s: a keyframe needs %.1f MiB (its training images at train.image_scale %.2f and its %dx%dx%d features), "
          "more than keyframes.memory_mb (%.0f): raise keyframes.memory_mb",
          VLFF_Q(sc->ds.dir), sc->key_mib, cfg->train.image_scale, sc->fw, sc->fh, sc->D, budget);
    fprintf(stderr,
            "vlff-eval: %s: the %d training frames need %.1f MiB as keyframes, more than keyframes.memory_mb (%.0f): "
            "the field fits on %ld of them spread over the whole scene (%.1f MiB); fusion and the evidence read all "
            "%d (raise keyframes.memory_mb to fit on more)\n",
            VLFF_Q(sc->ds.dir), ntrain, ntrain * sc->key_mib, budget, m, m * sc->key_mib, ntrain);
    sc->key_why = "keyframes.memory_mb";
  }
  sc->nkey = (int)m;
  for (int i = 0, t = 0, k = 0; i < sc->n && k < m; i++) {
    if (held_out(i, sc->holdout)) continue;
    /* training frame t is the k-th keyframe when it is the one nearest the
     * middle of the k-th m-th of them */
    if (t == (int)(((double)k + 0.5) * ntrain / (double)m)) sc->f[i].key = 1, k++;
    t++;
  }
}

/* The prompts' vectors: prompts.embeddings, else the scene's
 * prompt_embeddings.txt; ground-truth id k is record k. */
static void load_prompts(struct scene *sc, const struct vlff_dataset *ds, const struct vlff_config *cfg, char *p,
                         size_t cap) {
  char err[1024];
  if (cfg->prompts.embeddings[0]) snprintf(p, cap, "%s", cfg->prompts.embeddings);
  else snprintf(p, cap, "%s/prompt_embeddings.txt", ds->dir);
  /* Loaded with any dimension, then compared: a mismatch is between two
   * files, and either may be the wrong one. */
  struct vlff_embeddings *pe = vlff_embeddings_load(p, 0, err, sizeof err);
  if (!pe) die("%s", err);
  if (vlff_embeddings_dim(pe) != sc->D)
    die("%s: vectors have dim %d, but the features in %s/%s have D=%d: one of the two files is from "
        "another model",
        p, vlff_embeddings_dim(pe), ds->dir, ds->feat_files ? "features/" : "features.hdf", sc->D);
  if (vlff_embeddings_count(pe) > MAXK) die("%s: %d prompts, at most %d", p, vlff_embeddings_count(pe), MAXK);
  sc->K = vlff_embeddings_count(pe);
  for (int k = 0; k < sc->K; k++) {
    snprintf(sc->names[k], VLFF_PROMPT_LEN, "%s", vlff_embeddings_prompt(pe, k));
    memcpy(sc->emb + (size_t)k * sc->D, vlff_embeddings_vector(pe, k), (size_t)sc->D * sizeof(float));
  }
  vlff_embeddings_free(pe);
}

static void load_dataset(struct scene *sc, const struct opts *o, struct vlff_config *cfg) {
  char err[1024], p[4200];
  /* Every file the evaluation needs is checked before any frame is read,
   * and a missing one named as the layout calls it. */
  struct vlff_dataset_options dopt = {.layout = VLFF_DS_AUTO, .label_set = o->label_set, .label_tsv = o->label_tsv,
                                      .require = VLFF_DS_REQUIRE_POINTS | VLFF_DS_REQUIRE_LABELS |
                                                 VLFF_DS_REQUIRE_FEATURES};
  struct vlff_dataset ds;
  if (vlff_dataset_open_opts(&ds, o->dataset, &dopt, err, sizeof err) < 0) die("%s", err);
  /* the scene's directory, also when --dataset names its .sens file */
  const char *dir = ds.dir;
  if (!ds.has_features) die("%s: no features.hdf (needed for the feature field and the baselines)", dir);
  if (!ds.has_labels) die("%s: no gt_semantic/ or label-filt/ (needed for 2D evaluation)", dir);
  if (o->label_tsv && !ds.label_map) /* given, not used: said, not ignored */
    die("--label-tsv %s: %s's labels are class ids (gt_semantic/), which no label table maps", o->label_tsv, dir);
  if (ds.feature_dim > 1024) die("%s: D=%d is more than 1024", dir, ds.feature_dim);
  sc->W = ds.width, sc->H = ds.height, sc->fw = ds.feat_width, sc->fh = ds.feat_height, sc->D = ds.feature_dim;
  sc->fx = ds.fx, sc->fy = ds.fy, sc->cx = ds.cx, sc->cy = ds.cy;
  sc->holdout = o->holdout;
  char pts_path[4400];
  if (vlff_dataset_points_path(&ds, pts_path, sizeof pts_path, err, sizeof err) < 0) die("%s", err);
  load_prompts(sc, &ds, cfg, p, sizeof p);
  if (vlff_dataset_read_points(&ds, &sc->pts, err, sizeof err) < 0) die("%s", err);
  sc->stride = o->stride;
  int ntrain, *idx = xcalloc((size_t)ds.n, sizeof(int));
  sc->n = stride_frames(&ds, sc->stride, o->holdout, idx, &ntrain);
  /* features stored for some frames only must hold every frame the run takes */
  for (int i = 0; i < sc->n; i++)
    if (ds.feat_row[idx[i]] < 0) {
      char q[4400];
      if (ds.feat_files) snprintf(q, sizeof q, "%s/features/%s.hdf: missing", VLFF_Q(dir), VLFF_Q(ds.stem[idx[i]]));
      else snprintf(q, sizeof q, "%s/features.hdf: holds no map for frame %s", VLFF_Q(dir), VLFF_Q(ds.stem[idx[i]]));
      die("%s, which --stride %d takes (the features hold %d of the scene's %d frames): give a --stride whose "
          "frames they hold",
          q, sc->stride, ds.feat_frames, ds.n);
    }
  sc->f = xcalloc((size_t)sc->n, sizeof *sc->f);
  size_t npx = (size_t)sc->W * sc->H, nf = (size_t)sc->fw * sc->fh * sc->D;
  sc->srgb = xcalloc(npx, 3), sc->sfeat = xcalloc(nf, sizeof(uint16_t)), sc->sdepth = xcalloc(npx, sizeof(float));
  sc->slabel = xcalloc(npx, 1);
  for (int i = 0; i < sc->n; i++) {
    struct frame *f = &sc->f[i];
    f->index = idx[i];
    memcpy(f->c2w, ds.c2w + 16 * (size_t)f->index, sizeof f->c2w);
  }
  free(idx);
  sc->ds = ds; /* kept open: frames are read when a pass needs them */
  sc->streaming = 1;
  /* A ground-truth class without a record would silently count as
   * unlabelled and drop out of every score: refuse, naming the first file
   * that uses one, before anything is fitted (each label image is read
   * once here and again when scored). */
  for (int i = 0; i < sc->n; i++) {
    const struct frame *f = frame_data(sc, i, FD_LABEL);
    for (size_t j = 0; j < npx; j++)
      if (f->label[j] != 255 && f->label[j] >= sc->K)
        die("%s: %d records, but %s/%s/%s.png uses class id %d: ground-truth id k is record k, so "
            "every class needs one",
            p, sc->K, dir, sc->ds.label_dir, sc->ds.stem[f->index], f->label[j]);
  }
  for (size_t j = 0; j < sc->pts.n; j++)
    if (sc->pts.label[j] != 255 && sc->pts.label[j] >= sc->K)
      die("%s: %d records, but %s uses class id %d (vertex %zu): ground-truth id k is record k, so every class "
          "needs one",
          p, sc->K, pts_path, sc->pts.label[j], j);
  dataset_box(sc, &sc->ds, cfg);
}

/* The training image size at train.image_scale. */
static void training_size(struct scene *sc, double scale) {
  sc->tw = (int)(sc->W * scale + 0.5), sc->th = (int)(sc->H * scale + 0.5);
  if (sc->tw < 8) sc->tw = 8;
  if (sc->th < 8) sc->th = 8;
}

/* A keyframe's training copies at train.image_scale from its full-size
 * images: colour box-filtered, depth the nearest sample (averaging depth
 * across an edge invents surfaces). */
static void make_training_copy(const struct scene *sc, struct frame *f) {
  f->trgb = xcalloc((size_t)sc->tw * sc->th, 3);
  f->tdepth = xcalloc((size_t)sc->tw * sc->th, sizeof(float));
  for (int v = 0; v < sc->th; v++)
    for (int u = 0; u < sc->tw; u++) {
      int u0 = u * sc->W / sc->tw, u1 = (u + 1) * sc->W / sc->tw;
      int v0 = v * sc->H / sc->th, v1 = (v + 1) * sc->H / sc->th;
      if (u1 <= u0) u1 = u0 + 1;
      if (v1 <= v0) v1 = v0 + 1;
      unsigned acc[3] = {0, 0, 0}, cnt = 0;
      for (int y = v0; y < v1; y++)
        for (int x = u0; x < u1; x++) {
          for (int c = 0; c < 3; c++) acc[c] += f->rgb[((size_t)y * sc->W + x) * 3 + c];
          cnt++;
        }
      for (int c = 0; c < 3; c++) f->trgb[((size_t)v * sc->tw + u) * 3 + c] = (uint8_t)((acc[c] + cnt / 2) / cnt);
      int cu = (int)((u + 0.5) * sc->W / sc->tw), cv = (int)((v + 0.5) * sc->H / sc->th);
      f->tdepth[(size_t)v * sc->tw + u] = f->depth[(size_t)cv * sc->W + cu];
    }
}

/* ---- progress ----------------------------------------------------------- */

static void progress(int it, int total, const struct vlff_train_stats *st, double t0, int tty) {
  double el = vlff_seconds() - t0, rate = it / (el > 1e-9 ? el : 1e-9);
  double eta = rate > 0 ? (total - it) / rate : 0;
  int bar = total ? 30 * it / total : 30;
  char b[31];
  for (int i = 0; i < 30; i++) b[i] = i < bar ? '#' : '.';
  b[30] = 0;
  /* On a terminal the line is rewritten in place, and a warning logged
   * meanwhile gets a line of its own (log.h). */
  char line[256];
  snprintf(line, sizeof line, "[%s] it %d/%d  loss %.4f (rgb %.4f depth %.4f feat %.4f)  psnr %.1f  %.1f it/s  ETA %d:%02d",
           b, it, total, st->loss, st->loss_rgb, st->loss_depth, st->loss_feat, st->psnr, rate, (int)eta / 60,
           (int)eta % 60);
  if (tty) vlff_log_status("%s  ", line);
  else fprintf(stderr, "%s\n", line);
}

/* ---- output helpers ----------------------------------------------------- */

static void colour_of(int k, uint8_t out[3]) {
  const uint8_t *c = vlff_label_color(k >= 0 && k < 20 ? k : -1);
  memcpy(out, c, 3);
}

/* image | prediction | ground truth, at the image size (predictions at the
 * evaluation resolution are shown nearest-upsampled). */
static void write_overlay(const char *dir, const struct scene *sc, const struct frame *f, const int *pred,
                          int pw, int ph) {
  int W = sc->W, H = sc->H;
  uint8_t *img = xcalloc((size_t)W * 3 * H, 3);
  for (int v = 0; v < H; v++)
    for (int u = 0; u < W; u++) {
      uint8_t *row = img + (size_t)v * W * 3 * 3;
      memcpy(row + (size_t)u * 3, f->rgb + ((size_t)v * W + u) * 3, 3);
      int pu = u * pw / W, pv = v * ph / H;
      uint8_t c[3];
      colour_of(pred[(size_t)pv * pw + pu], c);
      for (int k = 0; k < 3; k++) row[(size_t)(W + u) * 3 + k] = (uint8_t)(0.35 * f->rgb[((size_t)v * W + u) * 3 + k] + 0.65 * c[k]);
      int g = f->label[(size_t)v * W + u];
      colour_of(g < sc->K ? g : -1, c);
      memcpy(row + (size_t)(2 * W + u) * 3, c, 3);
    }
  char p[4200], err[512];
  snprintf(p, sizeof p, "%s/overlay_%05d.png", dir, f->index);
  if (vlff_png_write(p, img, 3 * W, H, 3, 0, err, sizeof err) < 0) fprintf(stderr, "vlff-eval: %s\n", err);
  free(img);
}

struct result {
  struct vlff_confusion c;
  struct vlff_summary s;
  int valid;
};

static void summarize(struct result *r) {
  vlff_confusion_summary(&r->c, &r->s);
  /* No labelled sample (every held-out pixel or every point unlabelled):
   * nothing was scored, which is n/a, not a score of 0. */
  r->valid = r->s.present > 0;
}

/* A result as JSON (null when it was not computed). json-c escapes every
 * string: scene paths and prompt texts come from users. */
static struct json_object *json_result(const struct result *r) {
  if (!r->valid) return NULL;
  struct json_object *o = json_object_new_object();
  json_object_object_add(o, "miou", json_object_new_double(r->s.miou));
  json_object_object_add(o, "macc", json_object_new_double(r->s.macc));
  json_object_object_add(o, "mprec", json_object_new_double(r->s.mprec));
  json_object_object_add(o, "pixel_acc", json_object_new_double(r->s.pixel_acc));
  json_object_object_add(o, "present", json_object_new_int(r->s.present));
  struct json_object *cl = json_object_new_array();
  for (int k = 0; k < r->c.k; k++) {
    struct vlff_class_score cs;
    vlff_confusion_class(&r->c, k, &cs);
    struct json_object *c = json_object_new_object();
    json_object_object_add(c, "tp", json_object_new_uint64(cs.tp));
    json_object_object_add(c, "fp", json_object_new_uint64(cs.fp));
    json_object_object_add(c, "fn", json_object_new_uint64(cs.fn));
    json_object_array_add(cl, c);
  }
  json_object_object_add(o, "classes", cl);
  return o;
}

static const char *pct(const struct result *r, double v, char *buf) {
  if (!r->valid) return "n/a";
  snprintf(buf, 16, "%.1f", 100 * v);
  return buf;
}

/* A class's cell in the per-class tables: "-" where the result was not
 * computed or the class is absent from its ground truth. */
#define CELL(r, s, buf) ((r).valid && (s).present ? pct(&(r), (s).iou, buf) : "-")

/* ---- the run, stage by stage --------------------------------------------- */

/* What one run carries from stage to stage. */
struct eval {
  struct opts o;
  char page_dir[64]; /* the evidence's page file's directory while it pages */
  struct vlff_config cfg;
  struct scene sc;
  float *emb_raw;  /* the prompts' vectors as loaded; sc.emb holds them normalised */
  int ntrain, ntest;
  /* standard protocol: raw 2D and fusion 3D are the baselines; the
   * field's 3D also under the reference protocol */
  struct result r2_raw, r2_field, r3_fusion, r3_field, r3_field_ref, r3_alone, r2_alone;
  struct vlff_evidence *ev; /* the training frames' features per voxel, when publish.evidence_weight > 0 */
  uint8_t *gl;     /* a held-out frame's labels at the feature-map resolution */
  int *pl;         /* and a prediction at that resolution */
  int *p3;         /* fusion's label per point */
  uint8_t *seen3;  /* 1 where a training frame saw the point */
  int *pred3;      /* the field's label per point; NULL until it is queried */
  int fitted, steps;
  double fit_s;
  struct vlff_train_stats st;
};

/* Options, the config file and the options that override it, the report
 * directory. */
static void configure(struct eval *e, int argc, char **argv) {
  struct opts *o = &e->o;
  struct vlff_config *cfg = &e->cfg;
  char err[1024];
  parse_args(argc, argv, o);
  vlff_config_defaults(cfg);
  if (o->config && vlff_config_load(o->config, cfg, err, sizeof err) < 0) exit(vlff_cli_config_error(err));
  if (o->seed >= 0) cfg->sim.seed = o->seed;
  if (o->frames > 0) cfg->sim.frames = o->frames;
  if (o->difficulty >= 0) cfg->sim.difficulty = o->difficulty;
  if (o->dim > 0) cfg->field.feature_dim = o->dim;
  if (o->threads >= 0) cfg->node.threads = o->threads;
  if (mkdir(o->out, 0755) < 0 && errno != EEXIST) die("%s: cannot create: %s", o->out, strerror(errno));
  /* before the fit, not after it: a file, a FIFO or a directory it cannot
   * write in was found only when the report was written, hours later */
  struct stat st;
  if (stat(o->out, &st) < 0 || !S_ISDIR(st.st_mode)) die("--out %s: not a directory", o->out);
  char probe[4200];
  snprintf(probe, sizeof probe, "%s/.vlff-eval-probe-XXXXXX", o->out);
  int fd = mkstemp(probe);
  if (fd < 0) die("--out %s: cannot write there: %s", o->out, strerror(errno));
  close(fd);
  unlink(probe);
}

/* The scene (a dataset or the synthetic room), its training images, the
 * train/held-out split and the results' confusion matrices. */
static void load_scene(struct eval *e) {
  const struct opts *o = &e->o;
  struct scene *sc = &e->sc;
  char err[1024];
  double t_load = vlff_seconds();
  sc->holdout = o->holdout;
  if (o->dataset) load_dataset(sc, o, &e->cfg);
  else load_sim(sc, &e->cfg);
  count_outside(sc, &e->cfg.field);
  if (sc->D != e->cfg.field.feature_dim) {
    if (o->dataset) e->cfg.field.feature_dim = sc->D;
    else die("feature dims differ: scene %d, field %d", sc->D, e->cfg.field.feature_dim);
  }
  e->emb_raw = xcalloc((size_t)sc->K * sc->D, sizeof(float));
  memcpy(e->emb_raw, sc->emb, (size_t)sc->K * sc->D * sizeof(float));
  vlff_normalize_rows(e->emb_raw, sc->emb, sc->K, sc->D);
  for (int i = 0; i < sc->n; i++) held_out(i, o->holdout) ? e->ntest++ : e->ntrain++;
  if (e->ntest == 0 || e->ntrain == 0)
    die("%d frames with --holdout %d leave no training or no test frames", sc->n, o->holdout);
  training_size(sc, e->cfg.train.image_scale);
  choose_keyframes(sc, &e->cfg, o->iters > 0 || o->fit_seconds > 0);
  /* the synthetic room's frames are in memory: its keyframes' copies now
   * (a dataset's are made in the training pass, as each is read) */
  if (!sc->streaming)
    for (int i = 0; i < sc->n; i++)
      if (sc->f[i].key) make_training_copy(sc, &sc->f[i]);
  fprintf(stderr, "vlff-eval: scene %s: %d frames (%d train, %d held out) %dx%d, features %dx%dx%d, %zu labelled points, %d prompts (%.1f s)\n",
          o->dataset ? o->dataset : "synthetic", sc->n, e->ntrain, e->ntest, sc->W, sc->H, sc->fw, sc->fh, sc->D,
          sc->pts.n, sc->K, vlff_seconds() - t_load);
  if (o->dataset && sc->ds.skipped)
    fprintf(stderr, "vlff-eval: scene %s: %d more frames without a pose (lost tracking) skipped\n", o->dataset,
            sc->ds.skipped);
  const int K = sc->K;
  if (vlff_confusion_init(&e->r2_raw.c, K, err, sizeof err) < 0 ||
      vlff_confusion_init(&e->r2_field.c, K, err, sizeof err) < 0 ||
      vlff_confusion_init(&e->r3_fusion.c, K, err, sizeof err) < 0 ||
      vlff_confusion_init(&e->r3_field.c, K, err, sizeof err) < 0 ||
      vlff_confusion_init(&e->r3_field_ref.c, K, err, sizeof err) < 0 ||
      vlff_confusion_init(&e->r3_alone.c, K, err, sizeof err) < 0 ||
      vlff_confusion_init(&e->r2_alone.c, K, err, sizeof err) < 0)
    die("%s", err);
}

/* 2D baseline: the held-out frames' raw features, segmented with the
 * prompts at the feature-map resolution. */
static void baseline_raw_2d(struct eval *e) {
  struct scene *sc = &e->sc;
  const int fw = sc->fw, fh = sc->fh;
  e->gl = xcalloc((size_t)fw * fh, 1);
  e->pl = xcalloc((size_t)fw * fh, sizeof(int));
  for (int i = 0; i < sc->n; i++) {
    if (!held_out(i, e->o.holdout)) continue;
    const struct frame *f = frame_data(sc, i, FD_FEAT | FD_LABEL);
    vlff_downsample_labels(f->label, sc->W, sc->H, e->gl, fw, fh);
    vlff_classify_f16(f->feat, (size_t)fw * fh, sc->D, sc->emb, sc->K, e->pl, NULL);
    vlff_confusion_add(&e->r2_raw.c, e->gl, e->pl, (size_t)fw * fh);
  }
  summarize(&e->r2_raw);
}

static void build_evidence_begin(struct eval *e);

/* The pass over the training frames, each read once: OpenScene-style
 * multi-view fusion of their features at the labelled points (the 3D
 * baseline; vlff_fusion_add keeps [points][K] sums, so one view at a time
 * is in memory), the evidence the node would hold after admitting them
 * (when a fit will use it), and the keyframes' training copies and
 * features, which stay. Returns the labelled points no training view saw. */
static size_t training_pass(struct eval *e) {
  struct scene *sc = &e->sc;
  const int K = sc->K, D = sc->D;
  const size_t np = sc->pts.n, nf = (size_t)sc->fw * sc->fh * D;
  const int fit = e->o.iters > 0 || e->o.fit_seconds > 0;
  char err[1024];
  if (fit && e->cfg.publish.evidence_weight > 0) build_evidence_begin(e);
  e->p3 = xcalloc(np, sizeof(int));
  e->seen3 = xcalloc(np, 1);
  double *acc = xcalloc(np * (size_t)K, sizeof(double));
  int *seen = xcalloc(np, sizeof(int));
  for (int i = 0; i < sc->n; i++) {
    if (held_out(i, e->o.holdout)) continue;
    struct frame *f = frame_data(sc, i, FD_DEPTH | FD_FEAT | (sc->f[i].key ? FD_RGB : 0));
    struct vlff_fusion_view fv = {.width = sc->W, .height = sc->H, .fx = sc->fx, .fy = sc->fy, .cx = sc->cx,
                                  .cy = sc->cy, .depth = f->depth, .feat_width = sc->fw, .feat_height = sc->fh,
                                  .features = f->feat};
    memcpy(fv.c2w, f->c2w, sizeof fv.c2w);
    if (vlff_fusion_add(sc->pts.xyz, np, &fv, D, sc->emb, K, 0.05, acc, seen, err, sizeof err) < 0) die("%s", err);
    if (e->ev) {
      struct vlff_view v = {.width = sc->W, .height = sc->H, .fx = sc->fx, .fy = sc->fy, .cx = sc->cx, .cy = sc->cy,
                            .depth = f->depth, .features = f->feat, .feat_width = sc->fw, .feat_height = sc->fh,
                            .feature_dim = D};
      memcpy(v.c2w, f->c2w, sizeof v.c2w);
      if (vlff_evidence_add(e->ev, &v, err, sizeof err) < 0) die("frame %d: %s", f->index, err);
    }
    if (sc->streaming && f->key) {
      make_training_copy(sc, f);
      f->kfeat = xcalloc(nf, sizeof(uint16_t));
      memcpy(f->kfeat, f->feat, nf * sizeof(uint16_t));
    }
  }
  vlff_fusion_labels(acc, seen, np, K, e->p3);
  size_t unseen = 0;
  for (size_t k = 0; k < np; k++) {
    unseen += seen[k] == 0 && sc->pts.label[k] < K;
    e->seen3[k] = seen[k] != 0;
  }
  free(acc), free(seen);
  vlff_confusion_add(&e->r3_fusion.c, sc->pts.label, e->p3, np);
  summarize(&e->r3_fusion);
  if (e->ev && (vlff_evidence_overflow(e->ev) || vlff_evidence_evicted(e->ev)))
    fprintf(stderr,
            "vlff-eval: evidence: publish.evidence_max_mb holds %zu voxels, too few (%lld voxels given up, %lld "
            "samples lost)\n",
            vlff_evidence_voxels(e->ev), vlff_evidence_evicted(e->ev), vlff_evidence_overflow(e->ev));
  if (e->ev && vlff_evidence_paged_out(e->ev))
    fprintf(stderr, "vlff-eval: evidence: publish.evidence_max_mb holds %zu voxels; %zu more paged out%s%s\n",
            vlff_evidence_voxels(e->ev), vlff_evidence_paged(e->ev), vlff_evidence_page_errors(e->ev) ? ": " : "",
            vlff_evidence_page_error(e->ev));
  return unseen;
}

static void baselines(struct eval *e) {
  baseline_raw_2d(e);
  double t = vlff_seconds();
  size_t unseen = training_pass(e);
  char a[16], b[16];
  fprintf(stderr, "vlff-eval: baselines: raw 2D mIoU %s, fusion 3D mIoU %s, %zu labelled points no training view saw (%.1f s)\n",
          pct(&e->r2_raw, e->r2_raw.s.miou, a), pct(&e->r3_fusion, e->r3_fusion.s.miou, b), unseen,
          vlff_seconds() - t);
  if (!e->r2_raw.valid)
    fprintf(stderr, "vlff-eval: no held-out pixel carries a class (every one unlabelled): the 2D scores are n/a\n");
  if (!e->r3_fusion.valid)
    fprintf(stderr, "vlff-eval: no labelled point carries a class (every one unlabelled): the 3D scores are n/a\n");
}

/* The field, fitted on the training frames for --iters steps or
 * --fit-seconds of wall clock, with progress on stderr. */
static struct vlff_field *fit_field(struct eval *e) {
  const struct opts *o = &e->o;
  const struct scene *sc = &e->sc;
  char err[1024];
  struct vlff_field *fld = vlff_field_create(&e->cfg.field, &e->cfg.train, e->cfg.node.threads, err, sizeof err);
  if (!fld) die("%s", err);
  /* the prompts are known before fitting, as in the node (class-balanced
   * ray drawing reads them) */
  if (vlff_field_set_prompts(fld, e->emb_raw, sc->K, err, sizeof err) < 0) die("%s", err);
  struct vlff_view *views = xcalloc((size_t)e->ntrain, sizeof *views);
  int nv = 0;
  double s = (double)sc->tw / sc->W, sy = (double)sc->th / sc->H;
  for (int i = 0; i < sc->n; i++) {
    if (held_out(i, o->holdout) || !sc->f[i].key) continue;
    struct vlff_view *v = &views[nv++];
    v->width = sc->tw, v->height = sc->th, v->rgb = sc->f[i].trgb, v->depth = sc->f[i].tdepth;
    v->fx = sc->fx * s, v->fy = sc->fy * sy, v->cx = sc->cx * s, v->cy = sc->cy * sy;
    memcpy(v->c2w, sc->f[i].c2w, sizeof v->c2w);
    v->feat_width = sc->fw, v->feat_height = sc->fh, v->feature_dim = sc->D;
    v->features = sc->f[i].kfeat ? sc->f[i].kfeat : sc->f[i].feat;
  }
  int tty = isatty(2) && !o->quiet;
  double t0 = vlff_seconds(), last = t0;
  /* --fit-seconds: steps until the budget is spent (the clock is read
   * after each step, so the last step may end a little past it) */
  for (int it = 1; o->fit_seconds > 0 ? vlff_seconds() - t0 < o->fit_seconds : it <= o->iters; it++) {
    if (vlff_field_step(fld, views, nv, NULL, &e->st, err, sizeof err) < 0) die("training step %d: %s", it, err);
    e->steps = it;
    double t = vlff_seconds();
    int total = o->iters;
    if (o->fit_seconds > 0) total = (int)(it * o->fit_seconds / fmax(t - t0, 1e-9));
    int every = o->fit_seconds > 0 ? 0 : (o->iters / 10 > 0 ? o->iters / 10 : 1);
    if (!o->quiet && (it == o->iters || (tty ? t - last > 0.25
                                             : every ? it % every == 0 : t - last > o->fit_seconds / 10))) {
      progress(it, total > it ? total : it, &e->st, t0, tty);
      last = t;
    }
  }
  if (tty) vlff_log_status_end();
  e->fit_s = vlff_seconds() - t0;
  free(views);
  return fld;
}

struct field_read;
static void evidence_labels(struct eval *e, struct vlff_field *fld, const float *xyz, size_t n,
                            const struct field_read *fr, int *label, float *scores);

/* 2D: the held-out frames rendered at the feature-map resolution and
 * segmented: the field alone; and with evidence, the node's label image
 * (publish.label_image: surface): a pixel whose measured depth ends on a
 * surface is labelled there (moved onto the field's surface within the
 * sensor's noise) by the field's cosines and the evidence, voted with its
 * region of the view's image (publish.region_weight, regions.h), the rest
 * keep the rendered label. The first --overlays frames are drawn beside
 * their truth. */
static void score_field_2d(struct eval *e, struct vlff_field *fld) {
  struct scene *sc = &e->sc;
  const int fw = sc->fw, fh = sc->fh;
  const size_t npx = (size_t)fw * fh;
  struct vlff_view cam = {0};
  cam.width = fw, cam.height = fh;
  cam.fx = sc->fx * fw / sc->W, cam.fy = sc->fy * fh / sc->H, cam.cx = sc->cx * fw / sc->W, cam.cy = sc->cy * fh / sc->H;
  float *xyz = xcalloc(3 * npx, sizeof(float));
  uint32_t *pix = xcalloc(npx, sizeof(uint32_t));
  int *lab = xcalloc(npx, sizeof(int));
  const float beta = (float)e->cfg.publish.region_weight;
  struct vlff_regions *rg = e->ev && beta > 0 ? vlff_regions_create(fw, fh) : NULL;
  if (e->ev && beta > 0 && !rg) die("out of memory");
  float *col = rg ? xcalloc(3 * npx, sizeof(float)) : NULL, *vec = rg ? xcalloc(npx * (size_t)sc->K, sizeof(float)) : NULL;
  int nover = 0;
  for (int i = 0; i < sc->n; i++) {
    if (!held_out(i, e->o.holdout)) continue;
    memcpy(cam.c2w, sc->f[i].c2w, sizeof cam.c2w);
    if (vlff_field_render(fld, &cam, NULL, NULL, NULL, e->pl, NULL) < 0) die("render of frame %d failed", i);
    const int overlay = nover < e->o.overlays;
    const struct frame *f = frame_data(sc, i, FD_LABEL | (e->ev ? FD_DEPTH : 0) | (overlay || rg ? FD_RGB : 0));
    vlff_downsample_labels(f->label, sc->W, sc->H, e->gl, fw, fh);
    vlff_confusion_add(&e->r2_alone.c, e->gl, e->pl, npx);
    if (e->ev) {
      /* the cells the node's label image reads on the measured surface */
      size_t m = vlff_label_surface(f->c2w, sc->fx, sc->fy, sc->cx, sc->cy, sc->W, sc->H, f->depth, fw, fh, xyz, pix,
                                    NULL, NULL);
      if (rg) {
        /* regions of the measured points, as the publisher groups them */
        vlff_regions_colours(f->rgb, sc->W, sc->H, fw, fh, pix, m, col);
        const double o[3] = {f->c2w[3], f->c2w[7], f->c2w[11]};
        vlff_regions_build(rg, col, pix, xyz, m, o, (float)e->cfg.train.depth_noise_m);
      }
      vlff_field_snap_surface(fld, &cam, pix, m, xyz);
      evidence_labels(e, fld, xyz, m, NULL, lab, vec);
      if (rg && vlff_regions_vote(rg, vec, m, sc->K, beta, lab, NULL)) die("out of memory");
      for (size_t j = 0; j < m; j++) e->pl[pix[j]] = lab[j];
    }
    vlff_confusion_add(&e->r2_field.c, e->gl, e->pl, npx);
    if (overlay) {
      write_overlay(e->o.out, sc, f, e->pl, fw, fh);
      nover++;
    }
  }
  free(xyz), free(pix), free(lab), free(col), free(vec);
  vlff_regions_destroy(rg);
  summarize(&e->r2_field);
  summarize(&e->r2_alone);
}

/* The evidence the node would hold after admitting the training frames:
 * their features averaged per voxel of the node's map grid (evidence.h);
 * the training pass adds them. */
static void build_evidence_begin(struct eval *e) {
  char err[1024];
  e->ev = vlff_evidence_for(&e->cfg.publish, &e->cfg.field, MAXK, err, sizeof err);
  if (!e->ev) die("%s", err);
  /* Paged as the node pages it (publish.evidence_page_mb), in a directory
   * of its own under TMPDIR: vlff-eval keeps no state. */
  if (e->cfg.publish.evidence_page_mb > 0) {
    const char *tmp = getenv("TMPDIR") && *getenv("TMPDIR") ? getenv("TMPDIR") : "/tmp";
    char path[sizeof e->page_dir + 16];
    if (snprintf(e->page_dir, sizeof e->page_dir, "%s/vlff-eval-XXXXXX", tmp) >= (int)sizeof e->page_dir ||
        !mkdtemp(e->page_dir))
      die("evidence: no directory for its page file under %s: %s", tmp, strerror(errno));
    snprintf(path, sizeof path, "%s/evidence.pages", e->page_dir);
    if (vlff_evidence_page_to(e->ev, path, (size_t)e->cfg.publish.evidence_page_mb << 20, err, sizeof err))
      die("%s", err);
  }
}

/* The evidence and its page file's directory gone. */
static void evidence_free(struct eval *e) {
  vlff_evidence_destroy(e->ev);
  e->ev = NULL;
  if (e->page_dir[0]) rmdir(e->page_dir);
  e->page_dir[0] = 0;
}

/* What the field says at n points: its cosines with each prompt [n][K]
 * and its exposure there. */
struct field_read {
  float *cs;
  uint16_t *rays;
};

static struct field_read read_field(struct vlff_field *fld, const float *xyz, size_t n) {
  int K;
  vlff_field_prompt_embeddings(fld, &K);
  struct field_read r = {xcalloc(n * (size_t)K, sizeof(float)), xcalloc(n, sizeof(uint16_t))};
  if (vlff_field_query_cosines(fld, xyz, n, r.cs) < 0) die("3D query failed");
  vlff_field_exposure(fld, xyz, n, r.rays);
  return r;
}

/* n points labelled as the node labels its map: the field's cosines there,
 * weighed by its exposure, combined with the voxels' evidence (points in
 * voxels without evidence keep the field's label). fr: the field read at
 * those points, or NULL to read it now; scores: NULL, or [n][K] for each
 * point's sums (evidence.h). */
static void evidence_labels(struct eval *e, struct vlff_field *fld, const float *xyz, size_t n,
                            const struct field_read *fr, int *label, float *scores) {
  int K;
  const float *E = vlff_field_prompt_embeddings(fld, &K);
  struct field_read own = {0};
  if (!fr) own = read_field(fld, xyz, n), fr = &own;
  vlff_evidence_label_scores(e->ev, xyz, n, fr->cs, fr->rays, e->cfg.publish.field_trust_rays, E, K, 1,
                             (float)e->cfg.publish.evidence_weight, label, NULL, NULL, scores);
  free(own.cs), free(own.rays);
}

/* 3D standard protocol: one query per labelled point (fr: the field read
 * at them, for the evidence). */
static void score_field_3d(struct eval *e, struct vlff_field *fld, const struct field_read *fr) {
  const struct scene *sc = &e->sc;
  const size_t np = sc->pts.n;
  e->pred3 = xcalloc(np, sizeof(int));
  if (vlff_field_query(fld, sc->pts.xyz, np, NULL, NULL, e->pred3, NULL, NULL) < 0) die("3D query failed");
  vlff_confusion_add(&e->r3_alone.c, sc->pts.label, e->pred3, np);
  summarize(&e->r3_alone);
  if (e->ev) evidence_labels(e, fld, sc->pts.xyz, np, fr, e->pred3, NULL);
  vlff_confusion_add(&e->r3_field.c, sc->pts.label, e->pred3, np);
  summarize(&e->r3_field);
}

/* 3D reference protocol: features averaged over 10 queries jittered
 * uniformly within +-2 cm per axis */
static void score_field_3d_reference(struct eval *e, struct vlff_field *fld) {
  const struct scene *sc = &e->sc;
  const size_t np = sc->pts.n;
  const int D = sc->D;
  const size_t chunk = 4096;
  float *acc = xcalloc(chunk * D, sizeof(float)), *fb = xcalloc(chunk * D, sizeof(float));
  float *jx = xcalloc(chunk * 3, sizeof(float));
  int *pr = xcalloc(chunk, sizeof(int));
  uint64_t rs = 0; /* the jitter, the same every run */
  for (size_t s0 = 0; s0 < np; s0 += chunk) {
    size_t m = np - s0 < chunk ? np - s0 : chunk;
    memset(acc, 0, m * D * sizeof(float));
    for (int q = 0; q < 10; q++) {
      for (size_t k = 0; k < 3 * m; k++) {
        jx[k] = sc->pts.xyz[3 * s0 + k] + (float)(vlff_rng_double(&rs) * 0.04 - 0.02);
      }
      if (vlff_field_query(fld, jx, m, NULL, fb, NULL, NULL, NULL) < 0) die("3D query failed");
      for (size_t k = 0; k < m * D; k++) acc[k] += fb[k];
    }
    vlff_classify_f32(acc, m, D, sc->emb, sc->K, pr, NULL);
    vlff_confusion_add(&e->r3_field_ref.c, sc->pts.label + s0, pr, m);
  }
  free(acc), free(fb), free(jx), free(pr);
  summarize(&e->r3_field_ref);
}

/* The census of lost classes over the labelled points, as the node's 3D
 * map takes it (evidence.h, "Lost classes"), before anything is labelled. */
static void census(struct eval *e, struct vlff_field *fld, const struct field_read *fr) {
  const size_t np = e->sc.pts.n;
  int *lab = xcalloc(np, sizeof(int));
  vlff_evidence_census_begin(e->ev);
  evidence_labels(e, fld, e->sc.pts.xyz, np, fr, lab, NULL);
  int nlost = vlff_evidence_census_end(e->ev, e->cfg.publish.lost_class_ratio);
  for (int k = 0; k < e->sc.K && nlost; k++) {
    unsigned long long nf, ne;
    if (vlff_evidence_lost(e->ev, k, &nf, &ne))
      fprintf(stderr, "vlff-eval: the field labels '%s' at %llu points, the evidence at %llu: read from the evidence\n",
              VLFF_Q(e->sc.names[k]), nf, ne);
  }
  free(lab);
}

static void score_field(struct eval *e, struct vlff_field *fld) {
  char err[1024];
  if (vlff_field_set_prompts(fld, e->emb_raw, e->sc.K, err, sizeof err) < 0) die("%s", err);
  /* The field read at the 3D points serves the census and the 3D score. */
  struct field_read fr3 = {0};
  if (e->ev) {
    fr3 = read_field(fld, e->sc.pts.xyz, e->sc.pts.n);
    census(e, fld, &fr3);
  }
  score_field_2d(e, fld);
  score_field_3d(e, fld, &fr3);
  free(fr3.cs), free(fr3.rays);
  score_field_3d_reference(e, fld);
  evidence_free(e);
  e->fitted = 1;
}

/* prediction.ply: the labelled points coloured by the field's labels, or
 * by fusion's when the field was not fitted. */
static void write_prediction_ply(const struct eval *e) {
  const size_t np = e->sc.pts.n;
  const int *pred = e->pred3 ? e->pred3 : e->p3;
  char err[1024];
  uint8_t *col = xcalloc(np, 3), *lab = xcalloc(np, 1);
  for (size_t k = 0; k < np; k++) {
    colour_of(pred[k], col + 3 * k);
    lab[k] = pred[k] >= 0 && pred[k] < 255 ? (uint8_t)pred[k] : 255;
  }
  char p[4200];
  snprintf(p, sizeof p, "%s/prediction.ply", e->o.out);
  if (vlff_ply_write(p, e->sc.pts.xyz, col, lab, np, err, sizeof err) < 0) fprintf(stderr, "vlff-eval: %s\n", err);
  free(col), free(lab);
}

/* A dataset frame by its own name (its file stem: the frame number of a
 * ScanNet scene, which lost-tracking frames leave with gaps), not by its
 * position among the usable frames. */
static const char *frame_name(const struct scene *sc, int i) { return sc->ds.stem[sc->f[i].index]; }

/* The frame's name in report.json: a number when the stem is one (the
 * simulator's frames are their numbers). */
static struct json_object *frame_json(const struct scene *sc, int i) {
  if (!sc->ds.stem) return json_object_new_int(sc->f[i].index);
  const char *s = frame_name(sc, i);
  char *end;
  errno = 0;
  long v = strtol(s, &end, 10);
  if (s[0] && !*end && !errno && v >= 0 && v <= INT32_MAX) return json_object_new_int((int32_t)v);
  return json_object_new_string(s);
}

static void write_report_md(const struct eval *e) {
  const struct opts *o = &e->o;
  const struct scene *sc = &e->sc;
  const struct result *r2_raw = &e->r2_raw, *r2_field = &e->r2_field, *r3_fusion = &e->r3_fusion;
  const struct result *r3_field = &e->r3_field, *r3_field_ref = &e->r3_field_ref;
  char a[16], b[16], c[16], d[16], x[16];
  char path[4200];
  snprintf(path, sizeof path, "%s/report.md", o->out);
  FILE *md = fopen(path, "w");
  if (!md) die("%s: %s", path, strerror(errno));
  if (o->dataset) {
    fprintf(md, "# vlff-eval report\n\nScene: dataset `%s`, frames %s to %s, every %d-th", o->dataset,
            frame_name(sc, 0), frame_name(sc, sc->n - 1), sc->stride);
  }
  else
    fprintf(md, "# vlff-eval report\n\nScene: synthetic room (seed %d, difficulty %.2f)", e->cfg.sim.seed,
            e->cfg.sim.difficulty);
  fprintf(md, ", %d frames: %d train, %d held out (every %d-th); %dx%d images, features %dx%dx%d; "
              "%zu labelled points; %d prompts.\nField: %s.\n\n",
          sc->n, e->ntrain, e->ntest, o->holdout, sc->W, sc->H, sc->fw, sc->fh, sc->D, sc->pts.n, sc->K,
          e->fitted ? "fitted" : "not fitted (--iters 0)");
  if (e->fitted && sc->key_why)
    fprintf(md, "Keyframes: the field fitted on %d of the %d training frames, spread over the scene (all of them "
                "would need more than %s, %d MiB); fusion and the evidence used all.\n\n",
            sc->nkey, e->ntrain, sc->key_why, e->cfg.keyframes.memory_mb);
  if (e->fitted)
    fprintf(md, "Training: %d steps in %.1f s (%.2f steps/s), last loss %.4f, PSNR %.1f dB.\n\n", e->steps, e->fit_s,
            e->steps / e->fit_s, e->st.loss, e->st.psnr);
  fprintf(md, "## Standard protocol\n\nPer-class IoU from TP/FP/FN summed over the scene; mIoU and mAcc "
              "(per-class recall) averaged over classes present in the ground truth. Percent.\n\n"
              "| method | 2D mIoU | 2D mAcc | 3D mIoU | 3D mAcc |\n|---|---|---|---|---|\n");
  fprintf(md, "| raw per-frame features (2D) | %s | %s | - | - |\n", pct(r2_raw, r2_raw->s.miou, a), pct(r2_raw, r2_raw->s.macc, b));
  fprintf(md, "| multi-view fusion (3D) | - | - | %s | %s |\n", pct(r3_fusion, r3_fusion->s.miou, a), pct(r3_fusion, r3_fusion->s.macc, b));
  fprintf(md, "| vlff field | %s | %s | %s | %s |\n\n", pct(r2_field, r2_field->s.miou, a), pct(r2_field, r2_field->s.macc, b),
          pct(r3_field, r3_field->s.miou, c), pct(r3_field, r3_field->s.macc, d));
  fprintf(md, "## Reference-code protocol\n\n2D: summed IoU, \"accuracy\" = mean per-class precision. 3D: "
              "features averaged over 10 queries jittered within +-2 cm, \"accuracy\" = mean recall. Per scene "
              "(average scenes yourself).\n\n| method | 2D mIoU | 2D acc (precision) | 3D mIoU | 3D acc (recall) |\n|---|---|---|---|---|\n");
  fprintf(md, "| raw per-frame features (2D) | %s | %s | - | - |\n", pct(r2_raw, r2_raw->s.miou, a), pct(r2_raw, r2_raw->s.mprec, b));
  fprintf(md, "| multi-view fusion (3D, unjittered) | - | - | %s | %s |\n", pct(r3_fusion, r3_fusion->s.miou, a),
          pct(r3_fusion, r3_fusion->s.macc, b));
  fprintf(md, "| vlff field | %s | %s | %s | %s |\n\n", pct(r2_field, r2_field->s.miou, a), pct(r2_field, r2_field->s.mprec, b),
          pct(r3_field_ref, r3_field_ref->s.miou, c), pct(r3_field_ref, r3_field_ref->s.macc, d));
  fprintf(md, "## Per class (standard protocol, IoU %%)\n\n| class | 2D raw | 2D field | 3D fusion | 3D field | 3D field (ref) |\n|---|---|---|---|---|---|\n");
  for (int k = 0; k < sc->K; k++) {
    struct vlff_class_score s1, s2, s3, s4, s5;
    vlff_confusion_class(&r2_raw->c, k, &s1);
    vlff_confusion_class(&r2_field->c, k, &s2);
    vlff_confusion_class(&r3_fusion->c, k, &s3);
    vlff_confusion_class(&r3_field->c, k, &s4);
    vlff_confusion_class(&r3_field_ref->c, k, &s5);
    fprintf(md, "| %s | %s | %s | %s | %s | %s |\n", sc->names[k], CELL(*r2_raw, s1, a), CELL(*r2_field, s2, b),
            CELL(*r3_fusion, s3, c), CELL(*r3_field, s4, d), CELL(*r3_field_ref, s5, x));
  }
  fclose(md);
}

static void write_report_json(const struct eval *e) {
  const struct opts *o = &e->o;
  const struct scene *sc = &e->sc;
  char path[4200];
  snprintf(path, sizeof path, "%s/report.json", o->out);
  struct json_object *root = json_object_new_object(), *src = json_object_new_object();
  /* The source is named by what it is: a dataset's path and frames, or the
   * simulator's parameters; never the simulator's for a dataset run. */
  if (o->dataset) {
    json_object_object_add(src, "kind", json_object_new_string("dataset"));
    json_object_object_add(src, "path", json_object_new_string(o->dataset));
  } else {
    json_object_object_add(src, "kind", json_object_new_string("synthetic"));
    json_object_object_add(src, "seed", json_object_new_int(e->cfg.sim.seed));
    json_object_object_add(src, "difficulty", json_object_new_double(e->cfg.sim.difficulty));
  }
  struct json_object *trf = json_object_new_array(), *tef = json_object_new_array();
  for (int i = 0; i < sc->n; i++)
    json_object_array_add(held_out(i, o->holdout) ? tef : trf, frame_json(sc, i));
  if (o->dataset) {
    json_object_object_add(src, "stride", json_object_new_int(sc->stride));
    /* frames the scene lists whose pose was lost (ScanNet's -inf) */
    json_object_object_add(src, "frames_without_pose", json_object_new_int(sc->ds.skipped));
  }
  /* the training frames the field fitted on, and why when not all */
  struct json_object *kf = json_object_new_object(), *kff = json_object_new_array();
  for (int i = 0; i < sc->n; i++)
    if (sc->f[i].key) json_object_array_add(kff, frame_json(sc, i));
  json_object_object_add(kf, "frames", kff);
  json_object_object_add(kf, "frame_mib", json_object_new_double(sc->key_mib));
  json_object_object_add(kf, "memory_mb", json_object_new_int(e->cfg.keyframes.memory_mb));
  json_object_object_add(kf, "chosen_for", sc->key_why ? json_object_new_string(sc->key_why) : NULL);
  json_object_object_add(src, "keyframes", kf);
  json_object_object_add(src, "train_frames", trf);
  json_object_object_add(src, "test_frames", tef);
  json_object_object_add(root, "source", src);
  json_object_object_add(root, "frames", json_object_new_int(sc->n));
  json_object_object_add(root, "holdout", json_object_new_int(o->holdout));
  json_object_object_add(root, "points", json_object_new_int64((int64_t)sc->pts.n));
  struct json_object *box = json_object_new_object(), *bmin = json_object_new_array(), *bmax = json_object_new_array();
  for (int a = 0; a < 3; a++) {
    json_object_array_add(bmin, json_object_new_double(e->cfg.field.scene_min[a]));
    json_object_array_add(bmax, json_object_new_double(e->cfg.field.scene_max[a]));
  }
  json_object_object_add(box, "from", json_object_new_string(sc->box_from));
  json_object_object_add(box, "min", bmin);
  json_object_object_add(box, "max", bmax);
  json_object_object_add(box, "labelled_points_outside", json_object_new_int64((int64_t)sc->pts_outside));
  json_object_object_add(root, "scene_box", box);
  json_object_object_add(root, "iters", json_object_new_int(e->fitted ? e->steps : 0));
  json_object_object_add(root, "fit_seconds", json_object_new_double(e->fit_s));
  struct json_object *names = json_object_new_array();
  for (int k = 0; k < sc->K; k++) json_object_array_add(names, json_object_new_string(sc->names[k]));
  json_object_object_add(root, "classes", names);
  struct json_object *res = json_object_new_object();
  json_object_object_add(res, "raw_2d", json_result(&e->r2_raw));
  json_object_object_add(res, "field_2d", json_result(&e->r2_field));
  json_object_object_add(res, "fusion_3d", json_result(&e->r3_fusion));
  json_object_object_add(res, "field_3d", json_result(&e->r3_field));
  json_object_object_add(res, "field_3d_reference", json_result(&e->r3_field_ref));
  json_object_object_add(res, "field_alone_2d", json_result(&e->r2_alone));
  json_object_object_add(res, "field_alone_3d", json_result(&e->r3_alone));
  json_object_object_add(root, "results", res);
  if (json_object_to_file_ext(path, root, JSON_C_TO_STRING_PRETTY | JSON_C_TO_STRING_NOSLASHESCAPE) < 0)
    die("%s: %s", path, json_util_get_last_err());
  json_object_put(root);
}

/* Per class: the field's 3D IoU beside fusion's (the map controllers
 * read) and 2D beside the raw features'. The worst ratio counts classes
 * with at least 500 labelled points that fusion finds at all: fewer
 * points make the ratio noise. Returns the worst ratio's class (-1: none)
 * and sets *worst to it. */
static int print_per_class(const struct eval *e, double *worst) {
  const struct result *r2_raw = &e->r2_raw, *r2_field = &e->r2_field, *r3_fusion = &e->r3_fusion;
  const struct result *r3_field = &e->r3_field;
  char a[16], b[16], c[16], d[16];
  printf("%-18s %8s %10s %10s %7s %8s %9s\n", "per class (IoU %)", "points", "3D fusion", "3D field", "ratio",
         "2D raw", "2D field");
  *worst = INFINITY;
  int worst_k = -1;
  for (int k = 0; k < e->sc.K; k++) {
    struct vlff_class_score s1, s2, s3, s4;
    vlff_confusion_class(&r2_raw->c, k, &s1);
    vlff_confusion_class(&r2_field->c, k, &s2);
    vlff_confusion_class(&r3_fusion->c, k, &s3);
    vlff_confusion_class(&r3_field->c, k, &s4);
    unsigned long long npts = (unsigned long long)(s3.tp + s3.fn);
    if (!s1.present && !s3.present) continue;
    char ratio[16] = "-";
    if (r3_field->valid && s3.present && s3.iou > 0) {
      double q = s4.iou / s3.iou;
      snprintf(ratio, sizeof ratio, "%.2f", q);
      if (npts >= 500 && q < *worst) *worst = q, worst_k = k;
    }
    printf("%-18.18s %8llu %10s %10s %7s %8s %9s\n", e->sc.names[k], npts, CELL(*r3_fusion, s3, a),
           CELL(*r3_field, s4, b), ratio, CELL(*r2_raw, s1, c), CELL(*r2_field, s2, d));
  }
  return worst_k;
}

/* The console: both protocols' tables, the per-class table, the worst
 * class and the RESULT line. */
static void print_summary(const struct eval *e) {
  const struct opts *o = &e->o;
  const struct scene *sc = &e->sc;
  const struct result *r2_raw = &e->r2_raw, *r2_field = &e->r2_field, *r3_fusion = &e->r3_fusion;
  const struct result *r3_field = &e->r3_field, *r3_field_ref = &e->r3_field_ref;
  char a[16], b[16], c[16], d[16], x[16], y[16], z[16];
  if (o->dataset) printf("scene: dataset %s, frames %s to %s", o->dataset, frame_name(sc, 0), frame_name(sc, sc->n - 1));
  else printf("scene: synthetic room, seed %d, difficulty %.2f", e->cfg.sim.seed, e->cfg.sim.difficulty);
  printf(", %d train / %d held-out frames, %zu points\n", e->ntrain, e->ntest, sc->pts.n);
  printf("%-34s %8s %8s %8s %8s\n", "standard protocol", "2D mIoU", "2D mAcc", "3D mIoU", "3D mAcc");
  printf("%-34s %8s %8s %8s %8s\n", "raw per-frame features", pct(r2_raw, r2_raw->s.miou, a), pct(r2_raw, r2_raw->s.macc, b), "-", "-");
  printf("%-34s %8s %8s %8s %8s\n", "multi-view fusion", "-", "-", pct(r3_fusion, r3_fusion->s.miou, a), pct(r3_fusion, r3_fusion->s.macc, b));
  printf("%-34s %8s %8s %8s %8s\n", "vlff field", pct(r2_field, r2_field->s.miou, a), pct(r2_field, r2_field->s.macc, b),
         pct(r3_field, r3_field->s.miou, c), pct(r3_field, r3_field->s.macc, d));
  if (e->cfg.publish.evidence_weight > 0)
    printf("%-34s %8s %8s %8s %8s\n", "  field alone, no evidence", pct(&e->r2_alone, e->r2_alone.s.miou, a),
           pct(&e->r2_alone, e->r2_alone.s.macc, b), pct(&e->r3_alone, e->r3_alone.s.miou, c),
           pct(&e->r3_alone, e->r3_alone.s.macc, d));
  printf("%-34s %8s %8s %8s %8s\n", "reference protocol", "2D mIoU", "2D prec", "3D mIoU", "3D rec");
  printf("%-34s %8s %8s %8s %8s\n", "raw per-frame features", pct(r2_raw, r2_raw->s.miou, a), pct(r2_raw, r2_raw->s.mprec, b), "-", "-");
  printf("%-34s %8s %8s %8s %8s\n", "vlff field (3D: 10 jittered)", pct(r2_field, r2_field->s.miou, a),
         pct(r2_field, r2_field->s.mprec, b), pct(r3_field_ref, r3_field_ref->s.miou, c), pct(r3_field_ref, r3_field_ref->s.macc, d));
  double worst;
  int worst_k = print_per_class(e, &worst);
  char wbuf[64] = "n/a";
  if (worst_k >= 0) {
    snprintf(wbuf, sizeof wbuf, "%.2f", worst);
    printf("worst class vs fusion: %s %.2f\n", sc->names[worst_k], worst);
  }
  printf("report: %s/report.md\n", o->out);
  printf("RESULT miou3d=%s miou3d_fusion=%s miou2d=%s miou2d_raw=%s macc2d=%s macc2d_raw=%s "
         "worst_class_vs_fusion=%s fit_seconds=%.1f steps=%d miou3d_field_alone=%s ",
         pct(r3_field, r3_field->s.miou, a), pct(r3_fusion, r3_fusion->s.miou, b), pct(r2_field, r2_field->s.miou, c),
         pct(r2_raw, r2_raw->s.miou, d), pct(r2_field, r2_field->s.macc, x), pct(r2_raw, r2_raw->s.macc, y), wbuf,
         e->fit_s, e->steps, pct(&e->r3_alone, e->r3_alone.s.miou, z));
  printf("miou2d_field_alone=%s macc2d_field_alone=%s\n", pct(&e->r2_alone, e->r2_alone.s.miou, a),
         pct(&e->r2_alone, e->r2_alone.s.macc, b));
}

static void scene_free(struct eval *e) {
  struct scene *sc = &e->sc;
  for (int i = 0; i < sc->n; i++) {
    if (sc->streaming) /* scratch, or a keyframe's features freed below */
      sc->f[i].rgb = NULL, sc->f[i].feat = NULL, sc->f[i].depth = NULL, sc->f[i].label = NULL;
    free(sc->f[i].rgb), free(sc->f[i].label), free(sc->f[i].depth), free(sc->f[i].feat);
    free(sc->f[i].trgb), free(sc->f[i].tdepth), free(sc->f[i].kfeat);
  }
  free(sc->srgb), free(sc->sfeat), free(sc->sdepth), free(sc->slabel);
  if (sc->streaming) vlff_dataset_close(&sc->ds);
  free(sc->f), free(e->gl), free(e->pl), free(e->p3), free(e->pred3), free(e->emb_raw), free(e->seen3);
  vlff_points_free(&sc->pts);
  vlff_confusion_free(&e->r2_raw.c), vlff_confusion_free(&e->r2_field.c), vlff_confusion_free(&e->r3_fusion.c);
  vlff_confusion_free(&e->r3_field.c), vlff_confusion_free(&e->r3_field_ref.c);
  vlff_confusion_free(&e->r3_alone.c);
  vlff_confusion_free(&e->r2_alone.c);
  evidence_free(e);
}

/* --online (online.h): the same scene through vlff-replay into a vlff-node,
 * its published map scored over time beside this run's offline fit and
 * fusion, and the RESULT line of the two together. */
static int online(struct eval *e) {
  const struct opts *o = &e->o;
  struct scene *sc = &e->sc;
  char emb[4200], err[1024];
  if (e->cfg.prompts.embeddings[0]) snprintf(emb, sizeof emb, "%s", e->cfg.prompts.embeddings);
  else snprintf(emb, sizeof emb, "%s/prompt_embeddings.txt", o->dataset);
  struct vlff_online_opts oo = {.scene = o->dataset, .embeddings = emb, .out = o->out, .node_bin = o->node_bin,
                                .replay_bin = o->replay_bin, .interval_s = o->online_interval,
                                .after_s = o->online_after, .width = sc->W, .height = sc->H, .quiet = o->quiet,
                                /* a recording of at least 1 Hz, played ten times slower than it should */
                                .replay_limit_s = 10.0 * sc->n * o->stride + 60};
  struct vlff_online_result res;
  if (o->stride > 1)
    fprintf(stderr, "vlff-eval: --online plays every frame of the scene; --stride %d applied to the offline fit only\n",
            o->stride);
  if (vlff_eval_online(&oo, &e->cfg, &sc->pts, e->seen3, sc->K, (const char(*)[VLFF_PROMPT_LEN])sc->names, &res, err,
                       sizeof err) < 0) {
    fprintf(stderr, "vlff-eval: --online: %s\n", err);
    return 1;
  }
  char a[16], b[16];
  printf("online: after %.0f s past the replay's end: map v%llu, 3D mIoU %.1f mAcc %.1f, %.1f %% of the labelled points "
         "a training frame saw are labelled; offline fit %s, fusion %s; a map every %.2f s\n",
         o->online_after, (unsigned long long)res.version, 100 * res.miou3d, 100 * res.macc3d, 100 * res.coverage,
         pct(&e->r3_field, e->r3_field.s.miou, a), pct(&e->r3_fusion, e->r3_fusion.s.miou, b), res.publish_interval_s);
  printf("RESULT online_miou3d_%.0fs=%.2f offline_miou3d=%s fusion_miou3d=%s online_coverage_%.0fs=%.2f "
         "publish_interval_s=%.2f\n",
         o->online_after, 100 * res.miou3d, pct(&e->r3_field, e->r3_field.s.miou, a),
         pct(&e->r3_fusion, e->r3_fusion.s.miou, b), o->online_after, 100 * res.coverage, res.publish_interval_s);
  return 0;
}

/* ---- main --------------------------------------------------------------- */

int main(int argc, char **argv) {
  static struct eval e; /* zeroed; large (the scene's prompt vectors) */
  configure(&e, argc, argv);
  load_scene(&e);
  baselines(&e);
  if (e.o.iters > 0 || e.o.fit_seconds > 0) {
    struct vlff_field *fld = fit_field(&e);
    score_field(&e, fld);
    vlff_field_destroy(fld);
  }
  write_prediction_ply(&e);
  write_report_md(&e);
  write_report_json(&e);
  print_summary(&e);
  int rc = e.o.online ? online(&e) : 0;
  scene_free(&e);
  return rc;
}
