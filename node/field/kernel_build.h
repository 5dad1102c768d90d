/*
 * One ISA's build of the kernels (see kernels.h): gemm_<isa>.c defines
 * KERNEL_ISA (generic, v3, v4) and includes this file, which names the
 * functions after it and instantiates gemm_impl.h and score_impl.h.
 */
#include "kernels.h"

#define KERNEL_NAME_(f, isa) f##_##isa
#define KERNEL_NAME(f, isa) KERNEL_NAME_(f, isa)
#define GEMM_FN KERNEL_NAME(vlff_gemm, KERNEL_ISA)
#define GEMM_PEAK_FN KERNEL_NAME(vlff_fma_peak, KERNEL_ISA)
#define SCORE_FN KERNEL_NAME(vlff_score, KERNEL_ISA)

#include "gemm_impl.h"
#include "score_impl.h"
