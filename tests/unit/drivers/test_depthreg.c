/*
 * Depth registration against geometry: a slanted plane and a rotated box at
 * known poses are ray-cast into a distorted depth camera; its image,
 * registered into a colour camera 5 cm away, must land where ray-casting
 * the same scene from the colour camera says: the right range on every
 * surface both cameras see, object edges within a pixel on average, the box
 * in front wherever it hides the plane from the colour camera (z-buffer),
 * and nothing where the colour camera sees what the depth camera could not
 * (holes stay invalid); at the colour camera's resolution and at coarser
 * and finer ones. The same through the pairing into a record of a
 * configured size, its colour plane resampled to match. Also: calibration
 * files as OpenCV writes them (YAML and XML) and the bounds that refuse bad
 * ones.
 */
#include <math.h>
#include <setjmp.h>
#include <stdbool.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>
#include <cmocka.h>

#include "config.h"
#include "depthreg.h"
#include "pair.h"
#include "pixfmt.h"
#include "sink.h"
#include "unit.h"

#define DW 320
#define DH 240
#define CW 640
#define CH 480
#define UNIT 0.00025 /* a time-of-flight camera's quarter millimetre */
#define SPLIT 1.65   /* every box range is nearer than this, every plane range farther */

enum { NONE = 0, PLANE = 1, BOX = 2 };

/* ---- the scene, in the depth camera's frame ---------------------------- */

static const double plane_n[3] = {0.19518, -0.09759, 0.97590}; /* unit (0.2, -0.1, 1) */
static const double plane_d = 2.0;
static const double box_c[3] = {0.05, 0.02, 1.3}, box_h[3] = {0.18, 0.14, 0.12};
static double box_r[9]; /* box axes in the world: columns */

static void rot(double ax, double ay, double az, double out[9]) {
  double cx = cos(ax), sx = sin(ax), cy = cos(ay), sy = sin(ay), cz = cos(az), sz = sin(az);
  double X[9] = {1, 0, 0, 0, cx, -sx, 0, sx, cx}, Y[9] = {cy, 0, sy, 0, 1, 0, -sy, 0, cy},
         Z[9] = {cz, -sz, 0, sz, cz, 0, 0, 0, 1}, t[9];
  for (int i = 0; i < 9; i++) t[i] = Y[i / 3 * 3] * X[i % 3] + Y[i / 3 * 3 + 1] * X[3 + i % 3] + Y[i / 3 * 3 + 2] * X[6 + i % 3];
  for (int i = 0; i < 9; i++) out[i] = Z[i / 3 * 3] * t[i % 3] + Z[i / 3 * 3 + 1] * t[3 + i % 3] + Z[i / 3 * 3 + 2] * t[6 + i % 3];
}

/* Nearest hit along o + t d (t > 0): returns the object, *t its parameter
 * and *face which surface (0 the plane, 1..6 the box's faces). */
static int raycast_face(const double o[3], const double d[3], double *t, int *face) {
  int hit = NONE, lo_axis = 0;
  *face = 0;
  *t = INFINITY;
  double nd = plane_n[0] * d[0] + plane_n[1] * d[1] + plane_n[2] * d[2];
  double no = plane_n[0] * o[0] + plane_n[1] * o[1] + plane_n[2] * o[2];
  if (fabs(nd) > 1e-12) {
    double tp = (plane_d - no) / nd;
    if (tp > 1e-9) *t = tp, hit = PLANE;
  }
  double lo = -INFINITY, hi = INFINITY;
  for (int a = 0; a < 3; a++) {
    double oa = 0, da = 0;
    for (int k = 0; k < 3; k++) oa += box_r[k * 3 + a] * (o[k] - box_c[k]), da += box_r[k * 3 + a] * d[k];
    if (fabs(da) < 1e-15) {
      if (fabs(oa) > box_h[a]) lo = INFINITY;
      continue;
    }
    double t1 = (-box_h[a] - oa) / da, t2 = (box_h[a] - oa) / da;
    if (fmin(t1, t2) > lo) lo = fmin(t1, t2), lo_axis = 1 + a + 3 * (t1 > t2);
    hi = fmin(hi, fmax(t1, t2));
  }
  if (lo <= hi && lo > 1e-9 && lo < *t) *t = lo, hit = BOX, *face = lo_axis;
  return hit;
}

static int raycast(const double o[3], const double d[3], double *t) {
  int face;
  return raycast_face(o, d, t, &face);
}

/* ---- the rig ----------------------------------------------------------- */

static struct vlff_rgbd_calib rig(void) {
  struct vlff_rgbd_calib c;
  memset(&c, 0, sizeof c);
  double kd[9] = {260, 0, 159.3, 0, 261, 119.6, 0, 0, 1}, kc[9] = {525, 0, 319.2, 0, 523, 241.1, 0, 0, 1};
  double dd[5] = {-0.12, 0.06, 0.0008, -0.0005, -0.01}, dc[5] = {0.05, -0.1, 0.001, 0, 0.02};
  memcpy(c.kd, kd, sizeof kd), memcpy(c.kc, kc, sizeof kc);
  memcpy(c.dd, dd, sizeof dd), memcpy(c.dc, dc, sizeof dc);
  c.nd = c.nc = 5;
  rot(-1 * M_PI / 180, 2 * M_PI / 180, 0.5 * M_PI / 180, c.r);
  c.t[0] = -0.052, c.t[1] = 0.004, c.t[2] = 0.008;
  return c;
}

/* The depth camera's image of the scene, in UNIT counts. */
static void render_depth(const struct vlff_rgbd_calib *c, uint16_t *img) {
  const double o[3] = {0, 0, 0};
  for (int j = 0; j < DH; j++)
    for (int i = 0; i < DW; i++) {
      double x, y, t;
      assert_int_equal(vlff_undistort_point(c->dd, c->nd, (i - c->kd[2]) / c->kd[0], (j - c->kd[5]) / c->kd[4], &x, &y),
                       0);
      double d[3] = {x, y, 1};
      int hit = raycast(o, d, &t);
      img[j * DW + i] = hit ? (uint16_t)lround(t / UNIT) : 0; /* d[2] = 1: t is the range along z */
    }
}

/* What the colour camera (output intrinsics k, size w x h) sees at each
 * pixel: the object, its range along the colour axis, and whether the
 * depth camera sees that point too (in its field of view, unoccluded). */
struct truth {
  uint8_t obj, face, seen;
  float z;
};

static void colour_truth(const struct vlff_rgbd_calib *c, const double k[4], int w, int h, struct truth *gt) {
  const double *R = c->r, *T = c->t;
  double C[3];
  for (int a = 0; a < 3; a++) C[a] = -(R[a] * T[0] + R[3 + a] * T[1] + R[6 + a] * T[2]);
  for (int y = 0; y < h; y++)
    for (int x = 0; x < w; x++) {
      double dc[3] = {(x - k[2]) / k[0], (y - k[3]) / k[1], 1}, d[3], t;
      for (int a = 0; a < 3; a++) d[a] = R[a] * dc[0] + R[3 + a] * dc[1] + R[6 + a] * dc[2];
      struct truth *g = &gt[y * w + x];
      int face;
      g->obj = (uint8_t)raycast_face(C, d, &t, &face);
      g->face = (uint8_t)face;
      g->z = (float)t;
      g->seen = 0;
      if (!g->obj) continue;
      double P[3] = {C[0] + t * d[0], C[1] + t * d[1], C[2] + t * d[2]}, o[3] = {0, 0, 0}, td;
      raycast(o, P, &td);
      double xd, yd;
      vlff_distort_point(c->dd, c->nd, P[0] / P[2], P[1] / P[2], &xd, &yd);
      double u = c->kd[0] * xd + c->kd[2], v = c->kd[4] * yd + c->kd[5];
      g->seen = fabs(td - 1) < 1e-7 && u > -0.5 && u < DW - 0.5 && v > -0.5 && v < DH - 0.5;
    }
}

/* 1 when every pixel within rad of (x,y) has its object and visibility
 * (and, with faces set, its surface): the pixel is away from every edge. */
static int interior(const struct truth *gt, int w, int h, int x, int y, int rad, int faces) {
  if (x < rad || y < rad || x >= w - rad || y >= h - rad) return 0;
  const struct truth *c = &gt[y * w + x];
  for (int b = -rad; b <= rad; b++)
    for (int a = -rad; a <= rad; a++) {
      const struct truth *n = &gt[(y + b) * w + x + a];
      if (n->obj != c->obj || n->seen != c->seen || (faces && n->face != c->face)) return 0;
    }
  return 1;
}

/* The output camera for ow x oh: each axis scaled about pixel centres. */
static void check_intrinsics(const double k[4], int ow, int oh) {
  double sx = (double)ow / CW, sy = (double)oh / CH;
  assert_true(fabs(k[0] - 525 * sx) < 1e-9 && fabs(k[1] - 523 * sy) < 1e-9);
  assert_true(fabs(k[2] - ((319.2 + 0.5) * sx - 0.5)) < 1e-9 && fabs(k[3] - ((241.1 + 0.5) * sy - 0.5)) < 1e-9);
}

/* A registered depth image (ow x oh, rows os pixels apart, output camera k)
 * against the colour camera's view of the scene. zq: the range error the
 * quantisation of input and output allows, metres. */
static void check_registered(const struct vlff_rgbd_calib *c, const double k[4], int ow, int oh, const uint16_t *out,
                             int os, long valid, double zq) {
  struct truth *gt = malloc((size_t)ow * oh * sizeof *gt);
  assert_non_null(gt);
  colour_truth(c, k, ow, oh, gt);
  long inner = 0, covered = 0, zbuf_bad = 0, box_inner = 0, holes = 0, hole_bad = 0, outside = 0, outside_bad = 0;
  long mism = 0, edge = 0, zout = 0;
  /* Output pixels per depth pixel, rounded up; an edge lands within half
   * of that (the footprint of the depth pixel beside it), rounded up. */
  const int ratio = (int)ceil((double)ow / DW - 1e-9), half = (int)ceil(0.5 * ow / DW - 1e-9);
  double zerr = 0, zmax = 0;
  for (int y = 0; y < oh; y++)
    for (int x = 0; x < ow; x++) {
      const struct truth *g = &gt[y * ow + x];
      uint16_t v = out[y * os + x];
      if (g->obj == BOX) assert_true(g->z < SPLIT);
      if (g->obj == PLANE) assert_true(g->z > SPLIT);
      if (v && g->obj && (v * 0.001 < SPLIT) != (g->obj == BOX)) mism++;
      if (g->obj == BOX && x > 0 && y > 0 && x < ow - 1 && y < oh - 1 &&
          (gt[y * ow + x - 1].obj != BOX || gt[y * ow + x + 1].obj != BOX || gt[(y - 1) * ow + x].obj != BOX ||
           gt[(y + 1) * ow + x].obj != BOX))
        edge++;
      /* Ranges and coverage on each surface away from its edges and creases
       * (by more than a depth pixel: there the depth camera's samples stop).
       * A colour pixel takes the range of the depth pixel whose footprint
       * holds it, at most a depth pixel (ratio colour pixels) away: on a
       * sloped surface its error is bounded by that slope. */
      if (g->obj && g->seen && interior(gt, ow, oh, x, y, ratio, 1)) {
        inner++;
        if (v) {
          covered++;
          double e = fabs(v * 0.001 - g->z), slope = 0;
          for (int n = 0; n < 4; n++) {
            int nx = x + (n == 0) - (n == 1), ny = y + (n == 2) - (n == 3);
            slope = fmax(slope, fabs(gt[ny * ow + nx].z - g->z));
          }
          zerr += e, zmax = fmax(zmax, e);
          zout += e > ratio * slope + zq;
        }
      }
      if (!interior(gt, ow, oh, x, y, half, 0)) continue;
      if (g->obj == BOX) box_inner++, zbuf_bad += v && v * 0.001 > SPLIT;
      if (g->obj == PLANE && !g->seen) {
        /* in view of the colour camera only: the box hid it from the depth
         * camera, or it lies outside the depth camera's field */
        holes++;
        hole_bad += v != 0;
      }
      if (!g->obj) outside++, outside_bad += v != 0;
    }
  printf("%dx%d: %ld valid; interior %ld, covered %.2f %%, |dz| mean %.2f mm max %.2f mm; edge %ld px, "
         "%ld mismatched (%.2f px); box %ld px, %ld behind it; unseen %ld px, %ld filled; %ld ranges off\n",
         ow, oh, valid, inner, 100.0 * covered / inner, 1e3 * zerr / covered, 1e3 * zmax, edge, mism,
         (double)mism / edge, box_inner, zbuf_bad, holes, hole_bad, zout);
  /* The scene exercises each case. */
  assert_true(inner > ow * oh / 2);
  assert_true(box_inner > ow * oh / 50);
  assert_true(holes > ow * oh / 400);
  /* Every surface both cameras see gets a range, and the right one: on a
   * slanted surface a depth pixel's range differs from its neighbour's by
   * a few millimetres, the bound on the error. */
  assert_true(covered >= inner * 999 / 1000);
  assert_true(zerr / covered < 0.002);
  assert_int_equal(zout, 0);
  /* Edges land within a pixel on average (mismatched pixels per edge pixel). */
  assert_true((double)mism / edge < 1.0);
  /* Nearest wins: nothing seen behind the box. */
  assert_int_equal(zbuf_bad, 0);
  /* What only the colour camera sees stays invalid. */
  assert_int_equal(hole_bad, 0);
  assert_int_equal(outside_bad, 0);
  (void)outside;
  free(gt);
}

static void check_registration(int ow, int oh) {
  struct vlff_rgbd_calib c = rig();
  char err[512];
  struct vlff_depthreg *r = vlff_depthreg_new(&c, DW, DH, CW, CH, ow == CW ? 0 : ow, ow == CW ? 0 : oh, err, sizeof err);
  if (!r) fail_msg("%s", err);
  double k[4];
  int w, h;
  vlff_depthreg_intrinsics(r, k, &w, &h);
  assert_int_equal(w, ow);
  assert_int_equal(h, oh);
  check_intrinsics(k, ow, oh);

  const int os = ow + 8; /* output rows padded: strides need not be the row length */
  uint16_t *depth = malloc(DW * DH * 2), *out = malloc((size_t)os * oh * 2);
  assert_true(depth && out);
  render_depth(&c, depth);
  long valid = vlff_depthreg_apply(r, depth, DW * 2, UNIT, out, (size_t)os * 2, err, sizeof err);
  if (valid < 0) fail_msg("%s", err);
  /* quarter-millimetre input, millimetre output */
  check_registered(&c, k, ow, oh, out, os, valid, 0.001);
  free(depth), free(out);
  vlff_depthreg_free(r);
}

static void test_registers_at_colour_resolution(void **state) {
  (void)state;
  check_registration(CW, CH);
}

static void test_registers_at_configured_resolution(void **state) {
  (void)state;
  check_registration(320, 240);
  check_registration(800, 600);
}

/* ---- the record camd writes: colour and depth at a configured size ----- */

static char dir[128];
static const char *write_file(const char *name, const char *text);

/* The rig as stereoCalibrate would write it. */
static const char *write_rig(const struct vlff_rgbd_calib *c) {
  char text[4096], *t = text;
  size_t left = sizeof text;
  const char *names[5] = {"K1", "D1", "K2", "D2", "R"};
  const double *vals[5] = {c->kd, c->dd, c->kc, c->dc, c->r};
  const int rows[5] = {3, 1, 3, 1, 3}, cols[5] = {3, 5, 3, 5, 3};
  int n = snprintf(t, left, "%%YAML:1.0\n---\n");
  t += n, left -= (size_t)n;
  for (int m = 0; m < 6; m++) {
    const double *v = m < 5 ? vals[m] : c->t;
    int r = m < 5 ? rows[m] : 3, cl = m < 5 ? cols[m] : 1;
    n = snprintf(t, left, "%s: !!opencv-matrix\n   rows: %d\n   cols: %d\n   dt: d\n   data: [", m < 5 ? names[m] : "T",
                 r, cl);
    t += n, left -= (size_t)n;
    for (int i = 0; i < r * cl; i++) {
      n = snprintf(t, left, "%s %.17g", i ? "," : "", v[i]);
      t += n, left -= (size_t)n;
    }
    n = snprintf(t, left, " ]\n");
    t += n, left -= (size_t)n;
  }
  return write_file("pair-rig.yaml", text);
}

/* The colour camera's image (undistorted, as the colour pipeline delivers
 * it): each pixel's share of box, plane and background from 4 x 4 samples,
 * in its red, green and blue. *bx, *by: the box's centroid in pixels. */
static void render_colour(const struct vlff_rgbd_calib *c, uint8_t *img, double *bx, double *by) {
  const double k[4] = {c->kc[0], c->kc[4], c->kc[2], c->kc[5]};
  struct truth *gt = malloc((size_t)CW * 4 * CH * 4 * sizeof *gt);
  assert_non_null(gt);
  /* the samples at (x + (i + 0.5) / 4 - 0.5) of pixel x: a camera 4x as fine */
  const double k4[4] = {k[0] * 4, k[1] * 4, (k[2] + 0.5) * 4 - 0.5, (k[3] + 0.5) * 4 - 0.5};
  colour_truth(c, k4, CW * 4, CH * 4, gt);
  double sx = 0, sy = 0, sw = 0;
  for (int y = 0; y < CH; y++)
    for (int x = 0; x < CW; x++) {
      int cnt[3] = {0, 0, 0};
      for (int j = 0; j < 4; j++)
        for (int i = 0; i < 4; i++) {
          int o = gt[(size_t)(y * 4 + j) * CW * 4 + x * 4 + i].obj;
          cnt[o == BOX ? 0 : o == PLANE ? 1 : 2]++;
        }
      for (int a = 0; a < 3; a++) img[(y * CW + x) * 3 + a] = (uint8_t)((cnt[a] * 255 + 8) / 16);
      sx += x * cnt[0], sy += y * cnt[0], sw += cnt[0];
    }
  *bx = sx / sw, *by = sy / sw;
  free(gt);
}

/* One colour and one range frame through the pairing into a record of
 * ow x oh: both planes at that size, the intrinsics of the output camera;
 * the depth lands on the geometry (check_registered), the resampled colour
 * keeps the box where it was (its centroid maps through the same scaling
 * as the intrinsics), and colour and depth agree on the box's outline. */
static void check_pair_record(int ow, int oh) {
  struct vlff_rgbd_calib c = rig();
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  snprintf(cfg.depth_camera.calibration, sizeof cfg.depth_camera.calibration, "%s", write_rig(&c));
  cfg.depth_camera.register_width = ow, cfg.depth_camera.register_height = oh;
  struct vlff_memsink *ms = vlff_memsink_new(2, ow, oh);
  char err[512];
  struct vlff_pair *p = vlff_pair_new(&cfg.depth_camera, &cfg.camera, vlff_memsink_sink(ms), err, sizeof err);
  if (!p) fail_msg("%s", err);

  struct vlff_sink *cs = vlff_pair_color_sink(p), *ds = vlff_pair_depth_sink(p);
  struct vlff_sink_frame fc = {.width = CW, .height = CH, .color_format = VLFF_PIX_RGB8};
  assert_int_equal(cs->reserve(cs, &fc, err, sizeof err), 0);
  uint8_t *rgb = malloc(CW * CH * 3);
  uint16_t *counts = malloc(DW * DH * 2);
  assert_true(rgb && counts);
  double bx, by;
  render_colour(&c, rgb, &bx, &by);
  for (int y = 0; y < CH; y++) memcpy(fc.color + y * fc.color_stride, rgb + y * CW * 3, CW * 3);
  fc.host_ns = 1000000000;
  assert_int_equal(cs->commit(cs, &fc), 0);
  /* the range pipeline delivers millimetres */
  render_depth(&c, counts);
  struct vlff_sink_frame fd = {.width = DW, .height = DH, .depth_format = VLFF_DEPTH_FMT_U16_MM};
  assert_int_equal(ds->reserve(ds, &fd, err, sizeof err), 0);
  for (int y = 0; y < DH; y++)
    for (int x = 0; x < DW; x++)
      ((uint16_t *)((char *)fd.depth + y * fd.depth_stride))[x] = (uint16_t)lround(counts[y * DW + x] * UNIT * 1000);
  fd.host_ns = 1000000000;
  assert_int_equal(ds->commit(ds, &fd), 0);
  assert_int_equal(vlff_pair_get_stats(p)->pairs, 1);

  const struct vlff_sink_frame *f = vlff_memsink_get(ms, 0);
  assert_non_null(f);
  assert_int_equal(f->width, ow);
  assert_int_equal(f->height, oh);
  check_intrinsics(f->intrinsics, ow, oh);
  assert_int_equal(f->depth_stride % 2, 0);
  const uint16_t *dep = f->depth;
  const int os = (int)(f->depth_stride / 2);
  long valid = 0;
  for (int y = 0; y < oh; y++)
    for (int x = 0; x < ow; x++) valid += dep[y * os + x] != 0;
  /* millimetre input and output: a millimetre of rounding on each side */
  check_registered(&c, f->intrinsics, ow, oh, dep, os, valid, 0.0015);

  /* The colour plane: the box's centroid where the scaling puts it. */
  double sx = 0, sy = 0, sw = 0, ex = (bx + 0.5) * ow / CW - 0.5, ey = (by + 0.5) * oh / CH - 0.5;
  long disagree = 0, outline = 0;
  for (int y = 0; y < oh; y++)
    for (int x = 0; x < ow; x++) {
      const uint8_t *px = f->color + y * f->color_stride + x * 3;
      sx += x * px[0], sy += y * px[0], sw += px[0];
      /* the box by colour (more box than anything else) and by depth */
      bool cbox = px[0] > px[1] && px[0] > px[2];
      uint16_t v = dep[y * os + x];
      if (v) disagree += cbox != (v * 0.001 < SPLIT);
      if (x > 0 && y > 0 && x < ow - 1 && y < oh - 1) {
        const uint8_t *l = px - 3, *r = px + 3, *u = px - f->color_stride, *d = px + f->color_stride;
        bool n[4] = {l[0] > l[1] && l[0] > l[2], r[0] > r[1] && r[0] > r[2], u[0] > u[1] && u[0] > u[2],
                     d[0] > d[1] && d[0] > d[2]};
        outline += cbox && !(n[0] && n[1] && n[2] && n[3]);
      }
    }
  sx /= sw, sy /= sw;
  printf("%dx%d record: box centroid in colour (%.3f, %.3f), expected (%.3f, %.3f); colour and depth disagree "
         "on %ld px along a %ld px outline (%.2f px)\n",
         ow, oh, sx, sy, ex, ey, disagree, outline, (double)disagree / outline);
  /* A resampling off by the half-pixel convention moves it by
   * |0.5 s - 0.5| (an eighth of a pixel at these scales). */
  assert_true(fabs(sx - ex) < 0.02 && fabs(sy - ey) < 0.02);
  /* Colour and depth show the box's outline at the same place, within a
   * pixel on average. */
  assert_true(outline > 100);
  assert_true((double)disagree / outline < 1.0);
  free(rgb), free(counts);
  vlff_pair_free(p);
  vlff_memsink_free(ms);
}

/* Smaller than the colour camera, by a ratio that is no whole number and
 * differs between the axes (481/640 against 360/480: the aspect 0.2 %
 * off, within the tolerance). */
static void test_pair_record_smaller(void **state) {
  (void)state;
  check_pair_record(481, 360);
}

/* Larger than the colour camera: the colour plane is interpolated, the
 * depth registered directly at the finer size. */
static void test_pair_record_larger(void **state) {
  (void)state;
  check_pair_record(800, 600);
}

/* An aspect beyond the tolerance is refused when the calibration names the
 * colour camera's size, and by the registration when only the frames do. */
static void test_pair_record_aspect(void **state) {
  (void)state;
  struct vlff_rgbd_calib c = rig();
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  snprintf(cfg.depth_camera.calibration, sizeof cfg.depth_camera.calibration, "%s", write_rig(&c));
  cfg.depth_camera.register_width = 640, cfg.depth_camera.register_height = 360;
  char err[512];
  cfg.camera.width = CW, cfg.camera.height = CH;
  assert_null(vlff_pair_new(&cfg.depth_camera, &cfg.camera, NULL, err, sizeof err));
  assert_non_null(strstr(err, "depth_camera.register_width"));
  assert_non_null(strstr(err, "aspect"));
  assert_null(vlff_depthreg_new(&c, DW, DH, CW, CH, 640, 360, err, sizeof err));
  assert_non_null(strstr(err, "aspect"));
  assert_false(vlff_depthreg_aspect_ok(640, 360, CW, CH));
  assert_true(vlff_depthreg_aspect_ok(481, 360, CW, CH));
  assert_true(vlff_depthreg_aspect_ok(426, 240, 1280, 720));
}

/* The plane hides behind the box from the colour camera only where the
 * depth camera saw it: those depth pixels land inside the box's image,
 * where the z-buffer must keep the box. Count that they exist. */
static void test_scene_has_occlusion(void **state) {
  (void)state;
  struct vlff_rgbd_calib c = rig();
  char err[256];
  struct vlff_depthreg *r = vlff_depthreg_new(&c, DW, DH, CW, CH, 0, 0, err, sizeof err);
  assert_non_null(r);
  double k[4];
  vlff_depthreg_intrinsics(r, k, NULL, NULL);
  struct truth *gt = malloc(CW * CH * sizeof *gt);
  colour_truth(&c, k, CW, CH, gt);
  long hidden = 0;
  for (int j = 0; j < DH; j++)
    for (int i = 0; i < DW; i++) {
      double x, y, t, o[3] = {0, 0, 0};
      assert_int_equal(vlff_undistort_point(c.dd, c.nd, (i - c.kd[2]) / c.kd[0], (j - c.kd[5]) / c.kd[4], &x, &y), 0);
      double d[3] = {x, y, 1};
      if (raycast(o, d, &t) != PLANE) continue;
      double P[3] = {x * t, y * t, t}, X[3];
      for (int a = 0; a < 3; a++) X[a] = c.r[a * 3] * P[0] + c.r[a * 3 + 1] * P[1] + c.r[a * 3 + 2] * P[2] + c.t[a];
      long u = lround(k[0] * X[0] / X[2] + k[2]), v = lround(k[1] * X[1] / X[2] + k[3]);
      if (u >= 0 && u < CW && v >= 0 && v < CH && gt[v * CW + u].obj == BOX) hidden++;
    }
  printf("%ld depth pixels see plane the colour camera sees box at\n", hidden);
  assert_true(hidden > 200);
  free(gt);
  vlff_depthreg_free(r);
}

static void test_distortion_inverts(void **state) {
  (void)state;
  const double d8[8] = {-0.28, 0.09, 0.001, -0.0007, -0.012, 0.02, 0.003, 0.001};
  srand(7);
  for (int i = 0; i < 10000; i++) {
    double x = (rand() / (double)RAND_MAX - 0.5) * 1.2, y = (rand() / (double)RAND_MAX - 0.5) * 0.9, xd, yd, u, v;
    for (int n = 4; n <= 8; n += n == 5 ? 3 : 1) {
      vlff_distort_point(d8, n, x, y, &xd, &yd);
      assert_int_equal(vlff_undistort_point(d8, n, xd, yd, &u, &v), 0);
      assert_true(fabs(u - x) < 1e-9 && fabs(v - y) < 1e-9);
    }
  }
  /* A model that folds over has no inverse there: refused, not guessed. */
  const double fold[5] = {-1.5, 0, 0, 0, 0};
  double u, v;
  assert_int_equal(vlff_undistort_point(fold, 5, 0.9, 0.7, &u, &v), -1);
  struct vlff_rgbd_calib c = rig();
  c.dd[0] = -1.5;
  char err[256];
  assert_null(vlff_depthreg_new(&c, DW, DH, CW, CH, 0, 0, err, sizeof err));
  assert_non_null(strstr(err, "D1"));
}

/* ---- calibration files ------------------------------------------------- */

static const char *write_file(const char *name, const char *text) {
  static char p[256];
  snprintf(p, sizeof p, "%s/%s", dir, name);
  FILE *f = fopen(p, "w");
  assert_non_null(f);
  fputs(text, f);
  fclose(f);
  return p;
}

#define YMAT(name, r, c, data) name ": !!opencv-matrix\n   rows: " #r "\n   cols: " #c "\n   dt: d\n   data: [ " data " ]\n"
#define K1 YMAT("K1", 3, 3, "260., 0., 159.3, 0., 261., 119.6, 0., 0., 1.")
#define D1 YMAT("D1", 1, 5, "-0.12, 0.06, 8.0e-04, -5.0e-04, -0.01")
#define K2 YMAT("K2", 3, 3, "525., 0., 319.2, 0., 523., 241.1, 0., 0., 1.")
#define D2 YMAT("D2", 1, 5, "0.05, -0.1, 1.0e-03, 0., 0.02")
#define RI YMAT("R", 3, 3, "1., 0., 0., 0., 1., 0., 0., 0., 1.")
#define TM YMAT("T", 3, 1, "-0.052, 0.004, 0.008")

static void expect_refused(const char *name, const char *text, const char *what) {
  struct vlff_rgbd_calib c;
  char err[512];
  const char *p = write_file(name, text);
  assert_int_equal(vlff_rgbd_calib_load(p, &c, err, sizeof err), -1);
  if (!strstr(err, what) || !strstr(err, name)) fail_msg("%s: expected '%s' in: %s", name, what, err);
}

static int load_nonregular(void *fifo) {
  struct vlff_rgbd_calib c;
  char err[512];
  int ok = vlff_rgbd_calib_load(fifo, &c, err, sizeof err) == -1 && strstr(err, "fifo.yaml: is a FIFO, expected a regular file");
  return ok && vlff_rgbd_calib_load(dir, &c, err, sizeof err) == -1 && strstr(err, "is a directory") ? 0 : 1;
}

static void test_calibration_files(void **state) {
  (void)state;
  char cmd[200];
  struct vlff_rgbd_calib c;
  char err[512];
  /* YAML as cv::FileStorage writes stereoCalibrate's outputs. */
  const char *p = write_file("rig.yaml", "%YAML:1.0\n---\n" K1 D1 K2 D2 RI TM "depth_width: 320\ndepth_height: 240\n");
  if (vlff_rgbd_calib_load(p, &c, err, sizeof err)) fail_msg("%s", err);
  assert_true(c.kd[0] == 260 && c.kd[5] == 119.6 && c.kc[2] == 319.2 && c.nd == 5 && c.nc == 5);
  assert_true(c.dd[2] == 8e-4 && c.t[0] == -0.052 && c.r[4] == 1 && c.depth_w == 320 && c.color_w == 0);
  /* XML, the sample's names (M1, M2), a rotation vector, 4 coefficients,
   * T in millimetres with its unit. */
  p = write_file("rig.xml",
                 "<?xml version=\"1.0\"?>\n<opencv_storage>\n"
                 "<M1 type_id=\"opencv-matrix\"><rows>3</rows><cols>3</cols><dt>d</dt>\n"
                 "  <data>260. 0. 159.3 0. 261. 119.6 0. 0. 1.</data></M1>\n"
                 "<D1 type_id=\"opencv-matrix\"><rows>1</rows><cols>4</cols><dt>d</dt>\n"
                 "  <data>-0.12 0.06 0. 0.</data></D1>\n"
                 "<M2 type_id=\"opencv-matrix\"><rows>3</rows><cols>3</cols><dt>d</dt>\n"
                 "  <data>525. 0. 319.2 0. 523. 241.1 0. 0. 1.</data></M2>\n"
                 "<D2 type_id=\"opencv-matrix\"><rows>5</rows><cols>1</cols><dt>d</dt>\n"
                 "  <data>0.05 -0.1 0. 0. 0.02</data></D2>\n"
                 "<R type_id=\"opencv-matrix\"><rows>3</rows><cols>1</cols><dt>d</dt>\n"
                 "  <data>0. 0.1 0.</data></R>\n"
                 "<T type_id=\"opencv-matrix\"><rows>3</rows><cols>1</cols><dt>d</dt>\n"
                 "  <data>-52. 4. 8.</data></T>\n"
                 "<translation_unit_m>1.0e-03</translation_unit_m>\n"
                 "</opencv_storage>\n");
  if (vlff_rgbd_calib_load(p, &c, err, sizeof err)) fail_msg("%s", err);
  assert_int_equal(c.nd, 4);
  assert_true(fabs(c.t[0] + 0.052) < 1e-12 && fabs(c.t[2] - 0.008) < 1e-12);
  assert_true(fabs(c.r[0] - cos(0.1)) < 1e-12 && fabs(c.r[2] - sin(0.1)) < 1e-12 && fabs(c.r[6] + sin(0.1)) < 1e-12);

  /* Refusals name the file and what is wrong. */
  expect_refused("mm.yaml", "%YAML:1.0\n---\n" K1 D1 K2 D2 RI YMAT("T", 3, 1, "-52., 4., 8."), "translation_unit_m");
  expect_refused("noK2.yaml", "%YAML:1.0\n---\n" K1 D1 D2 RI TM, "K2");
  expect_refused("R.yaml", "%YAML:1.0\n---\n" K1 D1 K2 D2 YMAT("R", 3, 3, "1.1, 0., 0., 0., 1., 0., 0., 0., 1.") TM,
                 "R is not a rotation");
  expect_refused("mirror.yaml", "%YAML:1.0\n---\n" K1 D1 K2 D2 YMAT("R", 3, 3, "-1., 0., 0., 0., 1., 0., 0., 0., 1.") TM,
                 "R is not a rotation");
  expect_refused("fx.yaml",
                 "%YAML:1.0\n---\n" YMAT("K1", 3, 3, "-260., 0., 159.3, 0., 261., 119.6, 0., 0., 1.") D1 K2 D2 RI TM,
                 "focal lengths");
  expect_refused("skew.yaml",
                 "%YAML:1.0\n---\n" K1 D1 YMAT("K2", 3, 3, "525., 3., 319.2, 0., 523., 241.1, 0., 0., 1.") D2 RI TM,
                 "skew");
  expect_refused("d14.yaml",
                 "%YAML:1.0\n---\n" K1 YMAT("D1", 1, 14, "0., 0., 0., 0., 0., 0., 0., 0., 0., 0., 0., 0., 0., 0.") K2 D2 RI
                     TM,
                 "not supported");
  expect_refused("pp.yaml", "%YAML:1.0\n---\n" K1 D1 K2 D2 RI TM "color_width: 300\ncolor_height: 240\n",
                 "principal point");
  expect_refused("fov.yaml",
                 "%YAML:1.0\n---\n" YMAT("K1", 3, 3, "30000., 0., 159.3, 0., 30000., 119.6, 0., 0., 1.") D1 K2 D2 RI TM
                 "depth_width: 320\ndepth_height: 240\n",
                 "field of view");
  expect_refused("nan.yaml", "%YAML:1.0\n---\n" K1 D1 K2 D2 RI YMAT("T", 3, 1, "-0.05, .nan, 0."), "not finite");
  expect_refused("unit.yaml", "%YAML:1.0\n---\n" K1 D1 K2 D2 RI TM "translation_unit_m: 5\n", "translation_unit_m");
  expect_refused("garbage.yaml", "this is not a calibration: [\n", "garbage.yaml");
  snprintf(cmd, sizeof cmd, "%s/missing.yaml", dir);
  assert_int_equal(vlff_rgbd_calib_load(cmd, &c, err, sizeof err), -1);
  assert_non_null(strstr(err, "missing.yaml"));
  /* A FIFO or a directory is refused at once, never waited on (issue 29): the
   * loads run in a child, whose alarm ends it if one blocks. */
  snprintf(cmd, sizeof cmd, "%s/fifo.yaml", dir);
  assert_int_equal(mkfifo(cmd, 0600), 0);
  int rc = vlff_test_in_child(load_nonregular, cmd, 10);
  if (rc) fail_msg("a FIFO or directory as calibration file: %s", rc < 0 ? "blocked" : "not refused");

  /* The shipped example loads and fits the cameras it names. */
  const char *src = getenv("VLFF_SOURCE_DIR");
  assert_non_null(src);
  char ex[1024];
  snprintf(ex, sizeof ex, "%s/configs/rgbd-calibration.yaml", src);
  if (vlff_rgbd_calib_load(ex, &c, err, sizeof err)) fail_msg("%s", err);
  assert_true(fabs(c.t[0] + 0.02512) < 1e-12);
  struct vlff_depthreg *ex_reg = vlff_depthreg_new(&c, 640, 480, 1280, 960, 0, 0, err, sizeof err);
  if (!ex_reg) fail_msg("%s", err);
  vlff_depthreg_free(ex_reg);

    /* Sizes the file states must be the cameras'. */
  p = write_file("sized.yaml", "%YAML:1.0\n---\n" K1 D1 K2 D2 RI TM "depth_width: 320\ndepth_height: 240\n");
  assert_int_equal(vlff_rgbd_calib_load(p, &c, err, sizeof err), 0);
  assert_null(vlff_depthreg_new(&c, 640, 480, CW, CH, 0, 0, err, sizeof err));
  assert_non_null(strstr(err, "calibrated for"));
  assert_null(vlff_depthreg_new(&c, DW, DH, CW, CH, 400, 240, err, sizeof err));
  assert_non_null(strstr(err, "aspect"));
  struct vlff_depthreg *r = vlff_depthreg_new(&c, DW, DH, CW, CH, 0, 0, err, sizeof err);
  assert_non_null(r);
  uint16_t d[DW * DH] = {0}, o[4];
  assert_int_equal(vlff_depthreg_apply(r, d, DW * 2, 0, o, CW * 2, err, sizeof err), -1);
  assert_int_equal(vlff_depthreg_apply(r, d, DW, 0.001, o, CW * 2, err, sizeof err), -1);
  vlff_depthreg_free(r);
}

static int make_dir(void **state) {
  (void)state;
  snprintf(dir, sizeof dir, "/tmp/vlff-test-depthreg-%d", (int)getpid());
  char cmd[200];
  snprintf(cmd, sizeof cmd, "mkdir -p %s", dir);
  return system(cmd) ? -1 : 0;
}

static int remove_dir(void **state) {
  (void)state;
  char cmd[200];
  snprintf(cmd, sizeof cmd, "rm -rf %s", dir);
  return system(cmd) ? -1 : 0;
}

int main(void) {
  rot(10 * M_PI / 180, 25 * M_PI / 180, 0, box_r);
  const struct CMUnitTest tests[] = {
      cmocka_unit_test(test_distortion_inverts),
      cmocka_unit_test(test_scene_has_occlusion),
      cmocka_unit_test(test_registers_at_colour_resolution),
      cmocka_unit_test(test_registers_at_configured_resolution),
      cmocka_unit_test(test_calibration_files),
      cmocka_unit_test(test_pair_record_smaller),
      cmocka_unit_test(test_pair_record_larger),
      cmocka_unit_test(test_pair_record_aspect),
  };
  return cmocka_run_group_tests(tests, make_dir, remove_dir);
}
