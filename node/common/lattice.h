/*
 * vlff_lattice: dense grids that grow on a fixed lattice.
 *
 * A grid is dims cells of cell[a] metres on axis a from origin (x fastest,
 * then y, z; cubic for the map's and the evidence's voxels, the box's own
 * cells for the field's occupancy). A
 * larger grid on the same lattice holds the old one shifted by whole cells,
 * so each cell keeps its place in the world: what the field's occupancy, the
 * evidence and the published map learned stays where it was when their
 * box grows (docs/field.md "Growth").
 *
 * When a grid reaches its cap, it may instead be refitted to what it holds:
 * the new grid on the same lattice holds the cells that hold something and
 * the box asked for, and the old grid's empty cells beyond it are dropped
 * (vlff_lattice_fit). Nothing held moves then either.
 *
 * Contract (shift: the old grid's first cell counted in the new grid, per
 * axis; negative where the new grid starts inside the old one)
 *  - vlff_lattice_cover: the smallest grid on the lattice holding the old
 *    grid and [lo, hi], with [lo, hi] clipped to +-limit first: shift (>= 0)
 *    and ndims. 1 when it is larger than the old, 0 when the old holds it
 *    (shift 0, ndims = dims), -1 for a box that is empty or not finite, or a
 *    grid past 2^31 cells on an axis.
 *  - vlff_lattice_fit: as cover, but holding only the old grid's cells
 *    [keep_lo, keep_hi) (per axis, in old cells; keep_lo >= keep_hi on an
 *    axis: none) besides [lo, hi]: 1 when it differs from the old grid, 0
 *    when it is the old grid, -1 as cover.
 *  - vlff_lattice_window: a capped grid that must move on (the robot walked
 *    beyond what max_cells holds around what it saw): the grid on the
 *    lattice holding [lo, hi] (clipped to +-limit) and the old grid's cells
 *    within m cells of it, for the largest m (the same on every axis) that
 *    keeps it within max_cells: 1 and shift, ndims; -1 when [lo, hi] alone
 *    passes max_cells, or as fit. The old cells beyond it are the caller's
 *    to keep elsewhere (the map's far blocks) or to drop.
 *  - vlff_box_union: the smallest box holding boxes a and b (a NaN side
 *    of one gives the other's).
 *  - vlff_lattice_xyz: a cell index's x, y, z.
 *  - vlff_lattice_extend: widens [lo, hi) (old cells) to hold cell i.
 *  - vlff_lattice_copy: each of the old grid's cells (elem bytes) that lies
 *    in the new grid to its place there; the new grid's other cells are left
 *    as they are.
 *  - vlff_lattice_regrid: a new grid's array of elem-byte cells, every byte
 *    fill, with the old grid's cells (old NULL: none) copied to their
 *    places; NULL when out of memory.
 *  - vlff_lattice_index: an old cell index's index in the new grid, -1 when
 *    the cell lies beyond it.
 *  - vlff_lattice_saved: whether a saved grid (origin so, sd cells) lies on
 *    the lattice of a grid k0 cells from origin0 (k0 <= 0 after growths) and
 *    differs from it: 1 and the shift, else 0 (another lattice, or the same
 *    grid). What a grown or refitted grid's file is to a grid that starts
 *    again in the first box; the caller checks that nothing it holds lies
 *    beyond the saved grid.
 */
#ifndef VLFF_LATTICE_H
#define VLFF_LATTICE_H

#include <stddef.h>
#include <stdint.h>

void vlff_box_union(const double alo[3], const double ahi[3], const double blo[3], const double bhi[3], double lo[3],
                    double hi[3]);
int vlff_lattice_cover(const double origin[3], const double cell[3], const uint32_t dims[3], const double lo[3],
                       const double hi[3], double limit, int32_t shift[3], uint32_t ndims[3]);
int vlff_lattice_fit(const double origin[3], const double cell[3], const uint32_t dims[3], const long keep_lo[3],
                     const long keep_hi[3], const double lo[3], const double hi[3], double limit, int32_t shift[3],
                     uint32_t ndims[3]);
int vlff_lattice_window(const double origin[3], const double cell[3], const uint32_t dims[3], const double lo[3],
                        const double hi[3], double limit, size_t max_cells, int32_t shift[3], uint32_t ndims[3]);
/* A cubic lattice's cell (voxels) as the per-axis sizes the functions take. */
#define VLFF_LATTICE_CUBE(v) ((const double[3]){(v), (v), (v)})
/* Cell index i of a dims grid as its x, y, z. */
static inline void vlff_lattice_xyz(size_t i, const uint32_t dims[3], long c[3]) {
  c[0] = (long)(i % dims[0]), c[1] = (long)(i / dims[0] % dims[1]), c[2] = (long)(i / ((size_t)dims[0] * dims[1]));
}
static inline void vlff_lattice_extend(long lo[3], long hi[3], size_t i, const uint32_t dims[3]) {
  long c[3];
  vlff_lattice_xyz(i, dims, c);
  for (int a = 0; a < 3; a++) {
    if (c[a] < lo[a]) lo[a] = c[a];
    if (c[a] + 1 > hi[a]) hi[a] = c[a] + 1;
  }
}
void vlff_lattice_copy(void *dst, const uint32_t ndims[3], const void *src, const uint32_t dims[3],
                       const int32_t shift[3], size_t elem);
void *vlff_lattice_regrid(const void *old, size_t elem, int fill, const uint32_t dims[3], const int32_t shift[3],
                          const uint32_t ndims[3]);
static inline long vlff_lattice_index(size_t i, const uint32_t dims[3], const int32_t shift[3],
                                      const uint32_t ndims[3]) {
  long c[3];
  vlff_lattice_xyz(i, dims, c);
  const long x = c[0] + shift[0], y = c[1] + shift[1], z = c[2] + shift[2];
  if (x < 0 || y < 0 || z < 0 || x >= (long)ndims[0] || y >= (long)ndims[1] || z >= (long)ndims[2]) return -1;
  return x + (long)ndims[0] * (y + (long)ndims[1] * z);
}
static inline size_t vlff_lattice_cells(const uint32_t dims[3]) { return (size_t)dims[0] * dims[1] * dims[2]; }
int vlff_lattice_saved(const double origin0[3], double cell, const long k0[3], const uint32_t dims[3],
                       const double so[3], const uint32_t sd[3], int32_t shift[3]);

#endif
