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

enum place { APART, INSIDE, ACROSS };

/* Where block j's voxel centres lie against the grid: none covered, all
 * covered, or some. covered()'s grid index grows with the coordinate, so
 * the block's first and last centres on each axis decide. */
static enum place place_of(const struct vlff_map_far *far, uint32_t j, const struct vlff_map_grid *g) {
  if (!has_grid(g)) return APART;
  bool inside = true;
  for (int a = 0; a < 3; a++) {
    const double lo = far->origin[a] + ((double)far->blocks[j].key[a] * E + 0.5) * far->voxel_size,
                 hi = far->origin[a] + ((double)far->blocks[j].key[a] * E + E - 0.5) * far->voxel_size,
                 klo = floor((lo - g->origin[a]) / g->voxel_size), khi = floor((hi - g->origin[a]) / g->voxel_size);
    if (khi < 0 || klo >= (double)g->dims[a]) return APART;
    inside = inside && klo >= 0 && khi < (double)g->dims[a];
  }
  return inside ? INSIDE : ACROSS;
}

/* Block j's points: fn for each when fn is set; the count. A block apart
 * from the grid is counted from its runs, one inside it has none. One
 * across its boundary is read voxel by voxel where the far map's voxels
 * are the grid's (a few blocks along the grid's faces); of another size
 * (a writer's far map on a lattice of its own) it would be any number of
 * blocks, and is left out whole, its class voxels added to *cut. */
static size_t block_points(const struct vlff_map_far *far, uint32_t j, const struct vlff_map_grid *g,
                           vlff_far_point_fn fn, void *ctx, size_t *cut) {
  const uint32_t end = j + 1 < far->nblocks ? far->blocks[j + 1].first_run : far->nruns;
  const enum place where = place_of(far, j, g);
  if (where == INSIDE) return 0;
  const bool whole = where == APART,
             skip = !whole && fabs(far->voxel_size - g->voxel_size) > 1e-9 * g->voxel_size;
  size_t n = 0;
  uint32_t v = 0; /* the block's voxel the run starts at */
  for (uint32_t r = far->blocks[j].first_run; r < end; v += far->runs[r].count, r++) {
    const struct vlff_map_far_run *run = &far->runs[r];
    if (run->label > VLFF_LABEL_MAX) continue;
    if (skip) {
      if (cut) *cut += run->count;
      continue;
    }
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
  size_t all = 0, cut = 0;
  for (uint32_t j = 0; j < far->nblocks; j++) all += block_points(far, j, g, NULL, NULL, &cut);
  if (all <= max_points) {
    pick->points = all, pick->left = cut;
    return 0;
  }
  /* Past the bound: whole blocks, the nearest to the grid first. */
  struct order *o = malloc((size_t)far->nblocks * sizeof *o);
  pick->order = malloc((size_t)far->nblocks * sizeof *pick->order);
  if (!o || !pick->order) {
    free(o), free(pick->order);
    *pick = (struct vlff_far_pick){.left = all + cut};
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
    const size_t k = block_points(far, o[i].j, g, NULL, NULL, NULL);
    if (pick->points + k > max_points) break;
    if (k) pick->order[pick->norder++] = o[i].j;
    pick->points += k;
  }
  free(o);
  pick->left = all - pick->points + cut;
  return 0;
}

size_t vlff_far_emit(const struct vlff_map_far *far, const struct vlff_map_grid *g, const struct vlff_far_pick *pick,
                     vlff_far_point_fn fn, void *ctx) {
  size_t n = 0;
  if (!far || !pick->points) return 0;
  if (!pick->order)
    for (uint32_t j = 0; j < far->nblocks; j++) n += block_points(far, j, g, fn, ctx, NULL);
  else
    for (uint32_t i = 0; i < pick->norder; i++) n += block_points(far, pick->order[i], g, fn, ctx, NULL);
  return n;
}

void vlff_far_pick_free(struct vlff_far_pick *pick) {
  free(pick->order);
  *pick = (struct vlff_far_pick){0};
}
