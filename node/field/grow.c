/*
 * The field's box and its growth (field.h "Growth").
 *
 * A growing field's occupancy cells are cubic and lie on one lattice,
 * anchored at the first box's low corner, for the field's whole life: a
 * growth adds cells around the old ones and copies every old cell to the
 * same place in the world, so what was learned where the robot has been is
 * untouched. The hash grid needs nothing: its frame is the whole world
 * (encoding.c), so a point's cells never move.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "field_internal.h"
#include "mem.h"

#define MIB 1048576.0

void vlff_field_set_box(struct vlff_field *f) {
  for (int a = 0; a < 3; a++) {
    if (f->cfg.field.grow) {
      double c = f->occ.cell[a];
      f->box_lo[a] = f->first_lo[a] + f->occ_k0[a] * c;
      f->box_hi[a] = f->box_lo[a] + f->occ.dims[a] * c;
    } else {
      f->box_lo[a] = f->cfg.field.scene_min[a];
      f->box_hi[a] = f->cfg.field.scene_max[a];
    }
    f->occ.box_min[a] = (float)f->box_lo[a];
  }
  vlff_encoding_set_inside(&f->enc, f->box_lo, f->box_hi);
}

void vlff_field_first_layout(struct vlff_field *f, int k0[3], int dims[3]) {
  const struct vlff_cfg_field *c = &f->cfg.field;
  const int res = f->cfg.train.occupancy_resolution;
  double longest = 0;
  for (int a = 0; a < 3; a++) longest = fmax(longest, c->scene_max[a] - c->scene_min[a]);
  for (int a = 0; a < 3; a++) {
    double ext = c->scene_max[a] - c->scene_min[a];
    f->first_lo[a] = c->scene_min[a];
    k0[a] = 0;
    if (c->grow) {
      f->occ.cell[a] = (float)(longest / res);
      /* the first box rounded out to whole cells (the longest side is exact) */
      dims[a] = (int)ceil(ext / f->occ.cell[a] - 1e-6);
      if (dims[a] < 1) dims[a] = 1;
    } else {
      f->occ.cell[a] = (float)(ext / res);
      dims[a] = res;
    }
  }
  /* Occupied when a cell-long interval would stop >= 1 % of the light. */
  float cmin = fminf(f->occ.cell[0], fminf(f->occ.cell[1], f->occ.cell[2]));
  f->occ.threshold = 0.01005f / cmin;
}

int vlff_field_occ_layout(struct vlff_field *f, const int k0[3], const int dims[3]) {
  const size_t n = (size_t)dims[0] * dims[1] * dims[2];
  float *dens = malloc(n * sizeof *dens), *cerr = malloc(n * sizeof *cerr);
  uint8_t *occ = malloc(n);
  uint16_t *expo = malloc(n * sizeof *expo);
  if (!dens || !cerr || !occ || !expo) {
    VLFF_FREE_ALL(dens, cerr, occ, expo);
    return -1;
  }
  /* New cells: nothing learned, every one a candidate for samples (as a new
   * field's), no loss measured yet. */
  memset(dens, 0, n * sizeof *dens);
  memset(occ, 1, n);
  memset(expo, 0, n * sizeof *expo);
  for (size_t i = 0; i < n; i++) cerr[i] = -1;
  const struct vlff_occupancy *g = &f->occ;
  if (g->density) {
    /* The old cells that lie in the new grid, row by row (x is contiguous). */
    int o[3], lo[3], hi[3];
    for (int a = 0; a < 3; a++) {
      o[a] = f->occ_k0[a] - k0[a];
      lo[a] = o[a] < 0 ? -o[a] : 0;
      hi[a] = g->dims[a] < dims[a] - o[a] ? g->dims[a] : dims[a] - o[a];
    }
    if (lo[0] < hi[0])
      for (int z = lo[2]; z < hi[2]; z++)
        for (int y = lo[1]; y < hi[1]; y++) {
          size_t from = ((size_t)z * g->dims[1] + y) * g->dims[0] + lo[0];
          size_t to = ((size_t)(z + o[2]) * dims[1] + (y + o[1])) * dims[0] + lo[0] + o[0];
          size_t len = (size_t)(hi[0] - lo[0]);
          memcpy(dens + to, g->density + from, len * sizeof *dens);
          memcpy(occ + to, g->occ + from, len);
          memcpy(expo + to, f->exposure + from, len * sizeof *expo);
          memcpy(cerr + to, f->cell_err + from, len * sizeof *cerr);
        }
  }
  VLFF_FREE_ALL(f->occ.density, f->occ.occ, f->exposure, f->cell_err);
  f->occ.density = dens;
  f->occ.occ = occ;
  f->exposure = expo;
  f->cell_err = cerr;
  for (int a = 0; a < 3; a++) f->occ_k0[a] = k0[a], f->occ.dims[a] = dims[a];
  /* The sweep starts over: its cursor counted cells of the old grid. */
  f->occ_cursor = 0;
  vlff_field_set_box(f);
  return 0;
}

void vlff_field_box(const struct vlff_field *f, double lo[3], double hi[3]) {
  for (int a = 0; a < 3; a++) lo[a] = f->box_lo[a], hi[a] = f->box_hi[a];
}

long long vlff_field_growths(const struct vlff_field *f) { return f->grown; }

int vlff_field_grow(struct vlff_field *f, const double lo[3], const double hi[3], char *err, size_t errlen) {
  const struct vlff_cfg_field *c = &f->cfg.field;
  int in = 1;
  for (int a = 0; a < 3; a++) {
    if (!(isfinite(lo[a]) && isfinite(hi[a]) && lo[a] <= hi[a])) {
      if (err && errlen) snprintf(err, errlen, "field: growth to an empty or non-finite box (axis %d)", a);
      return -1;
    }
    in &= lo[a] >= f->box_lo[a] && hi[a] <= f->box_hi[a];
  }
  if (in) return 0;
  if (!c->grow) {
    if (err && errlen) snprintf(err, errlen, "field: the box is fixed (field.grow is off)");
    return -1;
  }
  /* Within the world (field.world_limit_m), in whole cells of the lattice. */
  int k0[3], dims[3];
  const double w = c->world_limit_m;
  for (int a = 0; a < 3; a++) {
    double cell = f->occ.cell[a];
    double l = fmax(lo[a], -w), h = fmin(hi[a], w);
    if (l > h) l = h = lo[a] < -w ? -w : w;
    long kl = (long)floor((l - f->first_lo[a]) / cell), kh = (long)ceil((h - f->first_lo[a]) / cell);
    long k_lo = kl < f->occ_k0[a] ? kl : f->occ_k0[a];
    long k_hi = kh > (long)f->occ_k0[a] + f->occ.dims[a] ? kh : (long)f->occ_k0[a] + f->occ.dims[a];
    k0[a] = (int)k_lo;
    dims[a] = (int)(k_hi - k_lo);
  }
  const double need = (double)dims[0] * dims[1] * dims[2] * (double)vlff_occ_cell_bytes();
  const double cap = f->cfg.train.occupancy_max_mb * MIB;
  if (need > cap) {
    if (err && errlen)
      snprintf(err, errlen,
               "field: growing the box to %.1f x %.1f x %.1f m needs %.0f MiB of occupancy cells, more than "
               "train.occupancy_max_mb (%g)",
               dims[0] * (double)f->occ.cell[0], dims[1] * (double)f->occ.cell[1], dims[2] * (double)f->occ.cell[2],
               need / MIB, f->cfg.train.occupancy_max_mb);
    return -1;
  }
  int same = 1;
  for (int a = 0; a < 3; a++) same &= k0[a] == f->occ_k0[a] && dims[a] == f->occ.dims[a];
  if (same) return 0; /* beyond the world's limit: nothing more to add */
  if (vlff_field_occ_layout(f, k0, dims)) {
    if (err && errlen) snprintf(err, errlen, "field: out of memory growing the box (%.0f MiB)", need / MIB);
    return -1;
  }
  f->grown++;
  return 1;
}
