/*
 * The GEMM kernel, compiled once per instruction set (gemm_*.c define GEMM_FN
 * and are built with matching -march flags; mlp.c picks one at run time).
 *
 * C[M][N] (+)= A[M][K] B[K][N] with A(i,k) = a[i*ars + k*acs]: the same kernel
 * serves forward (X·Wt), input gradients (dY·W) and weight gradients (Xᵀ·dY,
 * A read with swapped strides). An MR x (NV*VW) tile of C lives in registers
 * while a NV*VW-wide panel of B streams from L1; tile sizes fit the register
 * file of each ISA: AVX-512 8x32 (16 of 32 zmm), AVX2 6x16 (12 of 16 ymm),
 * otherwise 4x8 (SSE / NEON). Columns past the last whole vector: AVX-512
 * runs the same tile on masked loads and stores; the others copy that panel
 * zero-padded to a vector's width. Outputs at most NARROW wide take their
 * own two loops (below), vectorised along k or m instead of n.
 */
#include <stddef.h>
#include <string.h>

#if defined(__AVX512F__)
#define VW 16
#define MR 8
#define NV 2
#elif defined(__AVX2__)
#define VW 8
#define MR 6
#define NV 2
#else
#define VW 4
#define MR 4
#define NV 2
#endif

typedef float vf __attribute__((vector_size(VW * 4)));
typedef int vi __attribute__((vector_size(VW * 4)));

#if defined(__AVX512F__)
#include <immintrin.h>
#define MASKED_TAIL 1
typedef __mmask16 tailmask;
#else
#define MASKED_TAIL 0
typedef unsigned tailmask;
#endif

static inline __attribute__((always_inline)) vf vload(const float *p) {
  vf v;
  memcpy(&v, p, sizeof(v));
  return v;
}
static inline __attribute__((always_inline)) void vstore(float *p, vf v) { memcpy(p, &v, sizeof(v)); }
/* Vector v of nv, where the last one may be partial (tail: its lanes, when
 * masked; only AVX-512 builds pass masked = 1). */
static inline __attribute__((always_inline)) vf vload_t(const float *p, int v, int nv, int masked, tailmask tail) {
#if MASKED_TAIL
  if (masked && v == nv - 1) return (vf)_mm512_maskz_loadu_ps(tail, p);
#else
  (void)v, (void)nv, (void)masked, (void)tail;
#endif
  return vload(p);
}
static inline __attribute__((always_inline)) void vstore_t(float *p, vf x, int v, int nv, int masked,
                                                           tailmask tail) {
#if MASKED_TAIL
  if (masked && v == nv - 1) {
    _mm512_mask_storeu_ps(p, tail, (__m512)x);
    return;
  }
#else
  (void)v, (void)nv, (void)masked, (void)tail;
#endif
  vstore(p, x);
}

static inline __attribute__((always_inline)) void tile(const int mr, const int nv, const int masked, tailmask tail,
                                                       int k, const float *a, ptrdiff_t ars, ptrdiff_t acs,
                                                       const float *b, int ldb, float *c, int ldc, const float *bias,
                                                       int accumulate, int relu, const float *mask) {
  vf acc[MR][NV];
#pragma GCC unroll 8
  for (int r = 0; r < mr; r++)
#pragma GCC unroll 2
    for (int v = 0; v < nv; v++) {
      if (bias)
        acc[r][v] = vload_t(bias + VW * v, v, nv, masked, tail);
      else if (accumulate)
        acc[r][v] = vload_t(c + (ptrdiff_t)r * ldc + VW * v, v, nv, masked, tail);
      else
        acc[r][v] = (vf){0};
    }
  for (int kk = 0; kk < k; kk++) {
    const float *bk = b + (ptrdiff_t)kk * ldb;
    const float *ak = a + (ptrdiff_t)kk * acs;
    vf bv[NV];
#pragma GCC unroll 2
    for (int v = 0; v < nv; v++) bv[v] = vload_t(bk + VW * v, v, nv, masked, tail);
#pragma GCC unroll 8
    for (int r = 0; r < mr; r++) {
      float av = ak[(ptrdiff_t)r * ars];
#pragma GCC unroll 2
      for (int v = 0; v < nv; v++) acc[r][v] += av * bv[v];
    }
  }
#pragma GCC unroll 8
  for (int r = 0; r < mr; r++)
#pragma GCC unroll 2
    for (int v = 0; v < nv; v++) {
      vf x = acc[r][v];
      if (relu) x = (vf)((vi)x & (x > 0));
      if (mask) x = (vf)((vi)x & (vload_t(mask + (ptrdiff_t)r * ldc + VW * v, v, nv, masked, tail) > 0));
      vstore_t(c + (ptrdiff_t)r * ldc + VW * v, x, v, nv, masked, tail);
    }
}

/* All rows for one column block of nv vectors. */
static inline __attribute__((always_inline)) void rows(const int nv, const int masked, tailmask tail, int m, int k,
                                                       const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b,
                                                       int ldb, float *c, int ldc, const float *bias, int accumulate,
                                                       int relu, const float *mask) {
  int i = 0;
  for (; i + MR <= m; i += MR)
    tile(MR, nv, masked, tail, k, a + (ptrdiff_t)i * ars, ars, acs, b, ldb, c + (ptrdiff_t)i * ldc, ldc, bias,
         accumulate, relu, mask ? mask + (ptrdiff_t)i * ldc : NULL);
  /* The last m % MR rows as one tile of that height: row by row, a tile
   * has NV accumulator chains, too few to hide the FMA latency (the weight
   * gradients' m = 15, 31, 44 ran well below the full tiles' rate). */
#define TAIL(R)                                                                                                 \
  case R:                                                                                                       \
    tile(R, nv, masked, tail, k, a + (ptrdiff_t)i * ars, ars, acs, b, ldb, c + (ptrdiff_t)i * ldc, ldc, bias,   \
         accumulate, relu, mask ? mask + (ptrdiff_t)i * ldc : NULL);                                            \
    break;
  switch (m - i) {
    TAIL(1)
    TAIL(2)
    TAIL(3)
#if MR > 4
    TAIL(4)
    TAIL(5)
#endif
#if MR > 6
    TAIL(6)
    TAIL(7)
#endif
  }
#undef TAIL
}

#define KB 256

/* ---- outputs at most NARROW wide (the colour layer's 3) ----------------
 * The tile above spends a whole vector (or a masked one) per row on them,
 * 3 of 16 lanes for the colour layer's forward and weight gradient. These
 * put the vector along the other dimension instead. */
enum { NARROW = 4, NARROW_KMAX = 512, NARROW_RB = 4, NARROW_MV = 4 };

static inline __attribute__((always_inline)) float vsum(vf x) {
#if defined(__AVX512F__)
  return _mm512_reduce_add_ps((__m512)x);
#else
  float s = 0;
  for (int q = 0; q < VW; q++) s += x[q];
  return s;
#endif
}

/* The tile's ReLU and mask for one output, where a scalar loop stores it. */
static inline __attribute__((always_inline)) float relu_mask1(float x, int relu, const float *maskij) {
  if (relu && !(x > 0)) x = 0;
  if (maskij && !(*maskij > 0)) x = 0;
  return x;
}

/* The epilogue of one output: bias or accumulation, then ReLU and mask. */
static inline __attribute__((always_inline)) void narrow_put(float *cij, float sum, int j, const float *bias,
                                                             int accumulate, int relu, const float *maskij) {
  *cij = relu_mask1(bias ? bias[j] + sum : accumulate ? *cij + sum : sum, relu, maskij);
}

/* Rows of A contiguous along k (acs = 1), k >= VW: a dot product per
 * output, NARROW_RB rows at a time against B's columns packed contiguous
 * (padded to NARROW with zeros, so every loop has a constant trip count). */
static void narrow_dot(int m, int n, int k, const float *a, ptrdiff_t ars, const float *b, int ldb, float *c,
                       int ldc, const float *bias, int accumulate, int relu, const float *mask) {
  float bt[NARROW][NARROW_KMAX] __attribute__((aligned(64)));
  for (int j = 0; j < NARROW; j++)
    for (int kk = 0; kk < k; kk++) bt[j][kk] = j < n ? b[(ptrdiff_t)kk * ldb + j] : 0.0f;
  const int kv = k / VW;
  int i = 0;
  for (; i < m; i += NARROW_RB) {
    const int rb = m - i < NARROW_RB ? m - i : NARROW_RB;
    vf acc[NARROW_RB][NARROW];
    /* Zeroed by loops: an initializer left them in memory. */
#pragma GCC unroll 4
    for (int r = 0; r < NARROW_RB; r++)
#pragma GCC unroll 4
      for (int j = 0; j < NARROW; j++) acc[r][j] = (vf){0};
    for (int v = 0; v < kv; v++) {
      vf bv[NARROW];
#pragma GCC unroll 4
      for (int j = 0; j < NARROW; j++) bv[j] = vload(bt[j] + VW * v);
#pragma GCC unroll 4
      for (int r = 0; r < NARROW_RB; r++) {
        /* Rows past m repeat the last one (read, never stored). */
        vf av = vload(a + (ptrdiff_t)(i + (r < rb ? r : rb - 1)) * ars + VW * v);
#pragma GCC unroll 4
        for (int j = 0; j < NARROW; j++) acc[r][j] += av * bv[j];
      }
    }
    for (int r = 0; r < rb; r++) {
      const float *ar = a + (ptrdiff_t)(i + r) * ars;
      for (int j = 0; j < n; j++) {
        float sum = vsum(acc[r][j]);
        for (int kk = VW * kv; kk < k; kk++) sum += ar[kk] * bt[j][kk];
        ptrdiff_t o = (ptrdiff_t)(i + r) * ldc + j;
        narrow_put(c + o, sum, j, bias, accumulate, relu, mask ? mask + o : NULL);
      }
    }
  }
}

/* Columns of A contiguous along m (ars = 1; the weight gradients' Xt),
 * m a multiple of VW: outer products, NARROW_MV vectors of rows times the
 * NARROW broadcast values of each row of B. */
static void narrow_outer(int m, int n, int k, const float *a, ptrdiff_t acs, const float *b, int ldb, float *c,
                         int ldc, const float *bias, int accumulate, int relu, const float *mask) {
  for (int i0 = 0; i0 < m; i0 += VW * NARROW_MV) {
    const int mv = (m - i0) / VW < NARROW_MV ? (m - i0) / VW : NARROW_MV;
    vf acc[NARROW_MV][NARROW] = {{{0}}};
    for (int kk = 0; kk < k; kk++) {
      const float *bk = b + (ptrdiff_t)kk * ldb;
      const float *ak = a + (ptrdiff_t)kk * acs + i0;
      float bj[NARROW];
#pragma GCC unroll 4
      for (int j = 0; j < NARROW; j++) bj[j] = j < n ? bk[j] : 0.0f;
#pragma GCC unroll 4
      for (int v = 0; v < NARROW_MV; v++) {
        if (v >= mv) break;
        vf av = vload(ak + VW * v);
#pragma GCC unroll 4
        for (int j = 0; j < NARROW; j++) acc[v][j] += av * bj[j];
      }
    }
    for (int v = 0; v < mv; v++)
      for (int q = 0; q < VW; q++)
        for (int j = 0; j < n; j++) {
          ptrdiff_t o = (ptrdiff_t)(i0 + VW * v + q) * ldc + j;
          narrow_put(c + o, acc[v][j][q], j, bias, accumulate, relu, mask ? mask + o : NULL);
        }
  }
}

void GEMM_FN(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb, float *c,
             int ldc, const float *bias, int accumulate, int relu, const float *mask) {
  if (n <= NARROW && m > 0) {
    if (acs == 1 && k >= VW && k <= NARROW_KMAX) {
      narrow_dot(m, n, k, a, ars, b, ldb, c, ldc, bias, accumulate, relu, mask);
      return;
    }
    if (ars == 1 && m % VW == 0 && k > 0) {
      narrow_outer(m, n, k, a, acs, b, ldb, c, ldc, bias, accumulate, relu, mask);
      return;
    }
  }
  int j = 0;
  for (; j + VW * NV <= n; j += VW * NV)
    rows(NV, 0, 0, m, k, a, ars, acs, b + j, ldb, c + j, ldc, bias ? bias + j : NULL, accumulate, relu,
         mask ? mask + j : NULL);
#if MASKED_TAIL
  /* 1 to 2 * VW - 1 columns left: one or two vectors, the last masked (a
   * padded copy cost a large share on top of the tile at n = 15, 31, 44). */
  if (j + VW == n)
    rows(1, 0, 0, m, k, a, ars, acs, b + j, ldb, c + j, ldc, bias ? bias + j : NULL, accumulate, relu,
         mask ? mask + j : NULL);
  else if (j < n) {
    const int left = n - j, last = left > VW ? left - VW : left;
    const tailmask tail = (tailmask)((1u << last) - 1u);
    if (left > VW)
      rows(2, 1, tail, m, k, a, ars, acs, b + j, ldb, c + j, ldc, bias ? bias + j : NULL, accumulate, relu,
           mask ? mask + j : NULL);
    else
      rows(1, 1, tail, m, k, a, ars, acs, b + j, ldb, c + j, ldc, bias ? bias + j : NULL, accumulate, relu,
           mask ? mask + j : NULL);
  }
#else
  for (; j + VW <= n; j += VW)
    rows(1, 0, 0, m, k, a, ars, acs, b + j, ldb, c + j, ldc, bias ? bias + j : NULL, accumulate, relu,
         mask ? mask + j : NULL);
  if (j >= n) return;
  /* Fewer than VW columns left: pack that panel of B zero-padded to VW wide
   * (in blocks of K) and run the vector tile on a padded copy of C. */
  const int nc = n - j;
  float bp[KB * VW] __attribute__((aligned(64)));
  float ct[MR * VW] __attribute__((aligned(64)));
  for (int k0 = 0; k0 < k || k0 == 0; k0 += KB) {
    int kb = k - k0 < KB ? k - k0 : KB;
    for (int kk = 0; kk < kb; kk++) {
      const float *src = b + (ptrdiff_t)(k0 + kk) * ldb + j;
      for (int q = 0; q < VW; q++) bp[kk * VW + q] = q < nc ? src[q] : 0.0f;
    }
    int lastblk = k0 + KB >= k;
    for (int i = 0; i < m; i += MR) {
      int mr = m - i < MR ? m - i : MR;
      for (int r = 0; r < mr; r++) {
        float *cr = c + (ptrdiff_t)(i + r) * ldc + j;
        for (int q = 0; q < VW; q++)
          ct[r * VW + q] = q >= nc ? 0.0f : k0 > 0 ? cr[q] : bias ? bias[j + q] : accumulate ? cr[q] : 0.0f;
      }
      const float *ai = a + (ptrdiff_t)i * ars + (ptrdiff_t)k0 * acs;
      if (mr == MR)
        tile(MR, 1, 0, 0, kb, ai, ars, acs, bp, VW, ct, VW, NULL, 1, 0, NULL);
      else
        for (int r = 0; r < mr; r++)
          tile(1, 1, 0, 0, kb, ai + (ptrdiff_t)r * ars, ars, acs, bp, VW, ct + r * VW, VW, NULL, 1, 0, NULL);
      for (int r = 0; r < mr; r++) {
        float *cr = c + (ptrdiff_t)(i + r) * ldc + j;
        for (int q = 0; q < nc; q++) {
          float x = ct[r * VW + q];
          if (lastblk) x = relu_mask1(x, relu, mask ? mask + (ptrdiff_t)(i + r) * ldc + j + q : NULL);
          cr[q] = x;
        }
      }
    }
    if (k == 0) break;
  }
#endif
}

/* FMA throughput probe for this ISA: 12 independent chains per vector width
 * (enough to cover the latency of two FMA pipes). The chains are loop-carried
 * and the result depends on all of them, so nothing can be optimised away. */
float GEMM_PEAK_FN(long iters) {
  vf a[12], x = (vf){0} + 0.999f, y = (vf){0} + 1e-3f;
  for (int i = 0; i < 12; i++) a[i] = (vf){0} + (float)i;
  for (long it = 0; it < iters; it++) {
#pragma GCC unroll 12
    for (int i = 0; i < 12; i++) a[i] = a[i] * x + y;
  }
  float s = 0;
  for (int i = 0; i < 12; i++)
    for (int j = 0; j < VW; j++) s += a[i][j];
  return s;
}
