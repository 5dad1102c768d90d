/*
 * Input encoding: a multiresolution hash grid (Instant-NGP) concatenated with
 * a low-frequency sin/cos encoding of the normalised position.
 *
 * Coarse levels whose grid fits the table are indexed densely (no collisions);
 * finer ones are hashed with x multiplied by 1, so neighbours along x land in
 * neighbouring entries: points processed in grid order (x fastest) share cache
 * lines. Each level is processed for the whole block of points before the
 * next, keeping one level's table (the working set) hot.
 */
#include <math.h>

#include "field_internal.h"

void vlff_encoding_init(struct vlff_encoding *e, const struct vlff_config *cfg) {
  e->levels = cfg->field.hash_levels;
  e->feats = cfg->field.hash_features;
  e->log2_size = cfg->field.hash_log2_size;
  e->freq_bands = cfg->field.freq_bands;
  e->size = 1u << e->log2_size;
  e->dim = e->levels * e->feats + 6 * e->freq_bands;
  for (int i = 0; i < 3; i++) {
    e->box_min[i] = (float)cfg->field.scene_min[i];
    e->box_scale[i] = (float)(1.0 / (cfg->field.scene_max[i] - cfg->field.scene_min[i]));
  }
  double base = cfg->field.base_resolution, fine = cfg->field.finest_resolution;
  double growth = e->levels > 1 ? exp((log(fine) - log(base)) / (e->levels - 1)) : 1.0;
  for (int l = 0; l < e->levels; l++) {
    double r = floor(base * pow(growth, l) + 1e-6);
    if (r < 1) r = 1;
    e->res[l] = (float)r;
    double pts = (r + 1) * (r + 1) * (r + 1);
    e->dense[l] = pts <= (double)e->size;
  }
}

int vlff_encoding_normalise(const struct vlff_encoding *e, const float *x, float *p) {
  int inside = 1;
  for (int i = 0; i < 3; i++) {
    float v = (x[i] - e->box_min[i]) * e->box_scale[i];
    if (!(v >= 0.0f)) { v = 0.0f; inside = 0; }  /* also catches NaN */
    if (v > 1.0f) { v = 1.0f; inside = 0; }
    p[i] = v;
  }
  return inside;
}

/* Corner indices and trilinear weights of point p at level l. */
static inline void corners(const struct vlff_encoding *e, int l, const float *p, uint32_t idx[8], float w[8]) {
  float r = e->res[l];
  uint32_t ri = (uint32_t)r;
  uint32_t i0[3];
  float f[3];
  for (int a = 0; a < 3; a++) {
    float pos = p[a] * r;
    uint32_t c = (uint32_t)pos;
    if (c >= ri) c = ri - 1;
    i0[a] = c;
    f[a] = pos - (float)c;
  }
  uint32_t mask = e->size - 1;
  for (int c = 0; c < 8; c++) {
    uint32_t x = i0[0] + (c & 1), y = i0[1] + ((c >> 1) & 1), z = i0[2] + ((c >> 2) & 1);
    uint32_t h;
    if (e->dense[l])
      h = x + (ri + 1) * (y + (ri + 1) * z);
    else
      h = (x ^ (y * 2654435761u) ^ (z * 805459861u)) & mask;
    idx[c] = h;
    w[c] = ((c & 1) ? f[0] : 1.0f - f[0]) * (((c >> 1) & 1) ? f[1] : 1.0f - f[1]) *
           (((c >> 2) & 1) ? f[2] : 1.0f - f[2]);
  }
}

void vlff_encoding_forward(const struct vlff_encoding *e, const float *table, const float *p, int n,
                           float *out, int ldo) {
  const int F = e->feats;
  for (int l = 0; l < e->levels; l++) {
    const float *t = table + (size_t)l * e->size * F;
    for (int i = 0; i < n; i++) {
      uint32_t idx[8];
      float w[8];
      corners(e, l, p + 3 * i, idx, w);
      float *o = out + (size_t)i * ldo + l * F;
      if (F == 2) {
        float a0 = 0, a1 = 0;
        for (int c = 0; c < 8; c++) {
          const float *v = t + (size_t)idx[c] * 2;
          a0 += w[c] * v[0];
          a1 += w[c] * v[1];
        }
        o[0] = a0;
        o[1] = a1;
      } else {
        for (int f = 0; f < F; f++) o[f] = 0;
        for (int c = 0; c < 8; c++)
          for (int f = 0; f < F; f++) o[f] += w[c] * t[(size_t)idx[c] * F + f];
      }
    }
  }
  const int off = e->levels * F;
  for (int i = 0; i < n; i++) {
    float *o = out + (size_t)i * ldo + off;
    for (int a = 0; a < 3; a++) {
      /* One sin/cos per axis; higher octaves by the double-angle formulas. */
      float x = p[3 * i + a] * (float)M_PI;
      float s = sinf(x), c = cosf(x);
      for (int b = 0; b < e->freq_bands; b++) {
        *o++ = s;
        *o++ = c;
        float s2 = 2.0f * s * c;
        c = 1.0f - 2.0f * s * s;
        s = s2;
      }
    }
  }
}

void vlff_encoding_backward(const struct vlff_encoding *e, const float *p, int n, const float *d, int ld,
                            int l0, int l1, float *grad, uint32_t *stamp, uint32_t step,
                            uint32_t *touched, uint32_t *ntouched) {
  const int F = e->feats;
  for (int l = l0; l < l1; l++) {
    size_t base = (size_t)l * e->size;
    float *g = grad + base * F;
    uint32_t *st = stamp + base;
    uint32_t *tl = touched + base;
    uint32_t nt = ntouched[l];
    for (int i = 0; i < n; i++) {
      const float *di = d + (size_t)i * ld + l * F;
      uint32_t idx[8];
      float w[8];
      corners(e, l, p + 3 * i, idx, w);
      for (int c = 0; c < 8; c++) {
        uint32_t h = idx[c];
        float *gv = g + (size_t)h * F;
        if (st[h] != step) {
          st[h] = step;
          for (int f = 0; f < F; f++) gv[f] = 0;
          tl[nt++] = h;
        }
        for (int f = 0; f < F; f++) gv[f] += w[c] * di[f];
      }
    }
    ntouched[l] = nt;
  }
}
