/*
 * Adam (Kingma & Ba) with bias correction and decoupled-from-moments L2 weight
 * decay on MLP weights (added to the gradient, as torch.optim.Adam does).
 * The hash table is updated lazily: only entries that received a gradient
 * this step move, and their moments decay only then (as torch's SparseAdam):
 * a step touches a small part of a 2^19-entry level, and a dense pass over
 * every level's table would cost more than the rest of the step.
 */
#include <math.h>
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

#include "field_internal.h"

/* The update of one value; every portable path below goes through it. The
 * fused multiply-adds are spelled out (not left to contraction) so that the
 * AVX-512 kernel, which spells out the same ones, gives the same bits. They
 * are the ones GCC had contracted the dense update to (its results did not
 * change); the sparse paths had rounded otherwise, so the table's did, at
 * float rounding (eval within +-0.3 points of mIoU). */
static inline __attribute__((always_inline)) void adam_one(float b1, float b2, float c1, float c2, float eps,
                                                           float lr, float g, float *p, float *m, float *v) {
  float mi = fmaf(b1, *m, (1.0f - b1) * g);
  float vi = fmaf(b2, *v, (1.0f - b2) * g * g);
  *m = mi;
  *v = vi;
  *p -= (lr * (mi * c1)) / (sqrtf(vi * c2) + eps);
}

VLFF_HOT
void vlff_adam_dense(const struct vlff_adam *a, long long t, float lr, float *p, const float *g, float *m,
                     float *v, size_t i0, size_t i1, int decay) {
  float b1 = a->beta1, b2 = a->beta2;
  float c1 = 1.0f / (1.0f - powf(b1, (float)t)), c2 = 1.0f / (1.0f - powf(b2, (float)t));
  float wd = decay ? a->wd : 0.0f, eps = a->eps;
  for (size_t i = i0; i < i1; i++) adam_one(b1, b2, c1, c2, eps, lr, g[i] + wd * p[i], &p[i], &m[i], &v[i]);
}

/* One 64-entry block of the table in whole: every lane is computed and
 * the old values are kept where the entry was not touched. Late in a run most
 * words of the fine levels have many bits set; a streaming vector pass over
 * the block then costs less than one scattered scalar update per bit. */
static inline __attribute__((always_inline)) void adam_block(float b1, float b2, float c1, float c2, float eps,
                                                             float lr, float *restrict p, float *restrict g,
                                                             float *restrict m, float *restrict v, uint64_t word,
                                                             size_t entries, int width) {
  enum { MAXW = 8 };
  float on[64 * MAXW];
  size_t len = entries * (size_t)width;
  for (size_t j = 0; j < len; j++) on[j] = (float)((word >> (j / (size_t)width)) & 1);
  for (size_t j = 0; j < len; j++) {
    float pi = p[j], mi = m[j], vi = v[j];
    adam_one(b1, b2, c1, c2, eps, lr, g[j], &pi, &mi, &vi);
    g[j] = 0.0f; /* untouched lanes hold 0 already */
    bool t = on[j] != 0.0f;
    m[j] = t ? mi : m[j];
    v[j] = t ? vi : v[j];
    p[j] = t ? pi : p[j];
  }
}

/* Bit j: entry j of a run of ne <= 64 carries the stamp. */
static inline uint64_t marks_word(const uint8_t *t, uint8_t stamp, size_t ne) {
  uint64_t word = 0;
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
  if (ne == 64) {
    const uint64_t ones = 0x0101010101010101ull, low7 = 0x7f7f7f7f7f7f7f7full, high = 0x8080808080808080ull;
    for (int q = 0; q < 8; q++) {
      uint64_t x;
      memcpy(&x, t + 8 * q, 8);
      x ^= stamp * ones;
      /* High bit of each byte: that byte is nonzero (no carry crosses a
       * byte, as (x & 0x7f) + 0x7f <= 0xfe); then one 0/1 per equal byte. */
      uint64_t eq = (~(((x & low7) + low7) | x) & high) >> 7;
      /* Eight flags per multiply: byte q lands on bit 56 + q, and no two
       * partial products overlap, so nothing carries. */
      word |= ((eq * 0x0102040810204080ull) >> 56) << (8 * q);
    }
    return word;
  }
#endif
  for (size_t j = 0; j < ne; j++) word |= (uint64_t)(t[j] == stamp) << j;
  return word;
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define ADAM_BW 1
#include <immintrin.h>
/* One compare per 64 marks. The fine levels' marks are read whole every
 * step, so a byte-at-a-time portable scan is a visible share of it. */
__attribute__((target("avx512f,avx512bw"))) static void marks_words_bw(const uint8_t *t, uint8_t stamp, size_t nw,
                                                                      uint64_t *words) {
  const __m512i s = _mm512_set1_epi8((char)stamp);
  for (size_t k = 0; k < nw; k++) words[k] = _mm512_cmpeq_epi8_mask(_mm512_loadu_si512(t + 64 * k), s);
}

/* The same with AVX2: two compares and byte masks per 64 marks. */
__attribute__((target("avx2"))) static void marks_words_avx2(const uint8_t *t, uint8_t stamp, size_t nw,
                                                            uint64_t *words) {
  const __m256i s = _mm256_set1_epi8((char)stamp);
  for (size_t k = 0; k < nw; k++) {
    __m256i lo = _mm256_cmpeq_epi8(_mm256_loadu_si256((const __m256i *)(t + 64 * k)), s);
    __m256i hi = _mm256_cmpeq_epi8(_mm256_loadu_si256((const __m256i *)(t + 64 * k + 32)), s);
    words[k] = (uint64_t)(uint32_t)_mm256_movemask_epi8(lo) | (uint64_t)(uint32_t)_mm256_movemask_epi8(hi) << 32;
  }
}

/* One 64-entry word at width 2, a vector (eight entries: one line of each
 * array) per nonzero byte of its marks, untouched lanes kept by mask;
 * adam_one's arithmetic in the same order. A vector whenever any of a
 * line's entries was touched beats the portable policy below (scalar updates
 * for sparse words, a whole-block vector pass otherwise), whose loops GCC
 * compiles with scalar mask building. The sqrt and division are not what
 * bounds it (replaced by products, the time stayed); the lines' misses are. */
__attribute__((target("avx512f,avx512dq,fma"))) static void adam_word_v4(float b1, float b2, float c1, float c2,
                                                                        float eps, float lr, float *p, float *g,
                                                                        float *m, float *v, uint64_t word) {
  /* Lane pairs 2j, 2j+1 belong to entry j of the byte. */
  const __m512i lane_bit = _mm512_setr_epi32(1, 1, 2, 2, 4, 4, 8, 8, 16, 16, 32, 32, 64, 64, 128, 128);
  const __m512 vb1 = _mm512_set1_ps(b1), vb2 = _mm512_set1_ps(b2), nb1 = _mm512_set1_ps(1.0f - b1);
  const __m512 nb2 = _mm512_set1_ps(1.0f - b2), vc1 = _mm512_set1_ps(c1), vc2 = _mm512_set1_ps(c2);
  const __m512 veps = _mm512_set1_ps(eps), vlr = _mm512_set1_ps(lr);
  for (int by = 0; by < 8; by++) {
    unsigned bits = (unsigned)(word >> (8 * by)) & 0xffu;
    if (!bits) continue;
    const __mmask16 on = _mm512_test_epi32_mask(_mm512_set1_epi32((int)bits), lane_bit);
    const size_t o = 16 * (size_t)by;
    __m512 G = _mm512_loadu_ps(g + o), P = _mm512_loadu_ps(p + o);
    __m512 M = _mm512_loadu_ps(m + o), V = _mm512_loadu_ps(v + o);
    __m512 mi = _mm512_fmadd_ps(vb1, M, _mm512_mul_ps(nb1, G));
    __m512 vi = _mm512_fmadd_ps(vb2, V, _mm512_mul_ps(_mm512_mul_ps(nb2, G), G));
    __m512 den = _mm512_add_ps(_mm512_sqrt_ps(_mm512_mul_ps(vi, vc2)), veps);
    __m512 pi = _mm512_sub_ps(P, _mm512_div_ps(_mm512_mul_ps(vlr, _mm512_mul_ps(mi, vc1)), den));
    _mm512_storeu_ps(g + o, _mm512_setzero_ps()); /* untouched lanes hold 0 already */
    _mm512_mask_storeu_ps(p + o, on, pi);
    _mm512_mask_storeu_ps(m + o, on, mi);
    _mm512_mask_storeu_ps(v + o, on, vi);
  }
}

/* adam_word_v4 for CPUs with AVX2 but not AVX-512 (most x86 robot
 * computers): a vector per half line (four entries) with any entry touched,
 * the same arithmetic. AVX2 has no cheap masked store (vmaskmovps is slow
 * on AMD), so the new values are blended into the loaded ones and the half
 * line is stored whole: the same bits land in untouched lanes, and the
 * level's arrays belong to this thread while it updates them. AVX2-only
 * CPUs otherwise fall back to the portable policy, several times slower. */
__attribute__((target("avx2,fma"))) static void adam_word_v3(float b1, float b2, float c1, float c2, float eps,
                                                            float lr, float *p, float *g, float *m, float *v,
                                                            uint64_t word) {
  const __m256i lane_bit = _mm256_setr_epi32(1, 1, 2, 2, 4, 4, 8, 8);
  const __m256 vb1 = _mm256_set1_ps(b1), vb2 = _mm256_set1_ps(b2), nb1 = _mm256_set1_ps(1.0f - b1);
  const __m256 nb2 = _mm256_set1_ps(1.0f - b2), vc1 = _mm256_set1_ps(c1), vc2 = _mm256_set1_ps(c2);
  const __m256 veps = _mm256_set1_ps(eps), vlr = _mm256_set1_ps(lr);
  for (int q = 0; q < 16; q++) {
    unsigned bits = (unsigned)(word >> (4 * q)) & 0xfu;
    if (!bits) continue;
    const __m256 on = _mm256_castsi256_ps(
        _mm256_cmpeq_epi32(_mm256_and_si256(_mm256_set1_epi32((int)bits), lane_bit), lane_bit));
    const size_t o = 8 * (size_t)q;
    __m256 G = _mm256_loadu_ps(g + o), P = _mm256_loadu_ps(p + o);
    __m256 M = _mm256_loadu_ps(m + o), V = _mm256_loadu_ps(v + o);
    __m256 mi = _mm256_fmadd_ps(vb1, M, _mm256_mul_ps(nb1, G));
    __m256 vi = _mm256_fmadd_ps(vb2, V, _mm256_mul_ps(_mm256_mul_ps(nb2, G), G));
    __m256 den = _mm256_add_ps(_mm256_sqrt_ps(_mm256_mul_ps(vi, vc2)), veps);
    __m256 pi = _mm256_sub_ps(P, _mm256_div_ps(_mm256_mul_ps(vlr, _mm256_mul_ps(mi, vc1)), den));
    _mm256_storeu_ps(g + o, _mm256_setzero_ps()); /* untouched lanes hold 0 already */
    _mm256_storeu_ps(p + o, _mm256_blendv_ps(P, pi, on));
    _mm256_storeu_ps(m + o, _mm256_blendv_ps(M, mi, on));
    _mm256_storeu_ps(v + o, _mm256_blendv_ps(V, vi, on));
  }
}
#else
#define ADAM_BW 0
#endif

/* words[k] for the 64-entry runs from entry e0 on, nw of them, within n. */
static void marks_words(int simd, const uint8_t *marks, uint8_t stamp, size_t e0, size_t n, size_t nw,
                        uint64_t *words) {
  size_t k = 0;
#if ADAM_BW
  if (simd) {
    k = (n - e0) / 64 < nw ? (n - e0) / 64 : nw;
    if (simd == VLFF_ISA_AVX512)
      marks_words_bw(marks + e0, stamp, k, words);
    else
      marks_words_avx2(marks + e0, stamp, k, words);
  }
#else
  (void)simd;
#endif
  for (; k < nw; k++) {
    size_t s = e0 + 64 * k;
    words[k] = marks_word(marks + s, stamp, n - s < 64 ? n - s : 64);
  }
}

/* 64-byte lines of p holding an entry of the word at entry e0 (words start
 * on a line when a line holds whole entries; otherwise *last carries the
 * line counted last, which the next word's first entry may share). */
static inline size_t word_lines(uint64_t word, size_t e0, int width, size_t *last) {
  if (16 % width == 0) {
    const int per = 16 / width;
    uint64_t any = word;
    for (int s = 1; s < per; s <<= 1) any |= any >> s;
    return (size_t)__builtin_popcountll(any & (~0ull / ((1ull << per) - 1)));
  }
  size_t count = 0;
  for (; word; word &= word - 1) {
    size_t e = e0 + (size_t)__builtin_ctzll(word), bytes = (size_t)width * sizeof(float);
    for (size_t l = e * bytes / 64; l <= ((e + 1) * bytes - 1) / 64; l++)
      if (*last == SIZE_MAX || l > *last) {
        *last = l;
        count++;
      }
  }
  return count;
}

VLFF_HOT
size_t vlff_adam_sparse(const struct vlff_adam *a, long long t, float lr, float *p, float *g, float *m, float *v,
                        const uint8_t *marks, uint8_t stamp, size_t n, int width, size_t *lines) {
  /* Break-even: a vectorised block costs about what 16 scattered
   * single-entry updates do. Marks are packed to words a run at a time,
   * PF_AHEAD words beyond it, for the prefetch below. */
  enum { BLOCK_MIN_BITS = 16, PF_AHEAD = 16, RUN = 256 };
  float b1 = a->beta1, b2 = a->beta2;
  float c1 = 1.0f / (1.0f - powf(b1, (float)t)), c2 = 1.0f / (1.0f - powf(b2, (float)t));
  float eps = a->eps;
  size_t count = 0, nlines = 0, last = SIZE_MAX;
  const size_t nw = (n + 63) / 64;
#if ADAM_BW
  const int line_isa = width == 2 ? a->simd : 0;
#endif
  uint64_t words[RUN + PF_AHEAD];
  for (size_t w0 = 0; w0 < nw; w0 += RUN) {
    size_t nrun = nw - w0 < RUN ? nw - w0 : RUN;
    size_t npack = nw - w0 < RUN + PF_AHEAD ? nw - w0 : RUN + PF_AHEAD;
    marks_words(a->simd, marks, stamp, w0 * 64, n, npack, words);
    for (size_t k = 0; k < nrun; k++) {
      const size_t wi = w0 + k;
      /* Every word's lines are requested 16 words (8 KB per array) ahead,
       * a line per nonzero byte of its marks, so that their misses overlap
       * with the updates in between. Dense words too: four arrays read and
       * written, with sparse words between, are streams the hardware
       * prefetcher does not keep up with; the distance matters little
       * between 8 and 32 words. */
      uint64_t ahead = k + PF_AHEAD < npack ? words[k + PF_AHEAD] : 0;
      if (ahead)
        for (int by = 0; by < 8; by++)
          if ((ahead >> (8 * by)) & 0xff) {
            size_t i = ((wi + PF_AHEAD) * 64 + 8 * (size_t)by) * (size_t)width;
            __builtin_prefetch(p + i, 1);
            __builtin_prefetch(m + i, 1);
            __builtin_prefetch(v + i, 1);
            __builtin_prefetch(g + i, 1);
          }
      uint64_t word = words[k];
      if (!word) continue;
      size_t e0 = wi * 64, ne = n - e0 < 64 ? n - e0 : 64;
      int pop = __builtin_popcountll(word);
      nlines += word_lines(word, e0, width, &last);
#if ADAM_BW
      if (line_isa && ne == 64) {
        size_t o = e0 * 2;
        if (line_isa == VLFF_ISA_AVX512)
          adam_word_v4(b1, b2, c1, c2, eps, lr, p + o, g + o, m + o, v + o, word);
        else
          adam_word_v3(b1, b2, c1, c2, eps, lr, p + o, g + o, m + o, v + o, word);
        count += (size_t)pop;
        continue;
      }
#endif
      if (pop >= BLOCK_MIN_BITS && width <= 8) {
        size_t o = e0 * (size_t)width;
        /* The default width as a constant, so that call's index arithmetic
         * folds to shifts and its loop vectorises. */
        if (width == 2)
          adam_block(b1, b2, c1, c2, eps, lr, p + o, g + o, m + o, v + o, word, ne, 2);
        else
          adam_block(b1, b2, c1, c2, eps, lr, p + o, g + o, m + o, v + o, word, ne, width);
        count += (size_t)pop;
        continue;
      }
      while (word) {
        size_t e = e0 + (size_t)__builtin_ctzll(word);
        word &= word - 1;
        count++;
        for (int f = 0; f < width; f++) {
          size_t i = e * width + f;
          adam_one(b1, b2, c1, c2, eps, lr, g[i], &p[i], &m[i], &v[i]);
          g[i] = 0.0f;
        }
      }
    }
  }
  if (lines) *lines = nlines;
  return count;
}
