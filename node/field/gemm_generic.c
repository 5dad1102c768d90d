/* GEMM and scoring kernel build for generic (see gemm_impl.h, score_impl.h). */
#include <stddef.h>
void vlff_gemm_generic(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb, float *c,
                  int ldc, const float *bias, int accumulate, int relu, const float *mask);
#define GEMM_FN vlff_gemm_generic
#define GEMM_PEAK_FN vlff_fma_peak_generic
float vlff_fma_peak_generic(long iters);
#include "gemm_impl.h"
void vlff_score_generic(int m, int H, int K, const float *hT, int ldh, const float *ewt, const float *eb, const float *rt,
              const float *rv, float r22, int gram, int *label, float *score, float *margin);
#define SCORE_FN vlff_score_generic
#include "score_impl.h"
