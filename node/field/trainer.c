/*
 * The trainer: plans every buffer at create, then each step
 *   1. draws rays from the views (serial, cheap, deterministic),
 *   2. runs work chunks of rays in parallel: sample, encode, MLP1, weights,
 *      MLP2 on live samples, MLP3's hidden layers on samples that carry
 *      weight, render, loss, backward; MLP gradients go to per-thread buffers,
 *   3. reduces those, scatters hash-grid gradients level by level (each level
 *      owned by one thread: no atomics, no races),
 *   4. Adam (lazy on the table), refreshes derived weights.
 *
 * MLP3's output layer is linear, so it commutes with rendering: the hidden
 * activation h is rendered per ray, H = sum w_s h_s, and the D-wide layer is
 * applied once per ray, F = W H + (sum w_s) b. Backward likewise: dH = Wᵀ dF,
 * dh_s = w_s dH, and the sample's scalar for the weight gradient is
 * dF . f_s = dH . h_s + dF . b. Exact, and D x H work per ray, not per sample.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>
#include <unistd.h>

#include "field_internal.h"
#include "mem.h"

static void seterr(char *err, size_t n, const char *fmt, const char *what) {
  if (err && n) snprintf(err, n, fmt, what);
}

static void *xalloc(size_t n, int *ok) {
  if (!*ok) return NULL;
  void *p = NULL;
  if (n == 0) n = 64;
  if (posix_memalign(&p, 64, (n + 63) & ~(size_t)63)) {
    *ok = 0;
    return NULL;
  }
  memset(p, 0, n);
  return p;
}

static int imax(int a, int b) { return a > b ? a : b; }

/* Chunks of a step of nrays rays: as few as hold chunk_rays rays each, then
 * rounded up to a multiple of the threads, whose static shares would
 * otherwise differ by a chunk and leave one thread idle at the end of the
 * rays phase. Rays are spread evenly over them. */
static int step_chunks(const struct vlff_field *f, int nrays) {
  int n = (nrays + f->chunk_rays - 1) / f->chunk_rays;
  n = (n + f->threads - 1) / f->threads * f->threads;
  return n < nrays ? n : nrays;
}

static void work_free(struct vlff_work *w) {
  void **ptrs[] = {(void **)&w->t, (void **)&w->delta, (void **)&w->sigma, (void **)&w->w, (void **)&w->trans,
                   (void **)&w->e, (void **)&w->dsig, (void **)&w->ray_off, (void **)&w->ray_cnt,
                   (void **)&w->ray_used, (void **)&w->sel2, (void **)&w->sel3, (void **)&w->ray_of,
                   (void **)&w->p, (void **)&w->enc, (void **)&w->in2, (void **)&w->in3, (void **)&w->dy_a,
                   (void **)&w->dy_b, (void **)&w->dout1, (void **)&w->din2, (void **)&w->din3,
                   (void **)&w->denc, (void **)&w->hray, (void **)&w->fray, (void **)&w->gf, (void **)&w->dh,
                   (void **)&w->wsum, (void **)&w->tfeat, (void **)&w->rgb, (void **)&w->depth, (void **)&w->depth2,
                   (void **)&w->logits, (void **)&w->grad, (void **)&w->opac, (void **)&w->norm, (void **)&w->rbuf,
                   (void **)&w->tgrad, (void **)&w->tmarks};
  for (size_t i = 0; i < sizeof(ptrs) / sizeof(ptrs[0]); i++) {
    free(*ptrs[i]);
    *ptrs[i] = NULL;
  }
  for (int l = 0; l < VLFF_MLP_MAX_LAYERS; l++) {
    free(w->a1[l]);
    free(w->a2[l]);
    free(w->a3[l]);
    w->a1[l] = w->a2[l] = w->a3[l] = NULL;
  }
}

static int work_alloc(struct vlff_field *f, struct vlff_work *w) {
  int ok = 1;
  size_t N = (size_t)w->cap, R = (size_t)w->rcap, fs = sizeof(float);
  int maxw = imax(imax(imax(f->E, f->m1.width), imax(f->m2.width, f->H)), imax(f->geo + f->shdim, 16));
  w->t = xalloc(N * fs, &ok);
  w->delta = xalloc(N * fs, &ok);
  w->sigma = xalloc(N * fs, &ok);
  w->w = xalloc(N * fs, &ok);
  w->trans = xalloc(N * fs, &ok);
  w->e = xalloc(N * fs, &ok);
  w->dsig = xalloc(N * fs, &ok);
  w->ray_off = xalloc(R * sizeof(int), &ok);
  w->ray_cnt = xalloc(R * sizeof(int), &ok);
  w->ray_used = xalloc(R * sizeof(int), &ok);
  w->sel2 = xalloc(N * sizeof(int), &ok);
  w->sel3 = xalloc(N * sizeof(int), &ok);
  w->ray_of = xalloc(N * sizeof(int), &ok);
  w->p = xalloc(N * 3 * fs, &ok);
  w->enc = xalloc(N * f->E * fs, &ok);
  for (int l = 0; l < f->m1.nl; l++) w->a1[l] = xalloc(N * f->m1.dout[l] * fs, &ok);
  for (int l = 0; l < f->m2.nl; l++) w->a2[l] = xalloc(N * f->m2.dout[l] * fs, &ok);
  for (int l = 0; l < f->m3.nl - 1; l++) w->a3[l] = xalloc(N * f->m3.dout[l] * fs, &ok);
  w->in2 = xalloc(N * (f->geo + f->shdim) * fs, &ok);
  w->in3 = xalloc(N * f->geo * fs, &ok);
  w->dy_a = xalloc(N * maxw * fs, &ok);
  w->dy_b = xalloc(N * maxw * fs, &ok);
  w->dout1 = xalloc(N * maxw * fs, &ok);
  w->din2 = xalloc(N * (f->geo + f->shdim) * fs, &ok);
  w->din3 = xalloc(N * f->geo * fs, &ok);
  w->denc = xalloc(N * f->E * fs, &ok);
  size_t RD = R * (size_t)imax(f->D, imax(f->H, VLFF_FIELD_MAX_PROMPTS));
  w->hray = xalloc(R * f->H * fs, &ok);
  w->fray = xalloc(RD * fs, &ok);
  w->gf = xalloc(RD * fs, &ok);
  w->dh = xalloc(R * f->H * fs, &ok);
  w->wsum = xalloc(R * fs, &ok);
  w->tfeat = xalloc(RD * fs, &ok);
  w->rgb = xalloc(R * 3 * fs, &ok);
  w->depth = xalloc(R * fs, &ok);
  w->depth2 = xalloc(R * fs, &ok);
  w->logits = xalloc(RD * fs, &ok);
  w->grad = xalloc(f->nmlp * fs, &ok);
  w->tgrad = xalloc(f->enc.size * (size_t)f->enc.feats * fs, &ok);
  w->tmarks = xalloc(f->enc.size, &ok);
  w->opac = xalloc(R * fs, &ok);
  w->norm = xalloc(R * (size_t)f->H * fs, &ok);
  w->rbuf = xalloc(R * sizeof(struct vlff_ray), &ok);
  return ok ? 0 : -1;
}

/* The learned state of a new field, from a fixed seed: two fields built
 * from one config start identical, and a field re-initialised is the one
 * it was created as. */
static void init_state(struct vlff_field *f) {
  /* A growing field starts over in its first box (or, when memory for it
   * cannot be had, in the box it has: the cells are reset all the same).
   * A new field's grid is that box already. */
  if (f->cfg.field.grow) {
    int k0[3], dims[3], same = 1;
    vlff_field_first_layout(f, k0, dims);
    for (int a = 0; a < 3; a++) same &= f->occ_k0[a] == k0[a] && f->occ.dims[a] == dims[a];
    if (!same) (void)vlff_field_occ_layout(f, k0, dims, 0);
  }
  const size_t ncell = vlff_occ_cells(&f->occ), fs = sizeof(float);
  f->rng = 0x5eed0f1e1dull;
  for (size_t i = 0; i < f->ntable; i++) f->params[i] = (2.0f * vlff_rng_uniform(&f->rng) - 1.0f) * 1e-4f;
  float *pm = vlff_mlp_params(f);
  vlff_mlp_init_params(&f->m1, pm, &f->rng);
  vlff_mlp_init_params(&f->m2, pm, &f->rng);
  vlff_mlp_init_params(&f->m3, pm, &f->rng);
  memset(f->adam_m, 0, f->nparams * fs);
  memset(f->adam_v, 0, f->nparams * fs);
  memset(f->occ.density, 0, ncell * fs);
  memset(f->occ.occ, 1, ncell);
  memset(f->exposure, 0, ncell * sizeof *f->exposure);
  memset(f->bal_freq, 0, sizeof f->bal_freq);
  f->step = 0;
  f->occ_cursor = 0;
  vlff_encoding_set_cells(&f->enc, 1);
  vlff_field_forget_errors(f);
  vlff_field_reset_average(f);
}

void vlff_field_destroy(struct vlff_field *f) {
  if (!f) return;
  if (f->pool) vlff_pool_destroy(f->pool);
  if (f->work)
    for (int i = 0; i < f->threads; i++) work_free(&f->work[i]);
  VLFF_FREE_ALL(f->work, f->params, f->adam_m, f->adam_v, f->grad, f->wT, f->avg, f->avgT, f->occ.density,
                f->occ.occ, f->exposure, f->cell_err, f->ray_loss, f->rays, f->step_p, f->step_denc, f->chunk_n,
                f->E_, f->bal_feat, f->EW, f->EWt, f->Eb, f->G, f->u, f->Rt, f->r12, f);
}

uint64_t vlff_field_plan_bytes(const struct vlff_cfg_field *field, const struct vlff_cfg_train *train) {
  struct vlff_encoding enc;
  vlff_encoding_init(&enc, field);
  struct vlff_mlp m;
  const int geo = field->geo_dim, sh = field->sh_degree * field->sh_degree;
  size_t nmlp = vlff_mlp_init(&m, enc.dim, field->density_width, field->density_layers, 1 + geo, 0);
  nmlp = vlff_mlp_init(&m, geo + sh, field->color_width, field->color_layers, 3, nmlp);
  nmlp = vlff_mlp_init(&m, geo, field->feature_width, field->feature_layers, field->feature_dim, nmlp);
  const uint64_t ntable = (uint64_t)enc.levels * enc.size * (uint64_t)enc.feats;
  const uint64_t spr = (uint64_t)train->samples_per_ray, nrays = (uint64_t)train->rays_per_step;
  const uint64_t chunk = spr < VLFF_CHUNK_SAMPLES ? VLFF_CHUNK_SAMPLES / spr : 1;
  const uint64_t samples = (nrays + chunk - 1) / chunk * chunk * spr;
  double cells = (double)train->occupancy_resolution * train->occupancy_resolution * train->occupancy_resolution;
  if (field->grow && train->occupancy_cell_m > 0) {
    /* the first box's cells of that size (the growths are within occupancy_max_mb) */
    float cell[3];
    int dims[3];
    vlff_field_first_cells(field, train, cell, dims);
    cells = (double)dims[0] * dims[1] * dims[2];
  }
  const uint64_t fs = sizeof(float);
  return fs * (3 * (ntable + nmlp) + 4 * nmlp) + fs * samples * (3 + (uint64_t)enc.levels * enc.feats) +
         (uint64_t)vlff_occ_bytes(cells) + nrays * (sizeof(struct vlff_ray) + fs);
}

int vlff_field_check_memory(const struct vlff_cfg_field *field, const struct vlff_cfg_train *train, char *err,
                            size_t errlen) {
  long pages = sysconf(_SC_PHYS_PAGES), page = sysconf(_SC_PAGE_SIZE);
  if (pages <= 0 || page <= 0) return 0; /* unknown: nothing to compare with */
  const double gib = 1073741824.0, have = (double)pages * (double)page;
  const double need = (double)vlff_field_plan_bytes(field, train);
  if (need <= have) return 0;
  if (err && errlen)
    snprintf(err, errlen,
         "field: the model and its step buffers need %.1f GiB (field.hash_levels %d x 2^field.hash_log2_size %d x "
         "field.hash_features %d entries with Adam's two moments; train.rays_per_step %d x train.samples_per_ray %d "
         "samples a step), more than this machine's %.1f GiB of memory",
         need / gib, field->hash_levels, field->hash_log2_size, field->hash_features, train->rays_per_step,
         train->samples_per_ray, have / gib);
  return -1;
}

struct vlff_field *vlff_field_create(const struct vlff_cfg_field *field, const struct vlff_cfg_train *train, int threads,
                                     char *err, size_t errlen) {
  if (!field || !train) {
    seterr(err, errlen, "field: %s", "no config");
    return NULL;
  }
  if (vlff_field_check_memory(field, train, err, errlen)) return NULL;
  const int levels = field->hash_levels;
  if (levels > 32) {
    seterr(err, errlen, "field: %s", "field.hash_levels must be <= 32");
    return NULL;
  }
  struct vlff_field *f = calloc(1, sizeof(*f));
  if (!f) {
    seterr(err, errlen, "field: %s", "out of memory");
    return NULL;
  }
  f->cfg.field = *field;
  f->cfg.train = *train;
  const struct vlff_field_cfg *cfg = &f->cfg;
  vlff_encoding_init(&f->enc, &cfg->field);
  f->D = cfg->field.feature_dim;
  f->H = cfg->field.feature_width;
  f->geo = cfg->field.geo_dim;
  f->shdim = cfg->field.sh_degree * cfg->field.sh_degree;
  f->E = f->enc.dim;
  f->spr = cfg->train.samples_per_ray;
  f->chunk_rays = imax(1, VLFF_CHUNK_SAMPLES / f->spr);
  f->ntable = (size_t)levels * f->enc.size * f->enc.feats;
  size_t off = 0;
  off = vlff_mlp_init(&f->m1, f->E, cfg->field.density_width, cfg->field.density_layers, 1 + f->geo, off);
  off = vlff_mlp_init(&f->m2, f->geo + f->shdim, cfg->field.color_width, cfg->field.color_layers, 3, off);
  off = vlff_mlp_init(&f->m3, f->geo, f->H, cfg->field.feature_layers, f->D, off);
  f->nmlp = off;
  f->nparams = f->ntable + f->nmlp;
  f->adam.lr = (float)cfg->train.lr;
  f->adam.beta1 = (float)cfg->train.beta1;
  f->adam.beta2 = (float)cfg->train.beta2;
  f->adam.eps = (float)cfg->train.eps;
  f->adam.wd = (float)cfg->train.weight_decay;
  f->adam.simd = vlff_gemm_isa_level(); /* as the encoding: VLFF_GEMM=generic is all portable */
  f->feat_loss = cfg->train.feature_loss;

  f->pool = vlff_pool_create(threads);
  if (!f->pool) {
    seterr(err, errlen, "field: %s", "cannot start worker threads");
    vlff_field_destroy(f);
    return NULL;
  }
  f->threads = vlff_pool_threads(f->pool);

  int ok = 1;
  size_t fs = sizeof(float);
  f->params = xalloc(f->nparams * fs, &ok);
  f->adam_m = xalloc(f->nparams * fs, &ok);
  f->adam_v = xalloc(f->nparams * fs, &ok);
  f->grad = xalloc(f->nmlp * fs, &ok);
  f->wT = xalloc(f->nmlp * fs, &ok);
  f->avg = xalloc(f->nmlp * fs, &ok);
  f->avgT = xalloc(f->nmlp * fs, &ok);
  {
    int k0[3], dims[3];
    vlff_field_first_layout(f, k0, dims);
    const double cells = (double)dims[0] * dims[1] * dims[2];
    if (cfg->field.grow && !vlff_occ_fits(&cfg->train, cells)) {
      if (err && errlen)
        snprintf(err, errlen,
             "field: the first box's %d x %d x %d occupancy cells of %g x %g x %g m need %.0f MiB, more than "
             "train.occupancy_max_mb (%g): a larger train.occupancy_max_mb or train.occupancy_cell_m, a smaller "
             "train.occupancy_resolution or first box, or field.grow false",
             dims[0], dims[1], dims[2], (double)f->occ.cell[0], (double)f->occ.cell[1], (double)f->occ.cell[2],
             vlff_occ_bytes(cells) / 1048576.0, cfg->train.occupancy_max_mb);
      vlff_field_destroy(f);
      return NULL;
    }
    if (ok && vlff_field_occ_layout(f, k0, dims, 0)) ok = 0;
  }
  f->nrays = f->nrays_max = cfg->train.rays_per_step;
  f->rays = xalloc((size_t)f->nrays * sizeof(struct vlff_ray), &ok);
  f->ray_loss = xalloc((size_t)f->nrays * fs, &ok);
  int nchunks = step_chunks(f, f->nrays_max);
  size_t slot = (size_t)f->chunk_rays * f->spr;
  f->step_p = xalloc((size_t)nchunks * slot * 3 * fs, &ok);
  f->step_denc = xalloc((size_t)nchunks * slot * levels * f->enc.feats * fs, &ok);
  f->chunk_n = xalloc((size_t)nchunks * sizeof(int), &ok);
  f->E_ = xalloc((size_t)VLFF_FIELD_MAX_PROMPTS * f->D * fs, &ok);
  f->bal_feat = xalloc((size_t)f->D * fs, &ok);
  f->EW = xalloc((size_t)VLFF_FIELD_MAX_PROMPTS * f->H * fs, &ok);
  f->EWt = xalloc((size_t)VLFF_FIELD_MAX_PROMPTS * f->H * fs, &ok);
  f->Eb = xalloc((size_t)VLFF_FIELD_MAX_PROMPTS * fs, &ok);
  f->G = xalloc((size_t)f->H * f->H * fs, &ok);
  f->u = xalloc((size_t)f->H * fs, &ok);
  f->Rt = xalloc((size_t)f->H * f->H * fs, &ok);
  f->r12 = xalloc((size_t)f->H * fs, &ok);
  f->work = ok ? calloc((size_t)f->threads, sizeof(struct vlff_work)) : NULL;
  if (!f->work) ok = 0;
  for (int i = 0; ok && i < f->threads; i++) {
    f->work[i].cap = f->chunk_rays * f->spr;
    f->work[i].rcap = imax(f->chunk_rays, VLFF_QUERY_BLOCK);
    if (f->work[i].cap < VLFF_QUERY_BLOCK) f->work[i].cap = VLFF_QUERY_BLOCK;
    if (work_alloc(f, &f->work[i])) ok = 0;
  }
  if (!ok) {
    seterr(err, errlen, "field: %s", "out of memory planning the model and step buffers");
    vlff_field_destroy(f);
    return NULL;
  }
  init_state(f);
  return f;
}

void vlff_field_reinit(struct vlff_field *f) { init_state(f); }

long long vlff_field_steps(const struct vlff_field *f) { return f->step; }

/* Cholesky A = RᵀR of A = [[G, u], [uᵀ, |b|^2]] (the Gram matrix of
 * [W b]), in double. The triangular factor computes a feature norm with
 * 5/8 of the multiply-adds of the quadratic form through G (blocks of the
 * zero half are skipped) and as a sum of squares, never negative. */
static void gram_factor(struct vlff_field *f) {
  const int H = f->H, n = H + 1;
  double *a = malloc((size_t)n * n * sizeof(double));
  f->chol_ok = 0;
  if (!a) return;
  for (int i = 0; i < H; i++) {
    for (int j = 0; j < H; j++) a[(size_t)i * n + j] = f->G[(size_t)i * H + j];
    a[(size_t)i * n + H] = a[(size_t)H * n + i] = f->u[i];
  }
  a[(size_t)H * n + H] = f->bb;
  /* Upper factor in place, row by row: R[i][j] for j >= i. */
  int ok = 1;
  for (int i = 0; i < n && ok; i++) {
    double d = a[(size_t)i * n + i];
    for (int k = 0; k < i; k++) d -= a[(size_t)k * n + i] * a[(size_t)k * n + i];
    /* Relative pivot floor: below it float rounding would dominate. */
    if (!(d > 1e-6 * (a[(size_t)i * n + i] + 1e-30))) {
      ok = 0;
      break;
    }
    double r = sqrt(d);
    a[(size_t)i * n + i] = r;
    for (int j = i + 1; j < n; j++) {
      double v = a[(size_t)i * n + j];
      for (int k = 0; k < i; k++) v -= a[(size_t)k * n + i] * a[(size_t)k * n + j];
      a[(size_t)i * n + j] = v / r;
    }
  }
  if (ok) {
    for (int k = 0; k < H; k++)
      for (int j = 0; j < H; j++) f->Rt[(size_t)k * H + j] = k >= j ? (float)a[(size_t)j * n + k] : 0.0f;
    for (int j = 0; j < H; j++) f->r12[j] = (float)a[(size_t)j * n + H];
    f->r22 = (float)a[(size_t)H * n + H];
    f->chol_ok = 1;
  }
  free(a);
}

/* After a step the backward needs the transposed weights at once; the
 * prompt fold and the Gram factor (~18 MFLOP at the default sizes, on the
 * trainer thread while the pool idles) only when a query or render comes. */
static void refresh_weights(struct vlff_field *f) {
  float *pm = vlff_mlp_params(f);
  vlff_mlp_transpose(&f->m1, pm, f->wT);
  vlff_mlp_transpose(&f->m2, pm, f->wT);
  vlff_mlp_transpose(&f->m3, pm, f->wT);
  f->fold_stale = 1;
}

/* The prompt fold and the Gram factor, from the averaged weights queries
 * read (the trained weights' transposes are the step's business). */
static void fold_prompts(struct vlff_field *f) {
  const float *pm = f->avg;
  vlff_mlp_transpose(&f->m3, f->avg, f->avgT);
  f->fold_stale = 0;
  /* Folded prompts: EW = E W (K x H) and Eb = E b; Gram G = WᵀW, u = Wᵀb and
   * |b|^2 give |F|^2 = Hᵀ G H + 2 s u.H + s^2 |b|^2 without forming F. */
  const struct vlff_mlp *m = &f->m3;
  int last = m->nl - 1, H = f->H, D = f->D;
  const float *Wt = pm + m->woff[last];  /* [H][D] */
  const float *b = pm + m->boff[last];
  const float *W = f->avgT + m->woff[last]; /* [D][H] */
  if (f->K > 0) {
    vlff_gemm(f->K, H, D, f->E_, D, 1, W, H, f->EW, H, NULL, 0, 0);
    for (int k = 0; k < f->K; k++)
      for (int h = 0; h < H; h++) f->EWt[(size_t)h * f->K + k] = f->EW[(size_t)k * H + h];
    for (int k = 0; k < f->K; k++) {
      float s = 0;
      for (int j = 0; j < D; j++) s += f->E_[(size_t)k * D + j] * b[j];
      f->Eb[k] = s;
    }
  }
  vlff_gemm(H, H, D, Wt, D, 1, W, H, f->G, H, NULL, 0, 0);
  float bb = 0;
  for (int j = 0; j < D; j++) bb += b[j] * b[j];
  f->bb = bb;
  for (int h = 0; h < H; h++) {
    float s = 0;
    for (int j = 0; j < D; j++) s += Wt[(size_t)h * D + j] * b[j];
    f->u[h] = s;
  }
  gram_factor(f);
}

void vlff_field_fold(struct vlff_field *f) {
  if (f->fold_stale) fold_prompts(f);
}

void vlff_field_refresh(struct vlff_field *f) {
  refresh_weights(f);
  fold_prompts(f);
}

void vlff_field_reset_average(struct vlff_field *f) {
  memcpy(f->avg, vlff_mlp_params(f), f->nmlp * sizeof(float));
  vlff_field_refresh(f);
}

void vlff_field_density(struct vlff_field *f, struct vlff_work *w, const float *pm, const float *p, int n) {
  vlff_encoding_forward(&f->enc, f->params, p, n, w->enc, f->E);
  vlff_mlp_forward(&f->m1, pm, w->enc, f->E, n, f->m1.nl, w->a1);
  const float *o = w->a1[f->m1.nl - 1];
  int ld = f->m1.nout;
  for (int i = 0; i < n; i++) w->sigma[i] = expf(fminf(o[(size_t)i * ld], 15.0f));
}

/* The chunk's per-sample loops over MLP3's H = 128 hidden units and its
 * per-ray loops over the D feature values, as helpers with restrict
 * pointers and fixed-width inner loops: inline, the compiler could not rule
 * out aliasing (nor use AVX-512: vlff_field_chunk is not cloned) and ran them
 * a float at a time. The dot product keeps 16 partial
 * sums in a fixed order, so results do not vary from run to run. */
enum { CHUNK_VW = 16 };

VLFF_HOT
static void axpy_h(int n, float a, const float *restrict x, float *restrict y) {
  int j = 0;
  for (; j + CHUNK_VW <= n; j += CHUNK_VW)
    for (int t = 0; t < CHUNK_VW; t++) y[j + t] += a * x[j + t];
  for (; j < n; j++) y[j] += a * x[j];
}

VLFF_HOT
static float dot_h(int n, const float *restrict x, const float *restrict y) {
  float acc[CHUNK_VW] = {0};
  int j = 0;
  for (; j + CHUNK_VW <= n; j += CHUNK_VW)
    for (int t = 0; t < CHUNK_VW; t++) acc[t] += x[j + t] * y[j + t];
  float s = 0;
  for (; j < n; j++) s += x[j] * y[j];
  for (int t = 0; t < CHUNK_VW; t++) s += acc[t];
  return s;
}

/* dst[l][n][F] from src[n][ld] (level l's F values at column l*F), row by
 * row: each row is read once, and at the default F = 2 each value pair
 * moves as one 64-bit word. The column-by-column loop this replaced read
 * every row once per level and moved single floats. */
VLFF_HOT
static void level_major(int n, int levels, int F, const float *restrict src, int ld, float *restrict dst) {
  const size_t plane = (size_t)n * F;
  if (F == 2) {
    enum { ROWS = 64 };
    for (int i0 = 0; i0 < n; i0 += ROWS) {
      int i1 = n - i0 < ROWS ? n : i0 + ROWS;
      for (int l = 0; l < levels; l++)
        for (int i = i0; i < i1; i++) memcpy(dst + l * plane + 2 * (size_t)i, src + (size_t)i * ld + 2 * l, 8);
    }
    return;
  }
  for (int i = 0; i < n; i++)
    for (int l = 0; l < levels; l++)
      for (int q = 0; q < F; q++) dst[l * plane + (size_t)i * F + q] = src[(size_t)i * ld + l * F + q];
}

/* d = a g where the ReLU's output h is positive, else 0. The product is
 * taken for every lane and then selected: a multiply only where h > 0 may not
 * be made unconditional (it could raise an FP exception the source would
 * not), so that form stayed scalar. */
VLFF_HOT
static void relu_scale_h(int n, float a, const float *restrict h, const float *restrict g, float *restrict d) {
  int j = 0;
  for (; j + CHUNK_VW <= n; j += CHUNK_VW)
    for (int t = 0; t < CHUNK_VW; t++) {
      float v = a * g[j + t];
      d[j + t] = h[j + t] > 0 ? v : 0.0f;
    }
  for (; j < n; j++) {
    float v = a * g[j];
    d[j] = h[j] > 0 ? v : 0.0f;
  }
}

/* ---- the chunk pipeline, stage by stage ----------------------------------
 * Each stage runs once per chunk (its loops over rays and samples inside),
 * so a call costs nothing beside its work, and the compiler inlines them all
 * into vlff_field_chunk, which lists them in order. A stage copies what it
 * reads of the chunk into locals: its loops call out (the clones above, the
 * samplers), and a field read through a pointer could be reloaded after
 * every call. */

/* One chunk's state from stage to stage. */
struct chunk {
  const struct vlff_ray *rays;
  int nr, train;
  int need_feat;    /* MLP3 runs: a ray has a target feature, or rendering asks */
  int N;            /* samples */
  int n2, n3;       /* samples through MLP2 (live) and through MLP3 (with weight) */
  const float *pm;  /* the MLPs' parameters */
  float *c2;        /* MLP2's colours, n2 x 3, sigmoid applied */
  const float *h3;  /* MLP3's last hidden layer, n3 x H */
};

/* Per-ray loss gradients: colour, depth, and the feature gradient's dot
 * product with MLP3's output bias. */
struct chunk_grads {
  float rgb[VLFF_CHUNK_SAMPLES][3];
  float depth[VLFF_CHUNK_SAMPLES], fb[VLFF_CHUNK_SAMPLES];
};

/* Each ray's samples between the scene box's entry (no nearer than
 * train.near_m) and exit: uniform, around the ray's depth (training) or in
 * occupied cells; their positions normalised into p, their spacing scaled to
 * metres. Sets c->N. */
static void chunk_sample(struct vlff_field *f, struct vlff_work *w, struct chunk *c, float *p) {
  const struct vlff_field_cfg *cfg = &f->cfg;
  const struct vlff_ray *rays = c->rays;
  const int nr = c->nr, train = c->train, S = f->spr;
  float bmin[3], bmax[3];
  for (int a = 0; a < 3; a++) {
    bmin[a] = (float)f->box_lo[a];
    bmax[a] = (float)f->box_hi[a];
  }
  const int uniform = cfg->train.sampling == VLFF_SAMPLING_UNIFORM;
  int N = 0;
  for (int r = 0; r < nr; r++) {
    const struct vlff_ray *ray = &rays[r];
    w->ray_off[r] = N;
    float t0, t1, dt = 0;
    int cnt = 0;
    float *tt = w->t + N, *dd = w->delta + N;
    if (vlff_ray_box(ray->o, ray->d, bmin, bmax, &t0, &t1)) {
      t0 = fmaxf(t0, (float)cfg->train.near_m);
      if (t1 > t0) {
        if (uniform) {
          cnt = vlff_sample_uniform(t0, t1, S, &w->rng, tt, &dt);
          for (int s = 0; s < cnt; s++) dd[s] = dt;
        } else if (train && ray->depth > 0) {
          cnt = vlff_sample_depth(ray->depth, (float)cfg->train.depth_noise_m, t0, t1, S, &w->rng, tt, dd);
        } else {
          cnt = vlff_sample_occupied(&f->occ, ray->o, ray->d, t0, t1, S, train ? &w->rng : NULL, tt, &dt);
          for (int s = 0; s < cnt; s++) dd[s] = dt;
        }
      }
    }
    float dn = sqrtf(ray->d[0] * ray->d[0] + ray->d[1] * ray->d[1] + ray->d[2] * ray->d[2]);
    for (int s = 0; s < cnt; s++) {
      float x[3] = {ray->o[0] + tt[s] * ray->d[0], ray->o[1] + tt[s] * ray->d[1], ray->o[2] + tt[s] * ray->d[2]};
      vlff_encoding_normalise(&f->enc, x, p + 3 * (size_t)(N + s));
      dd[s] *= dn;
      w->ray_of[N + s] = r;
    }
    w->ray_cnt[r] = cnt;
    N += cnt;
  }
  c->N = N;
}

/* Each ray's weights from MLP1's densities; its live samples (before
 * termination) become MLP2's inputs (geometry code and the view direction's
 * SH), those with weight MLP3's (the code alone) when features are needed.
 * Sets c->n2, c->n3. */
static void chunk_select(struct vlff_field *f, struct vlff_work *w, struct chunk *c) {
  const struct vlff_field_cfg *cfg = &f->cfg;
  const struct vlff_ray *rays = c->rays;
  const int nr = c->nr, need_feat = c->need_feat;
  const int geo = f->geo, shd = f->shdim, in2w = geo + shd, ld1 = f->m1.nout;
  const float *out1 = w->a1[f->m1.nl - 1];
  int n2 = 0, n3 = 0;
  for (int r = 0; r < nr; r++) {
    int o = w->ray_off[r], cnt = w->ray_cnt[r];
    int used = cnt ? vlff_render_weights(w->sigma + o, w->delta + o, cnt, w->w + o, w->trans + o) : 0;
    w->ray_used[r] = used;
    float sh[16];
    float dn = sqrtf(rays[r].d[0] * rays[r].d[0] + rays[r].d[1] * rays[r].d[1] + rays[r].d[2] * rays[r].d[2]);
    float u[3] = {rays[r].d[0] / dn, rays[r].d[1] / dn, rays[r].d[2] / dn};
    vlff_sh_encode(u, cfg->field.sh_degree, sh);
    for (int s = o; s < o + used; s++) {
      float *row = w->in2 + (size_t)n2 * in2w;
      memcpy(row, out1 + (size_t)s * ld1 + 1, geo * sizeof(float));
      memcpy(row + geo, sh, shd * sizeof(float));
      w->sel2[n2++] = s;
      if (need_feat && w->w[s] >= VLFF_FEAT_WMIN) {
        memcpy(w->in3 + (size_t)n3 * geo, out1 + (size_t)s * ld1 + 1, geo * sizeof(float));
        w->sel3[n3++] = s;
      }
    }
  }
  c->n2 = n2, c->n3 = n3;
}

/* MLP2 (colour, through a sigmoid) on the live samples and MLP3's hidden
 * layers on the weighted ones; the chunk's dense-layer FLOPs counted. Sets
 * c->c2 and c->h3. */
static void chunk_heads(struct vlff_field *f, struct vlff_work *w, struct chunk *c) {
  const int N = c->N, n2 = c->n2, n3 = c->n3, nr = c->nr, train = c->train;
  const int geo = f->geo, in2w = geo + f->shdim, H = f->H, D = f->D;
  const float *pm = c->pm;
  float *c2 = NULL;
  if (n2) {
    vlff_mlp_forward(&f->m2, pm, w->in2, in2w, n2, f->m2.nl, w->a2);
    c2 = w->a2[f->m2.nl - 1];
    for (int k = 0; k < n2 * 3; k++) c2[k] = 1.0f / (1.0f + expf(-c2[k]));
  }
  w->flops += (double)N * vlff_mlp_flops(&f->m1, f->m1.nl, train) +
              (double)n2 * vlff_mlp_flops(&f->m2, f->m2.nl, train) +
              (double)n3 * vlff_mlp_flops(&f->m3, f->m3.nl - 1, train);
  if (c->need_feat) w->flops += (train ? 6.0 : 2.0) * nr * H * D;
  const float *h3 = NULL;
  if (n3) {
    vlff_mlp_forward(&f->m3, pm, w->in3, geo, n3, f->m3.nl - 1, w->a3);
    h3 = w->a3[f->m3.nl - 2];
  }
  c->c2 = c2, c->h3 = h3;
}

/* Ray outputs: colour, depth and opacity composited from the samples, and
 * MLP3's hidden layer rendered per ray (hray) with its weight sum. */
static void chunk_composite(const struct vlff_field *f, struct vlff_work *w, const struct chunk *c) {
  const int nr = c->nr, n3 = c->n3, H = f->H;
  const float *c2 = c->c2, *h3 = c->h3;
  memset(w->hray, 0, (size_t)nr * H * sizeof(float));
  int k2 = 0, k3 = 0;
  for (int r = 0; r < nr; r++) {
    int o = w->ray_off[r], used = w->ray_used[r];
    float cr[3] = {0, 0, 0}, dep = 0, ws = 0, op = 0;
    float *hr = w->hray + (size_t)r * H;
    for (int s = o; s < o + used; s++, k2++) {
      float ww = w->w[s];
      for (int ch = 0; ch < 3; ch++) cr[ch] += ww * c2[(size_t)k2 * 3 + ch];
      dep += ww * w->t[s];
      op += ww;
      if (k3 < n3 && w->sel3[k3] == s) {
        const float *hs = h3 + (size_t)k3 * H;
        axpy_h(H, ww, hs, hr);
        ws += ww;
        k3++;
      }
    }
    memcpy(w->rgb + 3 * r, cr, sizeof(cr));
    w->depth[r] = dep;
    w->wsum[r] = ws;
    w->opac[r] = op;
  }
}

/* Each ray's feature: MLP3's output layer applied once to the rendered
 * hidden layer, fray = hray W + wsum b (the layer is linear, so it commutes
 * with rendering). */
static void chunk_ray_features(const struct vlff_field *f, struct vlff_work *w, const struct chunk *c) {
  const struct vlff_mlp *m3 = &f->m3;
  const int last = m3->nl - 1, nr = c->nr, H = f->H, D = f->D;
  const float *pm = c->pm, *b3 = pm + m3->boff[last];
  vlff_gemm(nr, D, H, w->hray, H, 1, pm + m3->woff[last], D, w->fray, D, NULL, 0, 0);
  for (int r = 0; r < nr; r++)
    axpy_h(D, w->wsum[r], b3, w->fray + (size_t)r * D);
}

/* Each ray's losses against its targets (colour, depth, feature) into w's
 * sums, their gradients into g (colour, depth), w->gf (feature, by ray) and
 * MLP3's output bias gradient. */
static void chunk_losses(struct vlff_field *f, struct vlff_work *w, const struct chunk *c, struct chunk_grads *g) {
  const struct vlff_mlp *m3 = &f->m3;
  const struct vlff_ray *rays = c->rays;
  const int last = m3->nl - 1, nr = c->nr, need_feat = c->need_feat, D = f->D;
  const float *b3 = c->pm + m3->boff[last];
  float *grad = w->grad;
  for (int r = 0; r < nr; r++) {
    const struct vlff_ray *ray = &rays[r];
    /* A ray's target feature (D halves at a random pixel of a keyframe: a
     * cache miss) is requested two rays ahead of its loss, so its conversion
     * does not stall on it; requested all at the chunk's start, the requests
     * stalled on each other. */
    if (need_feat && r + 2 < nr && rays[r + 2].feat_index >= 0) {
      const uint16_t *src = f->views[rays[r + 2].view].features + (size_t)rays[r + 2].feat_index * D;
      for (int k = 0; k < D; k += 32) __builtin_prefetch(src + k, 0, 2);
    }
    g->rgb[r][0] = g->rgb[r][1] = g->rgb[r][2] = 0;
    g->depth[r] = 0;
    g->fb[r] = 0;
    if (ray->has_rgb) {
      float l = vlff_loss_rgb(w->rgb + 3 * r, ray->rgb, f->scale_rgb, g->rgb[r]);
      w->loss_rgb += l * f->scale_rgb;
      w->sq_rgb += l;
    }
    if (ray->depth > 0)
      w->loss_depth += vlff_loss_depth(w->depth[r], ray->depth, f->scale_depth, &g->depth[r]) * f->scale_depth;
    float *gfr = w->gf + (size_t)r * D;
    if (need_feat) {
      if (ray->feat_index >= 0) {
        const struct vlff_view *v = &f->views[ray->view];
        const uint16_t *src = v->features + (size_t)ray->feat_index * D;
        vlff_f16_to_f32_n(src, w->tfeat, (size_t)D);
        float l = vlff_loss_feat(w->fray + (size_t)r * D, w->tfeat, D, f->feat_loss, f->scale_feat, gfr);
        w->loss_feat += l * f->scale_feat;
        if (c->train) f->ray_loss[ray - f->rays] = l;
        g->fb[r] = dot_h(D, gfr, b3);
        axpy_h(D, w->wsum[r], gfr, grad + m3->boff[last]);
      } else {
        memset(gfr, 0, (size_t)D * sizeof(float));
      }
    }
  }
}

/* Backward through MLP3's output layer: its weight gradient, and dH = Wᵀ dF
 * per ray (w->dh). */
static void chunk_ray_features_backward(const struct vlff_field *f, struct vlff_work *w, const struct chunk *c) {
  const struct vlff_mlp *m3 = &f->m3;
  const int last = m3->nl - 1, nr = c->nr, H = f->H, D = f->D;
  vlff_gemm(H, D, nr, w->hray, 1, H, w->gf, D, w->grad + m3->woff[last], D, NULL, 1, 0);
  vlff_gemm(nr, H, D, w->gf, D, 1, f->wT + m3->woff[last], H, w->dh, H, NULL, 0, 0);
}

/* Per-sample scalars e_s (the loss's derivative by the sample's weight) and
 * the gradients into MLP2's outputs (w->dy_a). */
static void chunk_sample_grads(const struct vlff_field *f, struct vlff_work *w, const struct chunk *c,
                               const struct chunk_grads *g) {
  const int nr = c->nr, n3 = c->n3, H = f->H;
  const float *c2 = c->c2, *h3 = c->h3;
  float *dy2 = w->dy_a;
  int k2 = 0;
  for (int r = 0; r < nr; r++) {
    int o = w->ray_off[r], used = w->ray_used[r];
    for (int s = o; s < o + used; s++, k2++) {
      const float *cs = c2 + (size_t)k2 * 3;
      float e = g->rgb[r][0] * cs[0] + g->rgb[r][1] * cs[1] + g->rgb[r][2] * cs[2] + g->depth[r] * w->t[s];
      float ww = w->w[s];
      for (int ch = 0; ch < 3; ch++) dy2[(size_t)k2 * 3 + ch] = ww * g->rgb[r][ch] * cs[ch] * (1.0f - cs[ch]);
      w->e[s] = e;
    }
  }
  if (n3) {
    for (int k3 = 0; k3 < n3; k3++) {
      int s = w->sel3[k3], r = w->ray_of[s];
      const float *hs = h3 + (size_t)k3 * H, *dhr = w->dh + (size_t)r * H;
      w->e[s] += g->fb[r] + dot_h(H, dhr, hs);
    }
  }
}

/* Backward through rendering: each sample's density gradient, into MLP1's
 * density output (w->dout1, whose code columns the heads add to). */
static void chunk_density_grads(const struct vlff_field *f, struct vlff_work *w, const struct chunk *c) {
  const int nr = c->nr, ld1 = f->m1.nout;
  const float *out1 = w->a1[f->m1.nl - 1];
  float *dout1 = w->dout1;
  memset(dout1, 0, (size_t)c->N * ld1 * sizeof(float));
  for (int r = 0; r < nr; r++) {
    int o = w->ray_off[r], used = w->ray_used[r];
    if (!used) continue;
    vlff_render_backward(w->w + o, w->trans + o, w->sigma + o, w->delta + o, w->e + o, used, w->dsig + o);
    for (int s = o; s < o + used; s++) {
      float raw = out1[(size_t)s * ld1];
      dout1[(size_t)s * ld1] = raw < 15.0f ? w->dsig[s] * w->sigma[s] : 0.0f;
    }
  }
}

/* Backward through MLP2; its input gradient's code part added to MLP1's
 * output gradient. */
static void chunk_colour_backward(struct vlff_field *f, struct vlff_work *w, const struct chunk *c) {
  const int n2 = c->n2, geo = f->geo, in2w = geo + f->shdim, ld1 = f->m1.nout;
  float *dout1 = w->dout1;
  if (!n2) return;
  vlff_mlp_backward(&f->m2, f->wT, w->in2, in2w, n2, f->m2.nl, w->a2, w->dy_a, w->grad, w->din2, w->dy_b);
  for (int k = 0; k < n2; k++) {
    float *d1 = dout1 + (size_t)w->sel2[k] * ld1 + 1;
    const float *d2 = w->din2 + (size_t)k * in2w;
    for (int j = 0; j < geo; j++) d1[j] += d2[j];
  }
}

/* Backward through MLP3's hidden layers (dh_s = w_s dH through the ReLU;
 * w->dy_b is free again once MLP2's backward is done); its input gradient
 * added to MLP1's output gradient. */
static void chunk_feature_backward(struct vlff_field *f, struct vlff_work *w, const struct chunk *c) {
  const struct vlff_mlp *m3 = &f->m3;
  const int n3 = c->n3, geo = f->geo, H = f->H, ld1 = f->m1.nout;
  const float *h3 = c->h3;
  float *dout1 = w->dout1, *dy3 = w->dy_b;
  if (!n3) return;
  for (int k3 = 0; k3 < n3; k3++) {
    int s = w->sel3[k3], r = w->ray_of[s];
    float ww = w->w[s];
    const float *hs = h3 + (size_t)k3 * H, *dhr = w->dh + (size_t)r * H;
    float *d = dy3 + (size_t)k3 * H;
    relu_scale_h(H, ww, hs, dhr, d);
  }
  vlff_mlp_backward(m3, f->wT, w->in3, geo, n3, m3->nl - 1, w->a3, dy3, w->grad, w->din3, w->dy_a);
  for (int k = 0; k < n3; k++) {
    float *d1 = dout1 + (size_t)w->sel3[k] * ld1 + 1;
    const float *d3 = w->din3 + (size_t)k * geo;
    for (int j = 0; j < geo; j++) d1[j] += d3[j];
  }
}

/* Backward through MLP1 to the encoding, then a level-major copy while it
 * is in cache: each level's scatter (one thread per level) then streams its
 * own contiguous gradients. Levels masked by vlff_field_set_levels get no
 * scatter, so need no copy. */
static void chunk_encoding_backward(struct vlff_field *f, struct vlff_work *w, const struct chunk *c,
                                    float *dencslot) {
  const int N = c->N;
  if (N) vlff_mlp_backward(&f->m1, f->wT, w->enc, f->E, N, f->m1.nl, w->a1, w->dout1, w->grad, w->denc, w->dy_b);
  level_major(N, f->enc.active, f->enc.feats, w->denc, f->E, dencslot);
}

/* The chunk pipeline shared by training and rendering. */
void vlff_field_chunk(struct vlff_field *f, struct vlff_work *w, const struct vlff_ray *rays, int nr, int train,
                      float *pslot, float *dencslot, int *nsamples) {
  struct chunk c = {.rays = rays, .nr = nr, .train = train, .pm = vlff_mlp_params(f)};
  float *p = pslot ? pslot : w->p;
  chunk_sample(f, w, &c, p);
  *nsamples = c.N;
  w->samples += c.N;
  if (c.N > 0) vlff_field_density(f, w, c.pm, p, c.N);
  if (train)
    for (int r = 0; r < nr; r++) c.need_feat |= rays[r].feat_index >= 0;
  else
    c.need_feat = f->render_feat;
  chunk_select(f, w, &c);
  chunk_heads(f, w, &c);
  chunk_composite(f, w, &c);
  if (!train) return;

  struct chunk_grads g;
  if (c.need_feat) chunk_ray_features(f, w, &c);
  chunk_losses(f, w, &c, &g);
  if (c.need_feat) chunk_ray_features_backward(f, w, &c);
  chunk_sample_grads(f, w, &c, &g);
  chunk_density_grads(f, w, &c);
  chunk_colour_backward(f, w, &c);
  chunk_feature_backward(f, w, &c);
  chunk_encoding_backward(f, w, &c, dencslot);
}

/* ---- one optimisation step ---------------------------------------------- */


struct step_ctx {
  struct vlff_field *f;
  int nchunks;
  float lr;                /* this step's learning rate, table and MLPs alike */
};

static void chunk_task(void *ctx, int c, int thread) {
  struct step_ctx *sc = ctx;
  struct vlff_field *f = sc->f;
  struct vlff_work *w = &f->work[thread];
  int r0 = (int)((long long)c * f->nrays / sc->nchunks);
  int nr = (int)((long long)(c + 1) * f->nrays / sc->nchunks) - r0;
  size_t slot = (size_t)f->chunk_rays * f->spr;
  /* Per-chunk seed: sampling jitter does not depend on the thread count. */
  w->rng = (uint64_t)f->step * 0x9e3779b97f4a7c15ull ^ ((uint64_t)c << 32) ^ 0x243f6a8885a308d3ull;
  double g0 = vlff_gemm_thread_seconds();
  vlff_field_chunk(f, w, f->rays + r0, nr, 1, f->step_p + (size_t)c * slot * 3,
                   f->step_denc + (size_t)c * slot * f->enc.levels * f->enc.feats, &f->chunk_n[c]);
  w->gemm_s += vlff_gemm_thread_seconds() - g0;
}

/* A level's update does not depend on the thread that runs it (each
 * thread's gradient and marks are zero and stale wherever it starts), so
 * levels go to whichever thread is free: with static shares one thread held
 * one hashed level more and the other idled. Coarse to fine: finest first
 * (longest tasks first) took more thread time, both threads streaming fine
 * levels' moments at once. */
static void hash_task(void *ctx, int level, int thread) {
  struct step_ctx *sc = ctx;
  struct vlff_field *f = sc->f;
  struct vlff_work *w = &f->work[thread];
  if (level >= f->enc.active) return;
  /* A stamp comes back after 255 uses: clear its old marks first. */
  w->tstamp = (uint8_t)(w->tstamp % 255 + 1);
  if (w->tstamp == 1) memset(w->tmarks, 0, f->enc.size);
  size_t slot = (size_t)f->chunk_rays * f->spr;
  for (int c = 0; c < sc->nchunks; c++)
    vlff_encoding_backward(&f->enc, f->step_p + (size_t)c * slot * 3, f->chunk_n[c],
                           f->step_denc + ((size_t)c * slot * f->enc.levels + (size_t)level * f->chunk_n[c]) * f->enc.feats,
                           f->enc.feats, level, w->tgrad, w->tmarks, w->tstamp);
  size_t off = (size_t)level * f->enc.size * f->enc.feats;
  size_t lines;
  vlff_adam_sparse(&f->adam, f->step, sc->lr, f->params + off, w->tgrad, f->adam_m + off, f->adam_v + off,
                   w->tmarks, w->tstamp, vlff_encoding_entries(&f->enc, level), f->enc.feats, &lines);
  w->table_lines += lines;
}

#define MLP_SPLIT 64

static void mlp_task(void *ctx, int part, int thread) {
  struct step_ctx *sc = ctx;
  struct vlff_field *f = sc->f;
  (void)thread;
  size_t n = f->nmlp, i0 = n * part / MLP_SPLIT, i1 = n * (part + 1) / MLP_SPLIT;
  float *g = f->grad;
  for (size_t i = i0; i < i1; i++) {
    float s = 0;
    for (int t = 0; t < f->threads; t++) s += f->work[t].grad[i];
    g[i] = s;
  }
  const float lr = sc->lr;
  float *p = vlff_mlp_params(f), *m = f->adam_m + f->ntable, *v = f->adam_v + f->ntable;
  /* Weight decay applies to weights, not biases: walk the layer blocks. */
  const struct vlff_mlp *mm[3] = {&f->m1, &f->m2, &f->m3};
  for (int k = 0; k < 3; k++)
    for (int l = 0; l < mm[k]->nl; l++) {
      size_t w0 = mm[k]->woff[l], w1 = mm[k]->boff[l];
      size_t b1 = l + 1 < mm[k]->nl ? mm[k]->woff[l + 1] : (k < 2 ? mm[k + 1]->woff[0] : f->nmlp);
      size_t a0 = w0 > i0 ? w0 : i0, a1 = w1 < i1 ? w1 : i1;
      if (a1 > a0) vlff_adam_dense(&f->adam, f->step, lr, p, g, m, v, a0, a1, 1);
      a0 = w1 > i0 ? w1 : i0;
      a1 = b1 < i1 ? b1 : i1;
      if (a1 > a0) vlff_adam_dense(&f->adam, f->step, lr, p, g, m, v, a0, a1, 0);
    }
}

/* The average queries read follows the trained MLP weights: avg += (1 -
 * b) (p - avg) with b = min(train.weight_average, (1 + t) / (10 + t)) at
 * step t, so a young field's average is not held back by its random
 * start. Adam at the rate that fits the field in time moves the shared
 * decoders by about the rate at every step, and an object near a decision
 * boundary went with them: the map of a fitted field read 8 points of 3D
 * mIoU apart 50 steps apart. The average keeps the rate and drops the
 * jitter. Only the MLPs: they are small, and they are what every point
 * shares; the table's entries move one place each. */
static void average_weights(struct vlff_field *f) {
  const float *p = vlff_mlp_params(f);
  float b = (float)f->cfg.train.weight_average, warm = (1.0f + (float)f->step) / (10.0f + (float)f->step);
  if (warm < b) b = warm;
  if (b <= 0.0f) { /* exactly the latest: avg + (p - avg) need not round to p */
    memcpy(f->avg, p, f->nmlp * sizeof(float));
    return;
  }
  const float a = 1.0f - b;
  for (size_t i = 0; i < f->nmlp; i++) f->avg[i] += a * (p[i] - f->avg[i]);
}

static int check_views(const struct vlff_field *f, const struct vlff_view *views, int nviews, const float *weights,
                       char *err, size_t errlen) {
  if (!views || nviews <= 0) {
    if (err && errlen) snprintf(err, errlen, "field step: no views");
    return -1;
  }
  double wsum = 0;
  for (int i = 0; i < nviews; i++) {
    const struct vlff_view *v = &views[i];
    const char *bad = NULL;
    if (v->width <= 0 || v->height <= 0)
      bad = "width/height must be positive";
    else if (!(v->fx > 0) || !(v->fy > 0) || !isfinite(v->fx) || !isfinite(v->fy) || !isfinite(v->cx) ||
             !isfinite(v->cy))
      bad = "intrinsics must be finite with fx, fy > 0";
    else if (!v->rgb && !v->depth && !v->features)
      bad = "has no rgb, depth or features";
    else if (v->features && (v->feat_width <= 0 || v->feat_height <= 0))
      bad = "features need feat_width/feat_height > 0";
    else if (v->features && v->feature_dim != f->D)
      bad = "feature dimension differs from field.feature_dim";
    for (int k = 0; !bad && k < 16; k++)
      if (!isfinite(v->c2w[k])) bad = "pose has a non-finite entry";
    if (!bad && weights && (!(weights[i] >= 0) || !isfinite(weights[i]))) bad = "weight must be finite and >= 0";
    if (bad) {
      if (err && errlen) snprintf(err, errlen, "field step: view %d: %s", i, bad);
      return -1;
    }
    wsum += weights ? weights[i] : 1.0;
  }
  if (!(wsum > 0)) {
    if (err && errlen) snprintf(err, errlen, "field step: view weights sum to 0");
    return -1;
  }
  return 0;
}

/* Camera ray through continuous pixel coordinate (u, v). */
void vlff_camera_ray(const struct vlff_view *v, double u, double vv, float *o, float *d) {
  double dc[3] = {(u - v->cx) / v->fx, (vv - v->cy) / v->fy, 1.0};
  for (int a = 0; a < 3; a++) {
    d[a] = (float)(v->c2w[4 * a] * dc[0] + v->c2w[4 * a + 1] * dc[1] + v->c2w[4 * a + 2] * dc[2]);
    o[a] = (float)v->c2w[4 * a + 3];
  }
}

/* The prompt whose embedding is closest to a view's raw feature at (u, v):
 * the pixel's pseudo-class. */
static int pseudo_class(struct vlff_field *f, const struct vlff_view *v, double u, double vv) {
  int fx = (int)(u * v->feat_width / v->width), fy = (int)(vv * v->feat_height / v->height);
  if (fx >= v->feat_width) fx = v->feat_width - 1;
  if (fy >= v->feat_height) fy = v->feat_height - 1;
  const int D = f->D;
  vlff_f16_to_f32_n(v->features + ((size_t)fy * v->feat_width + fx) * D, f->bal_feat, (size_t)D);
  int best = 0;
  float bs = -INFINITY;
  const float *x = f->bal_feat;
  for (int k = 0; k < f->K; k++) {
    const float *e = f->E_ + (size_t)k * D;
    /* sixteen partial sums, so the dot product vectorises */
    float part[16] = {0}, s = 0;
    int j = 0;
    for (; j + 16 <= D; j += 16)
      for (int q = 0; q < 16; q++) part[q] += e[j + q] * x[j + q];
    for (; j < D; j++) part[0] += e[j] * x[j];
    for (int q = 0; q < 16; q++) s += part[q];
    if (s > bs) bs = s, best = k;
  }
  return best;
}

/* Candidates drawn per ray at most when balancing classes. */
#define BALANCE_TRIES 8

/* The occupancy cell holding world point x, -1 outside the box. */
static long occ_cell_of(const struct vlff_occupancy *g, const float x[3]) {
  long c[3];
  for (int a = 0; a < 3; a++) {
    float q = (x[a] - g->box_min[a]) / g->cell[a];
    if (!(q >= 0) || q >= (float)g->dims[a]) return -1;
    c[a] = (long)q;
  }
  return c[0] + (long)g->dims[0] * (c[1] + (long)g->dims[1] * c[2]);
}

void vlff_field_exposure(const struct vlff_field *f, const float *xyz, size_t n, uint16_t *rays) {
  for (size_t i = 0; i < n; i++) {
    long c = occ_cell_of(&f->occ, xyz + 3 * i);
    rays[i] = c < 0 ? 0 : f->exposure[c];
  }
}

void vlff_field_forget_errors(struct vlff_field *f) {
  size_t n = vlff_occ_cells(&f->occ);
  for (size_t i = 0; i < n; i++) f->cell_err[i] = -1;
  f->err_mean = 0;
}

/* View v's measured depth in the pixel holding (u, vv): 0 where it has
 * none, or none that is finite and beyond 1 cm. */
static float pixel_depth(const struct vlff_view *v, double u, double vv) {
  if (!v->depth) return 0;
  int px = (int)u, py = (int)vv;
  if (px >= v->width) px = v->width - 1;
  if (py >= v->height) py = v->height - 1;
  float dv = v->depth[(size_t)py * v->width + px];
  return isfinite(dv) && dv > 0.01f ? dv : 0;
}

/* The occupancy cell where the ray o + t d ends at t = depth, -1 outside
 * the box. */
static long ray_end_cell(const struct vlff_field *f, const float o[3], const float d[3], float depth) {
  const float end[3] = {o[0] + d[0] * depth, o[1] + d[1] * depth, o[2] + d[2] * depth};
  return occ_cell_of(&f->occ, end);
}

/* The occupancy cell where view v's measured depth at (u, vv) ends: -1
 * without a valid depth there or outside the box. */
static long pixel_cell(const struct vlff_field *f, const struct vlff_view *v, double u, double vv) {
  float dv = pixel_depth(v, u, vv);
  if (!(dv > 0)) return -1;
  float o[3], d[3];
  vlff_camera_ray(v, u, vv, o, d);
  return ray_end_cell(f, o, d, dv);
}

/* The probability of keeping a candidate pixel under train.error_sampling b:
 * (e / mean)^b below the candidates' running mean cell loss, 1 at or above
 * it and where its cell has not been trained yet (or it has no depth). */
static double error_keep(struct vlff_field *f, const struct vlff_view *v, double u, double vv, double b) {
  long c = pixel_cell(f, v, u, vv);
  float e = c >= 0 ? f->cell_err[c] : -1;
  if (!(e >= 0)) return 1;
  f->err_mean = f->err_mean > 0 ? 0.999 * f->err_mean + 0.001 * e : e;
  return e < f->err_mean ? pow(e / f->err_mean, b) : 1;
}

void vlff_field_draw_rays(struct vlff_field *f, const struct vlff_view *views, int nviews, const float *weights,
                          int *counts) {
  /* Draw the rays: view by weight, pixel uniformly with sub-pixel jitter.
   * With train.class_balance b and prompts set, a candidate pixel whose
   * raw-feature pseudo-class c has running frequency q_c among candidates
   * is kept with probability min(1, (1/(K q_c))^b): walls and floors give
   * up rays to the classes that fill few pixels, which otherwise get too
   * few feature gradients to survive in the shared grid and MLP.
   * With train.error_sampling b, a candidate is also kept with probability
   * (e / ē)^b when e, the running feature loss of the occupancy cell where
   * its measured depth ends, is below ē, the candidates' running mean:
   * fitted surfaces give up rays to what the camera has just seen and to
   * what the field still gets wrong. */
  double wtot = 0;
  for (int i = 0; i < nviews; i++) wtot += weights ? weights[i] : 1.0;
  const double bal = f->K > 1 ? f->cfg.train.class_balance : 0, errb = f->cfg.train.error_sampling;
  if (bal > 0 && !(f->bal_freq[0] > 0))
    for (int k = 0; k < f->K; k++) f->bal_freq[k] = 1.0 / f->K;
  int n_rgb = 0, n_depth = 0, n_feat = 0;
  for (int i = 0; i < f->nrays; i++) {
    struct vlff_ray *r = &f->rays[i];
    const struct vlff_view *v = NULL;
    double u = 0, vv = 0;
    int vi = nviews - 1;
    for (int tries = 0; tries < BALANCE_TRIES; tries++) {
      double pick = vlff_rng_uniform(&f->rng) * wtot, acc = 0;
      vi = nviews - 1;
      for (int k = 0; k < nviews; k++) {
        acc += weights ? weights[k] : 1.0;
        if (pick < acc) {
          vi = k;
          break;
        }
      }
      v = &views[vi];
      u = vlff_rng_uniform(&f->rng) * v->width, vv = vlff_rng_uniform(&f->rng) * v->height;
      double keep = errb > 0 ? error_keep(f, v, u, vv, errb) : 1;
      if (bal > 0 && v->features) {
        int c = pseudo_class(f, v, u, vv);
        for (int k = 0; k < f->K; k++) f->bal_freq[k] *= 0.999;
        f->bal_freq[c] += 0.001;
        keep *= pow(1.0 / (f->K * f->bal_freq[c]), bal);
      }
      if (keep >= 1 || vlff_rng_uniform(&f->rng) < keep) break;
    }
    int px = (int)u, py = (int)vv;
    if (px >= v->width) px = v->width - 1;
    if (py >= v->height) py = v->height - 1;
    vlff_camera_ray(v, u, vv, r->o, r->d);
    r->view = vi;
    r->has_rgb = v->rgb != NULL;
    if (r->has_rgb) {
      const uint8_t *c = v->rgb + 3 * ((size_t)py * v->width + px);
      for (int ch = 0; ch < 3; ch++) r->rgb[ch] = c[ch] * (1.0f / 255.0f);
      n_rgb++;
    }
    r->depth = pixel_depth(v, u, vv);
    r->cell = -1;
    f->ray_loss[i] = -1;
    if (r->depth > 0) {
      n_depth++;
      long c = ray_end_cell(f, r->o, r->d, r->depth);
      if (c >= 0 && f->exposure[c] < UINT16_MAX) f->exposure[c]++;
      r->cell = (int)c;
    }
    r->feat_index = -1;
    if (v->features) {
      int fx = (int)(u * v->feat_width / v->width), fy = (int)(vv * v->feat_height / v->height);
      if (fx >= v->feat_width) fx = v->feat_width - 1;
      if (fy >= v->feat_height) fy = v->feat_height - 1;
      r->feat_index = fy * v->feat_width + fx;
      n_feat++;
    }
  }
  f->views = views;
  f->scale_rgb = n_rgb ? 1.0f / (float)n_rgb : 0.0f;
  f->scale_depth = n_depth ? (float)f->cfg.train.depth_weight / (float)n_depth : 0.0f;
  f->scale_feat = n_feat ? (float)f->cfg.train.feature_weight / (float)n_feat : 0.0f;
  if (counts) {
    counts[0] = n_rgb;
    counts[1] = n_depth;
    counts[2] = n_feat;
  }
}

int vlff_field_set_levels(struct vlff_field *f, int n) {
  f->enc.active = n < 1 ? 1 : n > f->enc.levels ? f->enc.levels : n;
  return f->enc.active;
}

int vlff_field_set_rays(struct vlff_field *f, int n) {
  f->nrays = n < 1 ? 1 : n > f->nrays_max ? f->nrays_max : n;
  return f->nrays;
}

/* The step's statistics (field.h) from the threads' sums and the phases'
 * times. */
static void step_stats(const struct vlff_field *f, struct vlff_train_stats *stats, int n_rgb, double t0, double t1,
                       double t2, double t3) {
  if (!stats) return;
  memset(stats, 0, sizeof(*stats));
  double sq = 0;
  for (int t = 0; t < f->threads; t++) {
    struct vlff_work *w = &f->work[t];
    stats->loss_rgb += w->loss_rgb;
    stats->loss_depth += w->loss_depth;
    stats->loss_feat += w->loss_feat;
    stats->samples += w->samples;
    stats->flops += w->flops;
    stats->time_gemm += w->gemm_s;
    /* Each line of p, m and v read once and written once. */
    stats->table_bytes += 6.0 * 64.0 * (double)w->table_lines;
    sq += w->sq_rgb;
  }
  stats->step = f->step;
  stats->loss = stats->loss_rgb + stats->loss_depth + stats->loss_feat;
  stats->time_rays = t1 - t0;
  stats->time_table = t2 - t1;
  stats->time_dense = t3 - t2;
  double mse = n_rgb ? sq / n_rgb : 0;
  /* NaN, not the 100 dB of the floor, when the colour error is not finite. */
  stats->psnr = !n_rgb ? 0 : !isfinite(mse) ? NAN : -10.0 * log10(mse > 1e-10 ? mse : 1e-10);
}

int vlff_field_step(struct vlff_field *f, const struct vlff_view *views, int nviews, const float *weights,
                    struct vlff_train_stats *stats, char *err, size_t errlen) {
  if (check_views(f, views, nviews, weights, err, errlen)) return -1;
  f->step++;
  int counts[3];
  vlff_field_draw_rays(f, views, nviews, weights, counts);
  int n_rgb = counts[0];
  for (int t = 0; t < f->threads; t++) {
    struct vlff_work *w = &f->work[t];
    memset(w->grad, 0, f->nmlp * sizeof(float));
    w->loss_rgb = w->loss_depth = w->loss_feat = w->sq_rgb = 0;
    w->samples = 0;
    w->flops = w->gemm_s = 0;
    w->table_lines = 0;
  }
  struct step_ctx sc = {f, step_chunks(f, f->nrays),
                        f->adam.lr * powf((float)f->cfg.train.lr_decay, (float)(f->step / f->cfg.train.lr_decay_steps))};
  double t0 = vlff_seconds();
  vlff_pool_run(f->pool, sc.nchunks, chunk_task, &sc);
  double t1 = vlff_seconds();
  /* A non-finite loss (the field's own state gone non-finite, or an input
   * past validation) would carry NaN into every parameter and moment the
   * gradients reach: no update, and the caller is told (field.h). */
  double total = 0;
  for (int t = 0; t < f->threads; t++) total += f->work[t].loss_rgb + f->work[t].loss_depth + f->work[t].loss_feat;
  if (!isfinite(total)) {
    f->views = NULL;
    f->step--;
    step_stats(f, stats, n_rgb, t0, t1, t1, t1);
    if (err && errlen)
      snprintf(err, errlen, "field step: the loss is not finite (%g) at step %lld: no update applied", total,
               f->step + 1);
    return -2;
  }
  vlff_pool_run_dynamic(f->pool, f->enc.levels, hash_task, &sc);
  double t2 = vlff_seconds();
  vlff_pool_run(f->pool, MLP_SPLIT, mlp_task, &sc);
  average_weights(f);
  refresh_weights(f);
  double t3 = vlff_seconds();
  f->views = NULL;
  /* Each ray's feature loss into its cell's running loss (error_sampling). */
  for (int i = 0; i < f->nrays; i++) {
    const struct vlff_ray *r = &f->rays[i];
    float l = f->ray_loss[i];
    if (r->cell < 0 || !(l >= 0 && isfinite(l))) continue;
    float *e = &f->cell_err[r->cell];
    *e = *e < 0 ? l : 0.8f * *e + 0.2f * l;
  }
  if (f->cfg.train.sampling != VLFF_SAMPLING_UNIFORM && f->step % f->cfg.train.occupancy_update_steps == 0)
    vlff_field_occupancy_update(f, 0);

  step_stats(f, stats, n_rgb, t0, t1, t2, t3);
  return 0;
}

/* ---- occupancy grid ------------------------------------------------------- */

struct occ_ctx {
  struct vlff_field *f;
  size_t c0, n;          /* cells [c0, c0+n) (mod total) */
  int ntasks;
};

static void occ_task(void *ctx, int task, int thread) {
  struct occ_ctx *oc = ctx;
  struct vlff_field *f = oc->f;
  struct vlff_work *w = &f->work[thread];
  struct vlff_occupancy *g = &f->occ;
  size_t total = vlff_occ_cells(g);
  size_t a = oc->n * task / oc->ntasks, b = oc->n * (task + 1) / oc->ntasks;
  uint64_t rng = (uint64_t)f->step * 0x9e3779b97f4a7c15ull + (uint64_t)task * 0x632be59bd9b4e019ull + 1;
  for (size_t i = a; i < b;) {
    int n = 0;
    size_t first = i;
    for (; i < b && n < VLFF_QUERY_BLOCK; i++, n++) {
      size_t c = (oc->c0 + i) % total;
      int cx = (int)(c % g->dims[0]), cy = (int)(c / g->dims[0] % g->dims[1]),
          cz = (int)(c / ((size_t)g->dims[0] * g->dims[1]));
      float x[3] = {g->box_min[0] + (cx + vlff_rng_uniform(&rng)) * g->cell[0],
                    g->box_min[1] + (cy + vlff_rng_uniform(&rng)) * g->cell[1],
                    g->box_min[2] + (cz + vlff_rng_uniform(&rng)) * g->cell[2]};
      vlff_encoding_normalise(&f->enc, x, w->p + 3 * n);
    }
    vlff_field_density(f, w, vlff_mlp_params(f), w->p, n);
    for (int k = 0; k < n; k++) {
      size_t c = (oc->c0 + first + k) % total;
      /* Halving per visit (every fourth update) lets early, untrained density
       * fade within a few hundred steps; a surface keeps its cell alive. */
      float d = fmaxf(g->density[c] * 0.5f, w->sigma[k]);
      g->density[c] = d;
      g->occ[c] = d > g->threshold;
    }
  }
}

void vlff_field_occupancy_update(struct vlff_field *f, int full) {
  struct vlff_occupancy *g = &f->occ;
  size_t total = vlff_occ_cells(g);
  /* A quarter of the grid per update keeps the cost small; the grid is swept
   * completely every four updates. */
  size_t n = full ? total : (total + 3) / 4;
  struct occ_ctx oc = {f, (size_t)f->occ_cursor, n, 16};
  vlff_pool_run(f->pool, oc.ntasks, occ_task, &oc);
  f->occ_cursor = (int)((f->occ_cursor + n) % total);
}
