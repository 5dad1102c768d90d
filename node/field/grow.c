/*
 * The field's box and its growth (field.h "Growth").
 *
 * A growing field's occupancy cells keep their size and lie on one lattice,
 * anchored at the first box's low corner, for the field's whole life: a
 * growth adds cells around the old ones and copies every old cell to the
 * same place in the world, so what was learned where the robot has been is
 * untouched. The hash grid needs nothing: its frame is the whole world
 * (encoding.c), so a point's cells never move.
 */
#include <math.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "field_internal.h"
#include "lattice.h"
#include "mem.h"

#define MIB 1048576.0

/* How far (metres) the box's centre may move from the encoding's origin
 * before the origin follows it: a float resolves a position a few hundred
 * times finer than the finest cell there (the default first box's 2.4 mm
 * cells: 40 m from the origin is 2^14 of them, resolved to 2^-9). */
#define RECENTRE_M 16.0

void vlff_field_set_box(struct vlff_field *f) {
  bool far = false;
  double c[3];
  for (int a = 0; a < 3; a++) {
    if (f->cfg.field.grow) {
      double cell = f->occ.cell[a];
      f->box_lo[a] = f->first_lo[a] + f->occ_k0[a] * cell;
      f->box_hi[a] = f->box_lo[a] + f->occ.dims[a] * cell;
    } else {
      f->box_lo[a] = f->cfg.field.scene_min[a];
      f->box_hi[a] = f->cfg.field.scene_max[a];
    }
    f->occ.box_min[a] = (float)f->box_lo[a];
    c[a] = 0.5 * (f->box_lo[a] + f->box_hi[a]);
    far = far || fabs(c[a] - f->enc.box_min[a]) > RECENTRE_M;
  }
  /* A box that went far from where the encoding counts positions from
   * takes the origin with it: the cells are the world's whatever the
   * origin (field_internal.h), only the float rounding is nearer. */
  if (f->cfg.field.grow && far) vlff_encoding_set_origin(&f->enc, c);
  vlff_encoding_set_inside(&f->enc, f->box_lo, f->box_hi);
}

void vlff_field_first_cells(const struct vlff_cfg_field *c, const struct vlff_cfg_train *t, float cell[3],
                            int dims[3]) {
  const int res = t->occupancy_resolution;
  /* A growing field's cells are a size in metres for its whole life: cubes
   * of train.occupancy_cell_m, the first box only saying where they start;
   * or, when that is 0, the first box's own cells (each side over the
   * resolution), so that a growing field given a scene's box samples and
   * trusts as the fixed box did. */
  for (int a = 0; a < 3; a++) {
    double ext = c->scene_max[a] - c->scene_min[a];
    if (c->grow) {
      if (t->occupancy_cell_m > 0) {
        cell[a] = (float)t->occupancy_cell_m;
        /* the first box rounded out to whole cells */
        dims[a] = (int)ceil(ext / cell[a] - 1e-6);
        if (dims[a] < 1) dims[a] = 1;
      } else {
        /* the box's own, counted as the box counts them: a float cell's
         * rounding must not add one */
        cell[a] = (float)(ext / res);
        dims[a] = res;
      }
    } else {
      cell[a] = (float)(ext / res);
      dims[a] = res;
    }
  }
}

void vlff_field_first_layout(struct vlff_field *f, int k0[3], int dims[3]) {
  vlff_field_first_cells(&f->cfg.field, &f->cfg.train, f->occ.cell, dims);
  for (int a = 0; a < 3; a++) f->first_lo[a] = f->cfg.field.scene_min[a], k0[a] = 0;
  /* Occupied when a cell-long interval would stop >= 1 % of the light. */
  float cmin = fminf(f->occ.cell[0], fminf(f->occ.cell[1], f->occ.cell[2]));
  f->occ.threshold = 0.01005f / cmin;
}

int vlff_field_occ_layout(struct vlff_field *f, const int k0[3], const int dims[3], int copy) {
  const uint32_t nd[3] = {(uint32_t)dims[0], (uint32_t)dims[1], (uint32_t)dims[2]};
  const size_t n = vlff_lattice_cells(nd);
  /* the old grid, when copied, lies inside the new one */
  const uint32_t od[3] = {(uint32_t)f->occ.dims[0], (uint32_t)f->occ.dims[1], (uint32_t)f->occ.dims[2]};
  const int32_t sh[3] = {f->occ_k0[0] - k0[0], f->occ_k0[1] - k0[1], f->occ_k0[2] - k0[2]};
  /* New cells: nothing learned, every one a candidate for samples (as a new
   * field's), no loss measured yet (-1, which no byte fill gives). */
  float *dens = vlff_lattice_regrid(copy ? f->occ.density : NULL, sizeof *dens, 0, od, sh, nd);
  uint8_t *occ = vlff_lattice_regrid(copy ? f->occ.occ : NULL, 1, 1, od, sh, nd);
  uint16_t *expo = vlff_lattice_regrid(copy ? f->exposure : NULL, sizeof *expo, 0, od, sh, nd);
  float *cerr = malloc(n * sizeof *cerr);
  if (!dens || !cerr || !occ || !expo) {
    VLFF_FREE_ALL(dens, cerr, occ, expo);
    return -1;
  }
  for (size_t i = 0; i < n; i++) cerr[i] = -1;
  if (copy) vlff_lattice_copy(cerr, nd, f->cell_err, od, sh, sizeof *cerr);
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
long long vlff_field_slides(const struct vlff_field *f) { return f->slides; }

static int grow_or_slide(struct vlff_field *f, const double lo[3], const double hi[3], bool slide, char *err,
                         size_t errlen) {
  const struct vlff_cfg_field *c = &f->cfg.field;
  const uint32_t od[3] = {(uint32_t)f->occ.dims[0], (uint32_t)f->occ.dims[1], (uint32_t)f->occ.dims[2]};
  int32_t sh[3];
  uint32_t nd[3];
  const double cell[3] = {f->occ.cell[0], f->occ.cell[1], f->occ.cell[2]};
  int rc = vlff_lattice_cover(f->box_lo, cell, od, lo, hi, c->grow ? c->world_limit_m : INFINITY, sh, nd);
  if (rc < 0) {
    if (err && errlen) snprintf(err, errlen, "field: growth to an empty or non-finite box");
    return -1;
  }
  int in = 1;
  for (int a = 0; a < 3; a++) in &= lo[a] >= f->box_lo[a] && hi[a] <= f->box_hi[a];
  if (in || (c->grow && rc == 0)) return 0; /* held, or beyond the world's limit: nothing to add */
  if (!c->grow) {
    if (err && errlen) snprintf(err, errlen, "field: the box is fixed (field.grow is off)");
    return -1;
  }
  double need = vlff_occ_bytes((double)vlff_lattice_cells(nd));
  int grown = 1;
  /* Past train.occupancy_max_mb the box slides with the robot instead: the
   * cells it leaves are dropped, and come back, as a growth's new cells do,
   * occupied with nothing fitted (the hash grid is the world's: what was
   * learned there is still in it). */
  const size_t max_cells = (size_t)(f->cfg.train.occupancy_max_mb * 1048576.0 / vlff_occ_bytes(1));
  if (slide && !vlff_occ_fits(&f->cfg.train, (double)vlff_lattice_cells(nd)) &&
      vlff_lattice_window(f->box_lo, cell, od, lo, hi, c->world_limit_m, max_cells, sh, nd) > 0)
    grown = 2, need = vlff_occ_bytes((double)vlff_lattice_cells(nd));
  if (!vlff_occ_fits(&f->cfg.train, (double)vlff_lattice_cells(nd))) {
    if (err && errlen)
      snprintf(err, errlen,
               "field: growing the box to %.1f x %.1f x %.1f m needs %.0f MiB of occupancy cells, more than "
               "train.occupancy_max_mb (%g)",
               nd[0] * (double)f->occ.cell[0], nd[1] * (double)f->occ.cell[1], nd[2] * (double)f->occ.cell[2],
               need / MIB, f->cfg.train.occupancy_max_mb);
    return -1;
  }
  const int k0[3] = {f->occ_k0[0] - sh[0], f->occ_k0[1] - sh[1], f->occ_k0[2] - sh[2]};
  const int dims[3] = {(int)nd[0], (int)nd[1], (int)nd[2]};
  if (vlff_field_occ_layout(f, k0, dims, 1)) {
    if (err && errlen) snprintf(err, errlen, "field: out of memory growing the box (%.0f MiB)", need / MIB);
    return -1;
  }
  f->grown++;
  f->slides += grown == 2;
  return grown;
}

int vlff_field_grow(struct vlff_field *f, const double lo[3], const double hi[3], char *err, size_t errlen) {
  return grow_or_slide(f, lo, hi, false, err, errlen);
}

int vlff_field_slide(struct vlff_field *f, const double lo[3], const double hi[3], char *err, size_t errlen) {
  return grow_or_slide(f, lo, hi, true, err, errlen);
}
