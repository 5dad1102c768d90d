/*
 * vlff_field: the vision-language feature field (the learner core).
 *
 * A hash-grid + low-frequency encoding feeds MLP1 (density, geometric code);
 * MLP2 gives colour from the code and an SH view encoding; MLP3 gives the
 * D-dim feature. Colour, depth and features are volume-rendered and trained
 * on posed RGB-D views with dense feature maps (see docs/ and the paper).
 *
 * Conventions (every caller in vlff uses these)
 *  - World frame in metres. Cameras follow OpenCV: x right, y down, z
 *    forward; a pose is camera-to-world, 4x4 row-major double; pixel (u,v)
 *    centre is at (u+0.5, v+0.5).
 *  - Depth is metres along the camera z axis; 0 or non-finite = invalid.
 *  - Features are IEEE float16 (uint16_t bits), HWC, D = field.feature_dim.
 *  - Prompt embeddings are float32 [K][D]; the field L2-normalises them.
 *
 * Contract
 *  - Functions returning int give 0 on success, -1 on error with a message
 *    in err (when err is not NULL) naming what was wrong.
 *  - A vlff_field is used by one thread at a time (the caller serialises
 *    training, queries and checkpoints); internally each call uses
 *    node.threads worker threads. Distinct fields are independent.
 *  - All memory for a training step is planned at create time: steps and
 *    queries of up to the planned batch sizes do not allocate.
 *  - The caller owns every buffer it passes; nothing is retained after a
 *    call returns except the prompt embeddings (copied).
 */
#ifndef VLFF_FIELD_H
#define VLFF_FIELD_H

#include <stddef.h>
#include <stdint.h>

#include "config.h"

struct vlff_field;

/* One posed RGB-D(-feature) view, at training or rendering resolution. */
struct vlff_view {
  int width, height;
  const uint8_t *rgb;        /* RGB8, tightly packed rows; may be NULL (no colour loss) */
  const float *depth;        /* metres, width*height; may be NULL */
  double fx, fy, cx, cy;     /* intrinsics at width x height */
  double c2w[16];            /* camera-to-world, row-major */
  int feat_width, feat_height;
  int feature_dim;              /* D of features; must equal field.feature_dim when features != NULL */
  const uint16_t *features;  /* float16 [feat_height][feat_width][D]; may be NULL */
};

struct vlff_train_stats {
  long long step;
  double loss, loss_rgb, loss_depth, loss_feat;
  double psnr;               /* of this step's rays */
  long long samples;         /* network evaluations this step */
  double flops;              /* dense-layer FLOPs executed this step (forward + backward) */
  double time_gemm;          /* thread seconds in those layers' matrix products, summed over threads */
  double table_bytes;        /* the table's parameters and Adam moments its update read and wrote (64-byte lines) */
  /* Wall seconds of the step's three phases: the rays (sampling, network
   * forward and backward, losses), the hash table (gradient scatter and
   * its Adam update), the dense layers' Adam update. */
  double time_rays, time_table, time_dense;
};

/* The bytes vlff_field_create allocates and fills at once for these
 * sections, at the least (one worker thread): the hash table and MLPs with
 * Adam's two moments, the MLPs' gradient, transposes and average, each
 * step's sample positions and encodings (train.rays_per_step x
 * train.samples_per_ray), the occupancy grid. */
uint64_t vlff_field_plan_bytes(const struct vlff_cfg_field *field, const struct vlff_cfg_train *train);

/* 0 when that plan fits this machine's physical memory; -1 with err naming
 * the keys and both sizes. Every byte of the plan is written at create, so a
 * field larger than memory is not a slow start but the OOM killer: 32 levels
 * of 2^24 entries of 8 features are 48 GiB. */
int vlff_field_check_memory(const struct vlff_cfg_field *field, const struct vlff_cfg_train *train, char *err,
                            size_t errlen);

/* Create from the field and train sections, on threads worker threads
 * (node.threads: 0 = one per core); refuses what vlff_field_check_memory
 * refuses. */
struct vlff_field *vlff_field_create(const struct vlff_cfg_field *field, const struct vlff_cfg_train *train, int threads,
                                     char *err, size_t errlen);
void vlff_field_destroy(struct vlff_field *f);

/* One optimisation step on train.rays_per_step rays drawn from views.
 * weights (may be NULL = uniform) gives each view's share of the rays.
 * Views with features of the wrong D are an error, checked up front.
 * Queries and renders read a moving average of the MLP weights the steps
 * train (train.weight_average; 0 = the latest weights): the hash table is
 * the same, the decoders every point shares do not jitter from step to
 * step. */
/* Returns 0; -1 for bad views (checked up front, nothing changed); -2
 * when the step's loss came out non-finite: no update is applied (the step
 * count does not advance; the rays drawn, their exposure and the rng do),
 * stats (when given) carry the non-finite loss with psnr NaN, and err says
 * so. A non-finite loss comes from the field's own state gone non-finite
 * (then vlff_field_check names it, and the caller rolls back) or from an
 * input that slipped past validation. */
int vlff_field_step(struct vlff_field *f, const struct vlff_view *views, int nviews,
                    const float *weights, struct vlff_train_stats *stats, char *err, size_t errlen);

long long vlff_field_steps(const struct vlff_field *f);

/* Rays the next steps draw: n clamped to [1, train.rays_per_step] (the
 * batch memory planned at create); returns the value used. */
int vlff_field_set_rays(struct vlff_field *f, int n);

/* Hash levels in use, coarsest first: n clamped to [1, field.hash_levels]
 * (all by default); returns the value used. The finer levels then encode 0
 * in steps, queries and renders alike, and steps leave their parameters and
 * optimiser moments untouched, so a level joins later from where it was.
 * Not saved in checkpoints. */
int vlff_field_set_levels(struct vlff_field *f, int n);

/* Set the prompt set: K embeddings of dimension D (K <= VLFF_FIELD_MAX_PROMPTS).
 * The prompts are folded into MLP3's last layer; queries then cost K, not D,
 * output dot products. */
int vlff_field_set_prompts(struct vlff_field *f, const float *emb, int k, char *err, size_t errlen);

/* 3D queries at n points (xyz interleaved). Any output may be NULL.
 *  density[n]; feature[n][D] (unfolded, raw MLP3 output);
 *  label[n] = argmax_k E_k . f(x) over the prompt set, -1 outside the box;
 *  score[n] = the winning cosine similarity; margin[n] = best - second best. */
int vlff_field_query(struct vlff_field *f, const float *xyz, size_t n, float *density,
                     float *feature, int *label, float *score, float *margin);

/* Per-prompt cosine similarities at n points: cosine[n][K] = E_k . f(x) /
 * |f(x)| (0 outside the box or where the feature is zero). -1 without
 * prompts. Costs the unfolded D-wide layer, as a feature query. */
int vlff_field_query_cosines(struct vlff_field *f, const float *xyz, size_t n, float *cosine);
/* The prompt set's unit embeddings [K][D], valid until the next
 * vlff_field_set_prompts; *k = K (0: none). */
const float *vlff_field_prompt_embeddings(const struct vlff_field *f, int *k);

/* How much the field has been fitted at n points: rays[n] = the training
 * rays whose measured depth ended in the point's occupancy cell
 * (train.occupancy_resolution^3 over a fixed box), saturating at 65535; 0
 * outside the box. Checkpoints keep it; a field loaded from a version-1
 * checkpoint, which lacks it, counts 65535 in every cell. Where the camera
 * has only just looked, the field's feature is what the shared decoder
 * says of other places: a map can trust its own fused evidence more there
 * (evidence.h). */
void vlff_field_exposure(const struct vlff_field *f, const float *xyz, size_t n, uint16_t *rays);

/* Growth (field.grow). The field's box is where it samples rays and keeps
 * occupancy; outside it density is 0 and nothing is rendered. Fixed, it is
 * field.scene_min/max. Growing, those are the first box, and the hash grid
 * and the frequency part are laid over the whole world (+-field.world_limit_m
 * around the first box) with the first box's cell sizes in metres: a point's
 * encoding never changes when the box grows, so growing changes nothing the
 * field has learned. The occupancy cells keep their size: cubes of
 * train.occupancy_cell_m, or the first box's own cells (each side over
 * train.occupancy_resolution), on one lattice from the first box's low
 * corner.
 *  - vlff_field_grow: the box grows, in whole cells, to hold [lo, hi]
 *    (clipped to the world): 1 grown, 0 when it already held it, -1 (f
 *    unchanged) when the box is fixed, the box is empty or not finite, or
 *    [lo, hi] alone would pass train.occupancy_max_mb (err names the size).
 *    New cells start as a new field's (occupied, nothing fitted); old cells
 *    keep their state.
 *  - vlff_field_slide: as grow, but where the grown box would pass
 *    train.occupancy_max_mb the box slides instead (vlff_lattice_window:
 *    [lo, hi] and as much of the old box around it as fits): 2, the cells
 *    it leaves dropped (the hash grid, the world's, keeps what was learned
 *    there; docs/field.md "Beyond the caps"). A mapping reset
 *    (vlff_field_reinit) returns to the first box. Checkpoints keep the box.
 *  - vlff_field_box: the box now; vlff_field_growths: growths since create
 *    (slides too), vlff_field_slides: slides since create. */
int vlff_field_grow(struct vlff_field *f, const double lo[3], const double hi[3], char *err, size_t errlen);
int vlff_field_slide(struct vlff_field *f, const double lo[3], const double hi[3], char *err, size_t errlen);
void vlff_field_box(const struct vlff_field *f, double lo[3], double hi[3]);
long long vlff_field_growths(const struct vlff_field *f);
long long vlff_field_slides(const struct vlff_field *f);

/* Render a view at cam's pose and intrinsics (cam->rgb/depth/features are
 * ignored). Outputs may be NULL: rgb[h][w][3] in [0,1], depth[h][w] metres,
 * feature[h][w][D], label[h][w] (prompt index, -1 where nothing was hit),
 * score[h][w]. */
int vlff_field_render(struct vlff_field *f, const struct vlff_view *cam, float *rgb, float *depth,
                      float *feature, int *label, float *score);

/* The same for the n pixels listed in pix (y * width + x, each < width *
 * height): outputs are still image-sized, and only the listed pixels are
 * written. For filling in a few pixels without rendering the whole view. */
int vlff_field_render_pixels(struct vlff_field *f, const struct vlff_view *cam, const uint32_t *pix, size_t n,
                             float *rgb, float *depth, float *feature, int *label, float *score);

/* Measured surface points, refined by the field's surface: xyz[n] (moved in
 * place) are points a depth sensor measured along the rays of cam's pixels
 * pix[n]. Each moves along its ray toward the field's surface there (the
 * opacity-weighted depth of the rendered ray, where it is at least half
 * opaque) when that lies within the measurement's noise band (the band
 * depth-guided training samples: 4 cm + 3 % of the depth, at least 3 sigma
 * of train.depth_noise_m d^2), and stays where it was otherwise. It moves
 * to the two depths' inverse-variance mean: the sensor's variance
 * (train.depth_noise_m d^2)^2 against the square of the density's spread
 * along the ray (at least 5 mm), so a precise sensor's point barely moves
 * (a depth noise of 0 moves none) and a stereo one's goes nearly all the
 * way. A stereo sensor's single measurement is off by 9-16 cm at 3-4 m;
 * the field has fitted that surface from every view. Returns the points
 * moved (those left where they were are not counted); 0, with
 * nothing moved, also for n = 0, a NULL argument, a non-finite pose,
 * non-positive focal lengths or any pixel outside the image. Costs a
 * render of density alone. */
size_t vlff_field_snap_surface(struct vlff_field *f, const struct vlff_view *cam, const uint32_t *pix, size_t n,
                               float *xyz);
/* The depth sensor's noise sigma at 1 m the field was made with
 * (train.depth_noise_m; sigma grows with the range squared). */
double vlff_field_depth_noise(const struct vlff_field *f);

/* Bounds of the learned state, far beyond what training produces (the
 * analytic scene's field after 3,000 steps: |params| <= 5, |Adam m| <=
 * 0.009, Adam v <= 7e-4; even the demo trained at train.lr 10, the
 * config's ceiling, held |m| of 1.2e4 after 1,200 steps, and its field
 * must still save and resume) and where float arithmetic stays finite:
 * three layers of 64 products of values up to 1e6 stay below 1e30, and
 * v up to 1e16 times Adam's bias correction (at most 1000) and m over its
 * root stay far from overflow. params and the averaged MLP weights within
 * +-MAX_PARAM, Adam's first moment within +-MAX_MOMENT1, the second in
 * [0, MAX_MOMENT2] (a mean of squares), the occupancy density in [0, e^15]
 * (the density activation's clamp), the step in [0, 2^40] (35 years at
 * 1,000 steps/s: no count near overflow). Each also excludes NaN and
 * infinities. */
#define VLFF_FIELD_MAX_PARAM 1e6f
#define VLFF_FIELD_MAX_MOMENT1 1e8f
#define VLFF_FIELD_MAX_MOMENT2 1e16f
#define VLFF_FIELD_MAX_DENSITY 3.3e6f
#define VLFF_FIELD_MAX_STEP (1LL << 40)

/* 0 when the learned state is within those bounds; -1 with err naming the
 * first value outside ("params[17] (MLP weights) = nan, not finite"). A scan
 * of the whole state (parameters and moments): for checkpoint time and after
 * a non-finite loss, not every step. */
int vlff_field_check(const struct vlff_field *f, char *err, size_t errlen);

/* Atomic checkpoint (temp file, fsync, rename) of the whole learned state;
 * save refuses a state vlff_field_check refuses (a diverged field never
 * replaces a good checkpoint). Load refuses truncated, corrupt or
 * mismatched (config hash) files, and files whose values or step are
 * outside the bounds above (the checksum detects corruption, not forgery),
 * naming the file and the tensor and index; it then leaves f untouched. */
int vlff_field_save(const struct vlff_field *f, const char *path, char *err, size_t errlen);
int vlff_field_load(struct vlff_field *f, const char *path, char *err, size_t errlen);

/* Back to a field that learns, for one whose state went non-finite
 * (vlff_field_check): loads the newest (by modification time) of the npaths
 * checkpoints that loads (at most 64; missing ones are skipped), else
 * re-initialises f in place. Returns the index of the file loaded, or -1
 * when re-initialised, with err listing the files refused ("" when none
 * was). The prompt set, rays and levels are kept either way. */
int vlff_field_rollback(struct vlff_field *f, const char *const *paths, int npaths, char *err, size_t errlen);
/* The state vlff_field_create gives (from its fixed seed: step 0, no
 * moments, every cell occupied, nothing fitted), in place. */
void vlff_field_reinit(struct vlff_field *f);

/* float16 helpers shared by every module that handles features. */
uint16_t vlff_f32_to_f16(float x);
float vlff_f16_to_f32(uint16_t h);
/* The same conversions over n values (hardware-assisted where available,
 * bit-identical to the scalar pair). */
void vlff_f32_to_f16_n(const float *src, uint16_t *dst, size_t n);
void vlff_f16_to_f32_n(const uint16_t *src, float *dst, size_t n);

#endif
