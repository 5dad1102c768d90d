/*
 * vlff_far_pick / vlff_far_emit: the far map's labelled voxels as points,
 * for readers that send the whole map as a point cloud (the viewer's
 * /map/points, the DDS bridge's map).
 *
 * Why: a robot that walked beyond what the map's grid holds has its map in
 * two parts, the grid (the window around it) and the far map beside it
 * (vlff/shm.h "The far map"). A whole map sent as points is both: what the
 * window shows, and what it left. Where the grid covers a voxel the grid
 * answers (a far block the window has come back over is stale there), so
 * those far voxels are not points of their own. And a far map can hold far
 * more than a cloud should carry (the default shm.map_far_max_mb holds tens
 * of millions of labelled voxels, gigabytes as points), so the points are
 * bounded (the viewer and the DDS bridge: as many as the segment's grid
 * holds voxels, a whole map at most twice a full grid), and the work with
 * them: a block beside the grid is counted from its runs, not voxel by
 * voxel.
 *
 * Contract: far was checked (vlff_map_snapshot_far); g is the grid of the
 * same map version (NULL or without labels: every far voxel counts).
 *  - vlff_far_pick chooses the points: each far voxel whose label is a class
 *    (a prompt index, <= VLFF_LABEL_MAX) and that g does not cover (of a
 *    far map whose voxels are not the grid's size, the blocks across the
 *    grid's boundary are left out whole: reading them voxel by voxel could
 *    take any time). At most max_points of them: past it, whole blocks, the nearest to the grid's
 *    centre first, while they fit; pick->left counts those left out, for
 *    the caller to say. 0, or -1 out of memory (nothing picked; left: all).
 *  - vlff_far_emit gives exactly pick->points of them: fn(ctx, centre,
 *    label, conf) in block order (the nearest first when cut), then the
 *    voxels' order within a block (x fastest). Returns the count.
 *  - vlff_far_pick_free: the pick's memory (a zeroed pick too).
 */
#ifndef VLFF_FAR_WALK_H
#define VLFF_FAR_WALK_H
#include <stddef.h>
#include <stdint.h>

#include "vlff/shm.h"

struct vlff_far_pick {
  size_t points, left;
  uint32_t *order; /* the blocks to emit; NULL: every block, in its order */
  uint32_t norder;
};

typedef void (*vlff_far_point_fn)(void *ctx, const double centre[3], uint16_t label, uint8_t conf);
int vlff_far_pick(const struct vlff_map_far *far, const struct vlff_map_grid *g, size_t max_points,
                  struct vlff_far_pick *pick);
size_t vlff_far_emit(const struct vlff_map_far *far, const struct vlff_map_grid *g, const struct vlff_far_pick *pick,
                     vlff_far_point_fn fn, void *ctx);
void vlff_far_pick_free(struct vlff_far_pick *pick);

#endif
