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
  e->active = e->levels;
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

/* Corner indices and trilinear weights of point p at level l, straight-line
 * (the compiler keeps everything in registers). Corner c has x offset c&1,
 * y offset (c>>1)&1, z offset (c>>2)&1. */
static inline __attribute__((always_inline)) void corners(const struct vlff_encoding *e, int l, const float *p,
                                                          uint32_t idx[8], float w[8]) {
  const float r = e->res[l];
  const uint32_t ri = (uint32_t)r;
  uint32_t i0[3];
  float f[3];
  for (int a = 0; a < 3; a++) {
    float pos = p[a] * r;
    uint32_t c = (uint32_t)pos;
    c = c >= ri ? ri - 1 : c;
    i0[a] = c;
    f[a] = pos - (float)c;
  }
  uint32_t x0, x1, y0, y1, z0, z1;
  if (e->dense[l]) {
    uint32_t s1 = ri + 1, s2 = s1 * s1;
    x0 = i0[0];
    x1 = x0 + 1;
    y0 = i0[1] * s1;
    y1 = y0 + s1;
    z0 = i0[2] * s2;
    z1 = z0 + s2;
    idx[0] = x0 + y0 + z0;
    idx[1] = x1 + y0 + z0;
    idx[2] = x0 + y1 + z0;
    idx[3] = x1 + y1 + z0;
    idx[4] = x0 + y0 + z1;
    idx[5] = x1 + y0 + z1;
    idx[6] = x0 + y1 + z1;
    idx[7] = x1 + y1 + z1;
  } else {
    const uint32_t mask = e->size - 1;
    x0 = i0[0];
    x1 = x0 + 1;
    y0 = i0[1] * 2654435761u;
    y1 = y0 + 2654435761u;
    z0 = i0[2] * 805459861u;
    z1 = z0 + 805459861u;
    idx[0] = (x0 ^ y0 ^ z0) & mask;
    idx[1] = (x1 ^ y0 ^ z0) & mask;
    idx[2] = (x0 ^ y1 ^ z0) & mask;
    idx[3] = (x1 ^ y1 ^ z0) & mask;
    idx[4] = (x0 ^ y0 ^ z1) & mask;
    idx[5] = (x1 ^ y0 ^ z1) & mask;
    idx[6] = (x0 ^ y1 ^ z1) & mask;
    idx[7] = (x1 ^ y1 ^ z1) & mask;
  }
  float gx = 1.0f - f[0], gy = 1.0f - f[1], gz = 1.0f - f[2];
  float w00 = gx * gy, w10 = f[0] * gy, w01 = gx * f[1], w11 = f[0] * f[1];
  w[0] = w00 * gz;
  w[1] = w10 * gz;
  w[2] = w01 * gz;
  w[3] = w11 * gz;
  w[4] = w00 * f[2];
  w[5] = w10 * f[2];
  w[6] = w01 * f[2];
  w[7] = w11 * f[2];
}

VLFF_HOT
void vlff_encoding_forward(const struct vlff_encoding *e, const float *table, const float *p, int n,
                           float *out, int ldo) {
  const int F = e->feats;
  for (int l = 0; l < e->levels; l++) {
    const float *t = table + (size_t)l * e->size * F;
    float *ol = out + l * F;
    if (l >= e->active) {
      for (int i = 0; i < n; i++)
        for (int q = 0; q < F; q++) ol[(size_t)i * ldo + q] = 0;
      continue;
    }
    if (F == 2) {
      /* Two passes per block: all corner addresses first (prefetched, so
       * the block's cache misses overlap), then the gathers. */
      enum { B = 32 };
      uint32_t idx[B][8];
      float w[B][8];
      for (int i0 = 0; i0 < n; i0 += B) {
        int m = n - i0 < B ? n - i0 : B;
        for (int i = 0; i < m; i++) {
          corners(e, l, p + 3 * (i0 + i), idx[i], w[i]);
          if (!e->dense[l])
            for (int c = 0; c < 8; c++) __builtin_prefetch(t + (size_t)idx[i][c] * 2);
        }
        for (int i = 0; i < m; i++) {
          float a0 = 0, a1 = 0;
#pragma GCC unroll 8
          for (int c = 0; c < 8; c++) {
            const float *v = t + (size_t)idx[i][c] * 2;
            a0 += w[i][c] * v[0];
            a1 += w[i][c] * v[1];
          }
          ol[(size_t)(i0 + i) * ldo] = a0;
          ol[(size_t)(i0 + i) * ldo + 1] = a1;
        }
      }
    } else {
      for (int i = 0; i < n; i++) {
        uint32_t idx[8];
        float w[8];
        corners(e, l, p + 3 * i, idx, w);
        float *o = ol + (size_t)i * ldo;
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

VLFF_HOT
void vlff_encoding_backward(const struct vlff_encoding *e, const float *p, int n, const float *d, int ld,
                            int level, float *grad, uint64_t *bits) {
  const int F = e->feats, l = level;
  const size_t base = (size_t)l * e->size;
  float *g = grad + base * F;
  uint64_t *bt = bits + base / 64;
  if (F == 2) {
    /* As in the forward: addresses (prefetched) first, then the updates.
     * First touch writes instead of zeroing then adding. */
    enum { B = 32 };
    uint32_t ix[B][8];
    float wt[B][8];
    for (int i0 = 0; i0 < n; i0 += B) {
      int m = n - i0 < B ? n - i0 : B;
      for (int i = 0; i < m; i++) {
        corners(e, l, p + 3 * (i0 + i), ix[i], wt[i]);
        if (!e->dense[l])
          for (int c = 0; c < 8; c++) __builtin_prefetch(g + (size_t)ix[i][c] * 2, 1);
      }
      for (int i = 0; i < m; i++) {
        const float *di = d + (size_t)(i0 + i) * ld;
        const float d0 = di[0], d1 = di[1];
#pragma GCC unroll 8
        for (int c = 0; c < 8; c++) {
          uint32_t h = ix[i][c];
          float *gv = g + (size_t)h * 2;
          uint64_t bit = 1ull << (h & 63), word = bt[h >> 6];
          if (word & bit) {
            gv[0] += wt[i][c] * d0;
            gv[1] += wt[i][c] * d1;
          } else {
            bt[h >> 6] = word | bit;
            gv[0] = wt[i][c] * d0;
            gv[1] = wt[i][c] * d1;
          }
        }
      }
    }
    return;
  }
  for (int i = 0; i < n; i++) {
    const float *di = d + (size_t)i * ld;
    uint32_t idx[8];
    float w[8];
    corners(e, l, p + 3 * i, idx, w);
    for (int c = 0; c < 8; c++) {
      uint32_t h = idx[c];
      float *gv = g + (size_t)h * F;
      uint64_t bit = 1ull << (h & 63);
      if (!(bt[h >> 6] & bit)) {
        bt[h >> 6] |= bit;
        for (int f = 0; f < F; f++) gv[f] = 0;
      }
      for (int f = 0; f < F; f++) gv[f] += w[c] * di[f];
    }
  }
}
