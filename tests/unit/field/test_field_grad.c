/*
 * Gradient checks of every stage against finite differences in double
 * precision: the float kernels' analytic gradients must match central
 * differences of a double-precision reference of the same function.
 */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <cmocka.h>

#include "field_internal.h"
#include "unit.h"

static uint64_t rng = 42;
static float frand(void) { return 2.0f * vlff_rng_uniform(&rng) - 1.0f; }
static float *falloc(size_t n) {
  float *p = calloc(n + 16, sizeof(float));
  assert_non_null(p);
  return p;
}

/* The prompt-scoring kernel of every instruction set this CPU runs, against
 * a double reference: logits, first argmax, second best, and the norm from
 * the triangular factor or the Gram matrix, over shapes with row, prompt
 * and panel tails. */
typedef void (*score_kernel)(int, int, int, const float *, int, const float *, const float *, const float *,
                             const float *, float, int, int *, float *, float *);
void vlff_score_generic(int, int, int, const float *, int, const float *, const float *, const float *, const float *,
                        float, int, int *, float *, float *);
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
void vlff_score_v3(int, int, int, const float *, int, const float *, const float *, const float *, const float *,
                   float, int, int *, float *, float *);
void vlff_score_v4(int, int, int, const float *, int, const float *, const float *, const float *, const float *,
                   float, int, int *, float *, float *);
#endif

typedef void (*gemm_kernel)(int, int, int, const float *, ptrdiff_t, ptrdiff_t, const float *, int, float *, int,
                            const float *, int, int, const float *);
void vlff_gemm_generic(int, int, int, const float *, ptrdiff_t, ptrdiff_t, const float *, int, float *, int,
                       const float *, int, int, const float *);
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
void vlff_gemm_v3(int, int, int, const float *, ptrdiff_t, ptrdiff_t, const float *, int, float *, int,
                  const float *, int, int, const float *);
void vlff_gemm_v4(int, int, int, const float *, ptrdiff_t, ptrdiff_t, const float *, int, float *, int,
                  const float *, int, int, const float *);
#endif

/* Whether this CPU runs the kernels of isa 0 (portable), 1 (AVX2 + FMA) or
 * 2 (AVX-512), each built beside the others. */
static int cpu_runs(int isa) {
  if (isa == 0) return 1;
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
  if (isa == 1) return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
         __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512vl");
#else
  return 0;
#endif
}

static void check_score(score_kernel fn, const char *isa, int m, int H, int K, int mode) {
  const int ldh = (m + 31) / 32 * 32;
  float *hT = falloc((size_t)H * ldh), *ewt = falloc((size_t)H * K), *eb = falloc(K), *rt = falloc((size_t)H * H);
  float *rv = falloc(H), *score = falloc(m), *margin = falloc(m);
  int *label = calloc((size_t)m, sizeof(int));
  assert_non_null(label);
  for (int i = 0; i < H * ldh; i++) hT[i] = (i % ldh) < m ? frand() : 0.0f;
  for (int i = 0; i < H * K; i++) ewt[i] = frand();
  for (int i = 0; i < K; i++) eb[i] = frand();
  for (int k = 0; k < H; k++)
    for (int i = 0; i < H; i++) rt[k * H + i] = mode == 2 ? 0.0f : frand();
  for (int k = 0; k < H; k++)
    for (int i = 0; i < H; i++) {
      if (mode == 1 && k < i) rt[k * H + i] = 0; /* Rᵀ: R upper triangular */
      if (mode == 2) {                           /* a symmetric G = AᵀA */
        double v = 0;
        for (int q = 0; q < H; q++) v += (double)((3 * q + i) % 5 - 2) * ((3 * q + k) % 5 - 2);
        rt[k * H + i] = (float)(v / H);
      }
    }
  for (int i = 0; i < H; i++) rv[i] = frand();
  const float r22 = 0.3f;
  fn(m, H, K, hT, ldh, ewt, eb, mode ? rt : NULL, rv, r22, mode == 2, label, score, margin);
  for (int p = 0; p < m; p++) {
    double b1 = -INFINITY, b2 = -INFINITY, l[64];
    int best = 0;
    for (int k = 0; k < K; k++) {
      double v = eb[k];
      for (int j = 0; j < H; j++) v += (double)ewt[j * K + k] * hT[j * ldh + p];
      l[k] = v;
      if (v > b1) {
        b2 = b1, b1 = v, best = k;
      } else if (v > b2) {
        b2 = v;
      }
    }
    double nrm = 1;
    if (mode) {
      double q = (double)r22 * r22;
      for (int i = 0; i < H; i++) {
        double y = 0;
        for (int k = 0; k < H; k++) y += (double)rt[k * H + i] * hT[k * ldh + p];
        q += mode == 1 ? (y + rv[i]) * (y + rv[i]) : (y + 2.0 * rv[i]) * hT[i * ldh + p];
      }
      nrm = sqrt(q > 0 ? q : 0);
    }
    double tol = 1e-5 * (H + 1) * (1 + fabs(b1));
    if (label[p] != best && !(l[label[p]] > b1 - tol))
      fail_msg("score %s m=%d H=%d K=%d mode %d point %d: label %d, best %d", isa, m, H, K, mode, p, label[p], best);
    if (fabs(score[p] - b1 / nrm) > tol / nrm + 1e-5 * fabs(b1 / nrm))
      fail_msg("score %s m=%d H=%d K=%d mode %d point %d: score %g vs %g", isa, m, H, K, mode, p, score[p], b1 / nrm);
    double mg = K > 1 ? (b1 - b2) / nrm : 0;
    if (fabs(margin[p] - mg) > 2 * tol / nrm + 1e-5 * fabs(mg))
      fail_msg("score %s m=%d H=%d K=%d mode %d point %d: margin %g vs %g", isa, m, H, K, mode, p, margin[p], mg);
  }
  free(hT), free(ewt), free(eb), free(rt), free(rv), free(score), free(margin), free(label);
}

static void test_score(void **state) {
  (void)state;
  struct {
    score_kernel fn;
    const char *isa;
    int runs;
  } kernels[] = {
      {vlff_score_generic, "generic", cpu_runs(0)},
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
      {vlff_score_v3, "avx2", cpu_runs(1)},
      {vlff_score_v4, "avx512", cpu_runs(2)},
#endif
  };
  const int shapes[][3] = {{1, 1, 1}, {5, 13, 3}, {37, 37, 20}, {64, 128, 20}, {33, 40, 32}, {100, 9, 7}, {17, 16, 2}};
  int ran = 0;
  for (size_t q = 0; q < sizeof(kernels) / sizeof(kernels[0]); q++) {
    if (!kernels[q].runs) continue;
    ran++;
    for (size_t s = 0; s < sizeof(shapes) / sizeof(shapes[0]); s++)
      for (int mode = 0; mode < 3; mode++)
        check_score(kernels[q].fn, kernels[q].isa, shapes[s][0], shapes[s][1], shapes[s][2], mode);
  }
  assert_true(ran >= 1);
}

/* GEMM against a double reference over shapes that hit every kernel path
 * of every kernel this CPU runs: full tiles, row tails of each height (1-7
 * rows past a multiple of 8, 6 or 4), column tails, strided A, bias,
 * accumulate, relu, mask. */
static void check_gemm(gemm_kernel fn, const char *isa, int m, int n, int k, int variant) {
  int trans = variant & 1, mode = variant >> 1; /* 0 bias+relu, 1 accumulate, 2 plain+mask */
  float *a = falloc((size_t)m * k), *b = falloc((size_t)k * n), *c = falloc((size_t)m * n);
  float *bias = falloc(n), *mask = falloc((size_t)m * n);
  double *ref = calloc((size_t)m * n, sizeof(double));
  for (int i = 0; i < m * k; i++) a[i] = frand();
  for (int i = 0; i < k * n; i++) b[i] = frand();
  for (int i = 0; i < m * n; i++) {
    c[i] = frand();
    mask[i] = frand();
  }
  for (int i = 0; i < n; i++) bias[i] = frand();
  ptrdiff_t ars = trans ? 1 : k, acs = trans ? m : 1;
  for (int i = 0; i < m; i++)
    for (int j = 0; j < n; j++) {
      double v = mode == 0 ? bias[j] : mode == 1 ? c[i * n + j] : 0.0;
      for (int q = 0; q < k; q++) v += (double)a[i * ars + q * acs] * b[q * n + j];
      if (mode == 0 && v < 0) v = 0;
      if (mode == 2 && !(mask[i * n + j] > 0)) v = 0;
      ref[i * n + j] = v;
    }
  fn(m, n, k, a, ars, acs, b, n, c, n, mode == 0 ? bias : NULL, mode == 1, mode == 0, mode == 2 ? mask : NULL);
  for (int i = 0; i < m * n; i++) {
    double tol = 1e-5 * (k + 1) + 1e-5 * fabs(ref[i]);
    if (fabs(c[i] - ref[i]) > tol)
      fail_msg("gemm %s %dx%dx%d variant %d at %d: %g vs %g", isa, m, n, k, variant, i, c[i], ref[i]);
  }
  free(a);
  free(b);
  free(c);
  free(bias);
  free(mask);
  free(ref);
}

static void test_gemm(void **state) {
  (void)state;
  struct {
    gemm_kernel fn;
    const char *isa;
    int runs;
  } kernels[] = {
      {vlff_gemm_generic, "generic", cpu_runs(0)},
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
      {vlff_gemm_v3, "avx2", cpu_runs(1)},
      {vlff_gemm_v4, "avx512", cpu_runs(2)},
#endif
  };
  const int shapes[][3] = {{1, 1, 1},    {3, 5, 7},    {17, 33, 9},  {64, 64, 44}, {9, 15, 128},  {8, 3, 64},
                           {33, 48, 300}, {4, 512, 16}, {130, 16, 1}, {7, 47, 260}, {15, 128, 45}, {44, 64, 30},
                           {31, 40, 20}, {6, 33, 5},    {5, 17, 12},  {13, 16, 3},  {2, 64, 9},
                           /* narrow outputs: dot products (k >= a vector), outer products (m a
                            * multiple of 16) */
                           {70, 3, 64},  {9, 4, 37},   {5, 1, 16},   {64, 3, 70},  {32, 2, 1},   {48, 4, 19}};
  int ran = 0;
  for (size_t q = 0; q < sizeof(kernels) / sizeof(kernels[0]); q++) {
    if (!kernels[q].runs) continue;
    ran++;
    for (size_t s = 0; s < sizeof(shapes) / sizeof(shapes[0]); s++)
      for (int variant = 0; variant < 6; variant++)
        check_gemm(kernels[q].fn, kernels[q].isa, shapes[s][0], shapes[s][1], shapes[s][2], variant);
  }
  assert_true(ran >= 1);
  /* And through the dispatcher. */
  check_gemm(vlff_gemm_mask, vlff_gemm_isa(), 15, 128, 45, 1);
}

/* Double reference of an MLP (ReLU hidden, linear output) and its loss
 * L = sum g . y. */
static double mlp_ref_loss(const struct vlff_mlp *m, const double *p, const double *x, int n, const float *g) {
  double loss = 0;
  double *cur = malloc(sizeof(double) * 1024), *nxt = malloc(sizeof(double) * 1024);
  for (int s = 0; s < n; s++) {
    for (int i = 0; i < m->nin; i++) cur[i] = x[s * m->nin + i];
    for (int l = 0; l < m->nl; l++) {
      for (int o = 0; o < m->dout[l]; o++) {
        double v = p[m->boff[l] + o];
        for (int i = 0; i < m->din[l]; i++) v += cur[i] * p[m->woff[l] + (size_t)i * m->dout[l] + o];
        nxt[o] = l < m->nl - 1 && v < 0 ? 0 : v;
      }
      double *t = cur;
      cur = nxt;
      nxt = t;
    }
    for (int o = 0; o < m->nout; o++) loss += g[s * m->nout + o] * cur[o];
  }
  free(cur);
  free(nxt);
  return loss;
}

static void check_mlp(int width, int hidden, int nout) {
  struct vlff_mlp m;
  size_t np = vlff_mlp_init(&m, 13, width, hidden, nout, 0);
  const int n = 11, wmax = width > nout ? width : nout;
  float *p = falloc(np), *wT = falloc(np), *grad = falloc(np), *x = falloc(n * 13), *g = falloc(n * nout);
  float *dx = falloc(n * 13), *tmp = falloc(n * wmax), *dy = falloc(n * wmax);
  uint64_t r = 7;
  vlff_mlp_init_params(&m, p, &r);
  for (int l = 0; l < m.nl; l++)
    for (int o = 0; o < m.dout[l]; o++) p[m.boff[l] + o] = 0.1f * frand();
  vlff_mlp_transpose(&m, p, wT);
  for (int i = 0; i < n * 13; i++) x[i] = frand();
  for (int i = 0; i < n * nout; i++) g[i] = frand();
  float *act[VLFF_MLP_MAX_LAYERS];
  for (int l = 0; l < m.nl; l++) act[l] = falloc(n * wmax);
  vlff_mlp_forward(&m, p, x, 13, n, m.nl, act);
  memcpy(dy, g, sizeof(float) * n * nout);
  vlff_mlp_backward(&m, wT, x, 13, n, m.nl, act, dy, grad, dx, tmp);
  double *pd = malloc(sizeof(double) * np), *xd = malloc(sizeof(double) * n * 13);
  for (size_t i = 0; i < np; i++) pd[i] = p[i];
  for (int i = 0; i < n * 13; i++) xd[i] = x[i];
  int checked = 0;
  for (int l = 0; l < m.nl; l++) {
    size_t offs[2] = {m.woff[l], m.boff[l]};
    size_t cnt[2] = {(size_t)m.din[l] * m.dout[l], (size_t)m.dout[l]};
    /* Every bias (their sums run in column blocks of 32, 16, 3 and the
     * rest), every fifth weight. */
    for (int kind = 0; kind < 2; kind++)
      for (size_t q = 0; q < cnt[kind]; q += kind ? 1 : 5) {
        size_t i = offs[kind] + q;
        double h = 1e-6, save = pd[i];
        pd[i] = save + h;
        double lp = mlp_ref_loss(&m, pd, xd, n, g);
        pd[i] = save - h;
        double lm = mlp_ref_loss(&m, pd, xd, n, g);
        pd[i] = save;
        double fd = (lp - lm) / (2 * h);
        if (fabs(fd - grad[i]) > 1e-3 * (1 + fabs(fd)))
          fail_msg("mlp layer %d %s %zu: analytic %g vs fd %g", l, kind ? "bias" : "weight", q, grad[i], fd);
        checked++;
      }
  }
  /* Input gradient, the input moved in double: a step small enough that
   * no hidden unit's pre-activation crosses zero within it (with 1e-3 in
   * float, some did, depending on the data). */
  double *xs = malloc(sizeof(double) * n * 13);
  for (int i = 0; i < n * 13; i += 3) {
    memcpy(xs, xd, sizeof(double) * n * 13);
    double h = 1e-6;
    xs[i] = x[i] + h;
    double lp = mlp_ref_loss(&m, pd, xs, n, g);
    xs[i] = x[i] - h;
    double lm = mlp_ref_loss(&m, pd, xs, n, g);
    double fd = (lp - lm) / (2 * h);
    if (fabs(fd - dx[i]) > 2e-3 * (1 + fabs(fd))) fail_msg("mlp dx %d: analytic %g vs fd %g", i, dx[i], fd);
    checked++;
  }
  assert_true(checked > 100);
  for (int l = 0; l < m.nl; l++) free(act[l]);
  free(p);
  free(wT);
  free(grad);
  free(x);
  free(g);
  free(dx);
  free(tmp);
  free(dy);
  free(pd);
  free(xs);
  free(xd);
}

static void test_mlp(void **state) {
  (void)state;
  check_mlp(24, 2, 19);
  check_mlp(67, 1, 3); /* the colour layer's 3 outputs; 67 = 32 + 32 + 3 */
  check_mlp(53, 1, 12); /* 53 = 32 + 16 + 5 */
}

static void small_cfg(struct vlff_config *cfg) {
  vlff_config_defaults(cfg);
  cfg->field.grow = false; /* the fixed box's encoding: dense coarse levels, the box's periods */
  cfg->field.hash_levels = 6;
  cfg->field.hash_log2_size = 10;
  cfg->field.base_resolution = 4;
  cfg->field.finest_resolution = 64;
  cfg->field.feature_dim = 16;
}

/* The encoding is linear in the table: its gradient must equal the
 * derivative of a double-precision trilinear interpolation. */
static void test_encoding(void **state) {
  (void)state;
  struct vlff_config cfg;
  small_cfg(&cfg);
  struct vlff_encoding e;
  vlff_encoding_init(&e, &cfg.field);
  size_t nt = (size_t)e.levels * e.size * e.feats;
  float *table = falloc(nt), *grad = falloc(nt);
  for (size_t i = 0; i < nt; i++) table[i] = frand();
  const int n = 9;
  float p[3 * n], *out = falloc((size_t)n * e.dim), *d = falloc((size_t)n * e.dim);
  for (int i = 0; i < 3 * n; i++) p[i] = 0.5f + 0.5f * frand();
  p[0] = 0.0f;
  p[1] = 1.0f;  /* box faces */
  for (int i = 0; i < n * e.dim; i++) d[i] = frand();
  vlff_encoding_forward(&e, table, p, n, out, e.dim);
  uint8_t *marks = calloc((size_t)e.levels * e.size, 1);
  for (int l = 0; l < e.levels; l++)
    vlff_encoding_backward(&e, p, n, d + l * e.feats, e.dim, l, grad + (size_t)l * e.size * e.feats,
                           marks + (size_t)l * e.size, 1);
  /* Double FD: L(table) = sum d . out; perturb each touched entry. */
  int checked = 0;
  for (int l = 0; l < e.levels; l++) {
    uint32_t marked = 0;
    for (uint32_t q = 0; q < e.size; q++) {
      if (!marks[(size_t)l * e.size + q]) {
        /* Unmarked entries keep the zero gradient Adam relies on. */
        for (int f = 0; f < e.feats; f++) assert_true(grad[((size_t)l * e.size + q) * e.feats + f] == 0.0f);
        continue;
      }
      assert_true(marks[(size_t)l * e.size + q] == 1);
      marked++;
      for (int f = 0; f < e.feats; f++) {
        size_t i = ((size_t)l * e.size + q) * e.feats + f;
        double fd = 0;
        /* out is linear: FD with a unit perturbation in double is exact. */
        float save = table[i];
        float *o2 = falloc((size_t)n * e.dim);
        table[i] = save + 1.0f;
        vlff_encoding_forward(&e, table, p, n, o2, e.dim);
        table[i] = save;
        for (int s = 0; s < n; s++)
          for (int c = 0; c < e.levels * e.feats; c++)
            fd += (double)d[s * e.dim + c] * ((double)o2[s * e.dim + c] - out[s * e.dim + c]);
        free(o2);
        if (fabs(fd - grad[i]) > 1e-4 * (1 + fabs(fd))) fail_msg("encoding level %d entry %u: %g vs %g", l, q, grad[i], fd);
        checked++;
      }
    }
    assert_true(marked > 0 && marked <= 8u * n);
  }
  assert_true(checked > 50);
  /* Frequency part: sin/cos of the normalised position, to within float
   * rounding of the argument (the polynomial itself is within 1e-7). */
  for (int s = 0; s < n; s++)
    for (int a = 0; a < 3; a++)
      for (int b = 0; b < e.freq_bands; b++) {
        double x = M_PI * p[3 * s + a] * (1 << b);
        const float *o = out + s * e.dim + e.levels * e.feats + a * 2 * e.freq_bands + 2 * b;
        assert_true(fabs(o[0] - sin(x)) < 2e-6 && fabs(o[1] - cos(x)) < 2e-6);
      }
  free(table);
  free(grad);
  free(out);
  free(d);
  free(marks);
}

/* Cells are cubic (encoding.c): one scale for every axis of an 8 x 4 x 2 m
 * box, its longest axis spanning [0, 1], so a metre moves the position as
 * far along z as along x; a point beyond a short axis's face is outside,
 * clamped to the face. The frequency part still spans [0, pi] over each
 * axis. Scaled per axis (a field checkpointed before version 5), each axis
 * spans [0, 1] and the frequency part is the same. */
static void test_encoding_cells(void **state) {
  (void)state;
  struct vlff_config cfg;
  small_cfg(&cfg);
  const double lo[3] = {-1, 2, 0}, hi[3] = {7, 6, 2};
  memcpy(cfg.field.scene_min, lo, sizeof lo);
  memcpy(cfg.field.scene_max, hi, sizeof hi);
  struct vlff_encoding e;
  vlff_encoding_init(&e, &cfg.field);
  assert_int_equal(e.cubic, 1);
  const float corner[3] = {7, 6, 2}, a[3] = {0, 3, 0.5f}, ax[3] = {1, 3, 0.5f}, az[3] = {0, 3, 1.5f},
              above[3] = {3, 4, 2.5f}, mid[3] = {3, 4, 1};
  float p[3], pa[3], px[3], pz[3];
  const size_t nt = (size_t)e.levels * e.size * e.feats;
  float *table = falloc(nt), *cub = falloc(e.dim), *axis = falloc(e.dim);
  for (size_t i = 0; i < nt; i++) table[i] = frand();
  for (int cubic = 1; cubic >= 0; cubic--) {
    vlff_encoding_set_cells(&e, cubic);
    assert_int_equal(vlff_encoding_normalise(&e, corner, p), 1);
    const float want[2][3] = {{1, 1, 1}, {1, 0.5f, 0.25f}};
    for (int k = 0; k < 3; k++) assert_true(fabsf(p[k] - want[cubic][k]) < 1e-6f);
    vlff_encoding_normalise(&e, a, pa);
    vlff_encoding_normalise(&e, ax, px);
    vlff_encoding_normalise(&e, az, pz);
    /* a metre along x and along z: 1/8 both, or 1/8 and 1/2 */
    assert_true(fabsf((px[0] - pa[0]) - 0.125f) < 1e-6f);
    assert_true(fabsf((pz[2] - pa[2]) - (cubic ? 0.125f : 0.5f)) < 1e-6f);
    assert_int_equal(vlff_encoding_normalise(&e, above, p), 0);
    assert_true(fabsf(p[2] - (cubic ? 0.25f : 1.0f)) < 1e-6f);
    vlff_encoding_normalise(&e, mid, p);
    vlff_encoding_forward(&e, table, p, 1, cubic ? cub : axis, e.dim);
  }
  /* The box's centre: pi / 2 on every axis in both, so the same frequency
   * part (the lowest octave: sin 1, cos 0); the hash grid's differs. */
  const int off = e.levels * e.feats;
  for (int k = 0; k < 6 * e.freq_bands; k++) assert_true(fabsf(cub[off + k] - axis[off + k]) < 1e-6f);
  assert_true(fabsf(cub[off] - 1) < 1e-6f && fabsf(cub[off + 1]) < 1e-6f);
  assert_true(memcmp(cub, axis, (size_t)off * sizeof(float)) != 0);
  free(table), free(cub), free(axis);
}

/* FNV-1a of n bytes, continuing from h. */
static uint64_t fnv1a(uint64_t h, const void *p, size_t n) {
  for (size_t i = 0; i < n; i++) h = (h ^ ((const unsigned char *)p)[i]) * 0x100000001b3ull;
  return h;
}

/* The AVX-512 and AVX2 kernels (isa) against the portable loops: the same touched entries,
 * outputs and gradients equal to float rounding (a term is one fused
 * multiply-add in the kernels; the portable loops contract to the same in
 * GCC's AVX-512 clones, the default build, and round the product first
 * where they are compiled without FMA). Dense and hashed levels, points on
 * the box faces, a count that ends inside a vector, a prefetch group and a
 * coordinate block, and masked (inactive) levels. *bits receives a digest
 * of the kernel's outputs and gradients. */
static void check_encoding_simd(int isa, bool grow, uint64_t *bits) {
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  cfg.field.grow = grow; /* fixed: dense and hashed levels; growing: from the world's centre */
  cfg.field.hash_log2_size = 14;
  cfg.field.finest_resolution = 512;
  struct vlff_encoding e;
  vlff_encoding_init(&e, &cfg.field);
  int dense = 0, hashed = 0, odd = 0;
  for (int l = 0; l < e.levels; l++) dense += e.dense[l], hashed += !e.dense[l], odd += e.shift[l][0] != 0;
  assert_true(grow ? dense == 0 && odd > 0 && odd < e.levels : dense > 0 && hashed > 0);
  size_t nt = (size_t)e.levels * e.size * e.feats;
  float *table = falloc(nt);
  for (size_t i = 0; i < nt; i++) table[i] = frand();
  const int n = 300;
  float *p = falloc(3 * (size_t)n), *a = falloc((size_t)n * e.dim), *b = falloc((size_t)n * e.dim);
  /* growing: most points near the centre (the first box), some anywhere in
   * the world, both signs */
  for (int i = 0; i < 3 * n; i++) p[i] = grow ? 0.5f * frand() * (i % 3 ? 0.01f : 1.0f) : 0.5f + 0.5f * frand();
  for (int i = 0; i < 12; i++) p[i] = (float)(i % 2) - (grow ? 0.5f : 0.0f); /* faces and corners of the box */
  for (int active = e.levels; active >= e.levels - 3; active -= 3) {
    e.active = active;
    for (int i = 0; i < n * e.dim; i++) a[i] = b[i] = frand();
    e.simd = isa;
    vlff_encoding_forward(&e, table, p, n, a, e.dim);
    e.simd = 0;
    vlff_encoding_forward(&e, table, p, n, b, e.dim);
    for (int i = 0; i < n * e.dim; i++)
      if (fabsf(a[i] - b[i]) > 1e-6f) fail_msg("encoding output %d of point %d: %g vs %g", i % e.dim, i / e.dim, a[i], b[i]);
  }
  /* Gradients and touched-entry marks, every level, from the same d; a
   * second pass accumulates onto entries the first one touched. */
  float *d = falloc((size_t)n * e.dim), *ga = falloc(nt), *gb = falloc(nt);
  size_t nm = (size_t)e.levels * e.size;
  uint8_t *ba = calloc(nm, 1), *bb = calloc(nm, 1);
  for (int i = 0; i < n * e.dim; i++) d[i] = frand();
  for (int pass = 0; pass < 2; pass++)
    for (int l = 0; l < e.levels; l++) {
      e.simd = isa;
      size_t go = (size_t)l * e.size * e.feats, mo = (size_t)l * e.size;
      vlff_encoding_backward(&e, p + 3 * pass, n - pass, d, e.dim, l, ga + go, ba + mo, 9);
      e.simd = 0;
      vlff_encoding_backward(&e, p + 3 * pass, n - pass, d, e.dim, l, gb + go, bb + mo, 9);
    }
  assert_memory_equal(ba, bb, nm);
  size_t touched = 0;
  for (size_t q = 0; q < nt / 2; q++)
    if (ba[q] == 9) {
      touched++;
      /* |d| <= 1 and trilinear weights sum to 1: terms are at most 1, an
       * entry sums a handful, so 1e-6 is a few ulps of them. A wrong
       * corner or weight is off by O(0.1). */
      for (int f = 0; f < 2; f++)
        if (fabsf(ga[2 * q + f] - gb[2 * q + f]) > 1e-6f)
          fail_msg("encoding level %zu entry %zu: %g vs %g", q / e.size, q % e.size, ga[2 * q + f], gb[2 * q + f]);
    }
  assert_true(touched > (size_t)n);
  *bits = fnv1a(fnv1a(0xcbf29ce484222325ull, a, (size_t)n * e.dim * sizeof(float)), ga, nt * sizeof(float));
  free(d);
  free(ga);
  free(gb);
  free(ba);
  free(bb);
  /* Both paths reading a zero table would agree too: the active levels'
   * outputs must carry the table's values. */
  double sum = 0;
  for (int i = 0; i < n; i++)
    for (int c = 0; c < e.active * e.feats; c++) sum += fabs(a[(size_t)i * e.dim + c]);
  assert_true(sum > 0);
  free(table);
  free(p);
  free(a);
  free(b);
}

static void test_encoding_simd(void **state) {
  (void)state;
  /* Both ISAs' kernels on the same inputs: the same arithmetic in the same
   * order, so the same bits. */
  const uint64_t seed = rng;
  uint64_t bits[3] = {0};
  int ran = 0;
  for (int grow = 0; grow <= 1; grow++) {
    ran = 0;
    for (int isa = 1; isa <= 2; isa++)
      if (cpu_runs(isa)) rng = seed, check_encoding_simd(isa, grow, &bits[isa]), ran++;
    if (!ran) skip(); /* this CPU runs the portable loop only */
    if (ran == 2) assert_true(bits[1] == bits[2]);
  }
}

/* Every level's output at n points drawn in [lo, hi] against a
 * double-precision trilinear interpolation in the world's corner frame
 * (corner, side: the world cube), on every kernel the CPU runs; returns
 * the levels checked. */
static int check_world_frame(struct vlff_encoding *e, const float *table, const double lo[3], const double hi[3],
                             const double corner[3], double side, int n) {
  float *out = falloc(e->dim);
  int checked = 0;
  for (int isa = 0; isa <= 2; isa++) {
    if (!cpu_runs(isa)) continue;
    e->simd = isa;
    for (int k = 0; k < n; k++) {
      float x[3], p[3];
      for (int a = 0; a < 3; a++) x[a] = (float)(lo[a] + (hi[a] - lo[a]) * (0.5 + 0.5 * frand()));
      assert_int_equal(vlff_encoding_normalise(e, x, p), 1);
      vlff_encoding_forward(e, table, p, 1, out, e->dim);
      for (int l = 0; l < e->levels; l++) {
        const double r = e->res[l];
        uint32_t c[3];
        double f[3];
        bool edge = false;
        for (int a = 0; a < 3; a++) {
          double pos = ((double)x[a] - corner[a]) / side * r;
          c[a] = (uint32_t)floor(pos);
          f[a] = pos - floor(pos);
          edge = edge || f[a] < 1e-3 || f[a] > 1 - 1e-3; /* a cell boundary: either side is right */
        }
        if (edge) continue;
        double want[2] = {0, 0};
        for (int q = 0; q < 8; q++) {
          uint32_t cx = c[0] + (q & 1), cy = c[1] + ((q >> 1) & 1), cz = c[2] + ((q >> 2) & 1);
          uint32_t idx = (cx ^ cy * 2654435761u ^ cz * 805459861u) & (e->size - 1);
          double w = ((q & 1) ? f[0] : 1 - f[0]) * ((q & 2) ? f[1] : 1 - f[1]) * ((q & 4) ? f[2] : 1 - f[2]);
          for (int ft = 0; ft < 2; ft++) want[ft] += w * table[((size_t)l * e->size + idx) * 2 + ft];
        }
        /* a weight 1/256 of a cell off moves an output by ~1e-2 */
        for (int ft = 0; ft < 2; ft++)
          if (fabs(out[2 * l + ft] - want[ft]) > 2e-4)
            fail_msg("isa %d level %d (res %.0f) point (%g, %g, %g): %.6f, the world frame's %.6f", isa, l, r,
                     (double)x[0], (double)x[1], (double)x[2], (double)out[2 * l + ft], want[ft]);
        checked++;
      }
      /* the frequency part: the corner frame's angle, pi over the first box */
      const int off = e->levels * e->feats;
      for (int a = 0; a < 3; a++)
        for (int b = 0; b < e->freq_bands; b++) {
          double t = M_PI * ((double)x[a] - corner[a]) / e->freq_ext[a] * (1 << b);
          const float *fo = out + off + a * 2 * e->freq_bands + 2 * b;
          if (fabs(fo[0] - sin(t)) > 1e-4 || fabs(fo[1] - cos(t)) > 1e-4)
            fail_msg("isa %d axis %d octave %d: sin/cos %g %g, the world frame's %g %g", isa, a, b, (double)fo[0],
                     (double)fo[1], sin(t), cos(t));
        }
    }
  }
  free(out);
  return checked;
}

/* A growing field's encoding is the world frame's (cells counted from the
 * world's low corner, field.h "Growth") to double precision: a float
 * position counted from that corner, ~86000 cells into the finest level
 * of a 2 km world, resolved only 1/128 of a cell, and the trilinear
 * weights of every point near the robot were that coarse. Here every
 * level's output equals a double-precision interpolation in the corner
 * frame, with the corner frame's cells (what a growing checkpoint learned
 * in), for points in a building-sized first box of a 1 km world; and,
 * once the origin has followed the box 900 m away
 * (vlff_encoding_set_origin), for points there, on every kernel the CPU
 * runs. */
static void test_encoding_world(void **state) {
  (void)state;
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  assert_true(cfg.field.grow && cfg.field.world_limit_m >= 1000);
  cfg.field.hash_log2_size = 14;
  const double lo[3] = {-12.2, -5, -1.5}, hi[3] = {12.2, 5, 1.5};
  memcpy(cfg.field.scene_min, lo, sizeof lo);
  memcpy(cfg.field.scene_max, hi, sizeof hi);
  struct vlff_encoding e;
  vlff_encoding_init(&e, &cfg.field);
  const double half = cfg.field.world_limit_m + 24.4, corner[3] = {-half, -half, -half};
  const size_t nt = (size_t)e.levels * e.size * e.feats;
  float *table = falloc(nt);
  for (size_t i = 0; i < nt; i++) table[i] = frand();
  assert_true(check_world_frame(&e, table, lo, hi, corner, 2 * half, 200) > 1000);
  const double o[3] = {900.3, -412.7, 20.1}, flo[3] = {888.1, -417.7, 18.6}, fhi[3] = {912.5, -407.7, 21.6};
  vlff_encoding_set_origin(&e, o);
  vlff_encoding_set_inside(&e, flo, fhi);
  assert_true(check_world_frame(&e, table, flo, fhi, corner, 2 * half, 200) > 1000);
  /* and a point keeps its encoding whatever the origin, to float rounding */
  float xs[3] = {890.25f, -410.5f, 19.75f}, p[3], *a = falloc(e.dim), *b = falloc(e.dim);
  const double o2[3] = {895.0, -409.0, 19.0};
  vlff_encoding_normalise(&e, xs, p);
  vlff_encoding_forward(&e, table, p, 1, a, e.dim);
  vlff_encoding_set_origin(&e, o2);
  vlff_encoding_normalise(&e, xs, p);
  vlff_encoding_forward(&e, table, p, 1, b, e.dim);
  for (int k = 0; k < e.dim; k++)
    if (fabsf(a[k] - b[k]) > 2e-4f) fail_msg("output %d moved with the origin: %g vs %g", k, (double)a[k], (double)b[k]);
  free(table), free(a), free(b);
}

static double render_ref(const double *sig, const float *delta, const float *v, int ns) {
  double T = 1, o = 0;
  for (int s = 0; s < ns; s++) {
    double a = 1 - exp(-sig[s] * delta[s]);
    o += T * a * v[s];
    T *= 1 - a;
  }
  return o;
}

static void test_render(void **state) {
  (void)state;
  const int ns = 24;
  float sigma[ns], delta[ns], w[ns], tr[ns], v[ns], ds[ns];
  double sd[ns];
  for (int s = 0; s < ns; s++) {
    sigma[s] = 2.0f * (1.0f + frand());
    delta[s] = 0.05f + 0.02f * frand();
    v[s] = frand();
    sd[s] = sigma[s];
  }
  int used = vlff_render_weights(sigma, delta, ns, w, tr);
  assert_int_equal(used, ns);
  vlff_render_backward(w, tr, sigma, delta, v, ns, ds);
  for (int s = 0; s < ns; s++) {
    double h = 1e-6, save = sd[s];
    sd[s] = save + h;
    double lp = render_ref(sd, delta, v, ns);
    sd[s] = save - h;
    double lm = render_ref(sd, delta, v, ns);
    sd[s] = save;
    double fd = (lp - lm) / (2 * h);
    if (fabs(fd - ds[s]) > 1e-4 * (1 + fabs(fd))) fail_msg("render dsigma[%d]: %g vs %g", s, ds[s], fd);
  }
  /* Early termination: a wall of density stops the ray. */
  for (int s = 0; s < ns; s++) sigma[s] = s == 5 ? 1e4f : 0.1f;
  used = vlff_render_weights(sigma, delta, ns, w, tr);
  assert_int_equal(used, 6);
  assert_true(w[ns - 1] == 0.0f);
}

static void test_losses(void **state) {
  (void)state;
  float pred[8], tgt[8], g[8];
  for (int i = 0; i < 8; i++) {
    pred[i] = frand();
    tgt[i] = frand();
  }
  vlff_loss_rgb(pred, tgt, 1.0f, g);
  for (int c = 0; c < 3; c++) {
    double h = 1e-4, l0 = 0, l1 = 0;
    for (int q = 0; q < 3; q++) {
      double a = pred[q] + (q == c ? h : 0) - tgt[q], b = pred[q] - (q == c ? h : 0) - tgt[q];
      l0 += a * a / 3;
      l1 += b * b / 3;
    }
    assert_true(fabs((l0 - l1) / (2 * h) - g[c]) < 1e-5);
  }
  float gd;
  assert_true(fabsf(vlff_loss_depth(2.0f, 1.5f, 0.5f, &gd) - 0.5f) < 1e-6f && gd == 0.5f);
  for (int l1 = 0; l1 < 2; l1++) {
    float loss = vlff_loss_feat(pred, tgt, 8, l1, 2.0f, g);
    double ref = 0;
    for (int i = 0; i < 8; i++) {
      double e = (double)pred[i] - tgt[i];
      ref += l1 ? fabs(e) : e * e;
    }
    assert_true(fabs(loss - ref / 8) < 1e-5);
    for (int i = 0; i < 8; i++) {
      double h = 1e-4, e = (double)pred[i] - tgt[i];
      double fd = l1 ? (fabs(e + h) - fabs(e - h)) / (2 * h) : ((e + h) * (e + h) - (e - h) * (e - h)) / (2 * h);
      assert_true(fabs(2.0 * fd / 8 - g[i]) < 1e-4);
    }
  }
  /* cosine: 1 - cos, finite differences of the gradient, and no NaN on a
   * zero prediction */
  float loss = vlff_loss_feat(pred, tgt, 8, VLFF_FEAT_LOSS_COS, 2.0f, g);
  double pt = 0, pp = 0, tt = 0;
  for (int i = 0; i < 8; i++) pt += (double)pred[i] * tgt[i], pp += (double)pred[i] * pred[i], tt += (double)tgt[i] * tgt[i];
  assert_true(fabs(loss - (1 - pt / sqrt(pp * tt))) < 1e-5);
  for (int i = 0; i < 8; i++) {
    double h = 1e-3, lp, lm;
    float q[8], gq[8];
    memcpy(q, pred, sizeof q);
    q[i] = pred[i] + (float)h;
    lp = vlff_loss_feat(q, tgt, 8, VLFF_FEAT_LOSS_COS, 1.0f, gq);
    q[i] = pred[i] - (float)h;
    lm = vlff_loss_feat(q, tgt, 8, VLFF_FEAT_LOSS_COS, 1.0f, gq);
    assert_true(fabs(2.0 * (lp - lm) / (2 * h) - g[i]) < 1e-3);
  }
  float zero[8] = {0};
  assert_true(vlff_loss_feat(zero, tgt, 8, VLFF_FEAT_LOSS_COS, 1.0f, g) == 0.0f);
  for (int i = 0; i < 8; i++) assert_true(g[i] == 0.0f);
}

static void test_adam(void **state) {
  (void)state;
  /* One step from zero moments moves each parameter by lr * sign(g)
   * (bias-corrected Adam); weight decay adds wd * p to the gradient. */
  struct vlff_adam a = {0.01f, 0.9f, 0.99f, 1e-15f, 0.1f, 0};
  float p[4] = {1, -1, 2, 0.5f}, g[4] = {0.3f, -2, 0, 1e-3f}, m[4] = {0}, v[4] = {0};
  vlff_adam_dense(&a, 1, a.lr, p, g, m, v, 0, 4, 0);
  assert_true(fabsf(p[0] - 0.99f) < 1e-6f && fabsf(p[1] + 0.99f) < 1e-6f && p[2] == 2.0f &&
              fabsf(p[3] - 0.49f) < 1e-6f);
  float q[2] = {1, 1}, gq[2] = {0, 0}, mq[2] = {0}, vq[2] = {0};
  vlff_adam_dense(&a, 1, a.lr, q, gq, mq, vq, 0, 2, 1);
  assert_true(fabsf(q[0] - 0.99f) < 1e-6f);
  uint8_t marks[70] = {0};
  marks[1] = marks[64] = 5; /* entries 1 and 64 of 70 */
  marks[2] = 4;             /* an earlier step's */
  float s[140], gs[140] = {0}, ms[140] = {0}, vs[140] = {0};
  for (int i = 0; i < 140; i++) s[i] = 1;
  gs[2] = gs[3] = gs[128] = gs[129] = 1;
  size_t lines = 0;
  assert_int_equal(vlff_adam_sparse(&a, 1, a.lr, s, gs, ms, vs, marks, 5, 70, 2, &lines), 2);
  assert_int_equal(lines, 2); /* bytes 8-15 and 512-519 of p */
  assert_true(s[0] == 1 && s[1] == 1 && fabsf(s[2] - 0.99f) < 1e-6f && fabsf(s[3] - 0.99f) < 1e-6f);
  assert_true(fabsf(s[128] - 0.99f) < 1e-6f && s[130] == 1 && s[126] == 1);
  for (int i = 0; i < 70; i++) assert_true(gs[2 * i] == 0 && gs[2 * i + 1] == 0);
  assert_true(s[4] == 1 && s[5] == 1);

  /* Dense words go through the whole-block path: it must move exactly the
   * marked entries, by the scalar update (to rounding: the library
   * may be built for another ISA than this test), and leave the others (and
   * the partial last word's tail) bit for bit alone. Width 2 and 3, marks
   * and (width 2) lines done portably and, where the CPU has them, with
   * AVX2 and AVX-512: all must give the same bits. */
  enum { NE = 64 * 5 + 37 };
  float portable[3][NE * 2];
  for (int simd = 0; simd <= 2; simd++)
  for (int width = 2; width <= 3 && cpu_runs(simd); width++) {
    a.simd = simd;
    size_t nf = (size_t)NE * width;
    float *pp = malloc(nf * 4), *gg = malloc(nf * 4), *mm = malloc(nf * 4), *vv = malloc(nf * 4);
    float *rp = malloc(nf * 4), *rm = malloc(nf * 4), *rv = malloc(nf * 4);
    uint64_t bb[6], seed = 99;
    uint8_t mk[NE];
    for (size_t i = 0; i < nf; i++) {
      rp[i] = pp[i] = vlff_rng_uniform(&seed) - 0.5f;
      gg[i] = vlff_rng_uniform(&seed) - 0.5f;
      rm[i] = mm[i] = 0.1f * (vlff_rng_uniform(&seed) - 0.5f);
      rv[i] = vv[i] = 0.01f * vlff_rng_uniform(&seed);
    }
    bb[0] = 0x8000000000000001ull;                 /* sparse: bit by bit */
    bb[1] = 0xffffffffffffffffull;                 /* full */
    bb[2] = 0x5555555555555555ull;                 /* every other entry */
    bb[3] = 0;
    bb[4] = 0x00ff00ff0000f00full;                 /* 28 bits */
    bb[5] = (1ull << 37) - 1 - (1ull << 5);        /* partial last word */
    size_t expect = 0;
    /* Marks from the words: this step's stamp (200), else a stamp of an
     * earlier step. Those run through 195 distinct values from stamp ^ 0x80
     * (in steps of 37), 0 where that would give the stamp: values one bit
     * or one carry from it among them. Unmarked entries hold a zero
     * gradient, as the scatter leaves them. */
    const uint8_t stamp = 200;
    unsigned u = 0;
    for (size_t e = 0; e < NE; e++) {
      if ((bb[e / 64] >> (e % 64)) & 1) {
        mk[e] = stamp;
        continue;
      }
      mk[e] = (uint8_t)((stamp + 128 + 37 * u++) % 256);
      if (mk[e] == stamp) mk[e] = 0;
      for (int f = 0; f < width; f++) gg[e * width + f] = 0;
    }
    uint8_t mk_copy[NE];
    memcpy(mk_copy, mk, sizeof mk);
    for (int wi = 0; wi < 6; wi++) expect += (size_t)__builtin_popcountll(bb[wi]);
    float c1 = 1.0f / (1.0f - powf(a.beta1, 3.0f)), c2 = 1.0f / (1.0f - powf(a.beta2, 3.0f));
    for (size_t e = 0; e < NE; e++) {
      if (!((bb[e / 64] >> (e % 64)) & 1)) continue;
      for (int f = 0; f < width; f++) {
        size_t i = e * width + f;
        float mi = a.beta1 * rm[i] + (1.0f - a.beta1) * gg[i];
        float vi = a.beta2 * rv[i] + (1.0f - a.beta2) * gg[i] * gg[i];
        rm[i] = mi, rv[i] = vi;
        rp[i] -= a.lr * (mi * c1) / (sqrtf(vi * c2) + a.eps);
      }
    }
    /* The lines: every 64-byte block of p that a marked entry's bytes
     * reach, counted once (at width 3 an entry can straddle two, and the
     * words' boundaries fall inside lines). */
    bool hit[NE * 3 * 4 / 64 + 1] = {false};
    size_t expect_lines = 0;
    for (size_t e = 0; e < NE; e++)
      if ((bb[e / 64] >> (e % 64)) & 1)
        for (size_t l = e * width * 4 / 64; l <= ((e + 1) * width * 4 - 1) / 64; l++)
          if (!hit[l]) hit[l] = true, expect_lines++;
    assert_int_equal(vlff_adam_sparse(&a, 3, a.lr, pp, gg, mm, vv, mk, stamp, NE, width, &lines), expect);
    assert_int_equal(lines, expect_lines);
    for (size_t i = 0; i < nf; i++) {
      size_t e = i / width;
      bool moved = (bb[e / 64] >> (e % 64)) & 1;
      assert_true(gg[i] == 0.0f);
      /* Tolerances: a few ulps of each quantity's largest term. */
      bool ok = moved ? fabsf(pp[i] - rp[i]) <= 1e-6f && fabsf(mm[i] - rm[i]) <= 1e-7f &&
                            fabsf(vv[i] - rv[i]) <= 1e-9f
                      : pp[i] == rp[i] && mm[i] == rm[i] && vv[i] == rv[i];
      if (!ok)
        fail_msg("width %d entry %zu feature %zu: %g %g %g, expected %g %g %g", width, i / width, i % width,
                 pp[i], mm[i], vv[i], rp[i], rm[i], rv[i]);
    }
    assert_memory_equal(mk, mk_copy, sizeof mk);
    if (width == 2) {
      float *got[3] = {pp, mm, vv};
      for (int arr = 0; arr < 3; arr++) {
        if (!simd) memcpy(portable[arr], got[arr], nf * 4);
        else assert_memory_equal(got[arr], portable[arr], nf * 4);
      }
    }
    free(pp), free(gg), free(mm), free(vv), free(rp), free(rm), free(rv);
  }
}

typedef void (*to_f32_fn)(const uint16_t *, float *, size_t);
typedef void (*to_f16_fn)(const float *, uint16_t *, size_t);

/* Each bulk conversion kernel the CPU runs, and the dispatcher, agree bit
 * for bit with the scalar reference over every binary16 value and over
 * floats near every rounding boundary, at every offset of a vector's tail. */
static void test_f16_bulk(void **state) {
  (void)state;
  enum { N = 65536 };
  const struct {
    to_f32_fn to32;
    to_f16_fn to16;
    int runs;
  } kernels[] = {
      {vlff_f16_to_f32_n, vlff_f32_to_f16_n, 1},
      {vlff_f16_to_f32_generic, vlff_f32_to_f16_generic, cpu_runs(0)},
#if VLFF_HALF_X86
      {vlff_f16_to_f32_v3, vlff_f32_to_f16_v3, cpu_runs(1)},
      {vlff_f16_to_f32_v4, vlff_f32_to_f16_v4, cpu_runs(2)},
#endif
  };
  uint16_t *h = malloc(N * sizeof *h), *h2 = malloc(4 * N * sizeof *h2);
  float *x = malloc(4 * N * sizeof *x), *y = malloc(N * sizeof *y);
  for (int i = 0; i < N; i++) h[i] = (uint16_t)i;
  /* Each finite half value, and points a quarter, a half (the tie) and
   * three quarters of the way to the next one. */
  int m = 0;
  for (int i = 0; i < N; i++) {
    float a = vlff_f16_to_f32((uint16_t)i), b = vlff_f16_to_f32((uint16_t)(i + 1));
    if (!isfinite(a) || !isfinite(b) || ((i + 1) & 0x7fff) == 0) continue;
    for (int q = 0; q < 4 && m < 4 * N; q++) x[m++] = a + (b - a) * (float)q / 4;
  }
  int ran = 0;
  for (size_t k = 0; k < sizeof(kernels) / sizeof(kernels[0]); k++) {
    if (!kernels[k].runs) continue;
    ran++;
    /* Offsets 0..16 leave every tail length after the 16- and 8-wide
     * loops; the lengths end inside a vector too. */
    for (int off = 0; off <= 16; off += 5) {
      memset(y, 0, N * sizeof *y);
      kernels[k].to32(h + off, y, (size_t)(N - off - 3));
      for (int i = 0; i < N - off - 3; i++) {
        float r = vlff_f16_to_f32(h[i + off]);
        if (isnan(r)) assert_true(isnan(y[i]));
        else if (memcmp(&r, &y[i], sizeof r)) fail_msg("kernel %zu: half 0x%04x gave %a, not %a", k, h[i + off], y[i], r);
      }
      assert_true(y[N - off - 3] == 0.0f); /* nothing past n */
      memset(h2, 0, 4 * N * sizeof *h2);
      kernels[k].to16(x + off, h2, (size_t)(m - off - 3));
      for (int i = 0; i < m - off - 3; i++)
        if (h2[i] != vlff_f32_to_f16(x[i + off]))
          fail_msg("kernel %zu: %a gave 0x%04x, not 0x%04x", k, x[i + off], h2[i], vlff_f32_to_f16(x[i + off]));
      assert_int_equal(h2[m - off - 3], 0);
    }
  }
  assert_true(ran >= 2);
  free(h), free(h2), free(x), free(y);
}

static void test_f16(void **state) {
  (void)state;
  const float vals[] = {0.0f, -0.0f, 1.0f, -2.5f, 65504.0f, 6.1035156e-05f, 5.9604645e-08f, 0.333251953125f};
  for (size_t i = 0; i < sizeof(vals) / sizeof(vals[0]); i++)
    assert_true(vlff_f16_to_f32(vlff_f32_to_f16(vals[i])) == vals[i]);
  assert_int_equal(vlff_f32_to_f16(1e6f), 0x7c00);
  assert_true(isnan(vlff_f16_to_f32(vlff_f32_to_f16(NAN))));
  /* Every half value survives a round trip; rounding is to nearest even. */
  for (uint32_t h = 0; h < 0x10000; h++) {
    if ((h & 0x7c00) == 0x7c00 && (h & 0x3ff)) continue;
    assert_int_equal(vlff_f32_to_f16(vlff_f16_to_f32((uint16_t)h)), h);
  }
  assert_int_equal(vlff_f32_to_f16(1.0f + 1.0f / 2048), 0x3c00);        /* tie -> even */
  assert_int_equal(vlff_f32_to_f16(1.0f + 3.0f / 2048), 0x3c02);        /* tie -> even (up) */
  for (float x = -3.0f; x < 3.0f; x += 0.01234f) {
    float y = vlff_f16_to_f32(vlff_f32_to_f16(x));
    assert_true(fabsf(y - x) <= fabsf(x) * (1.0f / 2048) + 1e-7f);
  }
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_gemm), cmocka_unit_test(test_score), cmocka_unit_test(test_mlp),
    cmocka_unit_test(test_encoding), cmocka_unit_test(test_encoding_cells), cmocka_unit_test(test_encoding_simd), cmocka_unit_test(test_encoding_world),
    cmocka_unit_test(test_render), cmocka_unit_test(test_losses), cmocka_unit_test(test_adam),
    cmocka_unit_test(test_f16), cmocka_unit_test(test_f16_bulk))
