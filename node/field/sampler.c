/*
 * Where along a ray the network is evaluated.
 *  - depth:    a band around the measured depth (most samples, where the
 *              surface and its feature are) plus stratified free space in
 *              front of it (so empty space learns zero density);
 *  - occupied: rays without depth and rendering march the occupancy grid and
 *              spread the samples over occupied cells only;
 *  - uniform:  the reference's stratified samples over [near, far].
 * Ray parameters t are camera-z depths (directions have unit camera z), and
 * each sample gets the spacing dt of its stratum as its interval length.
 */
#include <math.h>

#include "field_internal.h"

int vlff_ray_box(const float *o, const float *d, const float *bmin, const float *bmax, float *t0, float *t1) {
  float lo = -INFINITY, hi = INFINITY;
  for (int a = 0; a < 3; a++) {
    if (fabsf(d[a]) < 1e-12f) {
      if (o[a] < bmin[a] || o[a] > bmax[a]) return 0;
      continue;
    }
    float inv = 1.0f / d[a];
    float ta = (bmin[a] - o[a]) * inv, tb = (bmax[a] - o[a]) * inv;
    if (ta > tb) {
      float x = ta;
      ta = tb;
      tb = x;
    }
    if (ta > lo) lo = ta;
    if (tb < hi) hi = tb;
  }
  if (!(hi > lo) || hi <= 0) return 0;
  *t0 = lo;
  *t1 = hi;
  return 1;
}

static float jitter(uint64_t *rng) { return rng ? vlff_rng_uniform(rng) : 0.5f; }

int vlff_sample_uniform(float t0, float t1, int ns, uint64_t *rng, float *t, float *dt) {
  float step = (t1 - t0) / (float)ns;
  for (int i = 0; i < ns; i++) t[i] = t0 + ((float)i + jitter(rng)) * step;
  *dt = step;
  return ns;
}

int vlff_sample_depth(float depth, float noise_1m, float t0, float t1, int ns, uint64_t *rng, float *t, float *dt) {
  /* The band (vlff_depth_band) is at least 3 sigma of the sensor's noise:
   * narrower than the noise, the band of a ray whose measurement fell in
   * front of the surface holds nothing, and the depth loss grows density
   * there: the surface drifted toward the camera by about the noise. */
  float band = vlff_depth_band(depth, noise_1m);
  float b0 = fmaxf(depth - band, t0), b1 = fminf(depth + band, t1);
  if (!(b1 > b0)) return vlff_sample_uniform(t0, t1, ns, rng, t, dt);
  int nfree = b0 - t0 > 1e-3f ? ns / 4 : 0;
  int nband = ns - nfree;
  int k = 0;
  if (nfree) {
    float step = (b0 - t0) / (float)nfree;
    for (int i = 0; i < nfree; i++) {
      t[k] = t0 + ((float)i + jitter(rng)) * step;
      dt[k++] = step;
    }
  }
  float step = (b1 - b0) / (float)nband;
  for (int i = 0; i < nband; i++) {
    t[k] = b0 + ((float)i + jitter(rng)) * step;
    dt[k++] = step;
  }
  return k;
}

#define MAX_SEGS 64

int vlff_sample_occupied(const struct vlff_occupancy *g, const float *o, const float *d, float t0, float t1,
                         int ns, uint64_t *rng, float *t, float *dt) {
  float cmin = fminf(g->cell[0], fminf(g->cell[1], g->cell[2]));
  float dn = sqrtf(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  float step = 0.5f * cmin / dn;
  float seg0[MAX_SEGS], seg1[MAX_SEGS];
  int nseg = 0, open = 0;
  float total = 0.0f;
  const int *dims = g->dims;
  /* The march in cell units: no division per step (it was most of the
   * sampler's cost on long rays through an empty room). */
  float x0[3], dx[3];
  for (int a = 0; a < 3; a++) {
    float inv = 1.0f / g->cell[a];
    x0[a] = (o[a] - g->box_min[a]) * inv;
    dx[a] = d[a] * inv;
  }
  const float top[3] = {(float)dims[0], (float)dims[1], (float)dims[2]};
  for (float tt = t0; tt < t1 && nseg < MAX_SEGS; tt += step) {
    float tm = fminf(tt + 0.5f * step, t1);
    int c[3], ok = 1;
    for (int a = 0; a < 3; a++) {
      float x = x0[a] + tm * dx[a];
      /* Clamped as a float first: the cast of an out-of-range float is undefined. */
      c[a] = x >= top[a] ? dims[a] - 1 : x > 0.0f ? (int)x : 0;
    }
    ok = g->occ[((size_t)c[2] * dims[1] + c[1]) * dims[0] + c[0]];
    float te = fminf(tt + step, t1);
    if (ok) {
      if (open) {
        seg1[nseg - 1] = te;
      } else {
        seg0[nseg] = tt;
        seg1[nseg] = te;
        nseg++;
        open = 1;
      }
    } else {
      open = 0;
    }
  }
  for (int i = 0; i < nseg; i++) total += seg1[i] - seg0[i];
  if (total <= 0.0f) return 0;
  /* Samples are spaced at least a sixth of a cell apart (so a ray stops a few
   * samples past its surface, and rendering marches front to back), and
   * spread wider only when the occupied length needs more than ns. */
  float q = fmaxf(total / (float)ns, cmin / (6.0f * dn));
  ns = (int)ceilf(total / q - 1e-3f);
  if (ns < 1) ns = 1;
  *dt = q;
  int s = 0;
  float acc = 0.0f;
  for (int i = 0; i < ns; i++) {
    float u = ((float)i + jitter(rng)) * q;
    while (s < nseg - 1 && u >= acc + (seg1[s] - seg0[s])) {
      acc += seg1[s] - seg0[s];
      s++;
    }
    float v = seg0[s] + (u - acc);
    t[i] = fminf(v, seg1[s]);
  }
  return ns;
}

/* Real SH basis (the constants of the standard table), degree <= 4. */
void vlff_sh_encode(const float *d, int deg, float *out) {
  float x = d[0], y = d[1], z = d[2];
  float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  out[0] = 0.28209479177387814f;
  if (deg <= 1) return;
  out[1] = -0.48860251190291987f * y;
  out[2] = 0.48860251190291987f * z;
  out[3] = -0.48860251190291987f * x;
  if (deg <= 2) return;
  out[4] = 1.0925484305920792f * xy;
  out[5] = -1.0925484305920792f * yz;
  out[6] = 0.94617469575755997f * zz - 0.31539156525251999f;
  out[7] = -1.0925484305920792f * xz;
  out[8] = 0.54627421529603959f * (xx - yy);
  if (deg <= 3) return;
  out[9] = 0.59004358992664352f * y * (-3.0f * xx + yy);
  out[10] = 2.8906114426405538f * xy * z;
  out[11] = 0.45704579946446572f * y * (1.0f - 5.0f * zz);
  out[12] = 0.3731763325901154f * z * (5.0f * zz - 3.0f);
  out[13] = 0.45704579946446572f * x * (1.0f - 5.0f * zz);
  out[14] = 1.4453057213202769f * z * (xx - yy);
  out[15] = 0.59004358992664352f * x * (-xx + 3.0f * yy);
}
