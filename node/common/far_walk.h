/*
 * vlff_far_walk: the far map's labelled voxels as points, for readers that
 * send the whole map as a point cloud (the viewer's /map/points, the DDS
 * bridge's map).
 *
 * Why: a robot that walked beyond what the map's grid holds has its map in
 * two parts, the grid (the window around it) and the far map beside it
 * (vlff/shm.h "The far map"). A whole map sent as points is both: what the
 * window shows, and what it left. Where the grid covers a voxel the grid
 * answers (a far block the window has come back over is stale there), so
 * those far voxels are not points of their own.
 *
 * Contract: far was checked (vlff_map_snapshot_far); g is the grid of the
 * same map version (NULL: no grid, every far voxel counts). fn(ctx, centre,
 * label, conf) for each far voxel whose label is a class (a prompt index,
 * <= VLFF_LABEL_MAX) and that g does not cover, in block order, then the
 * voxels' order within a block; fn NULL only counts. Returns the count.
 * At most max_points: a far map of more (the default shm.map_far_max_mb
 * holds tens of millions of labelled voxels, gigabytes as points) gives
 * whole blocks, the nearest to the grid's centre first, while they fit,
 * and *left_out (may be NULL) the points it left out, for the caller to
 * say. The same arguments always give the same points.
 */
#ifndef VLFF_FAR_WALK_H
#define VLFF_FAR_WALK_H
#include <stddef.h>
#include <stdint.h>

#include "vlff/shm.h"

/* The bound the viewer and the DDS bridge give: the default
 * shm.map_max_voxels, 40 MB of their 20-byte points, as many as a full grid. */
#define VLFF_FAR_POINTS_MAX ((size_t)2 << 20)

typedef void (*vlff_far_point_fn)(void *ctx, const double centre[3], uint16_t label, uint8_t conf);
size_t vlff_far_walk(const struct vlff_map_far *far, const struct vlff_map_grid *g, size_t max_points,
                     vlff_far_point_fn fn, void *ctx, size_t *left_out);

#endif
