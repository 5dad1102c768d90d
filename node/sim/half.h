/*
 * IEEE 754 binary16 <-> binary32, round to nearest even. Internal to the
 * sim/dataset/eval modules: the same conversion as node/field's
 * vlff_f32_to_f16, kept here so these modules do not link the learner.
 */
#ifndef VLFF_HALF_H
#define VLFF_HALF_H

#include <stdint.h>
#include <string.h>

static inline uint16_t vlff_half_from_f32(float x) {
  uint32_t b;
  memcpy(&b, &x, 4);
  uint32_t sign = (b >> 16) & 0x8000u;
  uint32_t exp = (b >> 23) & 0xffu;
  uint32_t man = b & 0x7fffffu;
  if (exp == 0xff) return (uint16_t)(sign | 0x7c00u | (man ? 0x200u : 0));
  int e = (int)exp - 127 + 15;
  if (e >= 31) return (uint16_t)(sign | 0x7c00u);
  if (e <= 0) {
    if (e < -10) return (uint16_t)sign;
    man |= 0x800000u;
    uint32_t shift = (uint32_t)(14 - e);
    uint32_t h = man >> shift;
    uint32_t rem = man & ((1u << shift) - 1);
    uint32_t half = 1u << (shift - 1);
    if (rem > half || (rem == half && (h & 1))) h++;
    return (uint16_t)(sign | h);
  }
  uint32_t h = ((uint32_t)e << 10) | (man >> 13);
  uint32_t rem = man & 0x1fffu;
  if (rem > 0x1000u || (rem == 0x1000u && (h & 1))) h++; /* may carry into the exponent: correct */
  return (uint16_t)(sign | h);
}

static inline float vlff_half_to_f32(uint16_t h) {
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

#endif
