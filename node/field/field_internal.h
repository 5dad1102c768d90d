/*
 * Internal interface of the learner core: the pieces behind field.h.
 *
 * The trainer wires encoding -> MLP1 (density, code) -> MLP2 (colour) and
 * MLP3 (feature) -> renderer -> loss -> backward -> Adam. Every piece works on
 * a block of samples laid out row-major ([sample][channel]) so the dense
 * layers are GEMMs; nothing here allocates: buffers come from the caller.
 * Not part of the public API; only node/field and its tests include it.
 */
#ifndef VLFF_FIELD_INTERNAL_H
#define VLFF_FIELD_INTERNAL_H

#include <stddef.h>
#include <stdint.h>

#include "clock.h" /* vlff_seconds for the step timers */
#include "field.h"
#include "hot.h"
#include "rng.h" /* vlff_rng_next, the generator of rays and initial weights */

/* ---- thread pool (pool.c) ---------------------------------------------- */
struct vlff_pool;
typedef void (*vlff_task_fn)(void *ctx, int task, int thread);
/* threads <= 0: one per online core. The calling thread is worker 0. */
struct vlff_pool *vlff_pool_create(int threads);
void vlff_pool_destroy(struct vlff_pool *p);
int vlff_pool_threads(const struct vlff_pool *p);
/* Runs fn(ctx, t, thread) for t in [0, ntasks): task t goes to thread
 * t % threads, so a run is deterministic for a given thread count. */
void vlff_pool_run(struct vlff_pool *p, int ntasks, vlff_task_fn fn, void *ctx);
/* The same, but each thread claims the next unclaimed task (in increasing
 * t) when it is free: for tasks of unequal cost whose results do not depend
 * on the thread that runs them. */
void vlff_pool_run_dynamic(struct vlff_pool *p, int ntasks, vlff_task_fn fn, void *ctx);
/* ---- the box (grow.c) ---------------------------------------------------- */
/* The first box's occupancy cells under a config: each cell's size (m) and
 * the cells per axis (what vlff_field_plan_bytes counts before a field is
 * made). */
void vlff_field_first_cells(const struct vlff_cfg_field *c, const struct vlff_cfg_train *t, float cell[3],
                            int dims[3]);
/* The first box's occupancy lattice: sets occ.cell and occ.threshold and
 * first_lo, and gives the first grid's cells. */
void vlff_field_first_layout(struct vlff_field *f, int k0[3], int dims[3]);
/* (Re)allocates the occupancy arrays for cells k0 .. k0+dims of the lattice,
 * starting every cell as a new field's, but with copy, the old grid's cells
 * in their places (the old grid must lie inside); sets the box. -1: out of
 * memory, f unchanged. */
int vlff_field_occ_layout(struct vlff_field *f, const int k0[3], const int dims[3], int copy);
/* The box from the grid's place on the lattice (the config's when fixed),
 * and the encoding's inside test with it. */
void vlff_field_set_box(struct vlff_field *f);
/* The bytes of `cells` occupancy cells (density, occupancy, exposure,
 * running loss, 11 a cell), and whether train.occupancy_max_mb holds them. */
static inline double vlff_occ_bytes(double cells) {
  return cells * (double)(sizeof(float) + 1 + sizeof(uint16_t) + sizeof(float));
}
static inline int vlff_occ_fits(const struct vlff_cfg_train *train, double cells) {
  return vlff_occ_bytes(cells) <= train->occupancy_max_mb * 1048576.0;
}

/* CLOCK_MONOTONIC in seconds: the pool's spin, the step's phases and the
 * GEMM's per-thread time share it. */

/* ---- encoding (encoding.c) --------------------------------------------- */
struct vlff_encoding {
  int levels, feats, log2_size, freq_bands;
  int active;              /* levels in use: finer ones output 0 and get no gradient */
  int dim;                 /* levels*feats + 6*freq_bands */
  uint32_t size;           /* entries per level */
  /* p = (x - min) * scale: the same scale on every axis (cubic cells), the
   * box's longest axis spanning [0, 1] and each axis [0, p_top]; the
   * frequency part's angle is p * freq_scale, [0, pi] over each axis.
   * Growing, min is the origin (below) and p spans [p_lo, p_hi], the
   * world's faces (+ phase on the angle). */
  float box_min[3], box_scale[3], p_top[3], freq_scale[3];
  float p_lo[3], p_hi[3];  /* the clamp: [0, p_top] fixed */
  float freq_phase[3];     /* added to the angle: 0 fixed; growing, what keeps it the world frame's */
  double corner[3];        /* growing: the world's low corner, metres (the frame cells count from) */
  double box_ext[3];       /* the box's size, metres */
  int cubic;               /* 1: as above; 0: each axis scaled to [0, 1] (checkpoints before version 5) */
  /* Growing (field.grow): the box above is the whole world, a cube of
   * +-(field.world_limit_m + the first box's longest side) around the first
   * box's centre, so that a point's cells never move as the field's box
   * grows; the levels keep the first box's cell sizes in metres and are all
   * hashed, and the frequency part keeps the first box's periods
   * (freq_ext). Fixed: freq_ext is the box's size.
   * A growing field's positions are taken from an origin near its box (min
   * above: the first box's centre, moved with the box when it has gone far,
   * vlff_encoding_set_origin), not from the world's corner: a float
   * position counted from the corner of a 2 km world is ~86000 cells into
   * the finest level, where a float resolves 1/128 of a cell, and the fit
   * lost 6 points of 3D mIoU in the field alone to that (docs/field.md
   * "Positions from an origin near the box"). A level's cell on axis a is
   * floor(p * res + shift) + kofs, the corner frame's cell: kofs + shift
   * is where the origin lies in the level's cells from the corner (kofs
   * the whole cells); fixed, both 0. */
  int grow;
  double freq_ext[3];
  float shift[32][3];
  int32_t kofs[32][3];
  /* The field's box in normalised units: a point outside is "outside" for
   * vlff_encoding_normalise (the whole of [0, p_top] when fixed). */
  float in_lo[3], in_hi[3];
  float res[32];           /* grid cells per axis, per level */
  int dense[32];           /* level indexed densely (no hashing) */
  int simd;                /* VLFF_ISA_*: the vector kernels (the portable loops' results to float rounding) */
};
void vlff_encoding_init(struct vlff_encoding *e, const struct vlff_cfg_field *cfg);
/* The cells' shape: cubic (1, the default) or each axis of the box scaled
 * to [0, 1] (0: what a field checkpointed before version 5 learned in). */
void vlff_encoding_set_cells(struct vlff_encoding *e, int cubic);
/* Growing: positions count from o (metres) from now on; every point keeps
 * its cells and its encoding (to float rounding). Call before
 * vlff_encoding_set_inside. */
void vlff_encoding_set_origin(struct vlff_encoding *e, const double o[3]);
/* Sets the field's box (metres) that vlff_encoding_normalise tests against. */
void vlff_encoding_set_inside(struct vlff_encoding *e, const double lo[3], const double hi[3]);
/* Normalised position of world point x, clamped to [p_lo, p_hi]; returns 0
 * when x was outside the field's box. */
int vlff_encoding_normalise(const struct vlff_encoding *e, const float *x, float *p);
/* out[n][dim] for n normalised points p[n][3]; table = level-major params. */
void vlff_encoding_forward(const struct vlff_encoding *e, const float *table, const float *p, int n,
                           float *out, int ldo);
/* Accumulate dL/dtable of one level from d[n][ld] (that level's F values
 * per point) into g[entries][F], which holds zeros at every entry not marked
 * with this stamp, and mark each entry reached: marks[entry] = stamp (one
 * byte per entry of the level; the caller's stamp differs from every mark
 * left by an earlier call). The lazy Adam update consumes the marked entries
 * in index order and zeroes the gradient it used, which keeps that invariant.
 * Bytes, not bits: a bit's read-modify-write of a word shared by x-adjacent
 * corners chains each corner's store to the next one's load, and that chain
 * bounded the scatter (twice the time per point of byte marks on a coarse
 * level); a byte store depends on nothing. A stamp, not a flag: nothing has
 * to clear the marks, which would write 512 KB per level back. */
void vlff_encoding_backward(const struct vlff_encoding *e, const float *p, int n, const float *d, int ld,
                            int level, float *g, uint8_t *marks, uint8_t stamp);
/* The bulk binary16 conversions' kernels (half.c); the public pair picks
 * one. Exposed so that the tests run every one the CPU has. */
void vlff_f16_to_f32_generic(const uint16_t *src, float *dst, size_t n);
void vlff_f32_to_f16_generic(const float *src, uint16_t *dst, size_t n);
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define VLFF_HALF_X86 1
void vlff_f16_to_f32_v4(const uint16_t *src, float *dst, size_t n);
void vlff_f32_to_f16_v4(const float *src, uint16_t *dst, size_t n);
void vlff_f16_to_f32_v3(const uint16_t *src, float *dst, size_t n);
void vlff_f32_to_f16_v3(const float *src, uint16_t *dst, size_t n);
#else
#define VLFF_HALF_X86 0
#endif
/* Table entries level l indexes: (res+1)^3 for a dense level, else size. */
size_t vlff_encoding_entries(const struct vlff_encoding *e, int l);

/* ---- dense layers (mlp.c) ---------------------------------------------- */
#define VLFF_MLP_MAX_LAYERS 9
struct vlff_mlp {
  int nin, nout, width, hidden;      /* hidden = number of hidden layers */
  int nl;                            /* linear layers = hidden + 1 */
  int din[VLFF_MLP_MAX_LAYERS], dout[VLFF_MLP_MAX_LAYERS];
  size_t woff[VLFF_MLP_MAX_LAYERS], boff[VLFF_MLP_MAX_LAYERS];  /* into params: Wt[in][out], b[out] */
  size_t nparams;
};
/* Lays the MLP out at params offset base; returns the next offset (each
 * block padded to 16 floats so rows stay vector aligned). */
size_t vlff_mlp_init(struct vlff_mlp *m, int nin, int width, int hidden, int nout, size_t base);
void vlff_mlp_init_params(const struct vlff_mlp *m, float *params, uint64_t *rng);
/* C[M][N] (+)= A[M][K] B[K][N]; A(i,k) = a[i*ars + k*acs]. bias (may be
 * NULL) initialises C; accumulate adds to C instead; relu clamps at 0. */
void vlff_gemm(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb,
               float *c, int ldc, const float *bias, int accumulate, int relu);
/* Seconds the calling thread has spent in vlff_gemm and vlff_gemm_mask. */
double vlff_gemm_thread_seconds(void);
/* Labels, scores and margins of m points from their MLP3 hidden vectors,
 * feature-major: hT[H][ldh], point i in column i; ldh and the columns read
 * are m rounded up to the kernel's panel (at most 32), so hT holds finite
 * values (zeros) there. Logits l = E W h + E b from ewt = (E W)ᵀ [H][K] and
 * eb [K] (K <= VLFF_FIELD_MAX_PROMPTS); label = first argmax, score = l_best/|f|,
 * margin = (l_best - l_second)/|f|. |f|^2 = |R h + rv|^2 + r22^2 with rt =
 * Rᵀ [H][H], R upper triangular; or, with gram set, hᵀ G h + 2 rv.h + r22^2
 * with rt = G. rt NULL: no norm (score and margin unscaled). label, score,
 * margin may each be NULL. */
void vlff_score(int m, int H, int K, const float *hT, int ldh, const float *ewt, const float *eb, const float *rt,
                const float *rv, float r22, int gram, int *label, float *score, float *margin);
/* Name of the GEMM kernel in use ("avx512", "avx2+fma", "generic").
 * VLFF_GEMM=generic forces the portable kernels everywhere, VLFF_GEMM=avx2
 * the AVX2 ones on a CPU with AVX-512 (as an AVX2-only CPU runs). */
const char *vlff_gemm_isa(void);
/* The same as a level: the kernels that follow the GEMM's choice. */
enum { VLFF_ISA_PORTABLE = 0, VLFF_ISA_AVX2 = 1, VLFF_ISA_AVX512 = 2 };
int vlff_gemm_isa_level(void);
/* Runs the FMA throughput probe of the kernel's ISA for iters iterations
 * on the calling thread; *flops_per_iter receives its FLOPs per iteration. */
float vlff_fma_probe(long iters, int *flops_per_iter);
/* Same, with C zeroed wherever mask (laid out like C) is not > 0. */
void vlff_gemm_mask(int m, int n, int k, const float *a, ptrdiff_t ars, ptrdiff_t acs, const float *b, int ldb,
                    float *c, int ldc, const float *bias, int accumulate, int relu, const float *mask);
/* FLOPs of forward (and backward) through layers [0, upto) for one row. */
double vlff_mlp_flops(const struct vlff_mlp *m, int upto, int backward);
/* Forward of layers [0, upto): act[l] is [n][dout[l]] (ReLU applied for
 * hidden layers, none for the output layer). x is [n][ldx]. */
void vlff_mlp_forward(const struct vlff_mlp *m, const float *params, const float *x, int ldx, int n,
                      int upto, float **act);
/* Backward through layers [0, upto): dy = dL/d(act[upto-1]) (already through
 * the output activation; overwritten). Accumulates parameter gradients into
 * grad (same layout as params) and writes dL/dx to dx[n][ldx] when dx is not
 * NULL. wT = per-layer transposed weights W[out][in]; tmp = scratch of
 * n*max(width,nin,nout) floats. */
void vlff_mlp_backward(const struct vlff_mlp *m, const float *wT, const float *x, int ldx, int n, int upto,
                       float *const *act, float *dy, float *grad, float *dx, float *tmp);
/* Refresh the transposed weight copies from params. */
void vlff_mlp_transpose(const struct vlff_mlp *m, const float *params, float *wT);

/* ---- volume rendering (render.c) --------------------------------------- */
/* Weights of one ray: sigma[s], delta[s] -> w[s], T[s] (transmittance before
 * sample s). Stops when T drops below VLFF_T_MIN; returns the samples used
 * (later weights are 0). */
#define VLFF_T_MIN 1e-4f
int vlff_render_weights(const float *sigma, const float *delta, int ns, float *w, float *trans);
/* dL/dsigma[s] from e[s] = dL/dw_s-direction scalars (see render.c). */
void vlff_render_backward(const float *w, const float *trans, const float *sigma, const float *delta,
                          const float *e, int ns, float *dsigma);

/* ---- losses (loss.c) --------------------------------------------------- */
/* Each returns the loss of one ray and writes its gradient (scaled by
 * scale). */
float vlff_loss_rgb(const float *pred, const float *target, float scale, float *grad);
float vlff_loss_depth(float pred, float target, float scale, float *grad);
float vlff_loss_feat(const float *pred, const float *target, int d, int mode, float scale, float *grad);

/* ---- Adam (adam.c) ----------------------------------------------------- */
struct vlff_adam {
  float lr, beta1, beta2, eps, wd;
  int simd;                /* VLFF_ISA_*: vector marks and line updates (the portable code's results, bit for bit) */
};
/* Dense update of params[i0,i1) (decay = apply weight decay). */
void vlff_adam_dense(const struct vlff_adam *a, long long t, float lr, float *p, const float *g, float *m,
                     float *v, size_t i0, size_t i1, int decay);
/* Lazy update of the entries whose mark equals stamp (n entries, each
 * `width` floats wide); sets those entries' g to 0. Returns the entries
 * updated; *lines (when not NULL) gets the 64-byte lines of p, counted from
 * p, that hold one: the least memory any update of them reads and writes in
 * p, and in m and v alike (the same layout). */
size_t vlff_adam_sparse(const struct vlff_adam *a, long long t, float lr, float *p, float *g, float *m,
                        float *v, const uint8_t *marks, uint8_t stamp, size_t n, int width, size_t *lines);

/* ---- sampling (sampler.c) ---------------------------------------------- */
struct vlff_occupancy {
  /* Cells per axis: train.occupancy_resolution on each over a fixed box;
   * over a growing one, train.occupancy_cell_m cubes or the first box's own
   * cells (each side over that resolution), as many as the box holds. x
   * fastest, then y, z. */
  int dims[3];
  float box_min[3], cell[3];
  float *density;          /* EMA of max density */
  uint8_t *occ;
  float threshold;         /* density above which a cell is occupied */
};
/* Cells in the grid. */
static inline size_t vlff_occ_cells(const struct vlff_occupancy *g) {
  return (size_t)g->dims[0] * g->dims[1] * g->dims[2];
}
/* Box entry/exit of a ray (t along dir); returns 0 when it misses. */
int vlff_ray_box(const float *o, const float *d, const float *bmin, const float *bmax, float *t0, float *t1);
/* Stratified samples in [t0,t1] restricted to occupied cells; returns the
 * count (<= ns) and the spacing of the samples in t. u = jitter source
 * (NULL = centred). */
int vlff_sample_occupied(const struct vlff_occupancy *g, const float *o, const float *d, float t0, float t1,
                         int ns, uint64_t *rng, float *t, float *dt);
int vlff_sample_uniform(float t0, float t1, int ns, uint64_t *rng, float *t, float *dt);
/* Depth-guided: a band around the measured depth plus free space before it. */
int vlff_sample_depth(float depth, float noise_1m, float t0, float t1, int ns, uint64_t *rng, float *t, float *dt);
/* The half-width of the band around a measured depth where the surface
 * lies: 4 cm + 3 % of the depth, and at least 3 sigma of the sensor's noise
 * there (noise_1m d^2). Training samples it; the label image's surface
 * points trust the field's surface within it (vlff_field_snap_surface). */
static inline float vlff_depth_band(float depth, float noise_1m) {
  float a = 0.04f + 0.03f * depth, b = 3.0f * noise_1m * depth * depth;
  return a > b ? a : b;
}

/* ---- small shared helpers ---------------------------------------------- */
static inline float vlff_rng_uniform(uint64_t *s) { return (float)(vlff_rng_next(s) >> 40) * (1.0f / 16777216.0f); }
/* Real spherical harmonics up to degree deg (deg*deg values) of unit d. */
void vlff_sh_encode(const float *d, int deg, float *out);

/* ---- the field object (trainer.c, query.c, checkpoint.c) -------------- */
#define VLFF_CHUNK_SAMPLES 1024  /* samples per work chunk (L2-sized activations) */
#define VLFF_FEAT_WMIN 1e-3f     /* MLP3 runs only where a sample's weight reaches this */
#define VLFF_QUERY_BLOCK 256     /* points per query task */

struct vlff_ray {
  float o[3], d[3];        /* world origin, direction with unit camera-z */
  float rgb[3], depth;     /* targets; depth <= 0: none */
  int has_rgb;
  int view, feat_index;    /* feat_index < 0: no feature target */
  int cell;                /* occupancy cell where the measured depth ends, -1: none */
};

/* Per-thread scratch, planned at create for one chunk. */
struct vlff_work {
  int cap;                 /* samples */
  int rcap;                /* rays */
  float *t, *delta, *sigma, *w, *trans, *e, *dsig;
  int *ray_off, *ray_cnt, *ray_used;
  int *sel2, *sel3, *ray_of;
  float *p, *enc;
  float *a1[VLFF_MLP_MAX_LAYERS], *a2[VLFF_MLP_MAX_LAYERS], *a3[VLFF_MLP_MAX_LAYERS];
  float *in2, *in3, *dy_a, *dy_b, *dout1, *din2, *din3, *denc;
  float *hray, *fray, *gf, *dh, *wsum, *tfeat, *rgb, *depth, *logits, *opac, *norm;
  float *depth2; /* per ray: opacity-weighted squared depth (render_chunk; the surface's spread) */
  struct vlff_ray *rbuf;
  float *grad;             /* this thread's MLP gradient */
  /* The table gradient of the level this thread updates, zero between
   * uses, and its touched-entry marks (the current one is tstamp). One level
   * at a time per thread, reused level after level: it stays in cache, where
   * a gradient array per level made every step read and write 8 MB of fine
   * level gradient and 512 KB of marks from memory. */
  float *tgrad;            /* size * feats */
  uint8_t *tmarks;         /* size */
  uint8_t tstamp;          /* 1..255, one more per level updated */
  double loss_rgb, loss_depth, loss_feat, sq_rgb;
  long long samples;
  double flops;            /* dense-layer FLOPs executed */
  double gemm_s;           /* seconds in their products, this step */
  size_t table_lines;      /* 64-byte lines of parameters the table update moved, this step */
  uint64_t rng;
};

/* The sections a field is made from (field.h). */
struct vlff_field_cfg {
  struct vlff_cfg_field field;
  struct vlff_cfg_train train;
};

struct vlff_field {
  struct vlff_field_cfg cfg;
  struct vlff_pool *pool;
  int threads;
  struct vlff_encoding enc;
  struct vlff_mlp m1, m2, m3;
  int D, H, geo, shdim, E;
  int spr;                 /* samples per ray */
  int chunk_rays;
  size_t ntable, nmlp, nparams;   /* table floats, MLP floats (params = table, then MLP) */
  float *params, *adam_m, *adam_v;
  float *grad;             /* the MLP gradient, summed over threads (the table's is in vlff_work) */
  float *wT;               /* transposed MLP weights, MLP-relative offsets */
  /* The MLP weights queries and renders read (and the prompt fold is made
   * from): an exponential moving average of the trained ones with decay
   * train.weight_average per step, and its transposes. Training reads and
   * updates params; the average only follows. */
  float *avg, *avgT;
  struct vlff_adam adam;
  struct vlff_occupancy occ;
  /* The field's box (metres): the fixed box, or the growing one, whose
   * occupancy cells start occ_k0 cells from the first box's low corner
   * (first_lo; 0 when fixed). grown: growths since create. */
  double box_lo[3], box_hi[3], first_lo[3];
  int occ_k0[3];
  long long grown, slides;
  /* Training rays whose measured depth ended in each occupancy cell
   * (saturating): how much the field has been fitted there
   * (vlff_field_exposure). */
  uint16_t *exposure;
  /* train.error_sampling: each occupancy cell's running feature loss of the
   * rays that ended in it (-1: none trained yet), each drawn ray's loss this
   * step (-1: none), and the running mean of the candidates' cell losses. */
  float *cell_err, *ray_loss;
  double err_mean;
  long long step;
  uint64_t rng;
  int occ_cursor;
  struct vlff_work *work;  /* [threads] */
  struct vlff_ray *rays;   /* [rays_per_step] */
  int nrays, nrays_max;
  float *step_p;           /* per chunk slots of chunk_rays*spr samples: positions */
  float *step_denc;        /* and dL/d(hash features), level-major [level][sample][F] */
  int *chunk_n;
  /* prompts (folded) */
  int K;
  float *E_, *EW, *EWt, *Eb, *G, *u;
  float bb;
  /* Cholesky factor of the Gram matrix of [W b]: |W h + s b| = |Rt h + s r12|
   * and (r22 s), with Rt = R11ᵀ lower triangular ([k][j], zero for k < j);
   * chol_ok = 0 (rank-deficient W) falls back to G. */
  float *Rt, *r12, r22;
  int chol_ok;
  int fold_stale;          /* a step changed W since the fold was computed */
  /* step context */
  const struct vlff_view *views;
  float scale_rgb, scale_depth, scale_feat;
  int feat_loss;                 /* enum vlff_feat_loss */
  /* class-balanced ray drawing (train.class_balance): running frequency of
   * each prompt's pseudo-class among candidate pixels, and a scratch
   * feature */
  double bal_freq[VLFF_FIELD_MAX_PROMPTS];
  float *bal_feat;
  int render_feat;         /* rendering needs MLP3 */
};

static inline float *vlff_mlp_params(struct vlff_field *f) { return f->params + f->ntable; }

/* Forward through encoding and MLP1 (MLP weights pm: vlff_mlp_params for
 * training, f->avg for queries) for n normalised points of work w; fills
 * w->sigma and w->a1 (out layer = [density raw, code]). */
void vlff_field_density(struct vlff_field *f, struct vlff_work *w, const float *pm, const float *p, int n);
/* Work chunk of rays [r0, r0+nr) of the given rays: samples, forward,
 * optional loss + backward (train: the rays are f->rays', and each one's
 * feature loss goes to f->ray_loss). */
void vlff_field_chunk(struct vlff_field *f, struct vlff_work *w, const struct vlff_ray *rays, int nr, int train,
                      float *pslot, float *dencslot, int *nsamples);
/* Refresh derived data after parameters change (transposes, folded prompts). */
void vlff_field_refresh(struct vlff_field *f);
/* After f->params was set wholesale (init, a test): the average restarts
 * from it, and everything derived is refreshed. */
void vlff_field_reset_average(struct vlff_field *f);
/* Refresh the prompt fold and Gram factor if a step made them stale. */
void vlff_field_fold(struct vlff_field *f);
void vlff_field_occupancy_update(struct vlff_field *f, int full);
/* Forgets every cell's running loss (train.error_sampling): a new field,
 * or one loaded from a checkpoint without them, knows none. */
void vlff_field_forget_errors(struct vlff_field *f);
/* Draw train.rays_per_step rays into f->rays and set the loss scales;
 * counts = rays with rgb, depth, features (may be NULL). */
void vlff_field_draw_rays(struct vlff_field *f, const struct vlff_view *views, int nviews, const float *weights,
                          int *counts);
void vlff_camera_ray(const struct vlff_view *v, double u, double vv, float *o, float *d);

#endif
