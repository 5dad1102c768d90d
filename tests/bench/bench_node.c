/*
 * bench_node: time to a useful map on the synthetic 5 Hz stream.
 *
 * vlff-sim streams configs/demo-sim.yaml's room into the frame and feature
 * rings; the node (in this process, exactly the library vlff-node runs)
 * learns it. Every 0.5 s the node's own 2D mIoU (its published label image
 * against the synthetic ground truth) is sampled. Useful = the 2D mIoU,
 * smoothed over the last 5 s, first reaches 90 % of its value at 120 s
 * (VLFF_BENCH_SECONDS; VLFF_BENCH_CONFIG replaces the config). That value is
 * the mean over 120 +- 15 s: one view's mIoU swings by 20 points with what
 * it sees (a chair or a bare wall), and a 5-s window's by 10, which moved
 * the threshold, not the map. Baseline in the same run: the raw per-frame
 * features' 2D mIoU on the same scene (what the field must beat).
 *
 * Same view: the camera's walk repeats every sim.frames frames, so each
 * sample's view is seen again in the loop around `seconds` (the frames
 * within half a loop of the one published then; the run lasts until that
 * loop is whole). time_to_useful_same_view_s compares
 * like with like: the first time the 5-s window's mIoU reaches 90 % of what
 * the same views (the nearest loop positions, within a second of walk)
 * score in that final loop. A bare wall early and a cluttered corner late
 * no longer move it; a room entered for the first time still does. Views
 * the final loop published no label image near (keyframes refused there)
 * are left out. VLFF_BENCH_TRACE=FILE writes every sample: seconds, frame
 * id, 2D mIoU, the same views' final mIoU.
 *
 * A building (sim.layout building, tests/bench/node-building.yaml): the
 * first walk through it (frames 0 .. sim.frames-1, from flat 1 through
 * every flat and back into flat 1) is scored as the robot walks it: when
 * the simulator has written the first frame outside flat 1 into the frame
 * ring (the ring's head), the map is read from its segment and scored at
 * flat 1's labelled points; when it has written the walk's last frame,
 * flat 1 is scored again and so is the whole building (every labelled
 * point): miou3d_end, forgetting_pts (flat 1's first score less its last;
 * > 0 is lost). The map is what the node has then, however far its
 * training lags the camera (a loaded host's lag shows as a lower score). The baseline: multi-view fusion (metrics.h, as vlff-eval's) of
 * every frame of that walk at the same points, miou3d_fusion_end.
 * rss_peak_mb is read before the baseline is computed.
 *
 * CPU: cpu_cores_used is the process's CPU time (the node's threads; the
 * simulator is a process of its own) over the wall time from the first
 * sample that shows a training step to the end of the run (before it the
 * node only waits for its first keyframes). VLFF_BENCH_BUDGET=CORES sets node.cpu_budget
 * (and prints cpu_budget and cpu_budget_ratio, use over budget); node.sh
 * runs it at 0.5, 1 and 2.
 *
 * label_flip_frac: over the final window (from `seconds` - 15 s to the
 * end), the share of the labelled voxels no keyframe observed between two
 * consecutive publishes whose published label changed all the same (the
 * node's label_flips_elsewhere / label_mapped_elsewhere: the camera looked
 * elsewhere), on its own RESULT line.
 *
 * change_visible_s (VLFF_BENCH_CHANGE=1, scene "change" of node.sh): the
 * config gets a sim.changes entry that moves the scene's first chair, at
 * sim time VLFF_BENCH_CHANGE_AT (30 s), to bare floor at least 1.2 m from
 * where it stood and off the camera's walk. From the time vlff-sim is due
 * to stream the first frame by which both places have been seen (the chair
 * at its new place, 200 pixels of it, and its old place seen through to a
 * surface 0.3 m or more behind its centre, by the simulator's own ground
 * truth; a simulator running late only makes this longer) to the first map (read from the map segment every 0.1 s) where
 * 90 % of the points of the old place that were labelled just before the
 * move read FREE and the new place has at least 0.3 times as many points
 * (3 at least) labelled as the map labelled the chair then (its most
 * common class at the old place). -1: never within the run, or the map
 * had not labelled the chair before it moved.
 */
#include <math.h>
#include <signal.h>
#include <stdbool.h>
#include <spawn.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "config.h"
#include "metrics.h"
#include "node.h"
#include "field.h" /* float16 conversions */
#include "log.h"
#include "testkit.h"
#include "sim.h"
#include "vlff/shm.h"

extern char **environ;

/* change_visible_s's state (see the top). */
struct change_watch {
  bool on;
  double t_change, t_seen;          /* bench time of the move, of the first frame showing the new place */
  double old_lo[3], old_hi[3], new_lo[3], new_hi[3], step;
  struct vlff_map *map;
  int cls, n_old;                   /* the map's class of the chair just before the move, its points */
  float old_pts[1024][3];           /* those points */
  double t_done, t_free, t_new;     /* both; the old place free; the new place labelled (first times) */
};

static bool inside(const double x[3], const double lo[3], const double hi[3], double pad) {
  for (int k = 0; k < 3; k++)
    if (x[k] < lo[k] - pad || x[k] > hi[k] + pad) return false;
  return true;
}

/* Points of a box on the map's voxel pitch. */
#define BOX_POINTS(w, lo, hi, x)                                                             \
  for (double x##z = (lo)[2] + (w)->step / 2; x##z < (hi)[2]; x##z += (w)->step)             \
    for (double x##y = (lo)[1] + (w)->step / 2; x##y < (hi)[1]; x##y += (w)->step)           \
      for (double x##x = (lo)[0] + (w)->step / 2, x[3] = {x##x, x##y, x##z}; x##x < (hi)[0]; \
           x##x += (w)->step, x[0] = x##x)

static void change_poll(struct change_watch *w, double t) {
  if (!w->on || w->t_done >= 0) return;
  uint16_t lab;
  if (t < w->t_change) {
    /* The chair as the map has it just before the move. */
    int count[VLFF_LABEL_MAX < 4096 ? VLFF_LABEL_MAX : 4096] = {0}, n = 0, best = -1;
    BOX_POINTS(w, w->old_lo, w->old_hi, x) {
      if (vlff_map_label_at(w->map, x[0], x[1], x[2], &lab, NULL) || lab >= 4096) continue;
      if (n < 1024) w->old_pts[n][0] = (float)x[0], w->old_pts[n][1] = (float)x[1], w->old_pts[n][2] = (float)x[2];
      n++;
      if (best < 0 || ++count[lab] > count[best]) best = lab;
    }
    w->n_old = n < 1024 ? n : 1024, w->cls = best;
    return;
  }
  if (t < w->t_seen || w->cls < 0 || !w->n_old) return;
  int free_n = 0, old_n = 0, new_n = 0;
  for (int i = 0; i < w->n_old; i++) {
    double x[3] = {w->old_pts[i][0], w->old_pts[i][1], w->old_pts[i][2]};
    if (inside(x, w->new_lo, w->new_hi, 0.05)) continue;
    old_n++;
    free_n += vlff_map_label_at(w->map, x[0], x[1], x[2], &lab, NULL) == 0 && lab == VLFF_LABEL_FREE;
  }
  BOX_POINTS(w, w->new_lo, w->new_hi, x) {
    new_n += vlff_map_label_at(w->map, x[0], x[1], x[2], &lab, NULL) == 0 && lab == w->cls;
  }
  bool is_free = free_n >= 0.9 * old_n, is_new = new_n >= 3 && new_n >= 0.3 * w->n_old;
  if (is_free && w->t_free < 0) w->t_free = t;
  if (is_new && w->t_new < 0) w->t_new = t;
  if (is_free && is_new) w->t_done = t;
}

/* Moves the first chair (see the top): the change is written into the
 * config at path, and w knows where and when. 0, or -1 with err. */
static int change_setup(const char *path, struct vlff_config *cfg, struct change_watch *w, char *err, size_t errlen) {
  struct vlff_sim *a = vlff_sim_create(&cfg->sim, &cfg->field, err, errlen);
  if (!a) return -1;
  const double at = getenv("VLFF_BENCH_CHANGE_AT") ? atof(getenv("VLFF_BENCH_CHANGE_AT")) : 30;
  double lo[3], hi[3], clo[3], chi[3], to[2] = {0, 0};
  bool found = false;
  vlff_sim_bounds(a, lo, hi);
  if (vlff_sim_object_box(a, "chair", 0, clo, chi, err, errlen) < 0) return vlff_sim_destroy(a), -1;
  const int FLOOR = vlff_sim_class_of("floor");
  for (double x = lo[0] + 0.6; x < hi[0] - 0.6 && !found; x += 0.2)
    for (double y = lo[1] + 0.6; y < hi[1] - 0.6 && !found; y += 0.2) {
      if (hypot(x - 0.5 * (clo[0] + chi[0]), y - 0.5 * (clo[1] + chi[1])) < 1.2) continue;
      /* Off the camera's walk (an ellipse at about half the room's half-sizes). */
      if (hypot((x - 0.5 * (lo[0] + hi[0])) / (0.5 * (hi[0] - lo[0])), (y - 0.5 * (lo[1] + hi[1])) / (0.5 * (hi[1] - lo[1]))) < 0.7)
        continue;
      bool bare = true;
      for (int k = 0; k < 9 && bare; k++) {
        int l;
        vlff_sim_raycast(a, (const double[3]){x + 0.4 * (k % 3 - 1), y + 0.4 * (k / 3 - 1), hi[2] - 0.05},
                         (const double[3]){0, 0, -1}, &l, NULL);
        bare = l == FLOOR;
      }
      if (bare) to[0] = x, to[1] = y, found = true;
    }
  vlff_sim_destroy(a);
  if (!found) return snprintf(err, errlen, "no bare floor to move the chair to"), -1;
  /* The change goes under the config's sim section. */
  static char text[20000];
  FILE *f = fopen(path, "r");
  size_t len = f ? fread(text, 1, sizeof text - 1, f) : 0;
  if (f) fclose(f);
  text[len] = 0;
  char line[200];
  snprintf(line, sizeof line, "  changes: [{time_s: %.3f, object: chair, action: move, to: [%.3f, %.3f]}]\n", at,
           to[0], to[1]);
  f = fopen(path, "w");
  char *sim = strstr(text, "\nsim:\n");
  if (!f) return snprintf(err, errlen, "cannot write %s", path), -1;
  if (sim) fprintf(f, "%.*s%s%s", (int)(sim + 6 - text), text, line, sim + 6);
  else fprintf(f, "%ssim:\n%s", text, line);
  fclose(f);
  if (vlff_config_load(path, cfg, err, errlen)) return -1;
  struct vlff_sim *b = vlff_sim_create(&cfg->sim, &cfg->field, err, errlen);
  struct vlff_sim_frame *fr = b ? vlff_sim_frame_new(b) : NULL;
  if (!fr) return vlff_sim_destroy(b), -1;
  vlff_sim_object_box(b, "chair", at - 1e-3, w->old_lo, w->old_hi, err, errlen);
  vlff_sim_object_box(b, "chair", at, w->new_lo, w->new_hi, err, errlen);
  /* Above the floor's voxels, which stay floor wherever the chair stands. */
  w->old_lo[2] += cfg->publish.voxel_size_m, w->new_lo[2] += cfg->publish.voxel_size_m;
  const int CHAIR = vlff_sim_class_of("chair");
  long long first = (long long)ceil(at * cfg->sim.rate_hz), seen = -1, seen_new = -1, seen_old = -1;
  const double oc[3] = {0.5 * (w->old_lo[0] + w->old_hi[0]), 0.5 * (w->old_lo[1] + w->old_hi[1]),
                        0.5 * (w->old_lo[2] + w->old_hi[2])};
  for (long long id = first; id < first + 2LL * cfg->sim.frames && seen < 0; id++) {
    if (vlff_sim_render(b, id, 0, fr, err, errlen)) break;
    /* The old place seen through: its centre in the image, the surface
     * behind it 0.3 m or more further. */
    const double *M = fr->c2w_true;
    double dw[3] = {oc[0] - M[3], oc[1] - M[7], oc[2] - M[11]}, pc[3];
    for (int r = 0; r < 3; r++) pc[r] = M[r] * dw[0] + M[4 + r] * dw[1] + M[8 + r] * dw[2];
    if (seen_old < 0 && pc[2] > 0.3) {
      int u = (int)(fr->fx * pc[0] / pc[2] + fr->cx), v = (int)(fr->fy * pc[1] / pc[2] + fr->cy);
      if (u >= 0 && v >= 0 && u < fr->width && v < fr->height && fr->depth_gt[(size_t)v * fr->width + u] > pc[2] + 0.3)
        seen_old = id;
    }
    int n = 0;
    for (int v = 0; v < fr->height; v++)
      for (int u = 0; u < fr->width; u++) {
        size_t k = (size_t)v * fr->width + u;
        if (fr->label[k] != CHAIR || !(fr->depth_gt[k] > 0)) continue;
        double x[3], d = fr->depth_gt[k], xc = (u + 0.5 - fr->cx) / fr->fx * d, yc = (v + 0.5 - fr->cy) / fr->fy * d;
        for (int r = 0; r < 3; r++) x[r] = fr->c2w_true[4 * r] * xc + fr->c2w_true[4 * r + 1] * yc + fr->c2w_true[4 * r + 2] * d + fr->c2w_true[4 * r + 3];
        n += inside(x, w->new_lo, w->new_hi, 0.05);
      }
    if (n >= 200 && seen_new < 0) seen_new = id;
    if (seen_new >= 0 && seen_old >= 0) seen = id;
  }
  vlff_sim_frame_free(fr);
  vlff_sim_destroy(b);
  if (seen < 0) return snprintf(err, errlen, "no frame shows the chair at its new place"), -1;
  w->on = true;
  w->t_change = at;          /* as sim time; made bench time once vlff-sim starts */
  w->t_seen = (double)seen / cfg->sim.rate_hz;
  w->step = cfg->publish.voxel_size_m;
  w->cls = -1;
  w->t_done = w->t_free = w->t_new = -1;
  printf("change: chair moved at %.1f s from (%.2f, %.2f) to (%.2f, %.2f); frame %lld first shows it there, frame %lld "
         "sees through its old place\n", at, oc[0], oc[1], to[0], to[1], seen_new, seen_old);
  return 0;
}

static double mono_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static double cpu_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static long peak_rss_kb(void) {
  FILE *f = fopen("/proc/self/status", "r");
  char line[256];
  long kb = -1;
  while (f && fgets(line, sizeof line, f))
    if (!strncmp(line, "VmHWM:", 6)) kb = atol(line + 6);
  if (f) fclose(f);
  return kb;
}

/* Raw per-frame features: argmax over the prompt embeddings at feature
 * resolution, against the ground truth sampled at the same pixels. */
static double raw_miou2d(const struct vlff_config *cfg, int frames) {
  char err[256];
  struct vlff_sim *s = vlff_sim_create(&cfg->sim, &cfg->field, err, sizeof err);
  struct vlff_sim_frame *f = s ? vlff_sim_frame_new(s) : NULL;
  struct vlff_confusion c;
  if (!f || vlff_confusion_init(&c, VLFF_SIM_CLASSES, err, sizeof err)) return -1;
  const struct vlff_prompt_set *ps = &cfg->prompts.sets[cfg->prompts.active];
  int d = cfg->field.feature_dim, k = ps->count;
  float *emb = malloc((size_t)k * d * sizeof(float)), *unit = malloc((size_t)k * d * sizeof(float));
  int *cls = malloc((size_t)k * sizeof(int));
  for (int i = 0; i < k; i++) {
    vlff_sim_text_embedding(s, ps->text[i], emb + (size_t)i * d);
    cls[i] = vlff_sim_class_of(ps->text[i]);
  }
  vlff_normalize_rows(emb, unit, k, d);
  for (int i = 0; i < frames; i++) {
    vlff_sim_render(s, (long long)i * cfg->sim.frames / frames, VLFF_SIM_ALL, f, err, sizeof err);
    size_t n = (size_t)f->feat_width * f->feat_height;
    int *lab = malloc(n * sizeof(int));
    vlff_classify_f16(f->features, n, d, unit, k, lab, NULL);
    for (int y = 0; y < f->feat_height; y++)
      for (int x = 0; x < f->feat_width; x++) {
        int gy = (y * f->height + f->height / 2) / f->feat_height, gx = (x * f->width + f->width / 2) / f->feat_width;
        int l = lab[(size_t)y * f->feat_width + x];
        vlff_confusion_add_one(&c, f->label[(size_t)gy * f->width + gx], l >= 0 ? cls[l] : -1);
      }
    free(lab);
  }
  struct vlff_summary sum;
  vlff_confusion_summary(&c, &sum);
  vlff_confusion_free(&c);
  free(emb), free(unit), free(cls);
  vlff_sim_frame_free(f);
  vlff_sim_destroy(s);
  return sum.miou * 100;
}

/* The labelled points the node's observer scores (sim_source.c's set). */
static int walk_points(const struct vlff_config *cfg, struct vlff_sim **sim, struct vlff_sim_points *pts) {
  char err[256];
  *sim = vlff_sim_create(&cfg->sim, &cfg->field, err, sizeof err);
  if (!*sim || vlff_sim_points(*sim, cfg->sim.frames, 5, 0.05, pts, err, sizeof err))
    return fprintf(stderr, "bench_node: %s\n", err), -1;
  return 0;
}

/* 3D mIoU of the published map (a snapshot of its segment) at the points
 * whose in[] is set: a point takes the class of its voxel's prompt. */
static double map_miou3d(struct vlff_map *map, struct vlff_map_snapshot *snap, const struct vlff_sim_points *p,
                         const uint8_t *in) {
  struct vlff_confusion c;
  char err[128];
  if (!map || !snap || vlff_map_snapshot_take(map, snap) || vlff_confusion_init(&c, VLFF_SIM_CLASSES, err, sizeof err))
    return -1;
  for (size_t i = 0; i < p->n; i++) {
    if (!in[i]) continue;
    const float *x = p->xyz + 3 * i;
    const char *pr = vlff_map_snapshot_prompt(snap, vlff_map_snapshot_label_at(snap, x[0], x[1], x[2], NULL));
    vlff_confusion_add_one(&c, p->label[i], pr ? vlff_sim_class_of(pr) : -1);
  }
  struct vlff_summary sum;
  vlff_confusion_summary(&c, &sum);
  vlff_confusion_free(&c);
  return sum.present ? sum.miou * 100 : -1;
}

/* Multi-view fusion of frames 0 .. sim.frames-1 at the points. Fusion
 * averages features, and a class's score (the dot product with its unit
 * embedding) is linear in the feature, so averaging each view's scores
 * picks the same class as scoring the averaged feature: the views carry
 * K scores per feature pixel instead of D features. */
static double fusion_miou3d(const struct vlff_config *cfg, const struct vlff_sim_points *p) {
  char err[256];
  struct vlff_sim *s = vlff_sim_create(&cfg->sim, &cfg->field, err, sizeof err);
  struct vlff_sim_frame *f = s ? vlff_sim_frame_new(s) : NULL;
  if (!f) return -1;
  const struct vlff_prompt_set *ps = &cfg->prompts.sets[cfg->prompts.active];
  const int d = cfg->field.feature_dim, k = ps->count, nv = cfg->sim.frames;
  const size_t npx = (size_t)f->width * f->height, nfp = (size_t)f->feat_width * f->feat_height;
  float *emb = malloc((size_t)k * d * sizeof(float)), *unit = malloc((size_t)k * d * sizeof(float));
  float *feat = malloc((size_t)d * sizeof(float)), *sc = malloc((size_t)k * sizeof(float));
  int *cls = malloc((size_t)k * sizeof(int)), *count = malloc(p->n * sizeof(int));
  struct vlff_fusion_view *views = calloc((size_t)nv, sizeof *views);
  float *depth = malloc((size_t)nv * npx * sizeof(float)), *out = malloc(p->n * (size_t)k * sizeof(float));
  uint16_t *score = malloc((size_t)nv * nfp * k * sizeof(uint16_t));
  double miou = -1;
  struct vlff_confusion c;
  if (!emb || !unit || !feat || !sc || !cls || !count || !views || !depth || !out || !score ||
      vlff_confusion_init(&c, VLFF_SIM_CLASSES, err, sizeof err))
    goto done;
  for (int i = 0; i < k; i++) {
    vlff_sim_text_embedding(s, ps->text[i], emb + (size_t)i * d);
    cls[i] = vlff_sim_class_of(ps->text[i]);
  }
  vlff_normalize_rows(emb, unit, k, d);
  for (int v = 0; v < nv; v++) {
    if (vlff_sim_render(s, v, VLFF_SIM_ALL, f, err, sizeof err)) goto done;
    memcpy(depth + (size_t)v * npx, f->depth, npx * sizeof(float));
    for (size_t q = 0; q < nfp; q++) {
      vlff_f16_to_f32_n(f->features + q * d, feat, (size_t)d);
      for (int j = 0; j < k; j++) {
        double dot = 0;
        for (int i = 0; i < d; i++) dot += (double)feat[i] * unit[(size_t)j * d + i];
        sc[j] = (float)dot;
      }
      vlff_f32_to_f16_n(sc, score + ((size_t)v * nfp + q) * k, (size_t)k);
    }
    views[v] = (struct vlff_fusion_view){f->width, f->height, f->fx, f->fy, f->cx, f->cy, {0},
                                         depth + (size_t)v * npx, f->feat_width, f->feat_height,
                                         score + (size_t)v * nfp * k};
    memcpy(views[v].c2w, f->c2w, sizeof views[v].c2w);
  }
  if (vlff_fusion(p->xyz, p->n, views, nv, k, 0.05, out, count, err, sizeof err)) goto done;
  for (size_t i = 0; i < p->n; i++) {
    int best = -1;
    for (int j = 0; count[i] && j < k; j++)
      if (best < 0 || out[i * k + j] > out[i * k + best]) best = j;
    vlff_confusion_add_one(&c, p->label[i], best >= 0 ? cls[best] : -1);
  }
  struct vlff_summary sum;
  vlff_confusion_summary(&c, &sum);
  miou = sum.present ? sum.miou * 100 : -1;
done:
  if (miou < 0) fprintf(stderr, "bench_node: fusion: %s\n", err);
  vlff_confusion_free(&c);
  free(emb), free(unit), free(feat), free(sc), free(cls), free(count), free(views), free(depth), free(out), free(score);
  vlff_sim_frame_free(f);
  vlff_sim_destroy(s);
  return miou;
}

int main(int argc, char **argv) {
  (void)argc;
  vlff_node_process_setup(); /* as vlff-node: the RSS measured is the deployed node's */
  const char *src = getenv("VLFF_SOURCE_DIR") ? getenv("VLFF_SOURCE_DIR") : VLFF_SOURCE_DEFAULT;
  double seconds = getenv("VLFF_BENCH_SECONDS") ? atof(getenv("VLFF_BENCH_SECONDS")) : 120;
  char path[1024], err[512], tmp[256];
  static char yaml[16384];
  snprintf(tmp, sizeof tmp, "/tmp/vlff-bench-node-%d", (int)getpid());
  snprintf(path, sizeof path, "mkdir -p %s", tmp);
  if (system(path)) return 1;
  /* The demo's config with this run's own segments and an empty state. */
  snprintf(path, sizeof path, "%s/configs/demo-sim.yaml", src);
  if (getenv("VLFF_BENCH_CONFIG")) snprintf(path, sizeof path, "%s", getenv("VLFF_BENCH_CONFIG"));
  FILE *in = fopen(path, "r");
  if (!in) return fprintf(stderr, "bench_node: %s missing\n", path), 1;
  size_t len = fread(yaml, 1, sizeof yaml - 1, in);
  yaml[len] = 0;
  fclose(in);
  char cfg_path[300];
  snprintf(cfg_path, sizeof cfg_path, "%s/node.yaml", tmp);
  FILE *out = fopen(cfg_path, "w");
  for (char *line = strtok(yaml, "\n"); line; line = strtok(NULL, "\n")) {
    if (strstr(line, "state_dir:")) fprintf(out, "  state_dir: %s/state\n  checkpoint_period_s: 0\n", tmp);
    else if (strstr(line, "checkpoint_period_s:")) continue;
    else if (strstr(line, ": /vlff-demo-")) fprintf(out, "%.*s/bn%d-%s\n", (int)(strstr(line, "/vlff-demo-") - line), line, (int)getpid(), strstr(line, "/vlff-demo-") + 11);
    else fprintf(out, "%s\n", line);
  }
  fclose(out);
  struct vlff_config cfg;
  if (vlff_config_load(cfg_path, &cfg, err, sizeof err)) return fprintf(stderr, "%s\n", err), 1;
  vlff_log_set_level(cfg.node.log_level); /* as vlff-node: node.log_level debug shows each publish's cost */
  double budget = getenv("VLFF_BENCH_BUDGET") ? atof(getenv("VLFF_BENCH_BUDGET")) : 0;
  if (budget < 0 || (budget > 0 && budget < 0.1) || budget > 256)
    return fprintf(stderr, "bench_node: VLFF_BENCH_BUDGET: expected 0 or 0.1 to 256 cores, got %g\n", budget), 1;
  cfg.node.cpu_budget = budget;
  static struct change_watch cw;
  if (getenv("VLFF_BENCH_CHANGE") && atoi(getenv("VLFF_BENCH_CHANGE")) &&
      change_setup(cfg_path, &cfg, &cw, err, sizeof err))
    return fprintf(stderr, "bench_node: change: %s\n", err), 1;

  double raw = raw_miou2d(&cfg, 30);
  printf("raw per-frame features: 2D mIoU %.1f (baseline)\n", raw);

  /* The building's walk: where it leaves flat 1, and flat 1's points. */
  const bool walk = cfg.sim.layout == VLFF_LAYOUT_BUILDING;
  struct vlff_sim *wsim = NULL;
  struct vlff_sim_points wpts = {0};
  uint8_t *in_flat1 = NULL, *in_all = NULL;
  long long leave_frame = -1;
  double flat1_leave = -1, flat1_end = -1, miou3d_end = -1;
  if (walk) {
    if (walk_points(&cfg, &wsim, &wpts)) return 1;
    in_flat1 = calloc(wpts.n + 1, 1), in_all = calloc(wpts.n + 1, 1);
    if (!in_flat1 || !in_all) return fprintf(stderr, "bench_node: out of memory\n"), 1;
    size_t n1 = 0;
    for (size_t i = 0; i < wpts.n; i++) {
      in_all[i] = 1;
      n1 += in_flat1[i] = vlff_sim_flat_at(wsim, wpts.xyz[3 * i], wpts.xyz[3 * i + 1]) == 0;
    }
    for (long long i = 1; i < cfg.sim.frames && leave_frame < 0; i++) {
      double m[16];
      vlff_sim_pose(wsim, i, m);
      if (vlff_sim_flat_at(wsim, m[3], m[7]) != 0) leave_frame = i;
    }
    printf("building: %d flats, walk %.1f m in %d frames, leaves flat 1 at frame %lld; %zu labelled points, %zu in "
           "flat 1\n",
           vlff_sim_flat_count(wsim), vlff_sim_walk_length(wsim), cfg.sim.frames, leave_frame, wpts.n, n1);
  }

  char simpath[1024];
  snprintf(simpath, sizeof simpath, "%.*s/../node/sim/vlff-sim", (int)(strrchr(argv[0], '/') - argv[0]), argv[0]);
  char *sargv[] = {simpath, "--config", cfg_path, "--quiet", NULL};
  pid_t sim;
  const double t_spawn = mono_s();
  if (posix_spawn(&sim, simpath, NULL, NULL, sargv, environ)) return fprintf(stderr, "cannot start %s\n", simpath), 1;
  struct vlff_sim_source *sim_src;
  struct vlff_node *n = tk_node_create(&cfg, &sim_src, err, sizeof err);
  if (!n) {
    kill(sim, SIGKILL);
    return fprintf(stderr, "%s\n", err), 1;
  }
  struct vlff_map *wmap = NULL;
  struct vlff_map_snapshot *wsnap = NULL;
  struct vlff_ring *wring = NULL;
  enum { MAXS = 4096 };
  static double ts[MAXS], m2[MAXS];
  static long long fr[MAXS];
  int ns = 0;
  const int loop_n = cfg.sim.frames;
  const double loop_s = cfg.sim.frames / cfg.sim.rate_hz;
  double t0 = mono_s(), cpu0 = -1, wall0 = 0;
  if (cw.on) {
    /* Sim time to bench time: vlff-sim streams frame i at t_spawn + i / rate. */
    cw.t_change += t_spawn - t0, cw.t_seen += t_spawn - t0;
    cw.map = vlff_map_attach(cfg.shm.map);
    if (!cw.map) cw.on = false, fprintf(stderr, "bench_node: change: cannot read the map segment\n");
  }
  struct vlff_node_status st;
  const double half = 15; /* the final value's window, each side of `seconds` */
  /* The final loop: the views whose frame ids lie within half a loop of the
   * one published at `seconds` (by ids, not by time: a simulator slower
   * than sim.rate_hz must still give every view). Run until it is whole,
   * or for one loop's time (twice, for a slow simulator) after `seconds`. */
  long long id_c = -1;
  long long flips0 = -1, mapped0 = 0; /* the flip counts where the final window starts */
  for (;;) {
    double t = mono_s() - t0;
    bool final_done = id_c >= 0 && ns > 0 && fr[ns - 1] >= id_c + loop_n / 2;
    bool walk_done = !walk || miou3d_end >= 0;
    if (ns >= MAXS || (t >= seconds + half && final_done && walk_done) || t >= seconds + 2 * loop_s) break;
    for (int k = 0; k < 5; k++) {
      struct timespec nap = {0, 100 * 1000 * 1000};
      nanosleep(&nap, NULL);
      change_poll(&cw, mono_s() - t0);
    }
    vlff_node_status(n, &st);
    ts[ns] = mono_s() - t0;
    fr[ns] = st.miou2d_frame;
    m2[ns++] = st.miou2d;
    if (cpu0 < 0 && st.iteration > 0) cpu0 = cpu_s(), wall0 = mono_s();
    if (id_c < 0 && ts[ns - 1] >= seconds && st.miou2d_frame >= 0) id_c = st.miou2d_frame;
    if (flips0 < 0 && ts[ns - 1] >= seconds - half) flips0 = st.label_flips_elsewhere, mapped0 = st.label_mapped_elsewhere;
    if (walk && !wmap && (wmap = vlff_map_attach(cfg.shm.map))) wsnap = vlff_map_snapshot_new(wmap);
    if (walk && !wring) wring = vlff_ring_attach(cfg.shm.ring, VLFF_RECORD_FRAME);
    /* frame ids count from 0: the head is the newest written id + 1 */
    long long written = wring ? (long long)vlff_ring_head(wring) : 0;
    if (walk && flat1_leave < 0 && written > leave_frame) {
      flat1_leave = map_miou3d(wmap, wsnap, &wpts, in_flat1);
      printf("t=%5.1f s  frame %lld written, the map at frame %lld: left flat 1; its 3D mIoU %.1f\n", ts[ns - 1],
             written - 1, st.miou2d_frame, flat1_leave);
    }
    if (walk && flat1_leave >= 0 && miou3d_end < 0 && written >= loop_n) {
      flat1_end = map_miou3d(wmap, wsnap, &wpts, in_flat1);
      miou3d_end = map_miou3d(wmap, wsnap, &wpts, in_all);
      printf("t=%5.1f s  frame %lld written, the map at frame %lld: the walk's end; flat 1's 3D mIoU %.1f, the "
             "building's %.1f, %d keyframes, %lld evicted (%lld paged out, %lld brought back, %lld dropped)\n",
             ts[ns - 1], written - 1, st.miou2d_frame, flat1_end, miou3d_end, st.keyframes, st.keyframes_evicted,
             st.keyframes_paged_out, st.keyframes_paged_in, st.keyframes_dropped);
    }
    if (ns % 10 == 0)
      printf("t=%5.1f s  it %lld  kf %d  2D mIoU %.1f  3D mIoU %.1f\n", ts[ns - 1], st.iteration, st.keyframes,
             st.miou2d, st.miou3d);
  }
  vlff_node_status(n, &st);
  if (cw.map) vlff_map_detach(cw.map);
  vlff_map_snapshot_free(wsnap);
  vlff_map_detach(wmap);
  if (wring) vlff_ring_close(wring);
  double cores = cpu0 >= 0 ? (cpu_s() - cpu0) / (mono_s() - wall0) : -1;
  tk_node_destroy(n, sim_src);
  kill(sim, SIGTERM);
  waitpid(sim, NULL, 0);
  snprintf(path, sizeof path, "rm -rf %s /dev/shm/bn%d-*", tmp, (int)getpid());
  if (system(path)) fprintf(stderr, "bench_node: cleanup failed\n");

  /* Smooth over 5 s: each sample is one view's label image. */
  static double sm[MAXS];
  for (int i = 0; i < ns; i++) {
    double acc = 0;
    int c = 0;
    for (int j = i; j >= 0 && ts[i] - ts[j] < 5.0; j--)
      if (m2[j] >= 0) acc += m2[j], c++;
    sm[i] = c ? acc / c : -1;
  }
  double acc = 0;
  int cnt = 0;
  for (int i = 0; i < ns; i++)
    if (fabs(ts[i] - seconds) <= half && m2[i] >= 0) acc += m2[i], cnt++;
  double final = cnt ? acc / cnt : -1, useful = -1;
  for (int i = 0; i < ns; i++)
    if (final > 0 && sm[i] >= 0.9 * final) {
      useful = ts[i];
      break;
    }
  /* Same view: each loop position's mean in the loop around `seconds`. */
  double *qs = calloc((size_t)loop_n, sizeof *qs), useful_sv = -1;
  int *qc = calloc((size_t)loop_n, sizeof *qc);
  static double q[MAXS];
  if (!qs || !qc) return fprintf(stderr, "bench_node: out of memory\n"), 1;
  for (int i = 0; i < ns; i++)
    if (m2[i] >= 0 && id_c >= 0 && fr[i] >= id_c - loop_n / 2 && fr[i] < id_c + loop_n / 2)
      qs[fr[i] % loop_n] += m2[i], qc[fr[i] % loop_n]++;
  const int reach = (int)ceil(cfg.sim.rate_hz); /* a second of walk either side */
  for (int i = 0; i < ns; i++) {
    double a = 0;
    int c = 0;
    for (int d = -reach; fr[i] >= 0 && d <= reach; d++) {
      int p = (int)(((fr[i] + d) % loop_n + loop_n) % loop_n);
      a += qs[p], c += qc[p];
    }
    q[i] = c ? a / c : -1;
  }
  printf("same-view ratio (%%, 5-s windows):");
  for (int i = 0; i < ns && fr[i] < id_c - loop_n / 2; i++) {
    double a = 0, b = 0;
    int c = 0;
    for (int j = i; j >= 0 && ts[i] - ts[j] < 5.0; j--)
      if (m2[j] >= 0 && q[j] > 0) a += m2[j], b += q[j], c++;
    if (i % 2 && ts[i] < 30.5) printf(" %.0f", c ? 100 * a / b : -1);
    if (useful_sv < 0 && c >= 4 && a >= 0.9 * b) useful_sv = ts[i];
  }
  printf("\n");
  if (getenv("VLFF_BENCH_TRACE")) {
    FILE *tf = fopen(getenv("VLFF_BENCH_TRACE"), "w");
    for (int i = 0; tf && i < ns; i++) fprintf(tf, "%.2f %lld %.1f %.1f\n", ts[i], fr[i], m2[i], q[i]);
    if (tf) fclose(tf);
  }
  free(qs);
  free(qc);
  /* The first 30 s, where time to useful is decided. */
  printf("smoothed 2D mIoU (threshold %.1f):", 0.9 * final);
  for (int i = 1; i < ns && ts[i] < 30.5; i += 2) printf(" %.0f", sm[i]);
  printf("\n");
  printf("final: %lld iterations, %d keyframes, 3D mIoU %.1f, frame-to-map p50 %.0f ms, map refreshed every %.2f s "
         "(publish.rate_hz %.2f)\n",
         st.iteration, st.keyframes, st.miou3d, st.frame_to_map_ms_p50, st.publish_interval_s, cfg.publish.rate_hz);
  const double rss_mb = peak_rss_kb() / 1024.0;
  char walk_kv[256] = "";
  if (walk) {
    double fusion = fusion_miou3d(&cfg, &wpts);
    printf("the walk: 3D mIoU at its end %.1f, fusion of its %d frames %.1f; flat 1 %.1f when left, %.1f at the "
           "end\n",
           miou3d_end, loop_n, fusion, flat1_leave, flat1_end);
    char forgot[32] = "n/a"; /* flat 1 never scored twice (no map yet, or the walk never ended) */
    if (flat1_leave >= 0 && flat1_end >= 0) snprintf(forgot, sizeof forgot, "%.1f", flat1_leave - flat1_end);
    snprintf(walk_kv, sizeof walk_kv, " miou3d_end=%.1f miou3d_fusion_end=%.1f forgetting_pts=%s rss_peak_mb=%.0f",
             miou3d_end, fusion, forgot, rss_mb);
    free(in_flat1), free(in_all);
    vlff_sim_points_free(&wpts);
    vlff_sim_destroy(wsim);
  }
  /* frame_to_map: a keyframe's capture stamp to the first map version whose
   * change log covers its voxels; publish_interval_s: the time between whole
   * refreshes of the map (target 1 / publish.rate_hz). */
  printf("RESULT time_to_useful_s=%.1f miou2d_at_%.0fs=%.1f frame_to_map_p99_ms=%.0f rss_mb=%.0f miou2d_raw=%.1f "
         "miou2d_vs_raw=%.2f miou3d=%.1f time_to_useful_same_view_s=%.1f publish_interval_s=%.2f%s\n",
         useful, seconds, final, st.frame_to_map_ms_p99, rss_mb, raw, raw > 0 ? final / raw : 0, st.miou3d,
         useful_sv, st.publish_interval_s, walk_kv);
  /* miou3d_end: the same 3D mIoU, named for comparing runs of one walk at
   * different budgets (node.sh). */
  if (walk) printf("RESULT cpu_cores_used=%.3f\n", cores); /* the walk's miou3d_end is above */
  else printf("RESULT cpu_cores_used=%.3f miou3d_end=%.1f\n", cores, st.miou3d);
  if (budget > 0) printf("RESULT cpu_budget=%.2f cpu_budget_ratio=%.3f\n", budget, cores / budget);
  long long dm = st.label_mapped_elsewhere - (flips0 < 0 ? 0 : mapped0);
  long long df = st.label_flips_elsewhere - (flips0 < 0 ? 0 : flips0);
  printf("label flips without new evidence: %lld of %lld labelled voxels over the final window; %lld keyframes "
         "retired (newer depth saw through them)\n", df, dm, st.keyframes_retired);
  printf("RESULT label_flip_frac=%.4f\n", dm > 0 ? (double)df / (double)dm : -1.0);
  if (cw.on) {
    printf("change: the map had the chair as label %d at %d points before the move; both places seen at %.1f s; the "
           "old place free at %.1f s, the new place labelled at %.1f s (-1: never); %lld keyframes retired\n",
           cw.cls, cw.n_old, cw.t_seen, cw.t_free, cw.t_new, st.keyframes_retired);
    printf("RESULT change_visible_s=%.2f\n", cw.t_done >= 0 ? fmax(0, cw.t_done - cw.t_seen) : -1.0);
  }
  return 0;
}
