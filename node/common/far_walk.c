/*
 * The far map's labelled voxels as points (far_walk.h).
 */
#include "far_walk.h"

#include <math.h>

/* Whether the grid covers world point c (its voxel inside dims). */
static int covered(const struct vlff_map_grid *g, const double c[3]) {
  if (!g || !g->labels) return 0;
  for (int a = 0; a < 3; a++) {
    const double k = floor((c[a] - g->origin[a]) / g->voxel_size);
    if (!(k >= 0 && k < (double)g->dims[a])) return 0;
  }
  return 1;
}

size_t vlff_far_walk(const struct vlff_map_far *far, const struct vlff_map_grid *g, vlff_far_point_fn fn, void *ctx) {
  const uint32_t E = VLFF_MAP_FAR_EDGE;
  size_t n = 0;
  for (uint32_t j = 0; far && j < far->nblocks; j++) {
    const uint32_t end = j + 1 < far->nblocks ? far->blocks[j + 1].first_run : far->nruns;
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
  }
  return n;
}
