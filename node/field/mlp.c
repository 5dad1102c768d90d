/*
 * Dense layers as GEMMs over a block of samples.
 *
 * One register-blocked kernel serves forward (X·Wt), input gradients
 * (dY·W, with W a transposed copy refreshed after each update) and weight
 * gradients (Xᵀ·dY, reading X with swapped strides). The micro-kernel keeps a
 * 4 x 32 tile of C in registers and streams a 32-wide panel of B, which stays
 * in L1 while the rows of A pass by. It is written with GCC/clang vector
 * extensions, so the same source becomes AVX-512, AVX2, SSE or NEON code.
 */
#include <math.h>
#include <string.h>

#include "field_internal.h"

typedef float v16 __attribute__((vector_size(64)));
typedef int v16i __attribute__((vector_size(64)));

#define MR 4
#define NV 2   /* vectors of 16 per tile row */

static inline __attribute__((always_inline)) v16 vload(const float *p) {
  v16 v;
  memcpy(&v, p, sizeof(v));
  return v;
}
static inline __attribute__((always_inline)) void vstore(float *p, v16 v) { memcpy(p, &v, sizeof(v)); }

static inline __attribute__((always_inline)) void tile(int mr, int nv, int k, const float *a, ptrdiff_t ars,
                                                       ptrdiff_t acs, const float *b, int ldb, float *c, int ldc,
                                                       const float *bias, int accumulate, int relu) {
  v16 acc[MR][NV];
  for (int r = 0; r < mr; r++)
    for (int v = 0; v < nv; v++) {
      if (bias)
        acc[r][v] = vload(bias + 16 * v);
      else if (accumulate)
        acc[r][v] = vload(c + (ptrdiff_t)r * ldc + 16 * v);
      else
        acc[r][v] = (v16){0};
    }
  for (int kk = 0; kk < k; kk++) {
    const float *bk = b + (ptrdiff_t)kk * ldb;
    v16 bv[NV];
    for (int v = 0; v < nv; v++) bv[v] = vload(bk + 16 * v);
    for (int r = 0; r < mr; r++) {
      float av = a[(ptrdiff_t)r * ars + (ptrdiff_t)kk * acs];
      for (int v = 0; v < nv; v++) acc[r][v] += av * bv[v];
    }
  }
  for (int r = 0; r < mr; r++)
    for (int v = 0; v < nv; v++) {
      v16 x = acc[r][v];
      if (relu) x = (v16)((v16i)x & (x > 0));
      vstore(c + (ptrdiff_t)r * ldc + 16 * v, x);
    }
}

static void tail_cols(int m, int n0, int n1, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b,
                      int ldb, float *c, int ldc, const float *bias, int accumulate, int relu) {
  for (int i = 0; i < m; i++)
    for (int j = n0; j < n1; j++) {
      float s = bias ? bias[j] : accumulate ? c[(ptrdiff_t)i * ldc + j] : 0.0f;
      for (int kk = 0; kk < k; kk++) s += a[(ptrdiff_t)i * ars + (ptrdiff_t)kk * acs] * b[(ptrdiff_t)kk * ldb + j];
      if (relu && !(s > 0)) s = 0;
      c[(ptrdiff_t)i * ldc + j] = s;
    }
}

#define TILE_CASES(NVV)                                                                                       \
  switch (mr) {                                                                                               \
  case 4: tile(4, NVV, k, ai, ars, acs, b + j, ldb, ci, ldc, bj, accumulate, relu); break;                    \
  case 3: tile(3, NVV, k, ai, ars, acs, b + j, ldb, ci, ldc, bj, accumulate, relu); break;                    \
  case 2: tile(2, NVV, k, ai, ars, acs, b + j, ldb, ci, ldc, bj, accumulate, relu); break;                    \
  default: tile(1, NVV, k, ai, ars, acs, b + j, ldb, ci, ldc, bj, accumulate, relu); break;                   \
  }

VLFF_HOT
void vlff_gemm(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb,
               float *c, int ldc, const float *bias, int accumulate, int relu) {
  int j = 0;
  for (; j + 16 * NV <= n; j += 16 * NV) {
    const float *bj = bias ? bias + j : NULL;
    for (int i = 0; i < m; i += MR) {
      int mr = m - i < MR ? m - i : MR;
      const float *ai = a + (ptrdiff_t)i * ars;
      float *ci = c + (ptrdiff_t)i * ldc + j;
      TILE_CASES(NV)
    }
  }
  for (; j + 16 <= n; j += 16) {
    const float *bj = bias ? bias + j : NULL;
    for (int i = 0; i < m; i += MR) {
      int mr = m - i < MR ? m - i : MR;
      const float *ai = a + (ptrdiff_t)i * ars;
      float *ci = c + (ptrdiff_t)i * ldc + j;
      TILE_CASES(1)
    }
  }
  if (j < n) tail_cols(m, j, n, k, a, ars, acs, b, ldb, c, ldc, bias, accumulate, relu);
}

static size_t pad16(size_t x) { return (x + 15) & ~(size_t)15; }

size_t vlff_mlp_init(struct vlff_mlp *m, int nin, int width, int hidden, int nout, size_t base) {
  memset(m, 0, sizeof(*m));
  m->nin = nin;
  m->nout = nout;
  m->width = width;
  m->hidden = hidden;
  m->nl = hidden + 1;
  size_t off = base;
  for (int l = 0; l < m->nl; l++) {
    m->din[l] = l == 0 ? nin : width;
    m->dout[l] = l == m->nl - 1 ? nout : width;
    m->woff[l] = off;
    off += pad16((size_t)m->din[l] * m->dout[l]);
    m->boff[l] = off;
    off += pad16((size_t)m->dout[l]);
  }
  m->nparams = off - base;
  return off;
}

void vlff_mlp_init_params(const struct vlff_mlp *m, float *params, uint64_t *rng) {
  for (int l = 0; l < m->nl; l++) {
    float bound = sqrtf(6.0f / (float)m->din[l]);
    if (l == m->nl - 1) bound = sqrtf(3.0f / (float)m->din[l]);
    size_t nw = (size_t)m->din[l] * m->dout[l];
    for (size_t i = 0; i < nw; i++) params[m->woff[l] + i] = (2.0f * vlff_rng_uniform(rng) - 1.0f) * bound;
    for (int i = 0; i < m->dout[l]; i++) params[m->boff[l] + i] = 0.0f;
  }
}

void vlff_mlp_transpose(const struct vlff_mlp *m, const float *params, float *wT) {
  for (int l = 0; l < m->nl; l++) {
    const float *w = params + m->woff[l];
    float *t = wT + m->woff[l];
    int din = m->din[l], dout = m->dout[l];
    for (int i = 0; i < din; i++)
      for (int o = 0; o < dout; o++) t[(size_t)o * din + i] = w[(size_t)i * dout + o];
  }
}

void vlff_mlp_forward(const struct vlff_mlp *m, const float *params, const float *x, int ldx, int n, int upto,
                      float **act) {
  const float *in = x;
  int ldin = ldx;
  for (int l = 0; l < upto; l++) {
    vlff_gemm(n, m->dout[l], m->din[l], in, ldin, 1, params + m->woff[l], m->dout[l], act[l], m->dout[l],
              params + m->boff[l], 0, l < m->nl - 1);
    in = act[l];
    ldin = m->dout[l];
  }
}

VLFF_HOT
static void col_sums(const float *dy, int n, int d, float *g) {
  for (int i = 0; i < n; i++)
    for (int j = 0; j < d; j++) g[j] += dy[(size_t)i * d + j];
}

VLFF_HOT
static void relu_mask(float *d, const float *act, size_t n) {
  for (size_t i = 0; i < n; i++) d[i] = act[i] > 0 ? d[i] : 0.0f;
}

void vlff_mlp_backward(const struct vlff_mlp *m, const float *wT, const float *x, int ldx, int n, int upto,
                       float *const *act, float *dy, float *grad, float *dx, float *tmp) {
  for (int l = upto - 1; l >= 0; l--) {
    const float *in = l == 0 ? x : act[l - 1];
    int ldin = l == 0 ? ldx : m->dout[l - 1];
    int din = m->din[l], dout = m->dout[l];
    vlff_gemm(din, dout, n, in, 1, ldin, dy, dout, grad + m->woff[l], dout, NULL, 1, 0);
    col_sums(dy, n, dout, grad + m->boff[l]);
    if (l > 0) {
      vlff_gemm(n, din, dout, dy, dout, 1, wT + m->woff[l], din, tmp, din, NULL, 0, 0);
      relu_mask(tmp, act[l - 1], (size_t)n * din);
      float *t = dy;
      dy = tmp;
      tmp = t;
    } else if (dx) {
      vlff_gemm(n, din, dout, dy, dout, 1, wT + m->woff[l], din, dx, ldx, NULL, 0, 0);
    }
  }
}
