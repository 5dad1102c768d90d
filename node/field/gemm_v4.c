/* GEMM kernel build for v4 (see gemm_impl.h). */
#include <stddef.h>
void vlff_gemm_v4(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb, float *c,
                  int ldc, const float *bias, int accumulate, int relu, const float *mask);
#define GEMM_FN vlff_gemm_v4
#define GEMM_PEAK_FN vlff_fma_peak_v4
float vlff_fma_peak_v4(long iters);
#include "gemm_impl.h"
