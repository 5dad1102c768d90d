/*
 * FNV-1a, 64-bit: the one content hash of the node (config digests in
 * checkpoints, the publisher's observation files, token caches, hashed
 * prompt vectors). Not cryptographic. Pure, thread-safe.
 */
#ifndef VLFF_HASH_H
#define VLFF_HASH_H

#include <stddef.h>
#include <stdint.h>

#define VLFF_FNV1A64_INIT 0xcbf29ce484222325ull

/* Continues hash h over n bytes at p; start with VLFF_FNV1A64_INIT. */
static inline uint64_t vlff_fnv1a64(uint64_t h, const void *p, size_t n) {
  const unsigned char *b = p;
  for (size_t i = 0; i < n; i++) h = (h ^ b[i]) * 0x100000001b3ull;
  return h;
}

#endif
