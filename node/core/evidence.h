/*
 * Per-voxel evidence: the raw vision-language features of admitted
 * keyframes, each scaled to unit length and averaged in the voxels where
 * their measured depth ends (OpenScene-style multi-view fusion, kept online
 * beside the field). Unit length because the map reads cosines, which
 * ignore a feature's length: in a plain mean a long feature outweighed a
 * short one (docs/field.md, "Evidence").
 *
 * Why: the field is a smooth, shared decoder. Over a large scene it can
 * give a small or rare object's feature away to a larger look-alike, and a
 * constant learning rate lets an object near a decision boundary flip
 * between classes from one minute to the next. Features averaged where
 * they were measured keep every object that the raw features find, but
 * carry the raw features' noise. The published map labels a point by both:
 * the prompt maximising E_k . (f/|f| + w e/|e|), f the field's feature at the
 * point, E_k . e/|e| the evidence's cosines read trilinearly between the
 * voxel centres around the point (over those with evidence), w
 * publish.evidence_weight (docs/field.md, "Evidence", "Evidence read between
 * voxel centres").
 *
 * Storage: a dense voxel -> slot index over the grid, and slots of D
 * float16 values (the running mean) allocated on first use, up to a budget
 * (publish.evidence_max_mb). A full budget gives up an eighth of its slots,
 * those with the fewest samples among the voxels that none of the last 8
 * views touched (counted: vlff_evidence_evicted), and goes on; only when
 * none can be given up does a new voxel go without evidence (field only;
 * counted: vlff_evidence_overflow). Why: a walk through a flat fills any
 * budget long before it ends, and many slots then hold a single sample
 * (noisy depth scatters samples in front of and behind a surface; a
 * surface seen once from afar gets few); without giving those up, every
 * room entered later would read the field alone, not fitted there yet
 * (docs/field.md, "A full evidence budget"; docs/benchmarks.md). The mean gives each sample
 * (a feature pixel of a view whose footprint reaches the voxel) equal
 * weight up to 64 samples per voxel, then new ones weigh 1/64: a recency
 * mean over the last few views, so a re-observation replaces old features
 * (a moved object's) instead of joining a lifetime average. The count
 * itself goes on to 255 (which voxels a full budget gives up).
 *
 * Paging (vlff_evidence_page_to): what a full budget gives up is written to
 * a page file (the node's state directory) instead of dropped, up to the
 * file's own budget: per voxel its count and mean, and in memory its
 * cosines with the current prompts at 8 bits (max_k + 8 bytes a voxel
 * instead of D x 2 + max_k x 4 + 10), which the map reads as it reads the
 * voxels in memory. A view that sees a paged voxel again brings its
 * evidence back into a slot, and its samples join that mean. New prompts
 * read every paged voxel back once for its cosines. Why: on a building
 * the budget holds a flat or two; without paging the rooms left behind
 * read the field alone, which training on the next rooms moves
 * (docs/field.md, "Evidence paging"). Saved with the rest (a checkpoint
 * holds every voxel's evidence, paged or not); a load pages out what is
 * beyond the budget. Only a full page file (or its write failing, counted)
 * drops evidence, as before (vlff_evidence_evicted).
 *
 * Contract: one owner thread. Functions returning int give 0, or -1 with
 * err filled; a refused view leaves the evidence untouched.
 */
#ifndef VLFF_EVIDENCE_H
#define VLFF_EVIDENCE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "config.h"
#include "field.h"

struct vlff_evidence;

/* The published map's grid over the box lo..hi: voxels of edge voxel,
 * coarsened in 10 % steps until there are at most max_voxels; returns the
 * edge used and sets dims. The publisher's grid and the evaluation's
 * evidence use it alike. */
double vlff_map_grid_plan(const double lo[3], const double hi[3], double voxel, size_t max_voxels, uint32_t dims[3]);
/* The index (x fastest) of the voxel holding world point x in such a grid
 * from origin, -1 outside it or for a non-finite x. */
long vlff_grid_voxel(const double origin[3], double voxel, const uint32_t dims[3], const double x[3]);

/* A grid of dims voxels of edge voxel from origin; D feature channels;
 * labelled with at most max_k prompts (1..VLFF_FIELD_MAX_PROMPTS: each slot
 * caches that many cosines); at most max_bytes of slots (at least one). */
struct vlff_evidence *vlff_evidence_create(const double origin[3], const uint32_t dims[3], double voxel, int D,
                                           int max_k, size_t max_bytes, char *err, size_t errlen);
/* The node's evidence for a field's box: voxels of publish.evidence_voxel_m
 * (coarsened so that the voxel index takes at most a quarter of
 * publish.evidence_max_mb), slots in the rest of that budget. */
struct vlff_evidence *vlff_evidence_for(const struct vlff_cfg_publish *pub, const struct vlff_cfg_field *field,
                                        int max_k, char *err, size_t errlen);
/* Growth (field.grow): the grid grows on its lattice, in whole voxels, to
 * hold [want_lo, want_hi] (taken together with [lo, hi]) clipped to
 * +-limit, or, when the budget or memory refuses that, [lo, hi] (what must
 * be held); past the budget it
 * is refitted to the voxels that hold evidence and the box (the voxels
 * scanned once for both). Every voxel's evidence (in a slot or
 * paged) stays where it is in the world, and more slots are allocated up
 * to the budget when the grid held fewer voxels than it. 1 grown, 0 when
 * the grid already held it; -1 with err for a box that is empty or not
 * finite, a fixed grid (vlff_evidence_for with field.grow off, or
 * vlff_evidence_create), an index past a quarter of publish.evidence_max_mb,
 * or no memory: the evidence unchanged. Where even a refit passes the index
 * budget, the grid slides with the box instead (vlff_lattice_window; 1): the
 * voxels it leaves page their evidence out, kept by their place in the
 * world, and come back to their voxels when a later grid covers them (a
 * slide back, a growth or a refit); without a page file, or with a full
 * one, it is given up (vlff_evidence_evicted). Such far records are not in
 * a save (vlff_evidence_save_size counts the grid's voxels). A load of
 * saved evidence whose grid holds this one on its lattice grows to it
 * first. */
int vlff_evidence_grow(struct vlff_evidence *e, const double want_lo[3], const double want_hi[3], const double lo[3],
                       const double hi[3], double limit, char *err, size_t errlen);
void vlff_evidence_destroy(struct vlff_evidence *e);
void vlff_evidence_reset(struct vlff_evidence *e);

/* Adds a view's features: each feature pixel's footprint is looked up in
 * the depth image (v->depth, metres along the camera axis, width x height;
 * a view without depth or features adds nothing) at its four quarter
 * points, unprojected with the view's intrinsics and pose, and its feature
 * averaged once into every voxel those points reach. Non-finite depths are
 * skipped. The caller has checked the view's intrinsics and
 * pose (vlff_publisher_check_view); D must match. Each feature joins the
 * means at unit length; one that is zero or not finite is skipped. A mean
 * longer than 1 (saved by a node that averaged features at their own
 * length) is brought to unit length when a sample joins it. */
int vlff_evidence_add(struct vlff_evidence *e, const struct vlff_view *v, char *err, size_t errlen);

/* The voxel index of world point x (-1 outside the grid). */
long vlff_evidence_voxel(const struct vlff_evidence *e, const double x[3]);
/* Copies voxel vi's mean feature into out[D] and returns the samples averaged
 * (0, out untouched, when the voxel has none). */
int vlff_evidence_get(const struct vlff_evidence *e, long vi, float *out);

/* Labels n points (xyz interleaved) from the field's per-prompt cosines
 * fcos[n][K] (vlff_field_query_cosines) and, where evidence reaches a point,
 * w times the evidence's cosines with the unit prompt embeddings E[K][D]
 * there: those of the voxels whose centres surround the point (up to
 * eight), blended with trilinear weights over the voxels that have
 * evidence (a point whose own voxel has evidence always reads some; one in
 * an empty voxel may read a neighbour's). The label is the argmax of
 * a cos_field + w cos_evidence, which is the argmax of E_k . (a f/|f| +
 * w e/|e|) for a single voxel. a is the field's trust at the point:
 * min(1, rays[i] / trust_rays), rays being its exposure there
 * (vlff_field_exposure); 1 where rays is NULL or trust_rays <= 0, and
 * where no evidence reaches (the field alone decides there). Where
 * the camera has only just looked, the field has not been fitted yet and
 * its feature is what the shared decoder says of other places, while the
 * evidence already holds what the camera saw. score (the winning sum) and
 * margin (best minus second) are divided by a + w where evidence counted,
 * so both stay cosines. Outputs may be NULL except label. A voxel's
 * evidence cosines are cached until its evidence or the prompts (stamp: a
 * hash of E) change. Points the field scores all 0 (outside the box) get
 * label -1. */
void vlff_evidence_label(struct vlff_evidence *e, const float *xyz, size_t n, const float *fcos,
                         const uint16_t *rays, int trust_rays, const float *E, int K, uint64_t stamp, float w,
                         int *label, float *score, float *margin);
/* As vlff_evidence_label, and each point's K sums into scores[n][K] (as
 * scaled; their best is the label, except where a lost class is read from
 * the evidence: that class then scores the best other plus the margin; all
 * 0 where the label is -1), for a vote over many points (regions.h). */
void vlff_evidence_label_scores(struct vlff_evidence *e, const float *xyz, size_t n, const float *fcos,
                                const uint16_t *rays, int trust_rays, const float *E, int K, uint64_t stamp, float w,
                                int *label, float *score, float *margin, float *scores);

/* Lost classes. The field is a shared decoder: over a large scene it can
 * give a whole object's class away to a look-alike (its every point labelled
 * the look-alike), which no per-point weight w undoes without giving up the
 * field's denoising everywhere else. A census counts, over the points
 * labelled between census_begin and census_end (the publisher's whole 3D
 * map) with the prompts (stamp, K) of the first of those calls, that have
 * evidence and where the field is fully trusted (a = 1; every point when
 * trust_rays <= 0 or rays is NULL), the points whose field cosines and whose
 * evidence cosines each pick prompt k. census_end(ratio) marks lost every
 * prompt the field picks at fewer than ratio times the points the evidence
 * picks it at, if those are at least 10 (ratio 0: none); a prompt the last
 * census found lost stays so until the field picks it at twice the ratio.
 * It returns how many are lost (census_end without census_begin: the count
 * as it stands). Then vlff_evidence_label gives a point with evidence the
 * evidence's own best prompt wherever that prompt is lost, with score that
 * prompt's combined sum and margin w times the evidence's best minus second
 * cosine (both scaled as always), for label calls with the census's
 * prompts, until the next census_end, a reset or a load. lost() tells
 * whether prompt k is lost and the last census's counts (either pointer may
 * be NULL; untouched for k outside 0..max_k-1). */
void vlff_evidence_census_begin(struct vlff_evidence *e);
int vlff_evidence_census_end(struct vlff_evidence *e, double ratio);
bool vlff_evidence_lost(const struct vlff_evidence *e, int k, unsigned long long *n_field, unsigned long long *n_ev);
/* The last census's verdict, saved with the map (publish.h): the prompts'
 * stamp and count, and one byte per prompt, 1 where lost (little-endian
 * u64, i32, u32 lost count, VLFF_FIELD_MAX_PROMPTS bytes). Restored after a
 * load, a restarted node reads its lost classes from the evidence from its
 * first publish, as the node before it did, not from the publish after its
 * first census. lost_check refuses a block no census writes (a count beyond
 * max_k prompts, a byte not 0 or 1, a lost prompt past the count, a wrong
 * lost count); lost_set takes a checked one. */
#define VLFF_EVIDENCE_LOST_BYTES (16 + VLFF_FIELD_MAX_PROMPTS)
void vlff_evidence_lost_save(const struct vlff_evidence *e, uint8_t out[VLFF_EVIDENCE_LOST_BYTES]);
int vlff_evidence_lost_check(const uint8_t in[VLFF_EVIDENCE_LOST_BYTES], int max_k, char *err, size_t errlen);
void vlff_evidence_lost_set(struct vlff_evidence *e, const uint8_t in[VLFF_EVIDENCE_LOST_BYTES]);

/* Learned state, saved beside the field (vlff_publisher_save): the bytes
 * of the grid's geometry and every voxel's mean and count (voxels in index
 * order). load checks the geometry, D, the length and every voxel record
 * (in the grid, in order, counted, a finite mean), and only then replaces
 * the evidence: 0; 1 with err for evidence of another grid or D (a config
 * changed: nothing to load, not a corrupt file); -1 with err for a
 * malformed one; the evidence untouched in both. Saved evidence of more
 * voxels than the budget holds (publish.evidence_max_mb lowered since it
 * was saved) keeps the most-observed, at equal counts the lowest voxel
 * indices; the rest are counted as given up (vlff_evidence_evicted).
 * Loaded voxels count as untouched by the last views, so a budget a load
 * filled makes room for the next view's new voxels. */
size_t vlff_evidence_save_size(const struct vlff_evidence *e);
void vlff_evidence_save(const struct vlff_evidence *e, uint8_t *out);
/* The same bytes a part at a time, so that evidence paged out is not held
 * in memory to be saved: from *cursor (0 at the start; updated) as many
 * whole records as fit in cap bytes (the header first) into out; the bytes
 * written, 0 once all were (cap must hold the header and a record). */
size_t vlff_evidence_save_part(const struct vlff_evidence *e, uint64_t *cursor, uint8_t *out, size_t cap);
int vlff_evidence_load(struct vlff_evidence *e, const uint8_t *in, size_t len, char *err, size_t errlen);
/* The same from a reader of the saved bytes (n bytes at offset off into
 * dst: 0, or -1 with err filled), so that a file of a larger budget's
 * evidence is read a record at a time, not held whole. Records are read
 * twice (checked, then loaded): a record that changed in between leaves
 * the evidence empty (-1). */
typedef int (*vlff_evidence_read_fn)(void *ctx, uint64_t off, void *dst, size_t n, char *err, size_t errlen);
int vlff_evidence_load_from(struct vlff_evidence *e, vlff_evidence_read_fn rd, void *ctx, uint64_t len,
                            char *err, size_t errlen);

/* The far records (evidence of voxels a slide left beyond the grid, kept in
 * the page file: vlff_evidence_grow), which a save of the grid does not
 * hold, saved beside it: read back from the page file and written to path
 * atomically (none: path removed). load_far takes such a file after a load
 * (0; 1 when there is none; -1 with err for one of another grid or feature
 * size, truncated, corrupt, a checksum that fails, a record of no samples
 * or a mean that is not finite: nothing taken): its records go to the page
 * file as far records again, those the grid covers back to their voxels;
 * without a page file, or with a full one, each is given up, counted in
 * *dropped and vlff_evidence_evicted. far_records: how many there are. */
int vlff_evidence_save_far(const struct vlff_evidence *e, const char *path, char *err, size_t errlen);
int vlff_evidence_load_far(struct vlff_evidence *e, const char *path, long long *dropped, char *err, size_t errlen);
size_t vlff_evidence_far_records(const struct vlff_evidence *e);
/* Changes whenever the far records may have changed (a slide, a record
 * back in the grid, a reset, a load): a checkpoint rewrites save_far's file
 * only then. */
uint64_t vlff_evidence_far_generation(const struct vlff_evidence *e);

/* Pages what the budget gives up to the file at path, holding at most
 * max_bytes of it (0: no paging; the default until called). The file is
 * made (0600, truncated) at the first page-out and removed at destroy; one
 * that cannot be made or written is counted in page_errors, said by
 * page_error ("PATH: why", "" before any) and what it would have held is
 * dropped as without paging (one that cannot be made ends paging). 0, or -1
 * with err (out of memory: no paging). */
int vlff_evidence_page_to(struct vlff_evidence *e, const char *path, size_t max_bytes, char *err, size_t errlen);
const char *vlff_evidence_page_error(const struct vlff_evidence *e);
size_t vlff_evidence_paged(const struct vlff_evidence *e);        /* voxels whose evidence is in the page file */
long long vlff_evidence_paged_out(const struct vlff_evidence *e); /* voxels written to it since the reset */
long long vlff_evidence_paged_in(const struct vlff_evidence *e);  /* ... and brought back by a view */
long long vlff_evidence_page_errors(const struct vlff_evidence *e); /* writes and reads that failed */
size_t vlff_evidence_page_memory(const struct vlff_evidence *e);  /* bytes the paged voxels take in memory */

size_t vlff_evidence_voxels(const struct vlff_evidence *e);   /* voxels with evidence */
size_t vlff_evidence_capacity(const struct vlff_evidence *e); /* voxels the budget holds */
long long vlff_evidence_overflow(const struct vlff_evidence *e); /* additions lost to a full budget */
long long vlff_evidence_evicted(const struct vlff_evidence *e);  /* voxels whose evidence was given up (dropped) for room */

#endif
