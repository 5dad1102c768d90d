/* The GEMM and scoring kernels built for x86-64-v3 (AVX2, FMA); see kernels.h. */
#define KERNEL_ISA v3
#include "kernel_build.h"
