/* vlff_far_pick / vlff_far_emit: the far map's labelled voxels as points,
 * those the grid covers left to the grid, and a far map past the bound cut
 * to whole blocks, the nearest to the grid first; what is emitted is
 * exactly what was picked. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "far_walk.h"

#define E3 (VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE)

struct seen {
  size_t n;
  double first[3], last[3];
  uint16_t last_label;
  uint8_t last_conf;
  double max_x;
};

static void collect(void *ctx, const double c[3], uint16_t label, uint8_t conf) {
  struct seen *s = ctx;
  if (!s->n) memcpy(s->first, c, sizeof s->first);
  memcpy(s->last, c, sizeof s->last);
  s->last_label = label, s->last_conf = conf;
  if (!s->n || c[0] > s->max_x) s->max_x = c[0];
  s->n++;
}

/* A corridor of n blocks along x from block 0: each a wall run of 256
 * voxels (its first z layer), the rest free. */
static void corridor(uint32_t n, struct vlff_map_far_block *b, struct vlff_map_far_run *r) {
  for (uint32_t j = 0; j < n; j++) {
    b[j] = (struct vlff_map_far_block){{(int32_t)j, 0, 0}, 2 * j};
    r[2 * j] = (struct vlff_map_far_run){1, 256, 100, 0};
    r[2 * j + 1] = (struct vlff_map_far_run){VLFF_LABEL_FREE, E3 - 256, 0, 0};
  }
}

/* pick, then emit into s: the points emitted (always the pick's). */
static size_t walk(const struct vlff_map_far *far, const struct vlff_map_grid *g, size_t max, struct seen *s,
                   size_t *left) {
  struct vlff_far_pick pick;
  assert_int_equal(vlff_far_pick(far, g, max, &pick), 0);
  size_t n = vlff_far_emit(far, g, &pick, s ? collect : NULL, s);
  assert_int_equal(n, pick.points);
  if (left) *left = pick.left;
  vlff_far_pick_free(&pick);
  return n;
}

static void test_points(void **state) {
  (void)state;
  struct vlff_map_far_block b[4];
  struct vlff_map_far_run r[8];
  corridor(4, b, r);
  const struct vlff_map_far far = {{0, 0, 0}, 0.1, 4, 8, b, r};
  assert_null(vlff_map_far_check(&far));
  struct seen s = {0};
  size_t left = 7;
  /* no grid: every labelled voxel, in block order, at its centre */
  assert_int_equal(walk(&far, NULL, 1 << 20, &s, &left), 4 * 256);
  assert_int_equal(s.n, 4 * 256);
  assert_int_equal(left, 0);
  assert_float_equal(s.first[0], 0.05, 1e-9);
  assert_float_equal(s.last[0], (63 + 0.5) * 0.1, 1e-9);
  assert_float_equal(s.last[1], (15 + 0.5) * 0.1, 1e-9);
  assert_float_equal(s.last[2], 0.05, 1e-9);
  assert_int_equal(s.last_label, 1);
  assert_int_equal(s.last_conf, 100);
  /* a grid over the first block and a half: those voxels are the grid's */
  uint16_t labels[24 * 16 * 16] = {0};
  const struct vlff_map_grid g = {{0, 0, 0}, 0.1, {24, 16, 16}, labels, NULL};
  memset(&s, 0, sizeof s);
  assert_int_equal(walk(&far, &g, 1 << 20, &s, NULL), 4 * 256 - 24 * 16);
  assert_float_equal(s.first[0], (24 + 0.5) * 0.1, 1e-9);
  /* a grid that ends a voxel before a block, and one a voxel into it:
   * counted from the runs or voxel by voxel, the same points */
  const struct vlff_map_grid g15 = {{0, 0, 0}, 0.1, {15, 16, 16}, labels, NULL},
                             g17 = {{0, 0, 0}, 0.1, {17, 16, 16}, labels, NULL};
  assert_int_equal(walk(&far, &g15, 1 << 20, NULL, NULL), 4 * 256 - 15 * 16);
  assert_int_equal(walk(&far, &g17, 1 << 20, NULL, NULL), 4 * 256 - 17 * 16);
  /* a grid holding the first two blocks whole: none of theirs */
  const struct vlff_map_grid g32 = {{0, 0, 0}, 0.1, {32, 16, 16}, labels, NULL};
  assert_int_equal(walk(&far, &g32, 1 << 20, NULL, NULL), 2 * 256);
  /* a far map of another voxel size: the blocks apart from the grid are
   * read, those across its boundary left out whole and said (read voxel by
   * voxel they could take any time), those inside it give nothing */
  const struct vlff_map_far fine = {{0, 0, 0}, 0.05, 4, 8, b, r}; /* blocks of 0.8 m: x 0-3.2 m */
  const struct vlff_map_grid g12 = {{0, 0, 0}, 0.1, {12, 16, 16}, labels, NULL}; /* x 0-1.2 m */
  assert_int_equal(walk(&fine, &g12, 1 << 20, NULL, &left), 2 * 256); /* blocks 2 and 3 */
  assert_int_equal(left, 256);                                          /* block 1, across x = 1.2 m */
  /* no far map, an empty one */
  struct vlff_far_pick pick;
  assert_int_equal(vlff_far_pick(NULL, &g, 1 << 20, &pick), 0);
  assert_int_equal(pick.points + pick.left, 0);
  assert_int_equal(vlff_far_emit(NULL, &g, &pick, collect, &s), 0);
  vlff_far_pick_free(&pick);
}

/* Past the bound: whole blocks, the nearest to the grid's centre first,
 * the rest counted as left out; the same call gives the same points. */
static void test_bound(void **state) {
  (void)state;
  enum { NB = 40 };
  struct vlff_map_far_block b[NB];
  struct vlff_map_far_run r[2 * NB];
  corridor(NB, b, r);
  const struct vlff_map_far far = {{0, 0, 0}, 0.1, NB, 2 * NB, b, r};
  assert_null(vlff_map_far_check(&far));
  /* the robot's window in block 30 (x 48-49.6 m), above the corridor's wall runs */
  uint16_t labels[8] = {0};
  const struct vlff_map_grid g = {{30 * 1.6 + 0.4, 0.4, 0.4}, 0.1, {2, 2, 2}, labels, NULL};
  struct seen s = {0};
  size_t left = 0;
  /* 5 whole blocks fit in 1300 points (not 5 and a part) */
  assert_int_equal(walk(&far, &g, 1300, &s, &left), 5 * 256);
  assert_int_equal(left, (NB - 5) * 256);
  /* the nearest: blocks 28-32 (x 44.8-52.8 m), block 30 first */
  assert_true(s.max_x < 33 * 1.6);
  assert_true(s.first[0] >= 30 * 1.6 && s.first[0] < 31 * 1.6);
  struct seen t = {0};
  assert_int_equal(walk(&far, &g, 1300, &t, NULL), 5 * 256);
  assert_memory_equal(s.first, t.first, sizeof s.first);
  assert_memory_equal(s.last, t.last, sizeof s.last);
  /* a bound under one block: none, all left out */
  assert_int_equal(walk(&far, &g, 100, NULL, &left), 0);
  assert_int_equal(left, NB * 256);
}

int main(void) {
  const struct CMUnitTest tests[] = {cmocka_unit_test(test_points), cmocka_unit_test(test_bound)};
  return cmocka_run_group_tests(tests, NULL, NULL);
}
