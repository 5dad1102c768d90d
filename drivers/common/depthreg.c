/*
 * Depth registration (see depthreg.h). The depth camera's distortion is
 * inverted once, at creation, for every pixel corner: a table of rotated
 * rays q = R * undistort(corner). A depth pixel at range z then has its
 * corners at z * q + T in the colour camera, four multiply-adds and one
 * division each, and its footprint there is the bounding box of the four
 * projected corners.
 *
 * A corner shared by pixels of one surface is placed at their mean range,
 * so their footprints meet exactly and a sloped surface tiles the output
 * without cracks at any scale (at each pixel's own range, the shared corner
 * would land in two places a fraction of a pixel apart). A corner where the
 * ranges jump (an object's edge) takes each pixel's own range: there the
 * footprints overlap (the z-buffer keeps the nearer) or leave the hole the
 * depth camera could not see into.
 */
#include "depthreg.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "bounds.h"
#include "cvshim.h"

#define MAX_SIDE 16384

/* A pixel corner in one frame: shared by pixels of one surface (projected
 * once, at their mean range), or at a range jump (each pixel projects it at
 * its own range), or behind the colour camera. */
enum { CORNER_OWN = 0, CORNER_SHARED = 1, CORNER_BEHIND = 2 };
struct corner {
  float u, v;
  int state;
};

struct vlff_depthreg {
  int dw, dh, ow, oh;
  double k[4];     /* output camera fx fy cx cy */
  double t[3];
  float *q;        /* [(dh+1)][(dw+1)][3] rotated corner rays */
  struct corner *corner; /* [(dh+1)][(dw+1)], per frame */
  int max_fp;      /* a footprint wider than this is a grazing surface: left empty */
};

static int bad(char *err, size_t errlen, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
static int bad(char *err, size_t errlen, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  if (err && errlen) vsnprintf(err, errlen, fmt, ap);
  va_end(ap);
  return -1;
}

void vlff_distort_point(const double *d, int n, double x, double y, double *xd, double *yd) {
  double k3 = n > 4 ? d[4] : 0, k4 = n > 5 ? d[5] : 0, k5 = n > 6 ? d[6] : 0, k6 = n > 7 ? d[7] : 0;
  double r2 = x * x + y * y, r4 = r2 * r2, r6 = r4 * r2;
  double rad = (1 + d[0] * r2 + d[1] * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6);
  *xd = x * rad + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x);
  *yd = y * rad + d[2] * (r2 + 2 * y * y) + 2 * d[3] * x * y;
}

/* Fixed-point iteration as OpenCV's undistortPoints does it, run to
 * convergence and then verified by distorting the result again: a model
 * that folds over inside the image has no inverse there. */
int vlff_undistort_point(const double *d, int n, double xd, double yd, double *x, double *y) {
  double k3 = n > 4 ? d[4] : 0, k4 = n > 5 ? d[5] : 0, k5 = n > 6 ? d[6] : 0, k6 = n > 7 ? d[7] : 0;
  double u = xd, v = yd;
  for (int it = 0; it < 200; it++) {
    double r2 = u * u + v * v, r4 = r2 * r2, r6 = r4 * r2;
    double rad = (1 + d[0] * r2 + d[1] * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6);
    if (!(rad > 0) || !isfinite(rad)) return -1;
    double nu = (xd - 2 * d[2] * u * v - d[3] * (r2 + 2 * u * u)) / rad;
    double nv = (yd - d[2] * (r2 + 2 * v * v) - 2 * d[3] * u * v) / rad;
    double step = fabs(nu - u) + fabs(nv - v);
    u = nu, v = nv;
    if (step < 1e-15) break;
  }
  double ex, ey;
  vlff_distort_point(d, n, u, v, &ex, &ey);
  if (!(fabs(ex - xd) + fabs(ey - yd) < 1e-9)) return -1;
  *x = u, *y = v;
  return 0;
}

static int check_camera(const double *k, const double *d, int n, int w, int h, const char *name, const char *which,
                        char *err, size_t errlen) {
  double fx = k[0], fy = k[4];
  for (int i = 0; i < 9; i++)
    if (!isfinite(k[i])) return bad(err, errlen, "%s: %s camera matrix: element %d is not finite", name, which, i);
  if (!(fx >= 1 && fx <= 1e5 && fy >= 1 && fy <= 1e5))
    return bad(err, errlen, "%s: %s camera matrix: focal lengths fx=%g fy=%g outside 1..1e5 pixels", name, which, fx,
               fy);
  if (!(fx / fy >= 0.2 && fx / fy <= 5))
    return bad(err, errlen, "%s: %s camera matrix: fx/fy = %g is not a physical pixel aspect (0.2..5)", name, which,
               fx / fy);
  if (fabs(k[1]) > 1e-9 * fx)
    return bad(err, errlen, "%s: %s camera matrix: skew %g is not supported (calibrate without it)", name, which, k[1]);
  if (fabs(k[3]) > 1e-9 || fabs(k[6]) > 1e-9 || fabs(k[7]) > 1e-9 || fabs(k[8] - 1) > 1e-9)
    return bad(err, errlen, "%s: %s camera matrix is not of the form [fx 0 cx; 0 fy cy; 0 0 1]", name, which);
  if (n != 4 && n != 5 && n != VLFF_DIST_MAX)
    return bad(err, errlen, "%s: %s distortion: %d coefficients, expected 4, 5 or 8", name, which, n);
  for (int i = 0; i < n; i++)
    if (!(fabs(d[i]) < 1000))
      return bad(err, errlen, "%s: %s distortion: coefficient %d = %g is not a lens's (|c| < 1000)", name, which, i,
                 d[i]);
  if (w || h) {
    if (w < 1 || w > MAX_SIDE || h < 1 || h > MAX_SIDE)
      return bad(err, errlen, "%s: %s image size %dx%d outside 1..%d", name, which, w, h, MAX_SIDE);
    /* the bounds every camera of the project meets (field of view, aspect) */
    char why[256];
    if (vlff_intrinsics_plausible(w, h, fx, fy, k[2], k[5], why, sizeof why))
      return bad(err, errlen, "%s: %s camera matrix: %s", name, which, why);
    /* a calibrated principal point lies in the image: outside it, the sizes
     * the matrix was calibrated for are not these */
    if (!(k[2] > 0 && k[2] < w && k[5] > 0 && k[5] < h))
      return bad(err, errlen, "%s: %s principal point (%g, %g) lies outside the %dx%d image", name, which, k[2], k[5],
                 w, h);
  }
  return 0;
}

int vlff_rgbd_calib_check(const struct vlff_rgbd_calib *c, const char *name, char *err, size_t errlen) {
  if (check_camera(c->kd, c->dd, c->nd, c->depth_w, c->depth_h, name, "depth (K1, D1)", err, errlen) ||
      check_camera(c->kc, c->dc, c->nc, c->color_w, c->color_h, name, "colour (K2, D2)", err, errlen))
    return -1;
  double worst = 0;
  for (int i = 0; i < 3; i++)
    for (int j = 0; j < 3; j++) {
      double s = 0;
      for (int k = 0; k < 3; k++) s += c->r[k * 3 + i] * c->r[k * 3 + j];
      if (!isfinite(s)) return bad(err, errlen, "%s: R is not finite", name);
      worst = fmax(worst, fabs(s - (i == j)));
    }
  double det = c->r[0] * (c->r[4] * c->r[8] - c->r[5] * c->r[7]) - c->r[1] * (c->r[3] * c->r[8] - c->r[5] * c->r[6]) +
               c->r[2] * (c->r[3] * c->r[7] - c->r[4] * c->r[6]);
  if (worst > 1e-4 || !(det > 0))
    return bad(err, errlen, "%s: R is not a rotation (|R^T R - I| = %.2g, det %.4f)", name, worst, det);
  double tn = sqrt(c->t[0] * c->t[0] + c->t[1] * c->t[1] + c->t[2] * c->t[2]);
  if (!isfinite(tn)) return bad(err, errlen, "%s: T is not finite", name);
  if (tn > 1.0)
    return bad(err, errlen,
               "%s: T is %g m long; a depth and a colour camera of one rig sit within 1 m (if the calibration "
               "target was measured in millimetres, add translation_unit_m: 0.001)",
               name, tn);
  return 0;
}

int vlff_rgbd_calib_load(const char *path, struct vlff_rgbd_calib *c, char *err, size_t errlen) {
  double unit;
  if (vlff_cv_rgbd_calib_read(path, c, &unit, err, errlen)) return -1;
  if (!(unit > 0 && unit <= 1))
    return bad(err, errlen, "%s: translation_unit_m = %g, expected metres per unit in (0, 1]", path, unit);
  for (int i = 0; i < 3; i++) c->t[i] *= unit;
  return vlff_rgbd_calib_check(c, path, err, errlen);
}

bool vlff_depthreg_aspect_ok(int out_w, int out_h, int color_w, int color_h) {
  double a = (double)out_w * color_h, b = (double)out_h * color_w;
  return out_w > 0 && out_h > 0 && color_w > 0 && color_h > 0 && fabs(a - b) <= VLFF_DEPTHREG_ASPECT_TOL * b;
}

struct vlff_depthreg *vlff_depthreg_new(const struct vlff_rgbd_calib *c, int dw, int dh, int cw, int ch, int ow,
                                        int oh, char *err, size_t errlen) {
  if (!ow && !oh) ow = cw, oh = ch;
  if (dw < 1 || dw > MAX_SIDE || dh < 1 || dh > MAX_SIDE || cw < 1 || cw > MAX_SIDE || ch < 1 || ch > MAX_SIDE ||
      ow < 1 || ow > MAX_SIDE || oh < 1 || oh > MAX_SIDE) {
    bad(err, errlen, "depth registration: image sizes depth %dx%d, colour %dx%d, output %dx%d outside 1..%d", dw, dh,
        cw, ch, ow, oh, MAX_SIDE);
    return NULL;
  }
  if (!vlff_depthreg_aspect_ok(ow, oh, cw, ch)) {
    bad(err, errlen,
        "depth registration: output %dx%d does not have the colour images' %dx%d aspect (within %g %%): a "
        "different aspect would stretch the image; crop the colour camera (camera.width, camera.height, "
        "camera.offset_x, camera.offset_y) instead",
        ow, oh, cw, ch, 100 * VLFF_DEPTHREG_ASPECT_TOL);
    return NULL;
  }
  if ((c->depth_w && (c->depth_w != dw || c->depth_h != dh)) || (c->color_w && (c->color_w != cw || c->color_h != ch))) {
    bad(err, errlen, "depth registration: calibrated for depth %dx%d and colour %dx%d, cameras deliver %dx%d and %dx%d",
        c->depth_w, c->depth_h, c->color_w, c->color_h, dw, dh, cw, ch);
    return NULL;
  }
  struct vlff_rgbd_calib sized = *c;
  sized.depth_w = dw, sized.depth_h = dh, sized.color_w = cw, sized.color_h = ch;
  if (vlff_rgbd_calib_check(&sized, "depth registration", err, errlen)) return NULL;
  struct vlff_depthreg *r = calloc(1, sizeof *r);
  if (!r || !(r->q = malloc((size_t)(dw + 1) * (dh + 1) * 3 * sizeof(float))) ||
      !(r->corner = malloc((size_t)(dw + 1) * (dh + 1) * sizeof *r->corner))) {
    vlff_depthreg_free(r);
    bad(err, errlen, "depth registration: out of memory for a %dx%d ray table", dw + 1, dh + 1);
    return NULL;
  }
  r->dw = dw, r->dh = dh, r->ow = ow, r->oh = oh;
  /* Scaling keeps pixel centres on pixel centres (OpenCV's convention),
   * each axis by its own ratio. */
  double sx = (double)ow / cw, sy = (double)oh / ch;
  r->k[0] = c->kc[0] * sx, r->k[1] = c->kc[4] * sy;
  r->k[2] = (c->kc[2] + 0.5) * sx - 0.5, r->k[3] = (c->kc[5] + 0.5) * sy - 0.5;
  memcpy(r->t, c->t, sizeof r->t);
  /* A pixel at a normal angle covers about the resolution ratio in output
   * pixels; eight times that is a surface seen nearly edge-on. */
  double ratio = fmax(1.0, fmax(r->k[0] / c->kd[0], r->k[1] / c->kd[4]));
  r->max_fp = (int)ceil(8 * ratio) + 2;
  const double *kd = c->kd, *R = c->r;
  for (int j = 0; j <= dh; j++)
    for (int i = 0; i <= dw; i++) {
      double x, y;
      double xd = (i - 0.5 - kd[2]) / kd[0], yd = (j - 0.5 - kd[5]) / kd[4];
      if (vlff_undistort_point(c->dd, c->nd, xd, yd, &x, &y)) {
        bad(err, errlen, "depth registration: the depth camera's distortion (D1) does not invert at pixel corner "
                         "(%g, %g): coefficients implausible for a %dx%d image",
            i - 0.5, j - 0.5, dw, dh);
        vlff_depthreg_free(r);
        return NULL;
      }
      float *q = r->q + ((size_t)j * (dw + 1) + i) * 3;
      for (int a = 0; a < 3; a++) q[a] = (float)(R[a * 3] * x + R[a * 3 + 1] * y + R[a * 3 + 2]);
    }
  return r;
}

void vlff_depthreg_free(struct vlff_depthreg *r) {
  if (!r) return;
  free(r->q);
  free(r->corner);
  free(r);
}

void vlff_depthreg_intrinsics(const struct vlff_depthreg *r, double k[4], int *ow, int *oh) {
  memcpy(k, r->k, sizeof r->k);
  if (ow) *ow = r->ow;
  if (oh) *oh = r->oh;
}

long vlff_depthreg_apply(struct vlff_depthreg *r, const uint16_t *depth, size_t stride, double unit_m,
                         uint16_t *out, size_t out_stride, char *err, size_t errlen) {
  if (!(unit_m > 0 && unit_m <= 1))
    return bad(err, errlen, "depth registration: depth unit %g m, expected (0, 1]", unit_m);
  if (stride < (size_t)r->dw * 2 || out_stride < (size_t)r->ow * 2)
    return bad(err, errlen, "depth registration: row strides %zu and %zu are shorter than the rows", stride,
               out_stride);
  const int ow = r->ow, oh = r->oh, cw = r->dw + 1;
  const float fx = (float)r->k[0], fy = (float)r->k[1], cx = (float)r->k[2], cy = (float)r->k[3];
  const float tx = (float)r->t[0], ty = (float)r->t[1], tz = (float)r->t[2];
  for (int y = 0; y < oh; y++) memset((char *)out + (size_t)y * out_stride, 0, (size_t)ow * 2);
  /* Corners: the pixels around a corner lie on one surface when their
   * ranges agree to a few percent (a slope seen at a steep angle still
   * does; an object in front of another does not). Such a corner is
   * projected once, here, at their mean range, for all of them. */
  const float inv[5] = {0, (float)unit_m, (float)unit_m / 2, (float)unit_m / 3, (float)unit_m / 4};
  for (int j = 0; j <= r->dh; j++) {
    const uint16_t *up = j > 0 ? (const uint16_t *)((const char *)depth + (size_t)(j - 1) * stride) : NULL;
    const uint16_t *dn = j < r->dh ? (const uint16_t *)((const char *)depth + (size_t)j * stride) : NULL;
    struct corner *cr = r->corner + (size_t)j * cw;
    const float *qr = r->q + (size_t)j * cw * 3;
    for (int i = 0; i <= r->dw; i++) {
      unsigned v[4] = {up && i > 0 ? up[i - 1] : 0u, up && i < r->dw ? up[i] : 0u, dn && i > 0 ? dn[i - 1] : 0u,
                       dn && i < r->dw ? dn[i] : 0u};
      unsigned lo = 65535, hi = 0, sum = 0, n = 0;
      for (int a = 0; a < 4; a++)
        if (v[a]) lo = v[a] < lo ? v[a] : lo, hi = v[a] > hi ? v[a] : hi, sum += v[a], n++;
      cr[i].state = CORNER_OWN;
      if (!n || (hi - lo) * 25 > lo) continue;
      const float zc = (float)sum * inv[n], *q = qr + i * 3;
      const float Z = zc * q[2] + tz;
      if (!(Z > 1e-3f)) {
        cr[i].state = CORNER_BEHIND;
        continue;
      }
      const float iz = 1.0f / Z;
      cr[i].u = fx * (zc * q[0] + tx) * iz + cx;
      cr[i].v = fy * (zc * q[1] + ty) * iz + cy;
      cr[i].state = CORNER_SHARED;
    }
  }
  for (int j = 0; j < r->dh; j++) {
    const uint16_t *drow = (const uint16_t *)((const char *)depth + (size_t)j * stride);
    const float *top = r->q + (size_t)j * cw * 3, *bot = top + (size_t)cw * 3;
    const struct corner *ct = r->corner + (size_t)j * cw, *cb = ct + cw;
    for (int i = 0; i < r->dw; i++) {
      if (!drow[i]) continue;
      const float z = (float)(drow[i] * unit_m);
      const float *cs[4] = {top + i * 3, top + i * 3 + 3, bot + i * 3, bot + i * 3 + 3};
      const struct corner *cc[4] = {ct + i, ct + i + 1, cb + i, cb + i + 1};
      float umin = INFINITY, umax = -INFINITY, vmin = INFINITY, vmax = -INFINITY, qz = 0;
      int behind = 0;
      for (int a = 0; a < 4; a++) {
        const float *q = cs[a];
        float u, v;
        qz += q[2];
        if (cc[a]->state == CORNER_SHARED) {
          u = cc[a]->u, v = cc[a]->v;
        } else {
          /* at an edge the corner sits at this pixel's own range */
          const float Z = z * q[2] + tz;
          behind |= cc[a]->state == CORNER_BEHIND || !(Z > 1e-3f);
          const float iz = 1.0f / Z;
          u = fx * (z * q[0] + tx) * iz + cx, v = fy * (z * q[1] + ty) * iz + cy;
        }
        /* plain compares (fminf's NaN rules cost a library call): ranges and
         * rays are finite and Z is checked, so no NaN reaches them */
        umin = u < umin ? u : umin, umax = u > umax ? u : umax;
        vmin = v < vmin ? v : vmin, vmax = v > vmax ? v : vmax;
      }
      if (behind) continue;
      const float zmm = (z * qz * 0.25f + tz) * 1000.0f; /* the pixel's own range, along the colour axis */
      if (!(zmm >= 0.5f && zmm < 65535.5f)) continue;
      const long mm = (long)(zmm + 0.5f);
      /* Off the output, or so large (edge-on, or near the colour camera)
       * that it would smear: nothing to draw. Checked before any float
       * becomes an int. */
      if (!(umax - umin <= r->max_fp && vmax - vmin <= r->max_fp && umax > -1 && umin < ow && vmax > -1 && vmin < oh))
        continue;
      /* The output pixels whose centres lie in the footprint; a footprint
       * smaller than a pixel (output coarser than depth) takes the nearest. */
      int x0 = (int)ceilf(umin), x1 = (int)floorf(umax), y0 = (int)ceilf(vmin), y1 = (int)floorf(vmax);
      if (x0 > x1) x0 = x1 = (int)floorf(0.5f * (umin + umax) + 0.5f);
      if (y0 > y1) y0 = y1 = (int)floorf(0.5f * (vmin + vmax) + 0.5f);
      if (x0 < 0) x0 = 0;
      if (y0 < 0) y0 = 0;
      if (x1 >= ow) x1 = ow - 1;
      if (y1 >= oh) y1 = oh - 1;
      const uint16_t zm = (uint16_t)mm;
      for (int y = y0; y <= y1; y++) {
        uint16_t *o = (uint16_t *)((char *)out + (size_t)y * out_stride);
        for (int x = x0; x <= x1; x++)
          if (!o[x] || zm < o[x]) o[x] = zm;
      }
    }
  }
  long valid = 0;
  for (int y = 0; y < oh; y++) {
    const uint16_t *o = (const uint16_t *)((const char *)out + (size_t)y * out_stride);
    for (int x = 0; x < ow; x++) valid += o[x] != 0;
  }
  return valid;
}
