/*
 * The pose check is the paper's open problem made concrete: a SLAM pose that
 * jumped makes the measured depth disagree with what the map already knows.
 * A median (not a mean) residual keeps a few moving objects or depth holes
 * from rejecting a good frame.
 */
#include "select.h"

#include <math.h>
#include <stdlib.h>

void vlff_kf_selector_init(struct vlff_kf_selector *s, double rate_hz, double min_translation_m,
                           double min_rotation_deg) {
  s->min_interval_s = rate_hz > 0 ? 1.0 / rate_hz : 0;
  s->min_translation_m = min_translation_m;
  s->min_rotation_deg = min_rotation_deg;
  s->have_last = false;
  s->last_t_ns = 0;
  s->credit_s = 0;
}

double vlff_pose_angle(const double a[16], const double b[16]) {
  double tr = 0;
  for (int r = 0; r < 3; r++)
    for (int c = 0; c < 3; c++) tr += a[r * 4 + c] * b[r * 4 + c];
  return acos(fmin(1.0, fmax(-1.0, (tr - 1.0) / 2.0)));
}

void vlff_unproject(const double m[16], double fx, double fy, double cx, double cy, double u, double v, double d,
                    double out[3]) {
  double q[3] = {(u - cx) / fx * d, (v - cy) / fy * d, d};
  for (int a = 0; a < 3; a++) out[a] = m[a * 4] * q[0] + m[a * 4 + 1] * q[1] + m[a * 4 + 2] * q[2] + m[a * 4 + 3];
}

size_t vlff_label_surface(const double c2w[16], double fx, double fy, double cx, double cy, int width, int height,
                          const float *depth, int lw, int lh, float *xyz, uint32_t *pix, uint32_t *holes,
                          size_t *nholes) {
  size_t n = 0, nh = 0;
  for (int y = 0; y < lh; y++)
    for (int x = 0; x < lw; x++) {
      /* The camera pixel under the label pixel's centre. */
      double u = (x + 0.5) * width / lw, w = (y + 0.5) * height / lh;
      float d = depth ? depth[(size_t)(int)w * width + (int)u] : 0;
      uint32_t cell = (uint32_t)(y * lw + x);
      if (!(d > 0 && isfinite(d))) {
        if (holes) holes[nh] = cell;
        nh++;
        continue;
      }
      double hp[3];
      vlff_unproject(c2w, fx, fy, cx, cy, u, w, d, hp);
      for (int a = 0; a < 3; a++) xyz[n * 3 + a] = (float)hp[a];
      pix[n++] = cell;
    }
  if (nholes) *nholes = nh;
  return n;
}

/* The time credit a frame at t_ns would find. */
static double credit_at(const struct vlff_kf_selector *s, long long t_ns) {
  return fmin(1.5 * s->min_interval_s, s->credit_s + (double)(t_ns - s->last_t_ns) * 1e-9);
}

bool vlff_kf_selector_due(const struct vlff_kf_selector *s, long long t_ns) {
  return !s->have_last || (t_ns >= s->last_t_ns && credit_at(s, t_ns) >= s->min_interval_s);
}

bool vlff_kf_selector_offer(struct vlff_kf_selector *s, long long t_ns, const double c2w[16]) {
  double credit = 0;
  if (s->have_last) {
    if (!vlff_kf_selector_due(s, t_ns)) return false;
    if (s->min_translation_m > 0 || s->min_rotation_deg > 0) {
      double dt = 0;
      for (int i = 0; i < 3; i++) dt += pow(c2w[i * 4 + 3] - s->last_c2w[i * 4 + 3], 2);
      bool moved = (s->min_translation_m > 0 && sqrt(dt) >= s->min_translation_m) ||
                   (s->min_rotation_deg > 0 && vlff_pose_angle(c2w, s->last_c2w) * 180.0 / M_PI >= s->min_rotation_deg);
      if (!moved) return false;
    }
    credit = credit_at(s, t_ns) - s->min_interval_s;
  }
  s->have_last = true;
  s->last_t_ns = t_ns;
  s->credit_s = credit;
  for (int i = 0; i < 16; i++) s->last_c2w[i] = c2w[i];
  return true;
}

bool vlff_pose_valid(const double m[16]) {
  for (int i = 0; i < 16; i++)
    if (!isfinite(m[i])) return false;
  if (fabs(m[12]) > 1e-6 || fabs(m[13]) > 1e-6 || fabs(m[14]) > 1e-6 || fabs(m[15] - 1) > 1e-6)
    return false;
  for (int a = 0; a < 3; a++)
    for (int b = 0; b < 3; b++) {
      double dot = 0;
      for (int r = 0; r < 3; r++) dot += m[r * 4 + a] * m[r * 4 + b];
      if (fabs(dot - (a == b)) > 1e-3) return false;
    }
  double det = m[0] * (m[5] * m[10] - m[6] * m[9]) - m[1] * (m[4] * m[10] - m[6] * m[8]) +
               m[2] * (m[4] * m[9] - m[5] * m[8]);
  return fabs(det - 1) < 1e-3;
}

static int cmp_float(const void *a, const void *b) {
  float x = *(const float *)a, y = *(const float *)b;
  return (x > y) - (x < y);
}

float vlff_medianf(float *v, size_t n) {
  qsort(v, n, sizeof v[0], cmp_float);
  return v[n / 2];
}

enum vlff_posecheck vlff_pose_evidence(const float *rendered, const unsigned char *hit, const float *measured,
                                       size_t n, double min_frac, double floor_m, double noise_1m,
                                       struct vlff_pose_evidence *ev) {
  ev->residual_m = ev->residual = ev->inlier_frac = -1;
  ev->usable = 0;
  if (n == 0) return VLFF_POSE_UNKNOWN;
  /* The residuals are sorted in small stack buffers: callers render the
   * check at low resolution, so n stays small. */
  enum { MAXN = 4096 };
  float r[MAXN], z[MAXN];
  size_t m = 0, inliers = 0, step = n > MAXN ? (n + MAXN - 1) / MAXN : 1, considered = 0;
  double f2 = floor_m * floor_m;
  for (size_t i = 0; i < n; i += step) {
    considered++;
    float d = measured[i], e = rendered[i];
    if (!hit[i] || !(d > 0) || !isfinite(d) || !isfinite(e)) continue;
    double sig = noise_1m * d * d;
    r[m] = fabsf(e - d);
    z[m] = (float)(r[m] / sqrt(f2 + sig * sig));
    inliers += z[m] < 2;
    m++;
  }
  ev->usable = m;
  if (m == 0 || (double)m < min_frac * (double)considered) return VLFF_POSE_UNKNOWN;
  ev->residual_m = vlff_medianf(r, m);
  ev->residual = vlff_medianf(z, m);
  ev->inlier_frac = (double)inliers / (double)m;
  return VLFF_POSE_OK;
}

enum vlff_posecheck vlff_pose_verdict(const struct vlff_pose_evidence *ev, double recent_residual,
                                      double recent_inliers) {
  if (ev->residual < 0) return VLFF_POSE_UNKNOWN;
  if (ev->residual <= 1) return VLFF_POSE_OK;
  if (recent_residual <= 0 || recent_inliers <= 0) return ev->residual > 3 ? VLFF_POSE_BAD : VLFF_POSE_OK;
  bool far = ev->residual > 1.6 * recent_residual && ev->inlier_frac < 0.8 * recent_inliers;
  return far ? VLFF_POSE_BAD : VLFF_POSE_OK;
}
