/* The GEMM and scoring kernels built for x86-64-v4 (AVX-512); see kernels.h. */
#define KERNEL_ISA v4
#include "kernel_build.h"
