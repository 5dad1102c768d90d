/* vlff_lattice: grids that grow on a fixed lattice keep every cell in its
 * place in the world. */
#include <limits.h>
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "lattice.h"

static void test_cover(void **state) {
  (void)state;
  const double origin[3] = {-1, -1, 0}, cell[3] = {0.5, 0.5, 0.5};
  const uint32_t dims[3] = {4, 4, 2}; /* [-1, 1] x [-1, 1] x [0, 1] */
  int32_t sh[3];
  uint32_t nd[3];
  const double in_lo[3] = {-0.9, 0, 0.1}, in_hi[3] = {0.99, 1, 1};
  assert_int_equal(vlff_lattice_cover(origin, cell, dims, in_lo, in_hi, 100, sh, nd), 0);
  for (int a = 0; a < 3; a++) assert_int_equal(sh[a], 0), assert_int_equal(nd[a], dims[a]);
  /* out by 0.2 below in x (one cell) and by 1.1 above in z (three cells) */
  const double lo[3] = {-1.2, 0, 0}, hi[3] = {0, 0, 2.1};
  assert_int_equal(vlff_lattice_cover(origin, cell, dims, lo, hi, 100, sh, nd), 1);
  assert_int_equal(sh[0], 1), assert_int_equal(nd[0], 5);
  assert_int_equal(sh[1], 0), assert_int_equal(nd[1], 4);
  assert_int_equal(sh[2], 0), assert_int_equal(nd[2], 5);
  /* clipped to +-limit (3 m): [-3, 3] in x is 12 cells, 4 of them below the
   * old grid's first */
  const double far_lo[3] = {-1e6, 0, 0}, far_hi[3] = {1e6, 0, 0};
  assert_int_equal(vlff_lattice_cover(origin, cell, dims, far_lo, far_hi, 3, sh, nd), 1);
  assert_int_equal(sh[0], 4), assert_int_equal(nd[0], 12);
  /* wholly beyond the limit: grows to the limit's edge only */
  const double past_lo[3] = {50, 0, 0}, past_hi[3] = {60, 0, 0};
  assert_int_equal(vlff_lattice_cover(origin, cell, dims, past_lo, past_hi, 3, sh, nd), 1);
  assert_int_equal(sh[0], 0), assert_int_equal(nd[0], 8);
  /* empty, non-finite, no cell */
  const double nan_hi[3] = {NAN, 0, 0}, empty_hi[3] = {-2, 0, 0};
  assert_int_equal(vlff_lattice_cover(origin, cell, dims, lo, nan_hi, 3, sh, nd), -1);
  assert_int_equal(vlff_lattice_cover(origin, cell, dims, lo, empty_hi, 3, sh, nd), -1);
  assert_int_equal(vlff_lattice_cover(origin, (const double[3]){0.5, 0, 0.5}, dims, lo, hi, 3, sh, nd), -1);
  /* past 2^31 cells on an axis */
  assert_int_equal(vlff_lattice_cover(origin, VLFF_LATTICE_CUBE(1e-6), dims, far_lo, far_hi, 1e4, sh, nd), -1);
  /* Cells of another size on each axis (a box's own occupancy cells): each
   * axis counts in its own. [-1, 1] x [-1, 1] x [0, 1] as 4 x 8 x 10 cells;
   * out by 0.2 below in x (one 0.5 cell), by 0.3 above in y (two 0.25
   * cells) and 0.25 above in z (three 0.1 cells). */
  const double aniso[3] = {0.5, 0.25, 0.1}, ahi[3] = {0, 1.3, 1.25};
  const uint32_t adims[3] = {4, 8, 10};
  assert_int_equal(vlff_lattice_cover(origin, aniso, adims, lo, ahi, 100, sh, nd), 1);
  assert_int_equal(sh[0], 1), assert_int_equal(nd[0], 5);
  assert_int_equal(sh[1], 0), assert_int_equal(nd[1], 10);
  assert_int_equal(sh[2], 0), assert_int_equal(nd[2], 13);
}

/* The wanted box of a growth is taken together with the needed one. */
static void test_box_union(void **state) {
  (void)state;
  const double alo[3] = {0, -1, 2}, ahi[3] = {4, 1, 3}, blo[3] = {-2, 0, 2.5}, bhi[3] = {1, 5, 2.6};
  double lo[3], hi[3];
  vlff_box_union(alo, ahi, blo, bhi, lo, hi);
  const double wlo[3] = {-2, -1, 2}, whi[3] = {4, 5, 3};
  assert_memory_equal(lo, wlo, sizeof lo);
  assert_memory_equal(hi, whi, sizeof hi);
  const double nlo[3] = {NAN, -1, 2};
  vlff_box_union(nlo, ahi, blo, bhi, lo, hi);
  assert_true(lo[0] == -2);
}

static void test_copy_and_index(void **state) {
  (void)state;
  const uint32_t dims[3] = {3, 2, 2}, nd[3] = {5, 4, 3};
  const int32_t sh[3] = {1, 2, 0};
  uint16_t old[12], grown[60];
  for (int i = 0; i < 12; i++) old[i] = (uint16_t)(100 + i);
  for (int i = 0; i < 60; i++) grown[i] = 7;
  vlff_lattice_copy(grown, nd, old, dims, sh, sizeof old[0]);
  int copied = 0;
  for (size_t i = 0; i < 12; i++) {
    long j = vlff_lattice_index(i, dims, sh, nd);
    assert_int_equal(grown[j], old[i]);
    /* the same place: x, y, z each moved by the shift */
    size_t x = i % 3, y = i / 3 % 2, z = i / 6;
    assert_int_equal(j, (long)((x + 1) + 5 * ((y + 2) + 4 * z)));
  }
  for (int i = 0; i < 60; i++) copied += grown[i] != 7;
  assert_int_equal(copied, 12); /* the rest left as it was */
  assert_int_equal(vlff_lattice_cells(nd), 60);
  /* regrid: the same copy into a new array whose other cells are the fill */
  uint16_t *r = vlff_lattice_regrid(old, sizeof old[0], 0x07, dims, sh, nd);
  assert_non_null(r);
  for (int i = 0; i < 60; i++) assert_int_equal(r[i], grown[i] == 7 ? 0x0707 : grown[i]);
  free(r);
  r = vlff_lattice_regrid(NULL, sizeof old[0], 0, dims, sh, nd); /* no old grid: all fill */
  assert_non_null(r);
  for (int i = 0; i < 60; i++) assert_int_equal(r[i], 0);
  free(r);
}

/* A refit: the smallest grid on the lattice holding the cells kept and a
 * box, smaller than the old grid where the old grid's cells beyond hold
 * nothing. The cells kept stay in their places; the others are dropped. */
static void test_fit(void **state) {
  (void)state;
  const double origin[3] = {0, 0, 0}, cell[3] = {1, 1, 1};
  const uint32_t dims[3] = {6, 4, 3}; /* [0, 6] x [0, 4] x [0, 3] */
  int32_t sh[3];
  uint32_t nd[3];
  /* held: x 1..2, y 0..3, z 1 (cells [1, 3) x [0, 4) x [1, 2)) */
  long klo[3] = {LONG_MAX, LONG_MAX, LONG_MAX}, khi[3] = {LONG_MIN, LONG_MIN, LONG_MIN};
  const size_t held[3] = {1 + 6 * (0 + 4 * 1), 2 + 6 * (3 + 4 * 1), 2 + 6 * (1 + 4 * 1)};
  for (int i = 0; i < 3; i++) vlff_lattice_extend(klo, khi, held[i], dims);
  assert_int_equal(klo[0], 1), assert_int_equal(khi[0], 3);
  assert_int_equal(klo[1], 0), assert_int_equal(khi[1], 4);
  assert_int_equal(klo[2], 1), assert_int_equal(khi[2], 2);
  /* and a box beyond the grid toward -x: [-2.5, -1] x [1, 2] x [1, 2] */
  const double lo[3] = {-2.5, 1, 1}, hi[3] = {-1, 2, 2};
  assert_int_equal(vlff_lattice_fit(origin, cell, dims, klo, khi, lo, hi, 100, sh, nd), 1);
  assert_int_equal(sh[0], 3), assert_int_equal(nd[0], 6);  /* cells -3 .. 2 */
  assert_int_equal(sh[1], 0), assert_int_equal(nd[1], 4);  /* 0 .. 3 */
  assert_int_equal(sh[2], -1), assert_int_equal(nd[2], 1); /* 1 only: starts inside the old grid */
  uint16_t old[72], *r;
  for (int i = 0; i < 72; i++) old[i] = (uint16_t)(1000 + i);
  r = vlff_lattice_regrid(old, sizeof old[0], 0, dims, sh, nd);
  assert_non_null(r);
  int kept = 0;
  for (size_t i = 0; i < 72; i++) {
    long j = vlff_lattice_index(i, dims, sh, nd);
    size_t x = i % 6, y = i / 6 % 4, z = i / 24;
    if (z != 1 || x >= 3) {
      assert_int_equal(j, -1); /* dropped: beyond the new grid */
      continue;
    }
    assert_int_equal(j, (long)((x + 3) + 6 * y)); /* the same place */
    assert_int_equal(r[j], old[i]);
    kept++;
  }
  assert_int_equal(kept, 12);
  for (size_t j = 0; j < 24; j++)
    if (j % 6 < 3) assert_int_equal(r[j], 0); /* the new cells: the fill */
  free(r);
  /* nothing held: the box alone */
  const long none_lo[3] = {0, 0, 0}, none_hi[3] = {0, 0, 0};
  assert_int_equal(vlff_lattice_fit(origin, cell, dims, none_lo, none_hi, lo, hi, 100, sh, nd), 1);
  assert_int_equal(nd[0] * nd[1] * nd[2], 2); /* x -3 .. -2, y 1, z 1 */
  /* the whole grid held and a box inside it: the same grid */
  const long all_lo[3] = {0, 0, 0}, all_hi[3] = {6, 4, 3};
  const double in_lo[3] = {1, 1, 1}, in_hi[3] = {2, 2, 2};
  assert_int_equal(vlff_lattice_fit(origin, cell, dims, all_lo, all_hi, in_lo, in_hi, 100, sh, nd), 0);
}

/* Random grids, held cells and boxes: a refit holds every held cell and the
 * box, and moves no cell in the world; a cover holds the whole old grid. */
static void test_fit_random(void **state) {
  (void)state;
  unsigned seed = 7;
  for (int t = 0; t < 300; t++) {
    /* a cell size per axis, as a box's occupancy cells */
    double cell[3], origin[3], lo[3], hi[3];
    for (int a = 0; a < 3; a++) cell[a] = 0.1 + 0.9 * rand_r(&seed) / (double)RAND_MAX;
    uint32_t dims[3];
    for (int a = 0; a < 3; a++) {
      origin[a] = (rand_r(&seed) % 2001 - 1000) * 0.01;
      dims[a] = 1 + (uint32_t)(rand_r(&seed) % 9);
      lo[a] = origin[a] + (rand_r(&seed) % 4001 - 2000) * 0.01;
      hi[a] = lo[a] + (rand_r(&seed) % 1001) * 0.01;
    }
    const size_t n = vlff_lattice_cells(dims);
    uint8_t held[9 * 9 * 9];
    long klo[3] = {LONG_MAX, LONG_MAX, LONG_MAX}, khi[3] = {LONG_MIN, LONG_MIN, LONG_MIN};
    for (size_t i = 0; i < n; i++) {
      held[i] = rand_r(&seed) % 5 == 0;
      if (held[i]) vlff_lattice_extend(klo, khi, i, dims);
    }
    int32_t sh[3];
    uint32_t nd[3];
    assert_true(vlff_lattice_fit(origin, cell, dims, klo, khi, lo, hi, 1e4, sh, nd) >= 0);
    double norigin[3];
    for (int a = 0; a < 3; a++) {
      norigin[a] = origin[a] - sh[a] * cell[a];
      /* the box, in whole cells */
      assert_true(norigin[a] <= lo[a] + 1e-9 && norigin[a] + nd[a] * cell[a] >= hi[a] - 1e-9);
    }
    for (size_t i = 0; i < n; i++) {
      long j = vlff_lattice_index(i, dims, sh, nd);
      if (!held[i]) continue;
      assert_true(j >= 0);
      /* the same cell corner in the world */
      const size_t c[3] = {i % dims[0], i / dims[0] % dims[1], i / ((size_t)dims[0] * dims[1])};
      const size_t d[3] = {(size_t)j % nd[0], (size_t)j / nd[0] % nd[1], (size_t)j / ((size_t)nd[0] * nd[1])};
      for (int a = 0; a < 3; a++) assert_true(fabs(origin[a] + c[a] * cell[a] - (norigin[a] + d[a] * cell[a])) < 1e-9);
    }
    assert_true(vlff_lattice_cover(origin, cell, dims, lo, hi, 1e4, sh, nd) >= 0);
    for (int a = 0; a < 3; a++) assert_true(sh[a] >= 0 && sh[a] + dims[a] <= nd[a]);
  }
}

/* A saved grid is recognised as a grown or refitted version of a grid on
 * its lattice. */
static void test_saved(void **state) {
  (void)state;
  const double origin0[3] = {-2.5, -2.5, 0};
  const long k0[3] = {0, -2, 0}; /* grown by 2 cells toward -y so far */
  const uint32_t dims[3] = {10, 12, 4};
  int32_t sh[3];
  const double so[3] = {-3.0, -4.5, 0}; /* 1 cell more toward -x, 2 more toward -y */
  const uint32_t sd[3] = {12, 14, 4};
  assert_int_equal(vlff_lattice_saved(origin0, 0.5, k0, dims, so, sd, sh), 1);
  assert_int_equal(sh[0], 1), assert_int_equal(sh[1], 2), assert_int_equal(sh[2], 0);
  const double same_o[3] = {-2.5, -3.5, 0};
  assert_int_equal(vlff_lattice_saved(origin0, 0.5, k0, dims, same_o, dims, sh), 0); /* the same grid */
  const double off[3] = {-3.1, -4.5, 0};
  assert_int_equal(vlff_lattice_saved(origin0, 0.5, k0, dims, off, sd, sh), 0); /* another lattice */
  /* a refitted one: starts inside, or is smaller (the caller checks what it holds) */
  const uint32_t small[3] = {10, 12, 3};
  assert_int_equal(vlff_lattice_saved(origin0, 0.5, k0, dims, same_o, small, sh), 1);
  assert_int_equal(sh[2], 0);
  const double inside[3] = {-2.0, -3.5, 0.5};
  assert_int_equal(vlff_lattice_saved(origin0, 0.5, k0, dims, inside, sd, sh), 1);
  assert_int_equal(sh[0], -1), assert_int_equal(sh[1], 0), assert_int_equal(sh[2], -1);
}

/* A capped grid that must move on (vlff_lattice_window): the box it needs
 * and the old cells within the largest margin that fits the cap. */
static void test_window(void **state) {
  (void)state;
  const double origin[3] = {0, 0, 0}, cell[3] = {1, 1, 1};
  const uint32_t dims[3] = {10, 10, 10};
  int32_t sh[3];
  uint32_t nd[3];
  /* far beyond +x: no old cell is near enough to keep: the box alone */
  const double flo[3] = {20, 0, 0}, fhi[3] = {22, 2, 2};
  assert_int_equal(vlff_lattice_window(origin, cell, dims, flo, fhi, 1000, 60, sh, nd), 1);
  assert_int_equal(sh[0], -20), assert_int_equal(nd[0], 2);
  assert_int_equal(sh[1], 0), assert_int_equal(nd[1], 2);
  assert_int_equal(sh[2], 0), assert_int_equal(nd[2], 2);
  /* across the +x face: margin 2 fits 200 cells (4 x 6 x 6 = 144), 3 would not (5 x 8 x 8) */
  const double lo[3] = {9, 4, 4}, hi[3] = {11, 6, 6};
  assert_int_equal(vlff_lattice_window(origin, cell, dims, lo, hi, 1000, 200, sh, nd), 1);
  assert_int_equal(sh[0], -7), assert_int_equal(nd[0], 4);
  assert_int_equal(sh[1], -2), assert_int_equal(nd[1], 6);
  assert_int_equal(sh[2], -2), assert_int_equal(nd[2], 6);
  /* the box alone passes the cap */
  assert_int_equal(vlff_lattice_window(origin, cell, dims, lo, hi, 1000, 7, sh, nd), -1);
  const double bad[3] = {NAN, 0, 0};
  assert_int_equal(vlff_lattice_window(origin, cell, dims, bad, hi, 1000, 200, sh, nd), -1);
  /* random grids and boxes: the window holds the box, fits the cap, and
   * keeps every old cell within its margin of the box */
  unsigned seed = 11;
  for (int t = 0; t < 300; t++) {
    double o[3], c[3], blo[3], bhi[3];
    uint32_t d[3];
    for (int a = 0; a < 3; a++) {
      c[a] = 0.1 + 0.9 * rand_r(&seed) / (double)RAND_MAX;
      o[a] = (rand_r(&seed) % 2001 - 1000) * 0.01;
      d[a] = 1 + (uint32_t)(rand_r(&seed) % 30);
      blo[a] = o[a] + (rand_r(&seed) % 8001 - 2000) * 0.01;
      bhi[a] = blo[a] + (rand_r(&seed) % 301) * 0.01;
    }
    const size_t cap = 1 + (size_t)(rand_r(&seed) % 5000);
    if (vlff_lattice_window(o, c, d, blo, bhi, 1000, cap, sh, nd) < 0) continue;
    assert_true(vlff_lattice_cells(nd) <= cap);
    for (int a = 0; a < 3; a++) {
      const double wlo = o[a] - sh[a] * c[a], whi = wlo + nd[a] * c[a];
      assert_true(wlo <= blo[a] + 1e-9 && whi >= bhi[a] - 1e-9);
    }
  }
}

int main(void) {
  const struct CMUnitTest tests[] = {cmocka_unit_test(test_cover), cmocka_unit_test(test_box_union),
                                     cmocka_unit_test(test_copy_and_index),
                                     cmocka_unit_test(test_fit), cmocka_unit_test(test_fit_random),
                                     cmocka_unit_test(test_saved), cmocka_unit_test(test_window)};
  return cmocka_run_group_tests(tests, NULL, NULL);
}
