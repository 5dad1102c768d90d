/*
 * The prompt-scoring kernel of 3D queries, compiled once per instruction set
 * next to the GEMM (gemm_*.c define SCORE_FN and include this after
 * gemm_impl.h, whose VW, MR, NV and vector helpers it uses).
 *
 * Points are the vector lanes: the MLP3 hidden vectors come feature-major
 * (hT[H][ldh], point i in column i), and a panel of VW*NV points is scored
 * in registers from start to end. That layout is what makes the three parts
 * cheap where the point-major GEMMs were not:
 * - K logits cost K x H per point with no padding of K to the vector width
 *   (K = 20 ran as 32 point-major, at half the FMA rate for the remainder);
 * - the norm's triangular product skips the zeros of R (H(H+1)/2
 *   multiply-adds, against H^2/2 + 16 H for the point-major 32-column
 *   blocks), and its squares are summed in the tile's epilogue, so the
 *   H-vector R h is never stored;
 * - label, best and second-best are selected across lanes with masks
 *   instead of a branchy loop per point.
 * Sums run in a fixed order, so results do not vary from run to run.
 */
#include <math.h>

#include "config.h" /* VLFF_FIELD_MAX_PROMPTS */

static inline __attribute__((always_inline)) vf vsel(vi m, vf x, vf y) { return (vf)(((vi)x & m) | ((vi)y & ~m)); }

/* acc[r][v] = sum over k in [k0, H) of A(r, k) hT[k][panel v], A(r,k) =
 * a[r + k*acs]: mr rows of a transposed (column-major) matrix, whose mr
 * values per k are adjacent. tri: A is upper triangular from k0 (A(r,k) = 0
 * for k < k0 + r), so the first mr steps touch only the rows not yet zero. */
static inline __attribute__((always_inline)) void score_rows(const int mr, int tri, int k0, int H, const float *a,
                                                             ptrdiff_t acs, const float *hp, int ldh,
                                                             vf acc[MR][NV]) {
#pragma GCC unroll 8
  for (int r = 0; r < mr; r++)
#pragma GCC unroll 2
    for (int v = 0; v < NV; v++) acc[r][v] = (vf){0};
  int k = k0;
  if (tri && k0 + mr <= H) {
#pragma GCC unroll 8
    for (int t = 0; t < mr; t++, k++) {
      const float *bk = hp + (ptrdiff_t)k * ldh, *ak = a + (ptrdiff_t)k * acs;
      vf bv[NV];
#pragma GCC unroll 2
      for (int v = 0; v < NV; v++) bv[v] = vload(bk + VW * v);
#pragma GCC unroll 8
      for (int r = 0; r <= t; r++) {
        float av = ak[r];
#pragma GCC unroll 2
        for (int v = 0; v < NV; v++) acc[r][v] += av * bv[v];
      }
    }
  }
  for (; k < H; k++) {
    const float *bk = hp + (ptrdiff_t)k * ldh, *ak = a + (ptrdiff_t)k * acs;
    vf bv[NV];
#pragma GCC unroll 2
    for (int v = 0; v < NV; v++) bv[v] = vload(bk + VW * v);
#pragma GCC unroll 8
    for (int r = 0; r < mr; r++) {
      float av = ak[r];
#pragma GCC unroll 2
      for (int v = 0; v < NV; v++) acc[r][v] += av * bv[v];
    }
  }
}

/* One instance per row count, so every tile keeps its accumulators in
 * registers (a loop of 1-row tiles for K % MR would run at a quarter of the
 * FMA rate, bound by latency). */
#define SCORE_ROWS_CASES(mr, ...)                                                                                    \
  switch (mr) {                                                                                                      \
  case 1: score_rows(1, __VA_ARGS__); break;                                                                         \
  case 2: score_rows(2 < MR ? 2 : MR, __VA_ARGS__); break;                                                           \
  case 3: score_rows(3 < MR ? 3 : MR, __VA_ARGS__); break;                                                           \
  case 4: score_rows(4 < MR ? 4 : MR, __VA_ARGS__); break;                                                           \
  case 5: score_rows(5 < MR ? 5 : MR, __VA_ARGS__); break;                                                           \
  case 6: score_rows(6 < MR ? 6 : MR, __VA_ARGS__); break;                                                           \
  case 7: score_rows(7 < MR ? 7 : MR, __VA_ARGS__); break;                                                           \
  default: score_rows(MR, __VA_ARGS__); break;                                                                       \
  }

void SCORE_FN(int m, int H, int K, const float *hT, int ldh, const float *ewt, const float *eb, const float *rt,
              const float *rv, float r22, int gram, int *label, float *score, float *margin) {
  const int P = VW * NV;
  vf lg[VLFF_FIELD_MAX_PROMPTS][NV], acc[MR][NV];
  for (int p0 = 0; p0 < m; p0 += P) {
    const float *hp = hT + p0;
    for (int k0 = 0; k0 < K; k0 += MR) {
      int mr = K - k0 < MR ? K - k0 : MR;
      SCORE_ROWS_CASES(mr, 0, 0, H, ewt + k0, K, hp, ldh, acc)
      for (int r = 0; r < mr; r++)
        for (int v = 0; v < NV; v++) lg[k0 + r][v] = acc[r][v] + eb[k0 + r];
    }
    /* The scalar selection's rule per lane: a strictly greater logit takes
     * the lead (ties keep the lower index), the old lead becomes second. */
    vf b1[NV], b2[NV];
    vi best[NV];
    for (int v = 0; v < NV; v++) {
      b1[v] = b2[v] = (vf){0} - __builtin_inff();
      best[v] = (vi){0};
    }
    for (int k = 0; k < K; k++)
      for (int v = 0; v < NV; v++) {
        vf x = lg[k][v];
        vi up1 = x > b1[v], up2 = x > b2[v];
        b2[v] = vsel(up1, b1[v], vsel(up2, x, b2[v]));
        b1[v] = vsel(up1, x, b1[v]);
        best[v] = (best[v] & ~up1) | (((vi){0} + k) & up1);
      }
    vf sq[NV];
    for (int v = 0; v < NV; v++) sq[v] = (vf){0};
    if (rt) {
      for (int i0 = 0; i0 < H; i0 += MR) {
        int mr = H - i0 < MR ? H - i0 : MR;
        /* R is upper triangular: row i needs k >= i only, so the tile
         * starts at its first row's diagonal. The Gram form needs all k. */
        SCORE_ROWS_CASES(mr, !gram, gram ? 0 : i0, H, rt + i0, H, hp, ldh, acc)
        for (int r = 0; r < mr; r++)
          for (int v = 0; v < NV; v++) {
            if (gram) {
              vf h = vload(hp + (ptrdiff_t)(i0 + r) * ldh + VW * v);
              sq[v] += (acc[r][v] + 2.0f * rv[i0 + r]) * h;
            } else {
              vf y = acc[r][v] + rv[i0 + r];
              sq[v] += y * y;
            }
          }
      }
    }
    int np = m - p0 < P ? m - p0 : P;
    for (int v = 0; v < NV; v++)
      for (int j = 0; j < VW && v * VW + j < np; j++) {
        int i = p0 + v * VW + j;
        float s1 = b1[v][j], s2 = b2[v][j], inv = 1.0f;
        if (rt) {
          float q = sq[v][j] + r22 * r22;
          float nrm = sqrtf(q > 0 ? q : 0);
          inv = nrm > 1e-20f ? 1.0f / nrm : 0.0f;
        }
        if (label) label[i] = best[v][j];
        if (score) score[i] = s1 * inv;
        if (margin) margin[i] = K > 1 ? (s1 - s2) * inv : 0.0f;
      }
  }
}
