/*
 * Why redundancy-based eviction: the reference evicts at random, which on a
 * robot that lingers in one room slowly forgets the rooms it left. Dropping
 * the view nearest to another view loses the least coverage per byte.
 */
#include "keyframes.h"

#include "select.h"
#include "mem.h"

#include <errno.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

struct kf {
  long long id, t_ns;
  size_t bytes;
  struct vlff_view view;
  void *mem; /* one block holding rgb, depth, features */
};

struct vlff_kfstore {
  size_t budget, bytes;
  int max_count, protect, count;
  long long evicted, retired;
  struct kf *kfs;              /* oldest first */
  struct vlff_view *views;     /* rebuilt by views() */
  float *weights;
};

size_t vlff_kfstore_cost(int w, int h, int fw, int fh, int d, int has_depth) {
  size_t px = (size_t)w * h;
  return sizeof(struct kf) + px * 3 + (has_depth ? px * sizeof(float) : 0) +
         (size_t)fw * fh * d * sizeof(uint16_t);
}

struct vlff_kfstore *vlff_kfstore_create(size_t budget_bytes, int max_count, int protect) {
  if (max_count < 1 || protect < 0) {
    errno = EINVAL;
    return NULL;
  }
  struct vlff_kfstore *s = calloc(1, sizeof *s);
  if (!s) return NULL;
  s->budget = budget_bytes;
  s->max_count = max_count;
  s->protect = protect;
  s->kfs = calloc((size_t)max_count + 1, sizeof *s->kfs);
  s->views = calloc((size_t)max_count + 1, sizeof *s->views);
  s->weights = calloc((size_t)max_count + 1, sizeof *s->weights);
  if (!s->kfs || !s->views || !s->weights) {
    vlff_kfstore_destroy(s);
    return NULL;
  }
  return s;
}

void vlff_kfstore_destroy(struct vlff_kfstore *s) {
  if (!s) return;
  for (int i = 0; i < s->count; i++) free(s->kfs[i].mem);
  VLFF_FREE_ALL(s->kfs, s->views, s->weights, s);
}

double vlff_pose_distance(const double a[16], const double b[16]) {
  double dt = 0;
  for (int i = 0; i < 3; i++) {
    double d = a[i * 4 + 3] - b[i * 4 + 3];
    dt += d * d;
  }
  return sqrt(dt) + 0.5 * vlff_pose_angle(a, b);
}

static void evict_one(struct vlff_kfstore *s) {
  int candidates = s->count - s->protect;
  int victim = 0;
  if (candidates > 1) {
    double best = INFINITY;
    for (int i = 0; i < candidates; i++) {
      double nn = INFINITY;
      for (int j = 0; j < s->count; j++)
        if (j != i) nn = fmin(nn, vlff_pose_distance(s->kfs[i].view.c2w, s->kfs[j].view.c2w));
      if (nn < best) { /* strict: on ties the older view goes */
        best = nn;
        victim = i;
      }
    }
  }
  s->bytes -= s->kfs[victim].bytes;
  free(s->kfs[victim].mem);
  memmove(&s->kfs[victim], &s->kfs[victim + 1], (size_t)(s->count - victim - 1) * sizeof *s->kfs);
  s->count--;
  s->evicted++;
}

int vlff_kfstore_add(struct vlff_kfstore *s, const struct vlff_keyframe_in *in) {
  const struct vlff_view *v = &in->view;
  int fw = v->features ? v->feat_width : 0, fh = v->features ? v->feat_height : 0;
  size_t cost = vlff_kfstore_cost(v->width, v->height, fw, fh, in->feature_dim, v->depth != NULL);
  if (cost > s->budget || v->width <= 0 || v->height <= 0 || !v->rgb) {
    errno = EINVAL;
    return -1;
  }
  size_t px = (size_t)v->width * v->height;
  size_t frgb = px * 3, fdepth = v->depth ? px * sizeof(float) : 0;
  size_t ffeat = (size_t)fw * fh * in->feature_dim * sizeof(uint16_t);
  /* Depth and features first in the block keeps them 4- and 2-byte aligned. */
  char *mem = malloc(fdepth + ffeat + frgb);
  if (!mem) return -1;
  while (s->count > 0 && (s->count >= s->max_count || s->bytes + cost > s->budget)) evict_one(s);
  struct kf *k = &s->kfs[s->count++];
  k->id = in->id;
  k->t_ns = in->t_ns;
  k->bytes = cost;
  k->mem = mem;
  k->view = *v;
  if (v->depth) {
    memcpy(mem, v->depth, fdepth);
    k->view.depth = (const float *)mem;
  }
  if (ffeat) {
    memcpy(mem + fdepth, v->features, ffeat);
    k->view.features = (const uint16_t *)(mem + fdepth);
  } else {
    k->view.features = NULL;
  }
  memcpy(mem + fdepth + ffeat, v->rgb, frgb);
  k->view.rgb = (const uint8_t *)(mem + fdepth + ffeat);
  s->bytes += cost;
  return 0;
}

int vlff_kfstore_retire(struct vlff_kfstore *s, bool (*contradicted)(void *ctx, const struct vlff_view *v), void *ctx) {
  int kept = 0, dropped = 0;
  for (int i = 0; i < s->count; i++) {
    if (i < s->count - 1 && contradicted(ctx, &s->kfs[i].view)) {
      s->bytes -= s->kfs[i].bytes;
      free(s->kfs[i].mem);
      dropped++;
      continue;
    }
    s->kfs[kept++] = s->kfs[i];
  }
  s->count = kept;
  s->retired += dropped;
  return dropped;
}

long long vlff_kfstore_retired(const struct vlff_kfstore *s) { return s->retired; }

int vlff_kfstore_count(const struct vlff_kfstore *s) { return s->count; }
size_t vlff_kfstore_bytes(const struct vlff_kfstore *s) { return s->bytes; }
long long vlff_kfstore_evicted(const struct vlff_kfstore *s) { return s->evicted; }
long long vlff_kfstore_id(const struct vlff_kfstore *s, int i) { return s->kfs[i].id; }

int vlff_kfstore_views(struct vlff_kfstore *s, int recent, const struct vlff_view **views, const float **weights) {
  int n = s->count;
  if (recent > n) recent = n;
  if (recent < 1) recent = 1;
  int old = n - recent;
  for (int i = 0; i < n; i++) {
    s->views[i] = s->kfs[i].view;
    /* Half the rays to the newest views, half spread over the older ones. */
    if (old == 0)
      s->weights[i] = 1.0f / (float)n;
    else
      s->weights[i] = i >= old ? 0.5f / (float)recent : 0.5f / (float)old;
  }
  *views = s->views;
  *weights = s->weights;
  return n;
}
