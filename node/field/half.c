/* IEEE 754 binary16 <-> binary32, round to nearest even; inf/NaN and
 * subnormals are preserved. The scalar pair is portable bit manipulation
 * (no F16C needed) and is the reference; the bulk pair converts whole
 * feature vectors, where the compiler has a binary16 type, through it:
 * F16C (vcvtps2ph/vcvtph2ps) in the x86-64-v3/v4 clones, native on ARMv8.2,
 * and libgcc's soft conversion otherwise, all rounding the same way. The
 * sim converts 1.2 M feature values per frame: the bit loop was a fifth of
 * its time. */
#include <pthread.h>
#include <string.h>

#include "field_internal.h"
#if VLFF_HALF_X86
#include <immintrin.h>
#endif

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
void vlff_f32_to_f16_generic(const float *src, uint16_t *dst, size_t n) {
  for (size_t i = 0; i < n; i++) {
    _Float16 h = (_Float16)src[i];
    memcpy(dst + i, &h, sizeof h);
  }
}

VLFF_HOT
void vlff_f16_to_f32_generic(const uint16_t *src, float *dst, size_t n) {
  for (size_t i = 0; i < n; i++) {
    _Float16 h;
    memcpy(&h, src + i, sizeof h);
    dst[i] = (float)h;
  }
}
#else
void vlff_f32_to_f16_generic(const float *src, uint16_t *dst, size_t n) {
  for (size_t i = 0; i < n; i++) dst[i] = vlff_f32_to_f16(src[i]);
}

void vlff_f16_to_f32_generic(const uint16_t *src, float *dst, size_t n) {
  for (size_t i = 0; i < n; i++) dst[i] = vlff_f16_to_f32(src[i]);
}
#endif

#if VLFF_HALF_X86
/* GCC 12 converts a _Float16 loop, and even a _Float16 vector, one value per
 * instruction, and every ray's D-wide target feature is converted each
 * step. These take 16 (8) per instruction. */
__attribute__((target("avx512f"))) void vlff_f16_to_f32_v4(const uint16_t *src, float *dst, size_t n) {
  size_t i = 0;
  for (; i + 16 <= n; i += 16)
    _mm512_storeu_ps(dst + i, _mm512_cvtph_ps(_mm256_loadu_si256((const __m256i *)(src + i))));
  vlff_f16_to_f32_generic(src + i, dst + i, n - i);
}

__attribute__((target("avx512f"))) void vlff_f32_to_f16_v4(const float *src, uint16_t *dst, size_t n) {
  size_t i = 0;
  for (; i + 16 <= n; i += 16)
    _mm256_storeu_si256((__m256i *)(dst + i), _mm512_cvtps_ph(_mm512_loadu_ps(src + i), _MM_FROUND_TO_NEAREST_INT));
  vlff_f32_to_f16_generic(src + i, dst + i, n - i);
}

__attribute__((target("avx,f16c"))) void vlff_f16_to_f32_v3(const uint16_t *src, float *dst, size_t n) {
  size_t i = 0;
  for (; i + 8 <= n; i += 8) _mm256_storeu_ps(dst + i, _mm256_cvtph_ps(_mm_loadu_si128((const __m128i *)(src + i))));
  vlff_f16_to_f32_generic(src + i, dst + i, n - i);
}

__attribute__((target("avx,f16c"))) void vlff_f32_to_f16_v3(const float *src, uint16_t *dst, size_t n) {
  size_t i = 0;
  for (; i + 8 <= n; i += 8)
    _mm_storeu_si128((__m128i *)(dst + i), _mm256_cvtps_ph(_mm256_loadu_ps(src + i), _MM_FROUND_TO_NEAREST_INT));
  vlff_f32_to_f16_generic(src + i, dst + i, n - i);
}
#endif

/* The kernel pair follows the GEMM's choice (VLFF_GEMM=generic makes it
 * portable). x86-64-v3 includes F16C, and no CPU with AVX2 and FMA lacks it;
 * libgcc 12's __builtin_cpu_supports does not report f16c. */
struct half_kernels {
  void (*to32)(const uint16_t *, float *, size_t);
  void (*to16)(const float *, uint16_t *, size_t);
};

static const struct half_kernels half_kernels[] = {
    {vlff_f16_to_f32_generic, vlff_f32_to_f16_generic},
#if VLFF_HALF_X86
    {vlff_f16_to_f32_v3, vlff_f32_to_f16_v3},
    {vlff_f16_to_f32_v4, vlff_f32_to_f16_v4},
#endif
};
static const struct half_kernels *half_used;
static pthread_once_t half_once = PTHREAD_ONCE_INIT;

/* Picked once: the conversions run per ray and per pixel. */
static void half_init(void) {
  half_used = &half_kernels[VLFF_HALF_X86 ? vlff_gemm_isa_level() : 0];
}

static const struct half_kernels *half_pick(void) {
  pthread_once(&half_once, half_init);
  return half_used;
}

void vlff_f16_to_f32_n(const uint16_t *src, float *dst, size_t n) { half_pick()->to32(src, dst, n); }

void vlff_f32_to_f16_n(const float *src, uint16_t *dst, size_t n) { half_pick()->to16(src, dst, n); }
