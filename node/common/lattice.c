/*
 * Grids that grow on a fixed lattice (lattice.h).
 */
#include "lattice.h"

#include <math.h>
#include <stdbool.h>
#include <stdlib.h>
#include <string.h>

int vlff_lattice_fit(const double origin[3], const double cell[3], const uint32_t dims[3], const long keep_lo[3],
                     const long keep_hi[3], const double lo[3], const double hi[3], double limit, int32_t shift[3],
                     uint32_t ndims[3]) {
  int differs = 0;
  for (int a = 0; a < 3; a++)
    if (!(isfinite(lo[a]) && isfinite(hi[a]) && lo[a] <= hi[a]) || !(cell[a] > 0)) return -1;
  for (int a = 0; a < 3; a++) {
    double l = fmax(lo[a], -limit), h = fmin(hi[a], limit);
    if (l > h) l = h = lo[a] < -limit ? -limit : limit; /* wholly beyond: its nearest edge */
    /* Cells from the old grid's first: the new range [k_lo, k_hi). */
    double kl = floor((l - origin[a]) / cell[a]), kh = ceil((h - origin[a]) / cell[a]);
    if (keep_lo[a] < keep_hi[a]) {
      if (kl > (double)keep_lo[a]) kl = (double)keep_lo[a];
      if (kh < (double)keep_hi[a]) kh = (double)keep_hi[a];
    }
    if (kh <= kl) kh = kl + 1; /* a point on a cell boundary: that cell */
    if (kh - kl > 2147483647.0 || fabs(kl) > 2147483647.0) return -1;
    shift[a] = (int32_t)-kl;
    ndims[a] = (uint32_t)(kh - kl);
    differs |= shift[a] != 0 || ndims[a] != dims[a];
  }
  return differs;
}

int vlff_lattice_window(const double origin[3], const double cell[3], const uint32_t dims[3], const double lo[3],
                        const double hi[3], double limit, size_t max_cells, int32_t shift[3], uint32_t ndims[3]) {
  long nlo[3], nhi[3], top = 0;
  for (int a = 0; a < 3; a++) {
    if (!(isfinite(lo[a]) && isfinite(hi[a]) && lo[a] <= hi[a]) || !(cell[a] > 0)) return -1;
    const double l = floor((fmax(lo[a], -limit) - origin[a]) / cell[a]);
    const double h = ceil((fmin(hi[a], limit) - origin[a]) / cell[a]);
    if (fabs(l) > 2147483647.0 || fabs(h) > 2147483647.0) return -1;
    nlo[a] = (long)l, nhi[a] = (long)h;
    if ((long)dims[a] > top) top = (long)dims[a];
  }
  /* The largest margin m (in cells, the same on every axis) whose grid fits:
   * the grid grows with m, so a bisection finds it. */
  long good = -1, bad = top + 1;
  int32_t sh[3];
  uint32_t nd[3];
  while (bad - good > 1) {
    const long m = good + (bad - good) / 2;
    long klo[3], khi[3];
    bool none = false;
    for (int a = 0; a < 3; a++) {
      klo[a] = nlo[a] - m > 0 ? nlo[a] - m : 0;
      khi[a] = nhi[a] + m < (long)dims[a] ? nhi[a] + m : (long)dims[a];
      none = none || klo[a] >= khi[a];
    }
    /* No old cell within m on some axis: none at all (fit keeps per axis). */
    for (int a = 0; none && a < 3; a++) klo[a] = khi[a] = 0;
    if (vlff_lattice_fit(origin, cell, dims, klo, khi, lo, hi, limit, sh, nd) >= 0 &&
        vlff_lattice_cells(nd) <= max_cells) {
      good = m;
      memcpy(shift, sh, sizeof sh), memcpy(ndims, nd, sizeof nd);
    } else {
      bad = m;
    }
  }
  return good >= 0 ? 1 : -1;
}

void vlff_box_union(const double alo[3], const double ahi[3], const double blo[3], const double bhi[3], double lo[3],
                    double hi[3]) {
  for (int a = 0; a < 3; a++) lo[a] = fmin(alo[a], blo[a]), hi[a] = fmax(ahi[a], bhi[a]);
}

int vlff_lattice_cover(const double origin[3], const double cell[3], const uint32_t dims[3], const double lo[3],
                       const double hi[3], double limit, int32_t shift[3], uint32_t ndims[3]) {
  const long keep_lo[3] = {0, 0, 0}, keep_hi[3] = {(long)dims[0], (long)dims[1], (long)dims[2]};
  return vlff_lattice_fit(origin, cell, dims, keep_lo, keep_hi, lo, hi, limit, shift, ndims);
}

void vlff_lattice_copy(void *dst, const uint32_t ndims[3], const void *src, const uint32_t dims[3],
                       const int32_t shift[3], size_t elem) {
  /* the old grid's x range that lands in the new grid */
  const long x0 = shift[0] < 0 ? -(long)shift[0] : 0;
  const long x1 = (long)ndims[0] - shift[0] < (long)dims[0] ? (long)ndims[0] - shift[0] : (long)dims[0];
  if (x1 <= x0) return;
  const size_t row = (size_t)(x1 - x0) * elem;
  for (uint32_t z = 0; z < dims[2]; z++) {
    const long nz = (long)z + shift[2];
    if (nz < 0 || nz >= (long)ndims[2]) continue;
    for (uint32_t y = 0; y < dims[1]; y++) {
      const long ny = (long)y + shift[1];
      if (ny < 0 || ny >= (long)ndims[1]) continue;
      size_t from = ((size_t)z * dims[1] + y) * dims[0] + (size_t)x0;
      size_t to = ((size_t)nz * ndims[1] + (size_t)ny) * ndims[0] + (size_t)(x0 + shift[0]);
      memcpy((char *)dst + to * elem, (const char *)src + from * elem, row);
    }
  }
}

void *vlff_lattice_regrid(const void *old, size_t elem, int fill, const uint32_t dims[3], const int32_t shift[3],
                          const uint32_t ndims[3]) {
  const size_t bytes = vlff_lattice_cells(ndims) * elem;
  void *a = malloc(bytes ? bytes : 1);
  if (!a) return NULL;
  memset(a, fill, bytes);
  if (old) vlff_lattice_copy(a, ndims, old, dims, shift, elem);
  return a;
}

int vlff_lattice_saved(const double origin0[3], double cell, const long k0[3], const uint32_t dims[3],
                       const double so[3], const uint32_t sd[3], int32_t shift[3]) {
  int same = 1;
  for (int a = 0; a < 3; a++) {
    double k = (so[a] - origin0[a]) / cell;
    long kr = lround(k);
    if (!(fabs(k - (double)kr) < 1e-6) || sd[a] < 1 || labs(k0[a] - kr) > 2147483647L) return 0; /* another lattice */
    shift[a] = (int32_t)(k0[a] - kr);
    same &= shift[a] == 0 && sd[a] == dims[a];
  }
  return !same;
}
