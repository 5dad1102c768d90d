/* IEEE 754 binary16 <-> binary32, round to nearest even; inf/NaN and
 * subnormals are preserved. The scalar pair is portable bit manipulation
 * (no F16C needed) and is the reference; the bulk pair converts whole
 * feature vectors, where the compiler has a binary16 type, through it:
 * F16C (vcvtps2ph/vcvtph2ps) in the x86-64-v3/v4 clones, native on ARMv8.2,
 * and libgcc's soft conversion otherwise, all rounding the same way. The
 * sim converts 1.2 M feature values per frame: the bit loop was a fifth of
 * its time. */
#include <string.h>

#include "field_internal.h"

uint16_t vlff_f32_to_f16(float x) {
  uint32_t b;
  memcpy(&b, &x, 4);
  uint32_t sign = (b >> 16) & 0x8000u;
  uint32_t exp = (b >> 23) & 0xffu;
  uint32_t man = b & 0x7fffffu;
  if (exp == 0xff) return (uint16_t)(sign | 0x7c00u | (man ? 0x200u | (man >> 13) : 0));
  int e = (int)exp - 127 + 15;
  if (e >= 31) return (uint16_t)(sign | 0x7c00u);
  if (e <= 0) {
    if (e < -10) return (uint16_t)sign;
    man |= 0x800000u;
    int shift = 14 - e;
    uint32_t h = man >> shift;
    uint32_t rem = man & ((1u << shift) - 1), half = 1u << (shift - 1);
    if (rem > half || (rem == half && (h & 1))) h++;
    return (uint16_t)(sign | h);
  }
  uint32_t h = ((uint32_t)e << 10) | (man >> 13);
  uint32_t rem = man & 0x1fffu;
  if (rem > 0x1000u || (rem == 0x1000u && (h & 1))) h++;  /* may carry into the exponent: correct */
  return (uint16_t)(sign | h);
}

float vlff_f16_to_f32(uint16_t h) {
  uint32_t sign = (uint32_t)(h & 0x8000u) << 16;
  uint32_t exp = (h >> 10) & 0x1fu;
  uint32_t man = h & 0x3ffu;
  uint32_t b;
  if (exp == 0) {
    if (man == 0) {
      b = sign;
    } else {
      int e = -1;
      do {
        e++;
        man <<= 1;
      } while (!(man & 0x400u));
      b = sign | ((uint32_t)(127 - 15 - e) << 23) | ((man & 0x3ffu) << 13);
    }
  } else if (exp == 31) {
    b = sign | 0x7f800000u | (man << 13);
  } else {
    b = sign | ((exp - 15 + 127) << 23) | (man << 13);
  }
  float x;
  memcpy(&x, &b, 4);
  return x;
}

#if defined(__FLT16_MAX__) && !defined(VLFF_NO_FLOAT16)
VLFF_HOT
void vlff_f32_to_f16_n(const float *src, uint16_t *dst, size_t n) {
  for (size_t i = 0; i < n; i++) {
    _Float16 h = (_Float16)src[i];
    memcpy(dst + i, &h, sizeof h);
  }
}

VLFF_HOT
void vlff_f16_to_f32_n(const uint16_t *src, float *dst, size_t n) {
  for (size_t i = 0; i < n; i++) {
    _Float16 h;
    memcpy(&h, src + i, sizeof h);
    dst[i] = (float)h;
  }
}
#else
void vlff_f32_to_f16_n(const float *src, uint16_t *dst, size_t n) {
  for (size_t i = 0; i < n; i++) dst[i] = vlff_f32_to_f16(src[i]);
}

void vlff_f16_to_f32_n(const uint16_t *src, float *dst, size_t n) {
  for (size_t i = 0; i < n; i++) dst[i] = vlff_f16_to_f32(src[i]);
}
#endif
