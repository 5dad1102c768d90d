/*
 * Dense layers as GEMMs over a block of samples.
 *
 * One register-blocked kernel serves forward (X·Wt), input gradients
 * (dY·W, with W a transposed copy refreshed after each update) and weight
 * gradients (Xᵀ·dY, reading X with swapped strides). The micro-kernel keeps a
 * 4 x 32 tile of C in registers and streams a 32-wide panel of B, which stays
 * in L1 while the rows of A pass by (gemm_impl.h). The kernel is written with
 * GCC/clang vector extensions and built per instruction set; this file picks
 * the best one the CPU runs.
 */
#include <math.h>
#include <pthread.h>
#include <stdlib.h>
#include <string.h>

#include "field_internal.h"
#include "kernels.h"

typedef void (*gemm_fn)(int, int, int, const float *, ptrdiff_t, ptrdiff_t, const float *, int, float *, int,
                        const float *, int, int, const float *);
typedef void (*score_fn)(int, int, int, const float *, int, const float *, const float *, const float *,
                         const float *, float, int, int *, float *, float *);
#define SCORE_ARGS                                                                                                   \
  int m, int H, int K, const float *hT, int ldh, const float *ewt, const float *eb, const float *rt, const float *rv, \
      float r22, int gram, int *label, float *score, float *margin

float vlff_fma_probe(long iters, int *flops_per_iter) {
  const int isa = vlff_gemm_isa_level();
#if VLFF_GEMM_X86
  if (isa == VLFF_ISA_AVX512) {
    *flops_per_iter = 12 * 16 * 2;
    return vlff_fma_peak_v4(iters);
  }
  if (isa == VLFF_ISA_AVX2) {
    *flops_per_iter = 12 * 8 * 2;
    return vlff_fma_peak_v3(iters);
  }
#endif
  (void)isa;
  *flops_per_iter = 12 * 4 * 2;
  return vlff_fma_peak_generic(iters);
}

/* The widest kernel this CPU runs; resolved once (a benign race: every
 * thread computes the same value). */
static gemm_fn pick_gemm(void) {
#if VLFF_GEMM_X86
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512bw") &&
      __builtin_cpu_supports("avx512vl"))
    return vlff_gemm_v4;
  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) return vlff_gemm_v3;
#endif
  return vlff_gemm_generic;
}

static gemm_fn gemm_impl;
static score_fn score_impl;
static pthread_once_t gemm_once = PTHREAD_ONCE_INIT;
static void gemm_init(void) {
  const char *force = getenv("VLFF_GEMM");
  gemm_impl = pick_gemm();
  if (force && !strcmp(force, "generic")) gemm_impl = vlff_gemm_generic;
#if VLFF_GEMM_X86
  /* What an AVX2-only CPU (most x86 robot computers) runs, on a CPU with
   * more: the kernels that follow this choice are then the AVX2 ones. */
  if (force && !strcmp(force, "avx2") && gemm_impl == vlff_gemm_v4) gemm_impl = vlff_gemm_v3;
#endif
  score_impl = vlff_score_generic;
#if VLFF_GEMM_X86
  if (gemm_impl == vlff_gemm_v4) score_impl = vlff_score_v4;
  if (gemm_impl == vlff_gemm_v3) score_impl = vlff_score_v3;
#endif
}

int vlff_gemm_isa_level(void) {
  pthread_once(&gemm_once, gemm_init);
#if VLFF_GEMM_X86
  if (gemm_impl == vlff_gemm_v4) return VLFF_ISA_AVX512;
  if (gemm_impl == vlff_gemm_v3) return VLFF_ISA_AVX2;
#endif
  return VLFF_ISA_PORTABLE;
}

const char *vlff_gemm_isa(void) {
  static const char *const name[] = {"generic", "avx2+fma", "avx512"};
  return name[vlff_gemm_isa_level()];
}

/* Per thread, so that the trainer can tell each worker's GEMM time apart
 * without a shared counter in the hot path. Two clock reads per product
 * are a negligible share of a step. */
static _Thread_local double gemm_seconds;

double vlff_gemm_thread_seconds(void) { return gemm_seconds; }

void vlff_gemm_mask(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb,
                    float *c, int ldc, const float *bias, int accumulate, int relu, const float *mask) {
  pthread_once(&gemm_once, gemm_init);
  double t0 = vlff_seconds();
  gemm_impl(m, n, k, a, ars, acs, b, ldb, c, ldc, bias, accumulate, relu, mask);
  gemm_seconds += vlff_seconds() - t0;
}

void vlff_score(SCORE_ARGS) {
  pthread_once(&gemm_once, gemm_init);
  score_impl(m, H, K, hT, ldh, ewt, eb, rt, rv, r22, gram, label, score, margin);
}

void vlff_gemm(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb,
               float *c, int ldc, const float *bias, int accumulate, int relu) {
  vlff_gemm_mask(m, n, k, a, ars, acs, b, ldb, c, ldc, bias, accumulate, relu, NULL);
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

/* g[0..w) += the column sums of dy's columns [0, w) (row stride d). */
static inline __attribute__((always_inline)) void col_sums_w(const float *restrict dy, int n, int d,
                                                             float *restrict g, int w) {
  float acc[32];
  for (int j = 0; j < w; j++) acc[j] = g[j];
  for (int i = 0; i < n; i++)
    for (int j = 0; j < w; j++) acc[j] += dy[(size_t)i * d + j];
  for (int j = 0; j < w; j++) g[j] = acc[j];
}

/* Bias gradients: g += column sums of dy[n][d]. Every column is summed over
 * the rows in order, from g's value, as a plain double loop into g would,
 * so the result is the same to the bit; but in registers, a constant-width
 * block of columns at a time. Into g, each add waited for the store of the
 * row before. */
VLFF_HOT
static void col_sums(const float *restrict dy, int n, int d, float *restrict g) {
  int j0 = 0;
  for (; j0 + 32 <= d; j0 += 32) col_sums_w(dy + j0, n, d, g + j0, 32);
  if (j0 + 16 <= d) {
    col_sums_w(dy + j0, n, d, g + j0, 16);
    j0 += 16;
  }
  if (d - j0 == 3)
    col_sums_w(dy + j0, n, d, g + j0, 3); /* the colour layer */
  else if (j0 < d)
    col_sums_w(dy + j0, n, d, g + j0, d - j0);
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
      /* The ReLU of the layer below masks the gradient in the same pass. */
      vlff_gemm_mask(n, din, dout, dy, dout, 1, wT + m->woff[l], din, tmp, din, NULL, 0, 0, act[l - 1]);
      float *t = dy;
      dy = tmp;
      tmp = t;
    } else if (dx) {
      vlff_gemm(n, din, dout, dy, dout, 1, wT + m->woff[l], din, dx, ldx, NULL, 0, 0);
    }
  }
}

double vlff_mlp_flops(const struct vlff_mlp *m, int upto, int backward) {
  double f = 0;
  for (int l = 0; l < upto; l++) f += 2.0 * m->din[l] * m->dout[l];
  return backward ? 3 * f : f;
}
