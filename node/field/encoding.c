/*
 * Input encoding: a multiresolution hash grid (Instant-NGP) concatenated with
 * a low-frequency sin/cos encoding of the normalised position.
 *
 * Coarse levels whose grid fits the table are indexed densely (no collisions);
 * finer ones are hashed with x multiplied by 1, so neighbours along x land in
 * neighbouring entries: points processed in grid order (x fastest) share cache
 * lines. Each level is processed for the whole block of points before the
 * next, keeping one level's table (the working set) hot.
 *
 * One level on one thread is bound by instructions (a level whose table
 * sits in L1 costs nearly as much per point as a hashed one); in a
 * full two-thread query the finer hashed levels wait on cache misses, and
 * prefetching every corner of a group beats fewer, shallower or L2-only
 * prefetches (bench field_isa). On CPUs with
 * AVX-512 it runs 16 points per vector and fetches each
 * corner's two features as one 64-bit lane (scalar loads and inserts, which
 * beat the gather instruction), well under the scalar loop's time per point
 * and level; its arithmetic is the scalar loop's, in
 * the same order with fused multiply-adds, so the outputs are bit-identical
 * to the scalar loop's AVX-512 clone (the default GCC build) and equal to
 * float rounding otherwise (tested). CPUs with AVX2 but not AVX-512 run the
 * same kernels 8 points per vector, with the same bits. Elsewhere (ARM,
 * older x86, VLFF_GEMM=generic) the portable loop runs.
 */
#include <math.h>
#include <string.h>

#include "field_internal.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define VLFF_ENC_V4 1
#include <immintrin.h>
#else
#define VLFF_ENC_V4 0
#endif

void vlff_encoding_init(struct vlff_encoding *e, const struct vlff_cfg_field *cfg) {
  e->levels = cfg->hash_levels;
  e->active = e->levels;
  e->feats = cfg->hash_features;
  e->log2_size = cfg->hash_log2_size;
  e->freq_bands = cfg->freq_bands;
  e->size = 1u << e->log2_size;
  e->dim = e->levels * e->feats + 6 * e->freq_bands;
  e->grow = cfg->grow;
  double first = 0; /* the first box's longest side */
  for (int i = 0; i < 3; i++) {
    e->freq_ext[i] = e->box_ext[i] = cfg->scene_max[i] - cfg->scene_min[i];
    first = fmax(first, e->box_ext[i]);
  }
  /* A growing field's levels count their cells over the world's side: that
   * many times the first box's, so each keeps its cell size in metres. */
  double world = 1.0;
  for (int i = 0; i < 3; i++) {
    if (e->grow) {
      double half = cfg->world_limit_m + first, c = 0.5 * (cfg->scene_min[i] + cfg->scene_max[i]);
      e->corner[i] = c - half;
      e->box_min[i] = (float)c; /* the origin: the first box's centre */
      e->box_ext[i] = 2 * half;
      world = 2 * half / first;
    } else {
      e->corner[i] = 0;
      e->box_min[i] = (float)cfg->scene_min[i];
    }
  }
  double base = cfg->base_resolution, fine = cfg->finest_resolution;
  double growth = e->levels > 1 ? exp((log(fine) - log(base)) / (e->levels - 1)) : 1.0;
  for (int l = 0; l < e->levels; l++) {
    double r = floor(base * pow(growth, l) * world + 1e-6);
    if (r < 1) r = 1;
    e->res[l] = (float)r;
    double pts = (r + 1) * (r + 1) * (r + 1);
    /* A dense level would have to cover the whole world. */
    e->dense[l] = !e->grow && pts <= (double)e->size;
  }
  vlff_encoding_set_cells(e, 1);
  vlff_encoding_set_inside(e, cfg->scene_min, cfg->scene_max);
  /* The gather kernel follows the GEMM's choice, so VLFF_GEMM=generic
   * makes the whole field portable code. */
  e->simd = VLFF_ENC_V4 && e->feats == 2 ? vlff_gemm_isa_level() : VLFF_ISA_PORTABLE;
}

/* Where the origin (box_min) lies in the corner frame: the clamp, the
 * frequency part's phase and each level's whole and fractional cells
 * (field_internal.h). Fixed: the origin is the corner. */
static void place_origin(struct vlff_encoding *e) {
  for (int i = 0; i < 3; i++) {
    /* the origin's position in the corner frame, in double */
    const double s = e->cubic ? fmax(e->box_ext[0], fmax(e->box_ext[1], e->box_ext[2])) : e->box_ext[i];
    const double o = e->grow ? ((double)e->box_min[i] - e->corner[i]) / s : 0.0;
    e->p_lo[i] = e->grow ? (float)-o : 0.0f;
    e->p_hi[i] = e->grow ? (float)(e->box_ext[i] / s - o) : e->p_top[i];
    /* (modulo 2 pi: every octave's angle is a multiple of the first's) */
    e->freq_phase[i] = (float)fmod(o * (M_PI * s / e->freq_ext[i]), 2 * M_PI);
    for (int l = 0; l < e->levels; l++) {
      double a = o * e->res[l];
      e->kofs[l][i] = (int32_t)floor(a);
      e->shift[l][i] = (float)(a - floor(a));
    }
  }
}

/* Cubic cells: one scale for every axis, the longest spanning [0, 1], so
 * that a level's cells are as long in z as in x. Scaled per axis, the
 * building's 24.4 x 10 x 3 m box had cells 8 times finer in z than in x:
 * eight times the entries per wall at the finer levels, for detail no
 * sensor measures, and their collisions. The frequency part keeps its
 * period: each axis of the box spans half of its lowest octave. */
void vlff_encoding_set_cells(struct vlff_encoding *e, int cubic) {
  double m = fmax(e->box_ext[0], fmax(e->box_ext[1], e->box_ext[2]));
  e->cubic = cubic;
  for (int i = 0; i < 3; i++) {
    double s = cubic ? m : e->box_ext[i];
    e->box_scale[i] = (float)(1.0 / s);
    e->p_top[i] = (float)(e->box_ext[i] / s);
    e->freq_scale[i] = (float)(M_PI * s / e->freq_ext[i]);
    if (!e->grow) e->in_lo[i] = 0.0f, e->in_hi[i] = e->p_top[i];
  }
  place_origin(e);
}

void vlff_encoding_set_origin(struct vlff_encoding *e, const double o[3]) {
  if (!e->grow) return;
  for (int i = 0; i < 3; i++) e->box_min[i] = (float)o[i];
  place_origin(e);
}

void vlff_encoding_set_inside(struct vlff_encoding *e, const double lo[3], const double hi[3]) {
  for (int i = 0; i < 3; i++) {
    if (e->grow) {
      e->in_lo[i] = (float)((lo[i] - e->box_min[i]) * e->box_scale[i]);
      e->in_hi[i] = (float)((hi[i] - e->box_min[i]) * e->box_scale[i]);
    } else { /* exactly the clamp's bounds: the fixed box's results are unchanged */
      e->in_lo[i] = 0.0f;
      e->in_hi[i] = e->p_top[i];
    }
  }
}

int vlff_encoding_normalise(const struct vlff_encoding *e, const float *x, float *p) {
  int inside = 1;
  for (int i = 0; i < 3; i++) {
    float v = (x[i] - e->box_min[i]) * e->box_scale[i];
    if (!(v >= e->p_lo[i])) { v = e->p_lo[i]; inside = 0; }  /* also catches NaN */
    if (v > e->p_hi[i]) { v = e->p_hi[i]; inside = 0; }
    if (v < e->in_lo[i] || v > e->in_hi[i]) inside = 0;
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
  const int32_t ri = (int32_t)r;
  uint32_t i0[3];
  float f[3];
  for (int a = 0; a < 3; a++) {
    const int32_t ko = e->kofs[l][a];
    /* one rounding, as the vector kernels' fused multiply-add (fixed: + 0) */
    float pos = fmaf(p[a], r, e->shift[l][a]);
    int32_t c = (int32_t)floorf(pos) + ko;
    c = c < 0 ? 0 : c >= ri ? ri - 1 : c;
    i0[a] = (uint32_t)c;
    f[a] = pos - (float)(c - ko);
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

#if VLFF_ENC_V4
/* Points per coordinate block (arrays on the stack), vectors per prefetch
 * group: 8 (128 points' corners requested before the first is loaded), the
 * smallest group that keeps the hashed levels' misses overlapped
 * (docs/field.md). */
enum { VLFF_ENC_V4_BLOCK = 256, V4_GROUP = 8 };
#define V4_TARGET __attribute__((target("avx512f,avx512vl,avx512bw,avx512dq,avx2,fma")))

/* A level's cell along one axis from pos = p * r + shift: floor(pos) +
 * kofs, clamped to [0, r - 1] as corners() clamps it. */
V4_TARGET static inline __m512i cell_v4(__m512 pos, __m512i ko, __m512i zero, __m512i rim1) {
  __m512i c = _mm512_cvttps_epi32(_mm512_roundscale_ps(pos, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC));
  return _mm512_min_epi32(_mm512_max_epi32(_mm512_add_epi32(c, ko), zero), rim1);
}

/* Corner indices and trilinear weights of up to V4_GROUP x 16 points from
 * g0 (of n) at level l, 16 points per vector, with the scalar corners()'s
 * arithmetic; lanes past n are computed from zeros (valid indices) and
 * never used. Returns the vectors filled. */
V4_TARGET static int corners_v4(const struct vlff_encoding *e, int l, const float *px, const float *py,
                                const float *pz, int g0, int n, uint32_t *ib, float *wb) {
  const float r = e->res[l];
  const int dense = e->dense[l];
  const uint32_t s1 = (uint32_t)r + 1, s2 = s1 * s1;
  const __m512 vr = _mm512_set1_ps(r), fone = _mm512_set1_ps(1.0f);
  const __m512 shx = _mm512_set1_ps(e->shift[l][0]), shy = _mm512_set1_ps(e->shift[l][1]),
               shz = _mm512_set1_ps(e->shift[l][2]);
  const __m512i rim1 = _mm512_set1_epi32((int)r - 1), one = _mm512_set1_epi32(1), zero = _mm512_setzero_si512();
  const __m512i kx = _mm512_set1_epi32(e->kofs[l][0]), ky = _mm512_set1_epi32(e->kofs[l][1]),
                kz = _mm512_set1_epi32(e->kofs[l][2]);
  const __m512i my = _mm512_set1_epi32(dense ? (int)s1 : (int)2654435761u);
  const __m512i mz = _mm512_set1_epi32(dense ? (int)s2 : (int)805459861u);
  const __m512i mask = _mm512_set1_epi32((int)(e->size - 1));
  int nv = (n - g0 + 15) / 16;
  nv = nv > V4_GROUP ? V4_GROUP : nv;
  for (int v = 0; v < nv; v++) {
    int i0 = g0 + 16 * v, m = n - i0 < 16 ? n - i0 : 16;
    __mmask16 k = (__mmask16)((1u << m) - 1);
    /* p * r + shift (fixed: + 0, exactly p * r); floor, then kofs on */
    __m512 x = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(k, px + i0), vr, shx);
    __m512 y = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(k, py + i0), vr, shy);
    __m512 z = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(k, pz + i0), vr, shz);
    __m512i cx = cell_v4(x, kx, zero, rim1), cy = cell_v4(y, ky, zero, rim1), cz = cell_v4(z, kz, zero, rim1);
    __m512 fx = _mm512_sub_ps(x, _mm512_cvtepi32_ps(_mm512_sub_epi32(cx, kx)));
    __m512 fy = _mm512_sub_ps(y, _mm512_cvtepi32_ps(_mm512_sub_epi32(cy, ky)));
    __m512 fz = _mm512_sub_ps(z, _mm512_cvtepi32_ps(_mm512_sub_epi32(cz, kz)));
    __m512i x0 = cx, x1 = _mm512_add_epi32(cx, one);
    __m512i y0 = _mm512_mullo_epi32(cy, my), y1 = _mm512_add_epi32(y0, my);
    __m512i z0 = _mm512_mullo_epi32(cz, mz), z1 = _mm512_add_epi32(z0, mz);
    __m512i c[8];
    if (dense) {
      __m512i a00 = _mm512_add_epi32(y0, z0), a10 = _mm512_add_epi32(y1, z0);
      __m512i a01 = _mm512_add_epi32(y0, z1), a11 = _mm512_add_epi32(y1, z1);
      c[0] = _mm512_add_epi32(x0, a00), c[1] = _mm512_add_epi32(x1, a00);
      c[2] = _mm512_add_epi32(x0, a10), c[3] = _mm512_add_epi32(x1, a10);
      c[4] = _mm512_add_epi32(x0, a01), c[5] = _mm512_add_epi32(x1, a01);
      c[6] = _mm512_add_epi32(x0, a11), c[7] = _mm512_add_epi32(x1, a11);
    } else {
      __m512i a00 = _mm512_xor_si512(y0, z0), a10 = _mm512_xor_si512(y1, z0);
      __m512i a01 = _mm512_xor_si512(y0, z1), a11 = _mm512_xor_si512(y1, z1);
      c[0] = _mm512_and_si512(_mm512_xor_si512(x0, a00), mask), c[1] = _mm512_and_si512(_mm512_xor_si512(x1, a00), mask);
      c[2] = _mm512_and_si512(_mm512_xor_si512(x0, a10), mask), c[3] = _mm512_and_si512(_mm512_xor_si512(x1, a10), mask);
      c[4] = _mm512_and_si512(_mm512_xor_si512(x0, a01), mask), c[5] = _mm512_and_si512(_mm512_xor_si512(x1, a01), mask);
      c[6] = _mm512_and_si512(_mm512_xor_si512(x0, a11), mask), c[7] = _mm512_and_si512(_mm512_xor_si512(x1, a11), mask);
    }
    __m512 gx = _mm512_sub_ps(fone, fx), gy = _mm512_sub_ps(fone, fy), gz = _mm512_sub_ps(fone, fz);
    __m512 w00 = _mm512_mul_ps(gx, gy), w10 = _mm512_mul_ps(fx, gy);
    __m512 w01 = _mm512_mul_ps(gx, fy), w11 = _mm512_mul_ps(fx, fy);
    _mm512_store_ps(wb + (v * 8 + 0) * 16, _mm512_mul_ps(w00, gz));
    _mm512_store_ps(wb + (v * 8 + 1) * 16, _mm512_mul_ps(w10, gz));
    _mm512_store_ps(wb + (v * 8 + 2) * 16, _mm512_mul_ps(w01, gz));
    _mm512_store_ps(wb + (v * 8 + 3) * 16, _mm512_mul_ps(w11, gz));
    _mm512_store_ps(wb + (v * 8 + 4) * 16, _mm512_mul_ps(w00, fz));
    _mm512_store_ps(wb + (v * 8 + 5) * 16, _mm512_mul_ps(w10, fz));
    _mm512_store_ps(wb + (v * 8 + 6) * 16, _mm512_mul_ps(w01, fz));
    _mm512_store_ps(wb + (v * 8 + 7) * 16, _mm512_mul_ps(w11, fz));
    for (int q = 0; q < 8; q++) _mm512_store_si512(ib + (v * 8 + q) * 16, c[q]);
  }
  return nv;
}

/* Eight 64-bit table entries (a corner's feature pair each) into one
 * vector by scalar loads and inserts: an 8-lane vpgatherqq is slow even
 * from L1, and the loads and inserts cost a fraction of it. */
static inline __attribute__((always_inline)) long long pair_bits(const float *t, uint32_t i) {
  long long v;
  memcpy(&v, t + (size_t)i * 2, sizeof(v)); /* one 8-byte load; no aliasing of float as integer */
  return v;
}
V4_TARGET static inline __m512i load8_pairs(const float *t, const uint32_t *ix) {
  __m128i a = _mm_insert_epi64(_mm_cvtsi64_si128(pair_bits(t, ix[0])), pair_bits(t, ix[1]), 1);
  __m128i b = _mm_insert_epi64(_mm_cvtsi64_si128(pair_bits(t, ix[2])), pair_bits(t, ix[3]), 1);
  __m128i c = _mm_insert_epi64(_mm_cvtsi64_si128(pair_bits(t, ix[4])), pair_bits(t, ix[5]), 1);
  __m128i d = _mm_insert_epi64(_mm_cvtsi64_si128(pair_bits(t, ix[6])), pair_bits(t, ix[7]), 1);
  __m256i ab = _mm256_inserti128_si256(_mm256_castsi128_si256(a), b, 1);
  __m256i cd = _mm256_inserti128_si256(_mm256_castsi128_si256(c), d, 1);
  return _mm512_inserti64x4(_mm512_castsi256_si512(ab), cd, 1);
}

/* Shared by both ISAs' kernels below: a group's corner indices and weights
 * are laid out [vector][corner][lane], GROUP_POINTS points a group. */
enum { GROUP_POINTS = 16 * V4_GROUP };

/* Requests every corner of a group's nv vectors of `lanes` points (lanes
 * past n hold valid indices), so that the group's misses overlap. */
#define PREFETCH_CORNERS(base, ib, count, rw)                                                   \
  for (int k_ = 0; k_ < (count); k_++) __builtin_prefetch((base) + (size_t)(ib)[k_] * 2, rw)

/* The accumulated pairs of a vector's m points into rows of the output. */
static inline __attribute__((always_inline)) void store_pairs(const float *pair, int m, float *ol, int ldo) {
  for (int i = 0; i < m; i++) memcpy(ol + (size_t)i * ldo, pair + 2 * i, 2 * sizeof(float));
}

/* The scalar loop's scatter in its order (point by point, c = 0..7) for
 * gm points of a group. */
static inline __attribute__((always_inline)) void scatter_group(const uint32_t *ib, const float *wb, int lanes,
                                                                int gm, const float *d, int ld, float *g,
                                                                uint8_t *tb, uint8_t stamp) {
  for (int j = 0; j < gm; j++) {
    const float *dj = d + (size_t)j * ld;
    const float d0 = dj[0], d1 = dj[1];
    const int base = (j / lanes) * 8 * lanes + j % lanes;
    for (int c = 0; c < 8; c++) {
      uint32_t h = ib[base + c * lanes];
      float wt = wb[base + c * lanes], *gv = g + (size_t)h * 2;
      tb[h] = stamp;
      gv[0] += wt * d0;
      gv[1] += wt * d1;
    }
  }
}

/* One level for n <= VLFF_ENC_V4_BLOCK points given as coordinate arrays:
 * a group's corners (prefetched on hashed levels, so the group's misses
 * overlap), then each corner's feature pair as one 64-bit lane (lanes past
 * n load the valid entry that zero coordinates give, and are not stored),
 * accumulated in the scalar loop's order (c = 0..7, fused multiply-add), so
 * the result is bit for bit that of the scalar loop's AVX-512 clone. */
V4_TARGET static void level_v4(const struct vlff_encoding *e, int l, const float *t, const float *px,
                               const float *py, const float *pz, int n, float *ol, int ldo) {
  /* Lane i of a pair vector holds point i's two features: weights repeat. */
  const __m512i dup_lo = _mm512_set_epi32(7, 7, 6, 6, 5, 5, 4, 4, 3, 3, 2, 2, 1, 1, 0, 0);
  const __m512i dup_hi = _mm512_set_epi32(15, 15, 14, 14, 13, 13, 12, 12, 11, 11, 10, 10, 9, 9, 8, 8);
  uint32_t ib[GROUP_POINTS * 8] __attribute__((aligned(64)));
  float wb[GROUP_POINTS * 8] __attribute__((aligned(64)));
  for (int g0 = 0; g0 < n; g0 += GROUP_POINTS) {
    int nv = corners_v4(e, l, px, py, pz, g0, n, ib, wb);
    if (!e->dense[l]) PREFETCH_CORNERS(t, ib, nv * 8 * 16, 0);
    for (int v = 0; v < nv; v++) {
      int i0 = g0 + 16 * v, m = n - i0 < 16 ? n - i0 : 16;
      __m512 alo = _mm512_setzero_ps(), ahi = _mm512_setzero_ps();
      for (int q = 0; q < 8; q++) {
        const uint32_t *iq = ib + (v * 8 + q) * 16;
        __m512 w = _mm512_load_ps(wb + (v * 8 + q) * 16);
        __m512i glo = load8_pairs(t, iq);
        __m512i ghi = load8_pairs(t, iq + 8);
        alo = _mm512_fmadd_ps(_mm512_permutexvar_ps(dup_lo, w), _mm512_castsi512_ps(glo), alo);
        ahi = _mm512_fmadd_ps(_mm512_permutexvar_ps(dup_hi, w), _mm512_castsi512_ps(ghi), ahi);
      }
      float pair[32] __attribute__((aligned(64)));
      _mm512_store_ps(pair, alo);
      _mm512_store_ps(pair + 16, ahi);
      store_pairs(pair, m, ol + (size_t)i0 * ldo, ldo);
    }
  }
}

#define V3_TARGET __attribute__((target("avx2,fma")))
/* cell_v4's arithmetic, 8 lanes */
V3_TARGET static inline __m256i cell_v3(__m256 pos, __m256i ko, __m256i zero, __m256i rim1) {
  __m256i c = _mm256_cvttps_epi32(_mm256_floor_ps(pos));
  return _mm256_min_epi32(_mm256_max_epi32(_mm256_add_epi32(c, ko), zero), rim1);
}

/* The same for CPUs with AVX2 but not AVX-512 (most x86 robot computers),
 * 8 points per vector, the same arithmetic in the same order: outputs and
 * gradients are the AVX-512 kernels' bit for bit. Without them such a CPU
 * runs the portable loops, much slower (bench field_isa measures it). */
V3_TARGET static int corners_v3(const struct vlff_encoding *e, int l, const float *px, const float *py,
                                const float *pz, int g0, int n, uint32_t *ib, float *wb) {
  const float r = e->res[l];
  const int dense = e->dense[l];
  const uint32_t s1 = (uint32_t)r + 1, s2 = s1 * s1;
  const __m256 vr = _mm256_set1_ps(r), fone = _mm256_set1_ps(1.0f);
  const __m256 shx = _mm256_set1_ps(e->shift[l][0]), shy = _mm256_set1_ps(e->shift[l][1]),
               shz = _mm256_set1_ps(e->shift[l][2]);
  const __m256i rim1 = _mm256_set1_epi32((int)r - 1), one = _mm256_set1_epi32(1), zero = _mm256_setzero_si256();
  const __m256i kx = _mm256_set1_epi32(e->kofs[l][0]), ky = _mm256_set1_epi32(e->kofs[l][1]),
                kz = _mm256_set1_epi32(e->kofs[l][2]);
  const __m256i my = _mm256_set1_epi32(dense ? (int)s1 : (int)2654435761u);
  const __m256i mz = _mm256_set1_epi32(dense ? (int)s2 : (int)805459861u);
  const __m256i mask = _mm256_set1_epi32((int)(e->size - 1));
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  int nv = (n - g0 + 7) / 8;
  nv = nv > 2 * V4_GROUP ? 2 * V4_GROUP : nv;
  for (int v = 0; v < nv; v++) {
    int i0 = g0 + 8 * v, m = n - i0 < 8 ? n - i0 : 8;
    __m256i k = _mm256_cmpgt_epi32(_mm256_set1_epi32(m), lane);
    __m256 x = _mm256_fmadd_ps(_mm256_maskload_ps(px + i0, k), vr, shx);
    __m256 y = _mm256_fmadd_ps(_mm256_maskload_ps(py + i0, k), vr, shy);
    __m256 z = _mm256_fmadd_ps(_mm256_maskload_ps(pz + i0, k), vr, shz);
    __m256i cx = cell_v3(x, kx, zero, rim1), cy = cell_v3(y, ky, zero, rim1), cz = cell_v3(z, kz, zero, rim1);
    __m256 fx = _mm256_sub_ps(x, _mm256_cvtepi32_ps(_mm256_sub_epi32(cx, kx)));
    __m256 fy = _mm256_sub_ps(y, _mm256_cvtepi32_ps(_mm256_sub_epi32(cy, ky)));
    __m256 fz = _mm256_sub_ps(z, _mm256_cvtepi32_ps(_mm256_sub_epi32(cz, kz)));
    __m256i x0 = cx, x1 = _mm256_add_epi32(cx, one);
    __m256i y0 = _mm256_mullo_epi32(cy, my), y1 = _mm256_add_epi32(y0, my);
    __m256i z0 = _mm256_mullo_epi32(cz, mz), z1 = _mm256_add_epi32(z0, mz);
    __m256i yz[4], c[8];
    if (dense) {
      yz[0] = _mm256_add_epi32(y0, z0), yz[1] = _mm256_add_epi32(y1, z0);
      yz[2] = _mm256_add_epi32(y0, z1), yz[3] = _mm256_add_epi32(y1, z1);
      for (int q = 0; q < 4; q++) c[2 * q] = _mm256_add_epi32(x0, yz[q]), c[2 * q + 1] = _mm256_add_epi32(x1, yz[q]);
    } else {
      yz[0] = _mm256_xor_si256(y0, z0), yz[1] = _mm256_xor_si256(y1, z0);
      yz[2] = _mm256_xor_si256(y0, z1), yz[3] = _mm256_xor_si256(y1, z1);
      for (int q = 0; q < 4; q++) {
        c[2 * q] = _mm256_and_si256(_mm256_xor_si256(x0, yz[q]), mask);
        c[2 * q + 1] = _mm256_and_si256(_mm256_xor_si256(x1, yz[q]), mask);
      }
    }
    __m256 gx = _mm256_sub_ps(fone, fx), gy = _mm256_sub_ps(fone, fy), gz = _mm256_sub_ps(fone, fz);
    __m256 wxy[4] = {_mm256_mul_ps(gx, gy), _mm256_mul_ps(fx, gy), _mm256_mul_ps(gx, fy), _mm256_mul_ps(fx, fy)};
    for (int q = 0; q < 4; q++) {
      _mm256_store_ps(wb + (v * 8 + q) * 8, _mm256_mul_ps(wxy[q], gz));
      _mm256_store_ps(wb + (v * 8 + 4 + q) * 8, _mm256_mul_ps(wxy[q], fz));
    }
    for (int q = 0; q < 8; q++) _mm256_store_si256((__m256i *)(ib + (v * 8 + q) * 8), c[q]);
  }
  return nv;
}

V3_TARGET static inline __m256i load4_pairs(const float *t, const uint32_t *ix) {
  return _mm256_set_epi64x(pair_bits(t, ix[3]), pair_bits(t, ix[2]), pair_bits(t, ix[1]), pair_bits(t, ix[0]));
}

V3_TARGET static void level_v3(const struct vlff_encoding *e, int l, const float *t, const float *px,
                               const float *py, const float *pz, int n, float *ol, int ldo) {
  const __m256i dup_lo = _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3), dup_hi = _mm256_setr_epi32(4, 4, 5, 5, 6, 6, 7, 7);
  uint32_t ib[GROUP_POINTS * 8] __attribute__((aligned(64)));
  float wb[GROUP_POINTS * 8] __attribute__((aligned(64)));
  for (int g0 = 0; g0 < n; g0 += GROUP_POINTS) {
    int nv = corners_v3(e, l, px, py, pz, g0, n, ib, wb);
    if (!e->dense[l]) PREFETCH_CORNERS(t, ib, nv * 8 * 8, 0);
    for (int v = 0; v < nv; v++) {
      int i0 = g0 + 8 * v, m = n - i0 < 8 ? n - i0 : 8;
      __m256 alo = _mm256_setzero_ps(), ahi = _mm256_setzero_ps();
      for (int q = 0; q < 8; q++) {
        const uint32_t *iq = ib + (v * 8 + q) * 8;
        __m256 w = _mm256_load_ps(wb + (v * 8 + q) * 8);
        alo = _mm256_fmadd_ps(_mm256_permutevar8x32_ps(w, dup_lo), _mm256_castsi256_ps(load4_pairs(t, iq)), alo);
        ahi = _mm256_fmadd_ps(_mm256_permutevar8x32_ps(w, dup_hi), _mm256_castsi256_ps(load4_pairs(t, iq + 4)), ahi);
      }
      float pair[16] __attribute__((aligned(32)));
      _mm256_store_ps(pair, alo);
      _mm256_store_ps(pair + 8, ahi);
      store_pairs(pair, m, ol + (size_t)i0 * ldo, ldo);
    }
  }
}

/* Coordinate arrays of points [b0, b0+m) of p[n][3]. */
static void split_xyz(const float *p, int b0, int m, float *px, float *py, float *pz) {
  for (int i = 0; i < m; i++) {
    px[i] = p[3 * (b0 + i)];
    py[i] = p[3 * (b0 + i) + 1];
    pz[i] = p[3 * (b0 + i) + 2];
  }
}

static void forward_simd(const struct vlff_encoding *e, const float *table, const float *p, int n, float *out,
                         int ldo) {
  float px[VLFF_ENC_V4_BLOCK], py[VLFF_ENC_V4_BLOCK], pz[VLFF_ENC_V4_BLOCK];
  for (int b0 = 0; b0 < n; b0 += VLFF_ENC_V4_BLOCK) {
    int m = n - b0 < VLFF_ENC_V4_BLOCK ? n - b0 : VLFF_ENC_V4_BLOCK;
    split_xyz(p, b0, m, px, py, pz);
    for (int l = 0; l < e->levels; l++) {
      float *ol = out + (size_t)b0 * ldo + 2 * l;
      const float *t = table + (size_t)l * e->size * 2;
      if (l >= e->active)
        for (int i = 0; i < m; i++) ol[(size_t)i * ldo] = ol[(size_t)i * ldo + 1] = 0;
      else if (e->simd == VLFF_ISA_AVX512)
        level_v4(e, l, t, px, py, pz, m, ol, ldo);
      else
        level_v3(e, l, t, px, py, pz, m, ol, ldo);
    }
  }
}

/* The gradient of one level: vector corners, then the scalar loop's
 * scatter in its order (point by point, c = 0..7). The touched entries are
 * the scalar loop's exactly; sums agree to float rounding (here each term
 * is one fused multiply-add, where the scalar loop may round the product
 * first, as its compiler decides). isa is a constant where this is inlined. */
static inline __attribute__((always_inline)) void backward_blocks(const struct vlff_encoding *e, const float *p,
                                                                  int n, const float *d, int ld, int l, float *g,
                                                                  uint8_t *tb, uint8_t stamp, int isa) {
  const int lanes = isa == VLFF_ISA_AVX512 ? 16 : 8;
  float px[VLFF_ENC_V4_BLOCK], py[VLFF_ENC_V4_BLOCK], pz[VLFF_ENC_V4_BLOCK];
  uint32_t ib[GROUP_POINTS * 8] __attribute__((aligned(64)));
  float wb[GROUP_POINTS * 8] __attribute__((aligned(64)));
  for (int b0 = 0; b0 < n; b0 += VLFF_ENC_V4_BLOCK) {
    int m = n - b0 < VLFF_ENC_V4_BLOCK ? n - b0 : VLFF_ENC_V4_BLOCK;
    split_xyz(p, b0, m, px, py, pz);
    for (int g0 = 0; g0 < m; g0 += GROUP_POINTS) {
      int nv = isa == VLFF_ISA_AVX512 ? corners_v4(e, l, px, py, pz, g0, m, ib, wb)
                                      : corners_v3(e, l, px, py, pz, g0, m, ib, wb);
      if (!e->dense[l]) PREFETCH_CORNERS(g, ib, nv * 8 * lanes, 1);
      int gm = m - g0 < GROUP_POINTS ? m - g0 : GROUP_POINTS;
      scatter_group(ib, wb, lanes, gm, d + (size_t)(b0 + g0) * ld, ld, g, tb, stamp);
    }
  }
}

V4_TARGET static void backward_v4(const struct vlff_encoding *e, const float *p, int n, const float *d, int ld,
                                  int l, float *g, uint8_t *tb, uint8_t stamp) {
  backward_blocks(e, p, n, d, ld, l, g, tb, stamp, VLFF_ISA_AVX512);
}

V3_TARGET static void backward_v3(const struct vlff_encoding *e, const float *p, int n, const float *d, int ld,
                                  int l, float *g, uint8_t *tb, uint8_t stamp) {
  backward_blocks(e, p, n, d, ld, l, g, tb, stamp, VLFF_ISA_AVX2);
}
#endif

/* sin and cos of x: reduction by pi/2 in two parts (pi/2 rounded to float,
 * then its error) and minimax polynomials on [-pi/4, pi/4] (the Cephes
 * single-precision coefficients): within 1e-7 of the exact values over the
 * [0, pi] a fixed box uses (measured; its points are normalised into
 * [0, 1]; a growing field's world reaches further, where the reduction's
 * error grows with the angle).
 * Written without calls or branches so that the loop over a block's points
 * vectorises: libm's sinf and cosf, called per point, were a fifth of the
 * encoding's time. */
static inline __attribute__((always_inline)) void sincos_poly(float x, float *s, float *c) {
  const float pio2_hi = 1.57079637050628662109375f, pio2_lo = -4.37113900018624283e-8f;
  float j = rintf(x * 0.636619772367581343f);
  int q = (int)j;
  float r = fmaf(-j, pio2_hi, x);
  r = fmaf(-j, pio2_lo, r);
  float z = r * r;
  float ps = r + r * z * (-1.6666654611e-1f + z * (8.3321608736e-3f + z * -1.9515295891e-4f));
  float pc = 1.0f - 0.5f * z + z * z * (4.166664568298827e-2f + z * (-1.388731625493765e-3f + z * 2.443315711809948e-5f));
  /* Quadrant q: (sin, cos) = (ps, pc), (pc, -ps), (-ps, -pc), (-pc, ps). */
  float sv = (q & 1) ? pc : ps, cv = (q & 1) ? ps : pc;
  *s = (q & 2) ? -sv : sv;
  *c = ((q + 1) & 2) ? -cv : cv;
}

/* The frequency part: one sin/cos per axis, higher octaves by the
 * double-angle formulas. */
VLFF_HOT
static void encode_freq(const struct vlff_encoding *e, const float *p, int n, float *out, int ldo) {
  enum { B = 64 };
  const int off = e->levels * e->feats;
  float x[3 * B], s[3 * B], c[3 * B];
  for (int i0 = 0; i0 < n; i0 += B) {
    int m = n - i0 < B ? n - i0 : B;
    /* A fixed trip count (a short block padded with zeros) is what GCC's
     * -O2 cost model vectorises. */
    for (int k = 0; k < 3 * m; k++) x[k] = p[3 * i0 + k] * e->freq_scale[k % 3] + e->freq_phase[k % 3];
    for (int k = 3 * m; k < 3 * B; k++) x[k] = 0.0f;
    for (int k = 0; k < 3 * B; k++) sincos_poly(x[k], &s[k], &c[k]);
    for (int i = 0; i < m; i++) {
      float *o = out + (size_t)(i0 + i) * ldo + off;
      for (int a = 0; a < 3; a++) {
        float sa = s[3 * i + a], ca = c[3 * i + a];
        for (int b = 0; b < e->freq_bands; b++) {
          *o++ = sa;
          *o++ = ca;
          float s2 = 2.0f * sa * ca;
          ca = 1.0f - 2.0f * sa * sa;
          sa = s2;
        }
      }
    }
  }
}

VLFF_HOT
void vlff_encoding_forward(const struct vlff_encoding *e, const float *table, const float *p, int n,
                           float *out, int ldo) {
  const int F = e->feats;
#if VLFF_ENC_V4
  if (e->simd && F == 2) {
    forward_simd(e, table, p, n, out, ldo);
    encode_freq(e, p, n, out, ldo);
    return;
  }
#endif
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
  encode_freq(e, p, n, out, ldo);
}

size_t vlff_encoding_entries(const struct vlff_encoding *e, int l) {
  if (!e->dense[l]) return e->size;
  size_t s1 = (size_t)e->res[l] + 1;
  return s1 * s1 * s1;
}

VLFF_HOT
void vlff_encoding_backward(const struct vlff_encoding *e, const float *p, int n, const float *d, int ld,
                            int level, float *g, uint8_t *tb, uint8_t stamp) {
  const int F = e->feats, l = level;
#if VLFF_ENC_V4
  if (e->simd && F == 2) {
    if (e->simd == VLFF_ISA_AVX512)
      backward_v4(e, p, n, d, ld, l, g, tb, stamp);
    else
      backward_v3(e, p, n, d, ld, l, g, tb, stamp);
    return;
  }
#endif
  if (F == 2) {
    /* As in the forward: addresses (prefetched) first, then the updates. */
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
          tb[h] = stamp;
          gv[0] += wt[i][c] * d0;
          gv[1] += wt[i][c] * d1;
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
      float *gv = g + (size_t)idx[c] * F;
      tb[idx[c]] = stamp;
      for (int f = 0; f < F; f++) gv[f] += w[c] * di[f];
    }
  }
}
