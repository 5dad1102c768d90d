/*
 * The GEMM kernel, compiled once per instruction set (gemm_*.c define GEMM_FN
 * and are built with matching -march flags; mlp.c picks one at run time).
 *
 * C[M][N] (+)= A[M][K] B[K][N] with A(i,k) = a[i*ars + k*acs]: the same kernel
 * serves forward (X·Wt), input gradients (dY·W) and weight gradients (Xᵀ·dY,
 * A read with swapped strides). An MR x (NV*VW) tile of C lives in registers
 * while a NV*VW-wide panel of B streams from L1; tile sizes fit the register
 * file of each ISA: AVX-512 8x32 (16 of 32 zmm), AVX2 6x16 (12 of 16 ymm),
 * otherwise 4x8 (SSE / NEON).
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

static inline __attribute__((always_inline)) vf vload(const float *p) {
  vf v;
  memcpy(&v, p, sizeof(v));
  return v;
}
static inline __attribute__((always_inline)) void vstore(float *p, vf v) { memcpy(p, &v, sizeof(v)); }

static inline __attribute__((always_inline)) void tile(const int mr, const int nv, int k, const float *a,
                                                       ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb,
                                                       float *c, int ldc, const float *bias, int accumulate,
                                                       int relu, const float *mask) {
  vf acc[MR][NV];
#pragma GCC unroll 8
  for (int r = 0; r < mr; r++)
#pragma GCC unroll 2
    for (int v = 0; v < nv; v++) {
      if (bias)
        acc[r][v] = vload(bias + VW * v);
      else if (accumulate)
        acc[r][v] = vload(c + (ptrdiff_t)r * ldc + VW * v);
      else
        acc[r][v] = (vf){0};
    }
  for (int kk = 0; kk < k; kk++) {
    const float *bk = b + (ptrdiff_t)kk * ldb;
    const float *ak = a + (ptrdiff_t)kk * acs;
    vf bv[NV];
#pragma GCC unroll 2
    for (int v = 0; v < nv; v++) bv[v] = vload(bk + VW * v);
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
      if (mask) x = (vf)((vi)x & (vload(mask + (ptrdiff_t)r * ldc + VW * v) > 0));
      vstore(c + (ptrdiff_t)r * ldc + VW * v, x);
    }
}

/* All rows for one column block of nv vectors. */
static inline __attribute__((always_inline)) void rows(const int nv, int m, int k, const float *a, ptrdiff_t ars,
                                                       ptrdiff_t acs, const float *b, int ldb, float *c, int ldc,
                                                       const float *bias, int accumulate, int relu,
                                                       const float *mask) {
  int i = 0;
  for (; i + MR <= m; i += MR)
    tile(MR, nv, k, a + (ptrdiff_t)i * ars, ars, acs, b, ldb, c + (ptrdiff_t)i * ldc, ldc, bias, accumulate, relu,
         mask ? mask + (ptrdiff_t)i * ldc : NULL);
  for (; i < m; i++)
    tile(1, nv, k, a + (ptrdiff_t)i * ars, ars, acs, b, ldb, c + (ptrdiff_t)i * ldc, ldc, bias, accumulate, relu,
         mask ? mask + (ptrdiff_t)i * ldc : NULL);
}

#define KB 256

void GEMM_FN(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb, float *c,
             int ldc, const float *bias, int accumulate, int relu, const float *mask) {
  int j = 0;
  for (; j + VW * NV <= n; j += VW * NV)
    rows(NV, m, k, a, ars, acs, b + j, ldb, c + j, ldc, bias ? bias + j : NULL, accumulate, relu,
         mask ? mask + j : NULL);
  for (; j + VW <= n; j += VW)
    rows(1, m, k, a, ars, acs, b + j, ldb, c + j, ldc, bias ? bias + j : NULL, accumulate, relu,
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
        tile(MR, 1, kb, ai, ars, acs, bp, VW, ct, VW, NULL, 1, 0, NULL);
      else
        for (int r = 0; r < mr; r++) tile(1, 1, kb, ai + (ptrdiff_t)r * ars, ars, acs, bp, VW, ct + r * VW, VW, NULL, 1, 0, NULL);
      for (int r = 0; r < mr; r++) {
        float *cr = c + (ptrdiff_t)(i + r) * ldc + j;
        for (int q = 0; q < nc; q++) {
          float x = ct[r * VW + q];
          if (lastblk) {
            if (relu && !(x > 0)) x = 0;
            if (mask && !(mask[(ptrdiff_t)(i + r) * ldc + j + q] > 0)) x = 0;
          }
          cr[q] = x;
        }
      }
    }
    if (k == 0) break;
  }
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
