/*
 * The per-ISA builds of the dense kernels: the GEMM (gemm_impl.h), the
 * prompt scoring of 3D queries (score_impl.h) and the FMA peak probe.
 *
 * Each gemm_<isa>.c defines KERNEL_ISA, is compiled with that ISA's -march
 * and includes kernel_build.h; mlp.c picks one build at run time. The
 * generic build exists everywhere, v3 (AVX2+FMA) and v4 (AVX-512) on x86-64
 * only (VLFF_GEMM_X86). Contract of each function: gemm_impl.h and
 * score_impl.h; all are pure and thread-safe.
 */
#ifndef VLFF_KERNELS_H
#define VLFF_KERNELS_H

#include <stddef.h>

#define VLFF_KERNEL_DECLS(isa)                                                                                 \
  void vlff_gemm_##isa(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b,      \
                       int ldb, float *c, int ldc, const float *bias, int accumulate, int relu,                \
                       const float *mask);                                                                     \
  void vlff_score_##isa(int m, int H, int K, const float *hT, int ldh, const float *ewt, const float *eb,      \
                        const float *rt, const float *rv, float r22, int gram, int *label, float *score,       \
                        float *margin);                                                                        \
  float vlff_fma_peak_##isa(long iters)

VLFF_KERNEL_DECLS(generic);
#if defined(VLFF_GEMM_X86) && VLFF_GEMM_X86
VLFF_KERNEL_DECLS(v3);
VLFF_KERNEL_DECLS(v4);
#endif

#endif
