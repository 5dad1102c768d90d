/*
 * The far map's labelled voxels as points (far_walk.h).
 */
#include "far_walk.h"

#include <math.h>
#include <stdlib.h>

#define E VLFF_MAP_FAR_EDGE

/* Whether the grid covers world point c (its voxel inside dims). */
static int covered(const struct vlff_map_grid *g, const double c[3]) {
  if (!g || !g->labels) return 0;
  for (int a = 0; a < 3; a++) {
    const double k = floor((c[a] - g->origin[a]) / g->voxel_size);
    if (!(k >= 0 && k < (double)g->dims[a])) return 0;
  }
  return 1;
}

/* Block j's points (fn NULL: counted only). */
static size_t walk_block(const struct vlff_map_far *far, uint32_t j, const struct vlff_map_grid *g,
                         vlff_far_point_fn fn, void *ctx) {
  const uint32_t end = j + 1 < far->nblocks ? far->blocks[j + 1].first_run : far->nruns;
  size_t n = 0;
  uint32_t v = 0; /* the block's voxel the run starts at: x fastest, then y, z */
  for (uint32_t r = far->blocks[j].first_run; r < end; v += far->runs[r].count, r++) {
    const struct vlff_map_far_run *run = &far->runs[r];
    if (run->label > VLFF_LABEL_MAX) continue;
    for (uint32_t i = v; i < v + run->count && i < E * E * E; i++) {
      const uint32_t l[3] = {i % E, i / E % E, i / (E * E)};
      double c[3];
      for (int a = 0; a < 3; a++)
        c[a] = far->origin[a] + ((double)far->blocks[j].key[a] * E + l[a] + 0.5) * far->voxel_size;
      if (covered(g, c)) continue;
      if (fn) fn(ctx, c, run->label, run->conf);
      n++;
    }
  }
  return n;
}

/* Squared distance of block j's centre from the grid's centre (the far
 * map's origin without a grid). */
static double block_dist(const struct vlff_map_far *far, uint32_t j, const struct vlff_map_grid *g) {
  double d = 0;
  for (int a = 0; a < 3; a++) {
    const double c = far->origin[a] + ((double)far->blocks[j].key[a] + 0.5) * E * far->voxel_size;
    const double o = g && g->labels ? g->origin[a] + 0.5 * g->dims[a] * g->voxel_size : far->origin[a];
    d += (c - o) * (c - o);
  }
  return d;
}

struct order {
  double d;
  uint32_t j;
};

static int by_dist(const void *a, const void *b) {
  const struct order *x = a, *y = b;
  return x->d < y->d ? -1 : x->d > y->d ? 1 : (x->j > y->j) - (x->j < y->j);
}

size_t vlff_far_walk(const struct vlff_map_far *far, const struct vlff_map_grid *g, size_t max_points,
                     vlff_far_point_fn fn, void *ctx, size_t *left_out) {
  size_t n = 0, all = 0;
  if (left_out) *left_out = 0;
  if (!far || !far->nblocks) return 0;
  for (uint32_t j = 0; j < far->nblocks; j++) all += walk_block(far, j, g, NULL, NULL);
  if (all <= max_points) {
    for (uint32_t j = 0; fn && j < far->nblocks; j++) walk_block(far, j, g, fn, ctx);
    return all;
  }
  /* Past the bound: whole blocks, the nearest to the grid first. */
  struct order *o = malloc((size_t)far->nblocks * sizeof *o);
  if (!o) {
    if (left_out) *left_out = all;
    return 0;
  }
  for (uint32_t j = 0; j < far->nblocks; j++) o[j] = (struct order){block_dist(far, j, g), j};
  qsort(o, far->nblocks, sizeof *o, by_dist);
  for (uint32_t i = 0; i < far->nblocks; i++) {
    const size_t k = walk_block(far, o[i].j, g, NULL, NULL);
    if (n + k > max_points) break;
    if (fn && k) walk_block(far, o[i].j, g, fn, ctx);
    n += k;
  }
  free(o);
  if (left_out) *left_out = all - n;
  return n;
}
