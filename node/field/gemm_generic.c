/* The GEMM and scoring kernels built for portable C (vectorised by the compiler for the target); see kernels.h. */
#define KERNEL_ISA generic
#include "kernel_build.h"
