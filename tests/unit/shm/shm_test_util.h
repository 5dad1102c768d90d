/* Helpers shared by the shm tests: unique segment names and a payload whose every
 * byte depends on the record number, so a torn or misplaced record cannot verify. */
#ifndef SHM_TEST_UTIL_H
#define SHM_TEST_UTIL_H

#include "vlff/shm.h"

#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <unistd.h>

static inline void test_name(char *buf, size_t len, const char *what) {
  static int counter;
  snprintf(buf, len, "/vlff-test-%s-%d-%d", what, (int)getpid(), counter++);
}

static inline uint64_t mix64(uint64_t x) {
  x ^= x >> 33;
  x *= 0xff51afd7ed558ccdull;
  x ^= x >> 33;
  x *= 0xc4ceb9fe1a85ec53ull;
  return x ^ (x >> 33);
}

/* Record: [id][len][payload...][checksum], len derived from id. */
struct test_rec_hdr {
  uint64_t id;
  uint64_t len;
};

static inline size_t test_rec_len(uint64_t id, size_t max) {
  size_t min = 32, l = min + (size_t)(mix64(id) % (max - min + 1));
  l &= ~(size_t)7;
  return l < min ? min : l;
}

static inline void test_rec_fill(uint8_t *p, uint64_t id, size_t len) {
  struct test_rec_hdr h = {id, len};
  memcpy(p, &h, sizeof h);
  uint64_t sum = 0, x = id;
  for (size_t o = sizeof h; o + 8 <= len - 8; o += 8) {
    x = mix64(x + o);
    memcpy(p + o, &x, 8);
    sum = sum * 31 + x;
  }
  sum ^= id;
  memcpy(p + len - 8, &sum, 8);
}

/* 0 if p holds exactly record id of length len. */
static inline int test_rec_check(const uint8_t *p, size_t len, uint64_t id) {
  struct test_rec_hdr h;
  if (len < sizeof h + 8)
    return -1;
  memcpy(&h, p, sizeof h);
  if (h.id != id || h.len != len)
    return -1;
  uint64_t sum = 0, x = id, v;
  for (size_t o = sizeof h; o + 8 <= len - 8; o += 8) {
    x = mix64(x + o);
    memcpy(&v, p + o, 8);
    if (v != x)
      return -1;
    sum = sum * 31 + x;
  }
  sum ^= id;
  memcpy(&v, p + len - 8, 8);
  return v == sum ? 0 : -1;
}

#endif
