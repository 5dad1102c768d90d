/* SPDX-License-Identifier: BSD-3-Clause */
/* vlff-merge's merging (merge.h): robots' clouds into one world grid. */
#include "merge.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dds.h"

int vlff_merge_add_path(struct vlff_merge_robot *r, const double p[3]) {
  if (!isfinite(p[0]) || !isfinite(p[1]) || !isfinite(p[2]) || fabs(p[0]) > 1e5 || fabs(p[1]) > 1e5 ||
      fabs(p[2]) > 1e5)
    return -1;
  for (uint32_t i = 0; i < r->npath; i++) {
    double dx = p[0] - r->path[i][0], dy = p[1] - r->path[i][1], dz = p[2] - r->path[i][2];
    if (dx * dx + dy * dy + dz * dz < VLFF_MERGE_PATH_STEP * VLFF_MERGE_PATH_STEP) return 0;
  }
  if (r->npath == VLFF_MERGE_MAX_PATH) {
    r->path_full++;
    return 0;
  }
  for (int a = 0; a < 3; a++) r->path[r->npath][a] = (float)p[a];
  r->npath++;
  return 1;
}

/* How much a robot's vote at p (its frame) counts by its distance from the
 * robot's camera path: 1 on it, a half VLFF_MERGE_PATH_NEAR away; 1 with no
 * path known. */
static float path_weight(const struct vlff_merge_robot *r, const float p[3]) {
  if (!r->npath) return 1;
  float d2 = INFINITY;
  for (uint32_t i = 0; i < r->npath; i++) {
    float dx = p[0] - r->path[i][0], dy = p[1] - r->path[i][1], dz = p[2] - r->path[i][2];
    float e = dx * dx + dy * dy + dz * dz;
    if (e < d2) d2 = e;
  }
  return 1.0f / (1.0f + d2 / (float)(VLFF_MERGE_PATH_NEAR * VLFF_MERGE_PATH_NEAR));
}

void vlff_merge_yaw(double rot[9], double yaw) {
  double c = cos(yaw), s = sin(yaw);
  const double m[9] = {c, -s, 0, s, c, 0, 0, 0, 1};
  memcpy(rot, m, sizeof m);
}

int vlff_merge_quat(double rot[9], const double q[4], char *why, size_t whylen) {
  double x = q[0], y = q[1], z = q[2], w = q[3], n = sqrt(x * x + y * y + z * z + w * w);
  if (!isfinite(n) || fabs(n - 1) > 0.01) {
    snprintf(why, whylen, "rotation (%g %g %g %g): expected a unit quaternion (norm within 1 +- 0.01)", x, y, z, w);
    return -1;
  }
  x /= n, y /= n, z /= n, w /= n;
  const double m[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - z * w),     2 * (x * z + y * w),
                       2 * (x * y + z * w),     1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                       2 * (x * z - y * w),     2 * (y * z + x * w),     1 - 2 * (x * x + y * y)};
  memcpy(rot, m, sizeof m);
  return 0;
}

int vlff_merge_grid_init(struct vlff_merge_grid *g, const double lo[3], const double hi[3], double voxel,
                         double half_life_s, char *why, size_t whylen) {
  memset(g, 0, sizeof *g);
  if (!(half_life_s > 0 && half_life_s <= 1e9)) {
    snprintf(why, whylen, "recency half-life %g s outside (0, 1e9]", half_life_s);
    return -1;
  }
  g->half_life_s = half_life_s;
  if (!(voxel >= 0.01 && voxel <= 10)) {
    snprintf(why, whylen, "voxel size %g m outside 0.01..10", voxel);
    return -1;
  }
  double n = 1;
  for (int a = 0; a < 3; a++) {
    if (!isfinite(lo[a]) || !isfinite(hi[a]) || !(hi[a] > lo[a]) || fabs(lo[a]) > 1e5 || fabs(hi[a]) > 1e5) {
      snprintf(why, whylen, "bounds axis %d: expected finite lo < hi within +-1e5 m, got %g..%g", a, lo[a], hi[a]);
      return -1;
    }
    g->origin[a] = lo[a];
    g->dims[a] = (uint32_t)ceil((hi[a] - lo[a]) / voxel);
    n *= g->dims[a];
  }
  /* The map segment's grid counts voxels in 32 bits; 64 M is 320 MB here. */
  if (n > (double)(64u << 20)) {
    snprintf(why, whylen, "%.0f voxels, more than %u: larger voxels or smaller bounds", n, 64u << 20);
    return -1;
  }
  g->voxel = voxel;
  size_t count = (size_t)n;
  g->labels = malloc(count * sizeof *g->labels);
  g->conf = malloc(count);
  if (!g->labels || !g->conf) {
    vlff_merge_grid_free(g);
    snprintf(why, whylen, "no memory for %zu voxels", count);
    return -1;
  }
  return 0;
}

void vlff_merge_grid_free(struct vlff_merge_grid *g) {
  free(g->labels);
  free(g->conf);
  free(g->votes);
  g->labels = NULL, g->conf = NULL, g->votes = NULL, g->nvotes_cap = 0;
}

void vlff_merge_robot_free(struct vlff_merge_robot *r) {
  free(r->xyz);
  free(r->label);
  free(r->conf);
  free(r->changed_ns);
  free(r->slot);
  r->xyz = NULL, r->label = NULL, r->conf = NULL, r->changed_ns = NULL, r->slot = NULL, r->n = r->cap = 0,
  r->nslot = 0;
}

static float f32_le(const uint8_t *p) {
  uint32_t u = (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
  float f;
  memcpy(&f, &u, 4);
  return f;
}

/* The layout vlff-dds writes: map's five fields, an update's six. 0 or -1. */
static int check_layout(bool update, uint32_t width, uint32_t height, uint32_t point_step, bool bigendian,
                        const char *const names[], const uint32_t offsets[], const uint8_t types[], uint32_t nfields,
                        size_t len, char *why, size_t whylen) {
  static const char *const want[6] = {"x", "y", "z", "label", "confidence", "version"};
  static const uint32_t woff[6] = {0, 4, 8, 12, 16, 20};
  static const uint8_t wtype[6] = {VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32, VLFF_DDS_FLOAT32,
                                   VLFF_DDS_UINT16,  VLFF_DDS_FLOAT32, VLFF_DDS_UINT32};
  uint32_t nf = update ? 6 : 5, step = update ? VLFF_DDS_UPDATE_STEP : VLFF_DDS_POINT_STEP;
  if (nfields != nf || bigendian || point_step < step) {
    snprintf(why, whylen, "expected vlff-dds's layout (%u fields, little-endian, point_step >= %u), got %u fields%s, "
             "point_step %u", nf, step, nfields, bigendian ? ", big-endian" : "", point_step);
    return -1;
  }
  for (uint32_t i = 0; i < nf; i++)
    if (!names[i] || strcmp(names[i], want[i]) || offsets[i] != woff[i] || types[i] != wtype[i]) {
      snprintf(why, whylen, "field %u: expected %s at %u of type %u", i, want[i], woff[i], wtype[i]);
      return -1;
    }
  uint64_t n = (uint64_t)width * height;
  if (n > VLFF_MERGE_MAX_POINTS || n * point_step != len) {
    snprintf(why, whylen, "%llu points of %u bytes in %zu bytes of data (at most %u points)", (unsigned long long)n,
             point_step, len, VLFF_MERGE_MAX_POINTS);
    return -1;
  }
  return 0;
}

/* A point's values, checked: 0, or -1 with why. Labels free and unknown
 * only where allowed (updates). */
static int take_point(const struct vlff_merge_robot *r, const uint8_t *p, uint64_t i, bool clears, float xyz[3],
                      uint16_t *label, uint8_t *conf, char *why, size_t whylen) {
  float c = f32_le(p + 16);
  uint16_t l = (uint16_t)(p[12] | p[13] << 8);
  for (int a = 0; a < 3; a++) xyz[a] = f32_le(p + 4 * a);
  bool label_ok = (int)l < (r->nprompts > 0 ? r->nprompts : VLFF_SHM_MAX_PROMPTS) ||
                  (clears && (l == VLFF_LABEL_FREE || l == VLFF_LABEL_UNKNOWN));
  if (!isfinite(xyz[0]) || !isfinite(xyz[1]) || !isfinite(xyz[2]) || !(c >= 0 && c <= 1) || !label_ok) {
    snprintf(why, whylen, "point %llu: coordinates (%g %g %g), confidence %g, label %u (expected finite, 0..1, a "
             "label of its %d prompts%s)", (unsigned long long)i, xyz[0], xyz[1], xyz[2], c, l, r->nprompts,
             clears ? ", free or unknown" : "");
    return -1;
  }
  *label = l;
  *conf = (uint8_t)lrintf(c * 255.0f);
  return 0;
}

static size_t point_hash(const float p[3], size_t mask) {
  uint32_t u[3];
  memcpy(u, p, sizeof u);
  uint64_t h = 1469598103934665603ull;
  for (int a = 0; a < 3; a++) h = (h ^ u[a]) * 1099511628211ull;
  return (size_t)(h ^ h >> 29) & mask;
}

/* The slot of the point at p, or the empty slot where it would go. */
static size_t find_slot(const struct vlff_merge_robot *r, const float p[3]) {
  size_t mask = r->nslot - 1, s = point_hash(p, mask);
  while (r->slot[s] != UINT32_MAX && memcmp(r->xyz + 3 * (size_t)r->slot[s], p, 3 * sizeof *p)) s = (s + 1) & mask;
  return s;
}

/* The position index over the held points, at most half full. 0 or -1. */
static int index_points(struct vlff_merge_robot *r, uint32_t need) {
  size_t want = 64;
  while (want < 2 * (size_t)need) want *= 2;
  if (r->slot && r->nslot >= want) return 0;
  free(r->slot);
  r->slot = malloc(want * sizeof *r->slot);
  r->nslot = r->slot ? want : 0;
  if (!r->slot) return -1;
  memset(r->slot, 0xff, want * sizeof *r->slot);
  for (uint32_t i = 0; i < r->n; i++) {
    size_t s = find_slot(r, r->xyz + 3 * (size_t)i);
    if (r->slot[s] == UINT32_MAX) r->slot[s] = i;
  }
  return 0;
}

int vlff_merge_take_cloud(struct vlff_merge_robot *r, uint32_t width, uint32_t height, uint32_t point_step,
                          bool bigendian, const char *const names[], const uint32_t offsets[], const uint8_t types[],
                          uint32_t nfields, const uint8_t *data, size_t len, int64_t stamp_ns, char *why,
                          size_t whylen) {
  if (check_layout(false, width, height, point_step, bigendian, names, offsets, types, nfields, len, why, whylen))
    return -1;
  uint64_t n = (uint64_t)width * height;
  if (r->xyz && stamp_ns < r->stamp_ns) return 0; /* what is held is newer */
  float *xyz = malloc(n ? n * 3 * sizeof *xyz : 1);
  uint16_t *label = malloc(n ? n * sizeof *label : 1);
  uint8_t *conf = malloc(n ? n : 1);
  int64_t *changed = malloc(n ? n * sizeof *changed : 1);
  if (!xyz || !label || !conf || !changed) {
    free(xyz), free(label), free(conf), free(changed);
    snprintf(why, whylen, "no memory for %llu points", (unsigned long long)n);
    return -1;
  }
  /* A voxel the new map repeats keeps the time it last changed: a whole map
   * resent as a safety net is no new observation (recency, merge.h). */
  bool old = r->xyz && index_points(r, r->n) == 0;
  for (uint64_t i = 0; i < n; i++) {
    if (take_point(r, data + i * point_step, i, false, xyz + 3 * i, &label[i], &conf[i], why, whylen) < 0) {
      free(xyz), free(label), free(conf), free(changed);
      return -1;
    }
    changed[i] = stamp_ns;
    if (old) {
      uint32_t k = r->slot[find_slot(r, xyz + 3 * i)];
      if (k != UINT32_MAX && r->label[k] == label[i] && r->conf[k] == conf[i]) changed[i] = r->changed_ns[k];
    }
  }
  vlff_merge_robot_free(r);
  r->xyz = xyz, r->label = label, r->conf = conf, r->changed_ns = changed, r->n = r->cap = (uint32_t)n;
  r->stamp_ns = stamp_ns;
  r->maps++;
  return 0;
}

int vlff_merge_take_update(struct vlff_merge_robot *r, uint32_t width, uint32_t height, uint32_t point_step,
                           bool bigendian, const char *const names[], const uint32_t offsets[], const uint8_t types[],
                           uint32_t nfields, const uint8_t *data, size_t len, int64_t stamp_ns, char *why,
                           size_t whylen) {
  if (check_layout(true, width, height, point_step, bigendian, names, offsets, types, nfields, len, why, whylen))
    return -1;
  uint64_t n = (uint64_t)width * height;
  /* checked whole first: a refused update changes nothing */
  for (uint64_t i = 0; i < n; i++) {
    float xyz[3];
    uint16_t l;
    uint8_t c;
    if (take_point(r, data + i * point_step, i, true, xyz, &l, &c, why, whylen) < 0) return -1;
  }
  if (!r->xyz || stamp_ns <= r->stamp_ns) return 0;
  if ((uint64_t)r->n + n > VLFF_MERGE_MAX_POINTS) {
    snprintf(why, whylen, "%llu points more than the %u held: more than %u", (unsigned long long)n, r->n,
             VLFF_MERGE_MAX_POINTS);
    return -1;
  }
  uint32_t need = r->n + (uint32_t)n;
  if (need > r->cap) {
    uint32_t cap = need > 2 * r->cap ? need : 2 * r->cap;
    float *xyz = realloc(r->xyz, (size_t)cap * 3 * sizeof *xyz);
    if (xyz) r->xyz = xyz;
    uint16_t *label = xyz ? realloc(r->label, (size_t)cap * sizeof *label) : NULL;
    if (label) r->label = label;
    uint8_t *conf = label ? realloc(r->conf, cap) : NULL;
    if (conf) r->conf = conf;
    int64_t *changed = conf ? realloc(r->changed_ns, (size_t)cap * sizeof *changed) : NULL;
    if (changed) r->changed_ns = changed;
    if (!changed) {
      snprintf(why, whylen, "no memory for %u points", cap);
      return -1;
    }
    r->cap = cap;
  }
  if (index_points(r, need) < 0) {
    snprintf(why, whylen, "no memory to index %u points", need);
    return -1;
  }
  for (uint64_t i = 0; i < n; i++) {
    float xyz[3];
    uint16_t l;
    uint8_t c;
    take_point(r, data + i * point_step, i, true, xyz, &l, &c, why, whylen);
    size_t s = find_slot(r, xyz);
    uint32_t k = r->slot[s];
    if (k == UINT32_MAX) {
      if (l > VLFF_LABEL_MAX) continue; /* clears a voxel not held */
      k = r->slot[s] = r->n++;
      memcpy(r->xyz + 3 * (size_t)k, xyz, sizeof xyz);
    }
    /* a cleared voxel keeps its place, unlabelled */
    r->label[k] = l <= VLFF_LABEL_MAX ? l : VLFF_LABEL_UNKNOWN;
    r->conf[k] = c;
    r->changed_ns[k] = stamp_ns;
  }
  r->stamp_ns = stamp_ns;
  r->updates++;
  return 1;
}

/* The fleet label of a robot's prompt text; -1 when the fleet list is full. */
static int fleet_label(struct vlff_merge_grid *g, const char *text) {
  for (int i = 0; i < g->nprompts; i++)
    if (!strcmp(g->prompts[i], text)) return i;
  if (g->nprompts >= VLFF_SHM_MAX_PROMPTS) return -1;
  snprintf(g->prompts[g->nprompts], sizeof g->prompts[0], "%s", text);
  return g->nprompts++;
}

static int vote_order(const void *a, const void *b) {
  const struct vlff_merge_vote *x = a, *y = b;
  if (x->voxel != y->voxel) return x->voxel < y->voxel ? -1 : 1;
  return x->label < y->label ? -1 : x->label > y->label;
}

/* Each robot point's vote, in its world voxel; the number of votes, or -1
 * without memory. */
static long collect_votes(struct vlff_merge_grid *g, struct vlff_merge_robot *robots, int nrobots) {
  size_t need = 0;
  int64_t newest = INT64_MIN;
  for (int k = 0; k < nrobots; k++) {
    const struct vlff_merge_robot *r = &robots[k];
    if (r->nprompts < 0 || !r->xyz) continue;
    need += r->n;
    for (uint32_t i = 0; i < r->n; i++)
      if (r->changed_ns[i] > newest) newest = r->changed_ns[i];
  }
  if (need > g->nvotes_cap) {
    free(g->votes);
    g->votes = malloc(need * sizeof *g->votes);
    g->nvotes_cap = g->votes ? need : 0;
    if (!g->votes) return -1;
  }
  size_t nv = 0;
  for (int k = 0; k < nrobots; k++) {
    struct vlff_merge_robot *r = &robots[k];
    r->left_out = 0;
    if (r->nprompts < 0 || !r->xyz) continue;
    int map_label[VLFF_SHM_MAX_PROMPTS];
    for (int i = 0; i < r->nprompts; i++) {
      map_label[i] = fleet_label(g, r->prompts[i]);
      if (map_label[i] < 0) r->left_out |= 1u << i;
    }
    const double *m = r->rot;
    for (uint32_t i = 0; i < r->n; i++) {
      if (r->label[i] > VLFF_LABEL_MAX) continue; /* cleared by an update */
      const float *p = r->xyz + 3 * (size_t)i;
      size_t ix[3];
      bool inside = true;
      for (int a = 0; a < 3 && inside; a++) {
        double w = m[3 * a] * p[0] + m[3 * a + 1] * p[1] + m[3 * a + 2] * p[2] + r->t[a];
        double f = floor((w - g->origin[a]) / g->voxel);
        inside = f >= 0 && f < g->dims[a];
        ix[a] = inside ? (size_t)f : 0;
      }
      if (!inside) {
        g->outside++;
        continue;
      }
      int l = r->label[i] < r->nprompts ? map_label[r->label[i]] : -1;
      if (l < 0) {
        g->no_label++;
        continue;
      }
      double age_s = 1e-9 * (double)(newest - r->changed_ns[i]);
      float rec = (float)exp2(-age_s / g->half_life_s) * path_weight(r, p);
      g->votes[nv++] = (struct vlff_merge_vote){(uint32_t)(ix[0] + g->dims[0] * (ix[1] + g->dims[1] * ix[2])),
                                                (uint16_t)l, rec * (float)r->conf[i] / 255.0f, rec,
                                                r->changed_ns[i]};
    }
  }
  return (long)nv;
}

long vlff_merge_compute(struct vlff_merge_grid *g, struct vlff_merge_robot *robots, int nrobots) {
  size_t total = (size_t)g->dims[0] * g->dims[1] * g->dims[2];
  for (size_t i = 0; i < total; i++) g->labels[i] = VLFF_LABEL_UNKNOWN, g->conf[i] = 0;
  g->nprompts = 0;
  g->outside = g->no_label = 0;
  long nv = collect_votes(g, robots, nrobots);
  if (nv < 0) return -1;
  /* Votes grouped by voxel, then label: each run of one label sums its
   * evidence; the voxel takes the run with the most (the newest on a tie). */
  if (nv > 1) qsort(g->votes, (size_t)nv, sizeof *g->votes, vote_order);
  long labelled = 0;
  for (long i = 0; i < nv;) {
    uint32_t v = g->votes[i].voxel;
    double all = 0, best = -1;
    int64_t best_t = INT64_MIN;
    uint16_t best_l = VLFF_LABEL_UNKNOWN;
    while (i < nv && g->votes[i].voxel == v) {
      uint16_t l = g->votes[i].label;
      double sum = 0;
      int64_t t = INT64_MIN;
      for (; i < nv && g->votes[i].voxel == v && g->votes[i].label == l; i++) {
        sum += g->votes[i].w, all += g->votes[i].rec;
        if (g->votes[i].changed_ns > t) t = g->votes[i].changed_ns;
      }
      if (sum > best || (sum == best && t > best_t)) best = sum, best_t = t, best_l = l;
    }
    g->labels[v] = best_l;
    g->conf[v] = (uint8_t)lrint(all > 0 ? 255 * best / all : 0);
    labelled++;
  }
  return labelled;
}
