/* GEMM kernel build for v3 (see gemm_impl.h). */
#include <stddef.h>
void vlff_gemm_v3(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb, float *c,
                  int ldc, const float *bias, int accumulate, int relu, const float *mask);
#define GEMM_FN vlff_gemm_v3
#define GEMM_PEAK_FN vlff_fma_peak_v3
float vlff_fma_peak_v3(long iters);
#include "gemm_impl.h"
