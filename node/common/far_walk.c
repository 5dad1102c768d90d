/*
 * The far map's labelled voxels as points (far_walk.h).
 */
#include "far_walk.h"

#include <math.h>
#include <stdbool.h>
#include <stdlib.h>

#define E VLFF_MAP_FAR_EDGE

static bool has_grid(const struct vlff_map_grid *g) { return g && g->labels; }

/* Whether the grid covers world point c (its voxel inside dims). */
static bool covered(const struct vlff_map_grid *g, const double c[3]) {
  if (!has_grid(g)) return false;
  for (int a = 0; a < 3; a++) {
    const double k = floor((c[a] - g->origin[a]) / g->voxel_size);
    if (!(k >= 0 && k < (double)g->dims[a])) return false;
  }
  return true;
}

/* Whether block j's voxel centres all lie clearly outside the grid's box
 * (a voxel's width from it), so none is covered. */
static bool apart(const struct vlff_map_far *far, uint32_t j, const struct vlff_map_grid *g) {
  if (!has_grid(g)) return true;
  for (int a = 0; a < 3; a++) {
    const double lo = far->origin[a] + ((double)far->blocks[j].key[a] * E + 0.5) * far->voxel_size,
                 hi = lo + (E - 1) * far->voxel_size, glo = g->origin[a] - g->voxel_size,
                 ghi = g->origin[a] + ((double)g->dims[a] + 1) * g->voxel_size;
    if (hi < glo || lo > ghi) return true;
  }
  return false;
}

/* Block j's points: fn for each when fn is set; the count. A block apart
 * from the grid is counted from its runs. */
static size_t block_points(const struct vlff_map_far *far, uint32_t j, const struct vlff_map_grid *g,
                           vlff_far_point_fn fn, void *ctx) {
  const uint32_t end = j + 1 < far->nblocks ? far->blocks[j + 1].first_run : far->nruns;
  const bool whole = apart(far, j, g);
  size_t n = 0;
  uint32_t v = 0; /* the block's voxel the run starts at */
  for (uint32_t r = far->blocks[j].first_run; r < end; v += far->runs[r].count, r++) {
    const struct vlff_map_far_run *run = &far->runs[r];
    if (run->label > VLFF_LABEL_MAX) continue;
    if (whole && !fn) {
      n += run->count;
      continue;
    }
    for (uint32_t i = v; i < v + run->count && i < E * E * E; i++) {
      const uint32_t l[3] = {i % E, i / E % E, i / (E * E)};
      double c[3];
      for (int a = 0; a < 3; a++)
        c[a] = far->origin[a] + ((double)far->blocks[j].key[a] * E + l[a] + 0.5) * far->voxel_size;
      if (!whole && covered(g, c)) continue;
      if (fn) fn(ctx, c, run->label, run->conf);
      n++;
    }
  }
  return n;
}

struct order {
  double d;
  uint32_t j;
};

static int by_dist(const void *a, const void *b) {
  const struct order *x = a, *y = b;
  return x->d < y->d ? -1 : x->d > y->d ? 1 : (x->j > y->j) - (x->j < y->j);
}

int vlff_far_pick(const struct vlff_map_far *far, const struct vlff_map_grid *g, size_t max_points,
                  struct vlff_far_pick *pick) {
  *pick = (struct vlff_far_pick){0};
  if (!far || !far->nblocks) return 0;
  size_t all = 0;
  for (uint32_t j = 0; j < far->nblocks; j++) all += block_points(far, j, g, NULL, NULL);
  if (all <= max_points) {
    pick->points = all;
    return 0;
  }
  /* Past the bound: whole blocks, the nearest to the grid first. */
  struct order *o = malloc((size_t)far->nblocks * sizeof *o);
  pick->order = malloc((size_t)far->nblocks * sizeof *pick->order);
  if (!o || !pick->order) {
    free(o), free(pick->order);
    *pick = (struct vlff_far_pick){.left = all};
    return -1;
  }
  for (uint32_t j = 0; j < far->nblocks; j++) {
    double d = 0;
    for (int a = 0; a < 3; a++) {
      const double c = far->origin[a] + ((double)far->blocks[j].key[a] + 0.5) * E * far->voxel_size,
                   at = has_grid(g) ? g->origin[a] + 0.5 * g->dims[a] * g->voxel_size : far->origin[a];
      d += (c - at) * (c - at);
    }
    o[j] = (struct order){d, j};
  }
  qsort(o, far->nblocks, sizeof *o, by_dist);
  for (uint32_t i = 0; i < far->nblocks; i++) {
    const size_t k = block_points(far, o[i].j, g, NULL, NULL);
    if (pick->points + k > max_points) break;
    if (k) pick->order[pick->norder++] = o[i].j;
    pick->points += k;
  }
  free(o);
  pick->left = all - pick->points;
  return 0;
}

size_t vlff_far_emit(const struct vlff_map_far *far, const struct vlff_map_grid *g, const struct vlff_far_pick *pick,
                     vlff_far_point_fn fn, void *ctx) {
  size_t n = 0;
  if (!far || !pick->points) return 0;
  if (!pick->order)
    for (uint32_t j = 0; j < far->nblocks; j++) n += block_points(far, j, g, fn, ctx);
  else
    for (uint32_t i = 0; i < pick->norder; i++) n += block_points(far, pick->order[i], g, fn, ctx);
  return n;
}

void vlff_far_pick_free(struct vlff_far_pick *pick) {
  free(pick->order);
  *pick = (struct vlff_far_pick){0};
}
