/* Regions of a label image (regions.h): surface cells are grouped by the
 * camera image's colour and the measured points' geometry, and a cell whose
 * own scores lean the wrong way by a little reads what its surface reads. */
#include <float.h>
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "regions.h"
#include "unit.h"

enum { LW = 40, LH = 30, IW = 160, IH = 120, K = 3 };
static const double O[3] = {0, 0, 0}; /* the camera */

/* A camera at the origin looking along +z at a wall 2 m away: cell (x, y)'s
 * point, with the cells in [x0, x1) x [y0, y1) pushed back by step metres. */
static size_t wall(uint32_t *pix, float *xyz, int x0, int x1, int y0, int y1, float step) {
  size_t n = 0;
  for (int y = 0; y < LH; y++)
    for (int x = 0; x < LW; x++) {
      const float z = 2.0f + (x >= x0 && x < x1 && y >= y0 && y < y1 ? step : 0.0f);
      pix[n] = (uint32_t)(y * LW + x);
      xyz[3 * n] = (x + 0.5f - LW / 2.0f) * 0.05f * z / 2.0f;
      xyz[3 * n + 1] = (y + 0.5f - LH / 2.0f) * 0.05f * z / 2.0f;
      xyz[3 * n + 2] = z;
      n++;
    }
  return n;
}

/* An image of one grey with the image pixels under cells [x0, x1) x [y0,
 * y1) in another colour. */
static void image(uint8_t *rgb, int x0, int x1, int y0, int y1, const uint8_t other[3]) {
  for (int y = 0; y < IH; y++)
    for (int x = 0; x < IW; x++) {
      const int cx = x * LW / IW, cy = y * LH / IH;
      const bool in = cx >= x0 && cx < x1 && cy >= y0 && cy < y1;
      for (int c = 0; c < 3; c++) rgb[(y * IW + x) * 3 + c] = in ? other[c] : 120;
    }
}

/* Scores: class 0 everywhere, clearly (0.6 against 0.3), except in the
 * patch, where class 1 leads by 0.05: what a surface's evidence does where
 * the views that saw it leaned toward a look-alike. */
static void scores(float *s, const uint32_t *pix, size_t n, int x0, int x1, int y0, int y1) {
  for (size_t i = 0; i < n; i++) {
    const int x = (int)(pix[i] % LW), y = (int)(pix[i] / LW);
    const bool in = x >= x0 && x < x1 && y >= y0 && y < y1;
    s[i * K] = in ? 0.45f : 0.6f;
    s[i * K + 1] = in ? 0.5f : 0.3f;
    s[i * K + 2] = 0.1f;
  }
}

struct world {
  uint32_t pix[LW * LH];
  float xyz[3 * LW * LH], col[3 * LW * LH], s[K * LW * LH];
  uint8_t rgb[IW * IH * 3];
  int lab[LW * LH];
  float score[LW * LH];
};

/* A world and regions of the LW x LH grid. */
static struct world *world_new(struct vlff_regions **r) {
  struct world *w = calloc(1, sizeof *w);
  *r = vlff_regions_create(LW, LH);
  assert_non_null(w);
  assert_non_null(*r);
  return w;
}

/* A flat wall 2 m away, its image grey but for cells [x0, x1) x [y0, y1)
 * in colour c, and the cells' colours: the cells. */
static size_t painted_wall(struct world *w, int x0, int x1, int y0, int y1, const uint8_t c[3]) {
  size_t n = wall(w->pix, w->xyz, 0, 0, 0, 0, 0);
  image(w->rgb, x0, x1, y0, y1, c);
  vlff_regions_colours(w->rgb, IW, IH, LW, LH, w->pix, n, w->col);
  return n;
}

static void world_free(struct world *w, struct vlff_regions *r) {
  vlff_regions_destroy(r);
  free(w);
}

static int label_at(const struct world *w, size_t n, int x, int y) {
  for (size_t i = 0; i < n; i++)
    if (w->pix[i] == (uint32_t)(y * LW + x)) return w->lab[i];
  return -2;
}

/* One wall of one colour: one region, and the patch whose scores lean to
 * class 1 reads class 0 as the wall does; with beta 0 each cell reads its
 * own best. */
static void test_patch_reads_its_surface(void **state) {
  (void)state;
  struct vlff_regions *r;
  struct world *w = world_new(&r);
  size_t n = painted_wall(w, 0, 0, 0, 0, (const uint8_t[3]){0, 0, 0});
  assert_float_equal(w->col[0], 120 / 255.0, 1e-6);
  assert_int_equal(vlff_regions_build(r, w->col, w->pix, w->xyz, n, O, 0), 1);
  scores(w->s, w->pix, n, 10, 20, 10, 20);
  assert_int_equal(vlff_regions_vote(r, w->s, n, K, 0.0f, w->lab, w->score), 0);
  assert_int_equal(label_at(w, n, 15, 15), 1);
  assert_int_equal(label_at(w, n, 2, 2), 0);
  assert_int_equal(vlff_regions_vote(r, w->s, n, K, 1.0f, w->lab, w->score), 0);
  for (size_t i = 0; i < n; i++) assert_int_equal(w->lab[i], 0);
  /* its score: the cell's own at the voted label */
  for (size_t i = 0; i < n; i++)
    if (w->pix[i] == 15 * LW + 15) assert_float_equal(w->score[i], 0.45f, 1e-6);
  world_free(w, r);
}

/* The patch in another colour (a picture on the wall), or set back by a
 * depth step of the same grey (a door ajar): a region of its own, which
 * keeps its own reading; the wall around it keeps its own. */
static void test_colour_and_depth_separate(void **state) {
  (void)state;
  struct vlff_regions *r;
  struct world *w = world_new(&r);
  size_t n = painted_wall(w, 10, 20, 10, 20, (const uint8_t[3]){200, 60, 40});
  assert_int_equal(vlff_regions_build(r, w->col, w->pix, w->xyz, n, O, 0), 2);
  assert_int_equal(vlff_regions_of(r, 15 * LW + 15), vlff_regions_of(r, 12 * LW + 12));
  assert_int_not_equal(vlff_regions_of(r, 15 * LW + 15), vlff_regions_of(r, 2 * LW + 2));
  scores(w->s, w->pix, n, 10, 20, 10, 20);
  assert_int_equal(vlff_regions_vote(r, w->s, n, K, 1.0f, w->lab, NULL), 0);
  assert_int_equal(label_at(w, n, 15, 15), 1);
  assert_int_equal(label_at(w, n, 2, 2), 0);

  n = wall(w->pix, w->xyz, 10, 20, 10, 20, 0.4f);
  image(w->rgb, 0, 0, 0, 0, (const uint8_t[3]){0, 0, 0});
  vlff_regions_colours(w->rgb, IW, IH, LW, LH, w->pix, n, w->col);
  assert_int_equal(vlff_regions_build(r, w->col, w->pix, w->xyz, n, O, 0), 2);
  assert_int_equal(vlff_regions_vote(r, w->s, n, K, 1.0f, w->lab, NULL), 0);
  assert_int_equal(label_at(w, n, 15, 15), 1);
  assert_int_equal(label_at(w, n, 2, 2), 0);
  /* without colours the depth step still separates; a flat wall is one */
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, 0), 2);
  n = wall(w->pix, w->xyz, 0, 0, 0, 0, 0);
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, 0), 1);
  world_free(w, r);
}

/* A wall 3 m away as a stereo camera measures it (sigma 0.01 d^2 = 9 cm,
 * each point off by up to two sigma): with the sensor's noise given it is
 * one surface, and the 0.6 m step of a door set back the wall's height
 * still cuts it (the wall left of the door, the door, the wall right of
 * it); taken as exact, the noise cuts it into pieces. */
static void test_depth_noise(void **state) {
  (void)state;
  struct vlff_regions *r;
  struct world *w = world_new(&r);
  size_t n = wall(w->pix, w->xyz, 10, 20, 0, LH, 0.6f);
  unsigned seed = 3;
  for (size_t i = 0; i < n; i++) {
    const float k = 1.5f + (2.0f * (float)rand_r(&seed) / (float)RAND_MAX - 1.0f) * 0.09f; /* 2 m -> 3 m +- 2 sigma */
    for (int c = 0; c < 3; c++) w->xyz[3 * i + c] *= k;
  }
  const size_t exact = vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, 0);
  assert_true(exact > 20);
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, 0.01f), 3);
  assert_int_not_equal(vlff_regions_of(r, 15), vlff_regions_of(r, 2));
  assert_int_not_equal(vlff_regions_of(r, 15), vlff_regions_of(r, 25));
  assert_int_equal(vlff_regions_of(r, 2), vlff_regions_of(r, (LH - 1) * LW + 2));
  /* a noise that is not one: every step counts */
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, NAN), exact);
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, -1.0f), exact);
  world_free(w, r);
}

/* The same scene on a grid twice as fine groups the same surfaces (k
 * scales with the cell count): the colour patch is a region at both. */
static void test_grid_size_free(void **state) {
  (void)state;
  enum { L2W = 2 * LW, L2H = 2 * LH };
  struct vlff_regions *r = vlff_regions_create(L2W, L2H);
  uint32_t *pix = calloc(L2W * L2H, sizeof *pix);
  float *xyz = calloc(3 * L2W * L2H, sizeof *xyz), *col = calloc(3 * L2W * L2H, sizeof *col);
  uint8_t *rgb = calloc(IW * IH * 3, 1);
  assert_non_null(r);
  assert_true(pix && xyz && col && rgb);
  size_t n = 0;
  for (int y = 0; y < L2H; y++)
    for (int x = 0; x < L2W; x++, n++) {
      pix[n] = (uint32_t)(y * L2W + x);
      xyz[3 * n] = (x + 0.5f - L2W / 2.0f) * 0.025f, xyz[3 * n + 1] = (y + 0.5f - L2H / 2.0f) * 0.025f;
      xyz[3 * n + 2] = 2.0f;
    }
  image(rgb, 10, 20, 10, 20, (const uint8_t[3]){200, 60, 40});
  vlff_regions_colours(rgb, IW, IH, L2W, L2H, pix, n, col);
  assert_int_equal(vlff_regions_build(r, col, pix, xyz, n, O, 0), 2);
  vlff_regions_destroy(r);
  free(pix), free(xyz), free(col), free(rgb);
}

/* Cells nothing scored (label -1) stay so and weigh nothing; cells outside
 * the grid or given twice are regions of their own; a point that is not a
 * number joins nothing. */
static void test_hostile_cells(void **state) {
  (void)state;
  struct vlff_regions *r;
  struct world *w = world_new(&r);
  assert_null(vlff_regions_create(0, 5));
  assert_null(vlff_regions_create(5, -1));
  size_t n = wall(w->pix, w->xyz, 0, 0, 0, 0, 0);
  /* the whole patch unscored, its scores huge for class 2: nothing moves */
  scores(w->s, w->pix, n, 10, 20, 10, 20);
  for (size_t i = 0; i < n; i++) {
    const int x = (int)(w->pix[i] % LW), y = (int)(w->pix[i] / LW);
    w->lab[i] = x >= 10 && x < 20 && y >= 10 && y < 20 ? -1 : 0;
    if (w->lab[i] < 0) w->s[i * K + 2] = 1e6f;
  }
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, 0), 1);
  assert_int_equal(vlff_regions_vote(r, w->s, n, K, 1.0f, w->lab, NULL), 0);
  for (size_t i = 0; i < n; i++) {
    const int x = (int)(w->pix[i] % LW), y = (int)(w->pix[i] / LW);
    assert_int_equal(w->lab[i], x >= 10 && x < 20 && y >= 10 && y < 20 ? -1 : 0);
  }
  /* a cell scoring NaN keeps its label and takes no region with it: its
   * neighbour, clearly class 2, stays so */
  w->s[0] = NAN, w->lab[0] = 1;
  w->s[K] = 0.1f, w->s[K + 1] = 0.1f, w->s[K + 2] = 0.9f;
  assert_int_equal(vlff_regions_vote(r, w->s, n, K, 1.0f, w->lab, NULL), 0);
  assert_int_equal(w->lab[0], 1);
  assert_int_equal(w->lab[1], 2);
  w->pix[5] = LW * LH + 7;   /* outside */
  w->pix[6] = w->pix[7];     /* twice */
  w->xyz[3 * 100] = NAN;     /* not a point */
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, 0), 4);
  assert_int_not_equal(vlff_regions_of(r, 5), vlff_regions_of(r, 0));
  assert_int_not_equal(vlff_regions_of(r, 100), vlff_regions_of(r, 0));
  /* more cells than the grid holds: the grid's; the rest are in no region
   * and the vote leaves them as they are */
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, (size_t)LW * LH * 2, O, 0) >= 1, 1);
  assert_int_equal(vlff_regions_of(r, (size_t)LW * LH), UINT32_MAX);
  world_free(w, r);
}

/* A wall whose grey ramps from left to right in steps too small for any
 * edge to separate: its regions' mean colours stay within 0.1 of each
 * other (regions.h), so a ramp across more than that is cut where a ramp
 * within it is one region. */
static void test_colour_leak(void **state) {
  (void)state;
  struct vlff_regions *r;
  struct world *w = world_new(&r);
  size_t n = wall(w->pix, w->xyz, 0, 0, 0, 0, 0);
  const float spans[] = {40.0f / 255, 8.0f / 255}; /* 0.27 and 0.054 apart as rgb */
  for (int t = 0; t < 2; t++) {
    for (size_t i = 0; i < n; i++)
      for (int c = 0; c < 3; c++) w->col[3 * i + c] = 100.0f / 255 + spans[t] * (float)(w->pix[i] % LW) / (LW - 1);
    size_t nr = vlff_regions_build(r, w->col, w->pix, w->xyz, n, O, 0);
    const uint32_t left = vlff_regions_of(r, 0), right = vlff_regions_of(r, LW - 1);
    if (t == 0) {
      assert_true(nr > 1);
      assert_int_not_equal(left, right);
    } else {
      assert_int_equal(nr, 1);
    }
  }
  /* without colours only depth separates: one region */
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, 0), 1);
  world_free(w, r);
}

/* Extremes that are numbers still vote sanely: an empty build, a beta
 * from 0 to FLT_MAX (or not a number), scores near FLT_MAX, a camera
 * position that is not a number. */
static void test_extremes(void **state) {
  (void)state;
  struct vlff_regions *r;
  struct world *w = world_new(&r);
  /* nothing built, nothing to vote: no work, no label touched */
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, 0, O, 0), 0);
  w->lab[0] = 7;
  assert_int_equal(vlff_regions_vote(r, w->s, 0, K, 1.0f, w->lab, NULL), 0);
  assert_int_equal(w->lab[0], 7);
  /* the leaning patch on one wall: any beta > 0 large enough takes it back,
   * the largest too; 0, negative and NaN leave each cell its own best */
  size_t n = wall(w->pix, w->xyz, 0, 0, 0, 0, 0);
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, O, 0), 1);
  const float betas[] = {1.0f, 10.0f, 1e30f, FLT_MAX, INFINITY, 0.0f, -1.0f, NAN};
  for (size_t b = 0; b < sizeof betas / sizeof *betas; b++) {
    scores(w->s, w->pix, n, 10, 20, 10, 20);
    for (size_t i = 0; i < n; i++) w->lab[i] = 0;
    assert_int_equal(vlff_regions_vote(r, w->s, n, K, betas[b], w->lab, w->score), 0);
    const int patch = betas[b] > 0 ? 0 : 1;
    assert_int_equal(label_at(w, n, 15, 15), patch);
    assert_int_equal(label_at(w, n, 2, 2), 0);
  }
  /* a cell whose best two are 2 FLT_MAX apart weighs nothing (its margin is
   * not a number we can add) and keeps its label; its neighbours vote as
   * before */
  scores(w->s, w->pix, n, 10, 20, 10, 20);
  for (size_t i = 0; i < n; i++) w->lab[i] = 0;
  w->s[0] = -FLT_MAX, w->s[1] = FLT_MAX, w->s[2] = -FLT_MAX, w->lab[0] = 1;
  assert_int_equal(vlff_regions_vote(r, w->s, n, K, 1.0f, w->lab, NULL), 0);
  assert_int_equal(w->lab[0], 1);
  assert_int_equal(label_at(w, n, 15, 15), 0);
  assert_int_equal(label_at(w, n, 1, 0), 0);
  /* scores near FLT_MAX whose weighted sum overflows: each cell its own
   * best, not one label for the whole region */
  for (size_t i = 0; i < n; i++) {
    w->s[i * K] = 0.0f, w->s[i * K + 1] = 0.5f * FLT_MAX, w->s[i * K + 2] = FLT_MAX;
    w->lab[i] = 0;
  }
  w->s[3 * K + 1] = FLT_MAX, w->s[3 * K + 2] = 0.5f * FLT_MAX;
  assert_int_equal(vlff_regions_vote(r, w->s, n, K, 1.0f, w->lab, w->score), 0);
  assert_int_equal(w->lab[3], 1);
  assert_int_equal(w->lab[4], 2);
  /* each with its own score at that label */
  assert_true(w->score[3] == FLT_MAX && w->score[4] == FLT_MAX);
  /* a camera position that is not a number: the flat wall stays one
   * region (its steps are all 0), as without a noise */
  const double nan_o[3] = {NAN, 0, 0};
  assert_int_equal(vlff_regions_build(r, NULL, w->pix, w->xyz, n, nan_o, 0.01f), 1);
  world_free(w, r);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_patch_reads_its_surface), cmocka_unit_test(test_colour_and_depth_separate),
               cmocka_unit_test(test_grid_size_free), cmocka_unit_test(test_depth_noise), cmocka_unit_test(test_hostile_cells),
               cmocka_unit_test(test_extremes), cmocka_unit_test(test_colour_leak))
