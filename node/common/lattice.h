/*
 * vlff_lattice: dense grids that grow on a fixed lattice.
 *
 * A grid is dims cells of edge cell from origin (x fastest, then y, z). A
 * larger grid on the same lattice holds the old one shifted by whole cells,
 * so each cell keeps its place in the world: what the field's occupancy, the
 * evidence and the published map learned stays where it was when their
 * box grows (docs/field.md "Growth").
 *
 * Contract
 *  - vlff_lattice_cover: the smallest grid on the lattice holding the old
 *    grid and [lo, hi], with [lo, hi] clipped to +-limit first: shift (the
 *    old grid's first cell, counted in the new grid) and ndims. 1 when it is
 *    larger than the old, 0 when the old holds it (shift 0, ndims = dims),
 *    -1 for a box that is empty or not finite, or a grid past 2^31 cells on
 *    an axis.
 *  - vlff_lattice_copy: each of the old grid's cells (elem bytes) to its
 *    place in the new grid; the new grid's other cells are left as they are.
 *  - vlff_lattice_regrid: a new grid's array of elem-byte cells, every byte
 *    fill, with the old grid's cells (old NULL: none) copied to their
 *    places; NULL when out of memory.
 *  - vlff_lattice_index: an old cell index's index in the new grid.
 *  - vlff_lattice_saved: whether a saved grid (origin so, sd cells) lies on
 *    the lattice of a grid k0 cells from origin0 (k0 <= 0 after growths) and
 *    holds it, larger: 1 and the shift, else 0 (another lattice, a grid that
 *    does not hold it, or the same grid). What a grown grid's file is to a
 *    grid that starts again in the first box.
 */
#ifndef VLFF_LATTICE_H
#define VLFF_LATTICE_H

#include <stddef.h>
#include <stdint.h>

int vlff_lattice_cover(const double origin[3], double cell, const uint32_t dims[3], const double lo[3],
                       const double hi[3], double limit, uint32_t shift[3], uint32_t ndims[3]);
void vlff_lattice_copy(void *dst, const uint32_t ndims[3], const void *src, const uint32_t dims[3],
                       const uint32_t shift[3], size_t elem);
void *vlff_lattice_regrid(const void *old, size_t elem, int fill, const uint32_t dims[3], const uint32_t shift[3],
                          const uint32_t ndims[3]);
static inline size_t vlff_lattice_index(size_t i, const uint32_t dims[3], const uint32_t shift[3],
                                        const uint32_t ndims[3]) {
  size_t x = i % dims[0], y = i / dims[0] % dims[1], z = i / ((size_t)dims[0] * dims[1]);
  return (x + shift[0]) + (size_t)ndims[0] * ((y + shift[1]) + (size_t)ndims[1] * (z + shift[2]));
}
static inline size_t vlff_lattice_cells(const uint32_t dims[3]) { return (size_t)dims[0] * dims[1] * dims[2]; }
int vlff_lattice_saved(const double origin0[3], double cell, const long k0[3], const uint32_t dims[3],
                       const double so[3], const uint32_t sd[3], uint32_t shift[3]);

#endif
