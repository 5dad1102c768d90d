/*
 * The far map: what the published map's window (publish.h) left behind as
 * the robot went on, kept compacted and published beside the window in the
 * map segment (vlff/shm.h "The far map"; docs/field.md "Beyond the caps").
 *
 * Why: the map's grid, the evidence and the field's occupancy are dense
 * grids over a box, each capped by configuration. A robot that walks on
 * past what the caps hold would otherwise stop being mapped there. So at a
 * cap the window slides with the robot (vlff_lattice_window), and the
 * voxels it leaves are kept here as the map segment's far blocks: 16^3
 * voxels on the map's lattice, run-length coded (a block of wall, floor and
 * free space takes a few hundred bytes, where the window takes 12 KiB).
 * When the window comes back over them, they are restored into it
 * (vlff_far_restore), so a room the robot returns to starts from what was
 * published there, not from nothing.
 *
 * The lattice: voxel k (integer, on each axis) of the map's lattice covers
 * origin + [k, k + 1) x voxel; block key floor(k / 16). The window's voxel
 * (i, j, l) is lattice voxel k0 + (i, j, l).
 *
 * Memory: at most max_bytes of runs and block records; past it the blocks
 * farthest from the robot are dropped (vlff_far_dropped counts them, the
 * caller logs it): they then read UNKNOWN.
 *
 * Contract: one owner thread (the publisher's). Functions returning int
 * give 0, or -1 (out of memory: the far map as it was).
 */
#ifndef VLFF_FAR_H
#define VLFF_FAR_H

#include <stddef.h>
#include <stdint.h>

#include "vlff/shm.h"

struct vlff_far;

struct vlff_far *vlff_far_create(const double origin[3], double voxel, size_t max_bytes);
void vlff_far_destroy(struct vlff_far *f);
void vlff_far_reset(struct vlff_far *f);

/* The window of dims voxels from lattice voxel k0 moves by sh into nd
 * (lattice.h's shift): each of its voxels that leaves it goes to its block
 * (labels/conf: the window's values), in every block that holds one of them
 * that is not VLFF_LABEL_UNKNOWN or that existed already. What it stores
 * are copies: a slide that then fails leaves the window holding them too,
 * and the grid answers before the far map. */
int vlff_far_store(struct vlff_far *f, const uint32_t dims[3], const long k0[3], const int32_t sh[3],
                   const uint32_t nd[3], const uint16_t *labels, const uint8_t *conf);
/* Blocks beyond max_bytes dropped, the farthest from the centre of the
 * window of dims voxels from lattice voxel k0 first (counted). */
void vlff_far_trim(struct vlff_far *f, const long k0[3], const uint32_t dims[3]);
/* The prompts the far map's labels index: the first call says them; a
 * later list that differs remaps every stored label to its text's index in
 * the new list, or to UNKNOWN where the new list lacks it (a label's
 * meaning is its text, not its number). 1 when a label changed, else 0. */
int vlff_far_prompts(struct vlff_far *f, const char *const *prompts, int k);
/* The voxels of the new window (nd from lattice voxel nk0) that were not in
 * the old one (dims, at shift sh in the new) and that a far block holds as
 * something else than UNKNOWN: fn(ctx, index in the new window, label,
 * confidence) for each. */
void vlff_far_restore(const struct vlff_far *f, const uint32_t dims[3], const int32_t sh[3], const uint32_t nd[3],
                      const long nk0[3], void (*fn)(void *ctx, size_t i, uint16_t label, uint8_t conf), void *ctx);
/* The far map as the segment takes it (pointers valid until the next
 * store, reset, export, save or release): 0, or -1 when out of memory. */
int vlff_far_export(struct vlff_far *f, struct vlff_map_far *out);
/* The last export's arrays freed (its pointers then invalid): the segment
 * stages a copy of its own (vlff_map_set_far), and a far map kept whole
 * twice in the node's memory would double what shm.map_far_max_mb bounds. */
void vlff_far_export_release(struct vlff_far *f);
/* Checkpoints: the far map and the prompts its labels index to path,
 * written atomically (none: path removed), and read back: 0, 1 when there is no file, -1 with err for a
 * file that is not a far map of this lattice (truncated, corrupt, a
 * checksum that fails, a block that breaks the segment's contract,
 * vlff_map_far_check), the far map then as it was. A file of more than
 * max_bytes is refused. */
int vlff_far_save(struct vlff_far *f, const char *path, char *err, size_t errlen);
int vlff_far_load(struct vlff_far *f, const char *path, char *err, size_t errlen);
/* Blocks held, bytes they take (vlff_map_far_bytes), blocks dropped for the
 * budget since the start or the last reset. */
size_t vlff_far_blocks(const struct vlff_far *f);
size_t vlff_far_bytes(const struct vlff_far *f);
long long vlff_far_dropped(const struct vlff_far *f);
/* Changes whenever what vlff_far_save would write may have changed (a
 * store, a drop, a reset, a load, the prompts): a checkpoint rewrites the
 * file only then (learned state is written only when it changed). */
uint64_t vlff_far_generation(const struct vlff_far *f);

#endif
