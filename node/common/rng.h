/*
 * The one pseudo-random generator of the node, its tools and the field:
 * SplitMix64 (a Weyl sequence through a 64-bit finaliser). Deterministic,
 * so a seed reproduces a scene, a ray batch or a test; not cryptographic.
 * Pure functions of their arguments and the state they are handed, so
 * thread-safe with one state per thread.
 */
#ifndef VLFF_RNG_H
#define VLFF_RNG_H

#include <stdint.h>

#define VLFF_RNG_GAMMA 0x9e3779b97f4a7c15ull

/* The generator's output for state x + VLFF_RNG_GAMMA: also a good 64-bit
 * mix of x for hash tables and counter-based draws. */
static inline uint64_t vlff_mix64(uint64_t x) {
  uint64_t z = x + VLFF_RNG_GAMMA;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

/* Advances *s and returns the next 64 random bits. */
static inline uint64_t vlff_rng_next(uint64_t *s) {
  uint64_t z = vlff_mix64(*s);
  *s += VLFF_RNG_GAMMA;
  return z;
}

/* Uniform in [0, 1) with 53 random bits. */
static inline double vlff_rng_double(uint64_t *s) { return (double)(vlff_rng_next(s) >> 11) * 0x1.0p-53; }

#endif
