/*
 * VLFF_HOT marks a hot kernel: on x86-64 with GCC it gets AVX-512 and
 * AVX2+FMA clones chosen at load time; elsewhere (ARM, clang) the portable
 * code is compiled for the target the build selects. Not under
 * ThreadSanitizer: its instrumented ifunc resolvers run before the runtime
 * is initialised and crash. A clone computes exactly what the default does
 * unless its file allows FMA contraction (-ffp-contract=fast).
 */
#ifndef VLFF_HOT_H
#define VLFF_HOT_H

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && !defined(VLFF_NO_CLONES) && \
    !defined(__SANITIZE_THREAD__)
#define VLFF_HOT __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define VLFF_HOT
#endif

#endif
