/*
 * Grids that grow on a fixed lattice (lattice.h).
 */
#include "lattice.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

int vlff_lattice_cover(const double origin[3], double cell, const uint32_t dims[3], const double lo[3],
                       const double hi[3], double limit, uint32_t shift[3], uint32_t ndims[3]) {
  int larger = 0;
  for (int a = 0; a < 3; a++)
    if (!(isfinite(lo[a]) && isfinite(hi[a]) && lo[a] <= hi[a]) || !(cell > 0)) return -1;
  for (int a = 0; a < 3; a++) {
    double l = fmax(lo[a], -limit), h = fmin(hi[a], limit);
    if (l > h) l = h = lo[a] < -limit ? -limit : limit; /* wholly beyond: its nearest edge */
    /* Cells from the old grid's first: the new range [k_lo, k_hi). */
    double kl = floor((l - origin[a]) / cell), kh = ceil((h - origin[a]) / cell);
    if (kl > 0) kl = 0;
    if (kh < dims[a]) kh = dims[a];
    if (kh - kl > 2147483647.0) return -1;
    shift[a] = (uint32_t)-kl;
    ndims[a] = (uint32_t)(kh - kl);
    larger |= ndims[a] != dims[a];
  }
  return larger;
}

int vlff_lattice_saved(const double origin0[3], double cell, const long k0[3], const uint32_t dims[3],
                       const double so[3], const uint32_t sd[3], uint32_t shift[3]) {
  int same = 1;
  for (int a = 0; a < 3; a++) {
    double k = (so[a] - origin0[a]) / cell;
    long kr = lround(k);
    if (!(fabs(k - (double)kr) < 1e-6) || kr > k0[a]) return 0;  /* another lattice, or starts inside */
    if ((double)(k0[a] - kr) + dims[a] > (double)sd[a]) return 0; /* does not hold the grid */
    shift[a] = (uint32_t)(k0[a] - kr);
    same &= shift[a] == 0 && sd[a] == dims[a];
  }
  return !same;
}

void vlff_lattice_copy(void *dst, const uint32_t ndims[3], const void *src, const uint32_t dims[3],
                       const uint32_t shift[3], size_t elem) {
  const size_t row = (size_t)dims[0] * elem;
  for (uint32_t z = 0; z < dims[2]; z++)
    for (uint32_t y = 0; y < dims[1]; y++) {
      size_t from = ((size_t)z * dims[1] + y) * dims[0];
      size_t to = ((size_t)(z + shift[2]) * ndims[1] + (y + shift[1])) * ndims[0] + shift[0];
      memcpy((char *)dst + to * elem, (const char *)src + from * elem, row);
    }
}

void *vlff_lattice_regrid(const void *old, size_t elem, int fill, const uint32_t dims[3], const uint32_t shift[3],
                          const uint32_t ndims[3]) {
  const size_t bytes = vlff_lattice_cells(ndims) * elem;
  void *a = malloc(bytes ? bytes : 1);
  if (!a) return NULL;
  memset(a, fill, bytes);
  if (old) vlff_lattice_copy(a, ndims, old, dims, shift, elem);
  return a;
}
