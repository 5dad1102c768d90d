/*
 * The map publisher: turns the field into the segmented voxel map and 2D
 * label image that controllers read from the map segment.
 *
 * Voxel states: a voxel where measured depth ended ("hit") or where the
 * field's density is at least publish.free_density gets the label of the
 * field's feature there, combined with the evidence of observe()d
 * keyframes (evidence.h) when publish.evidence_weight > 0; a voxel only
 * passed through by measured rays is FREE; a voxel no ray reached is
 * UNKNOWN. The voxels between neighbouring pixels' measured points that lie
 * on one surface (up to 4 voxels apart) are hits too: a surface seen at a
 * grazing angle keeps no holes between its sampled points. Hit voxels are
 * queried at the mean of the measured points inside
 * them, so the feature is read on the surface rather than in the air at the
 * voxel centre.
 *
 * A voxel's published label changes only when a keyframe observed it since
 * it was last labelled, or when its new label wins by more than
 * publish.label_hysteresis (hold.h); the result counts the flips.
 *
 * The 2D label image is made at the latest keyframe's pose. With
 * publish.label_image: surface, a pixel with measured depth gets the label
 * of the field's feature (and evidence) at that measured surface point,
 * for the same reason; the rest are volume-rendered (label -1, UNKNOWN,
 * where the rendered opacity stays under one half). With evidence and
 * publish.region_weight > 0, those surface pixels are grouped into regions
 * of the keyframe's image (colour and measured points, regions.h) and each
 * reads its own sums plus the weight times its region's mean; its
 * confidence stays its own score at the label it gets.
 *
 * Contract: one owner thread (the trainer). Functions returning int give 0,
 * or -1 with err filled.
 */
#ifndef VLFF_PUBLISH_H
#define VLFF_PUBLISH_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "config.h"
#include "field.h"
#include "source.h"
#include "vlff/shm.h"

struct vlff_publisher;

struct vlff_publish_result {
  uint64_t version; /* the map's version after the call (unchanged when nothing was published) */
  double miou2d, miou3d; /* the source's observer's scores (source.h), -1 when not available */
  long long miou2d_frame; /* the frame id of the label image miou2d scored, -1 when none */
  size_t labelled, free_voxels, unknown; /* the whole map's voxels by state */
  size_t changed;   /* voxels the publish logged as changed (0: nothing published) */
  bool whole;       /* the whole grid was relabelled and published */
  bool cycle_done;  /* the map was wholly refreshed: a whole publish, or the last slice */
  bool scored;      /* miou2d/miou3d are this call's: a whole publish, or publish_image */
  /* Voxels whose label differs from what it was before this publish
   * relabelled it (a voxel labelled for the first time is new, not
   * counted); of those, the ones no keyframe observed since
   * (flips_elsewhere), among the mapped_elsewhere voxels labelled before and
   * not observed since (hold.h: labels held within publish.label_hysteresis). */
  size_t flips, flips_elsewhere, mapped_elsewhere;
};

/* From the publish section, the map segment's shm keys and the field's
 * scene box (field.scene_min/max). hooks (source.h) may be NULL or have no
 * observer: no ground truth; kept, not copied. Creates the map segment. */
struct vlff_publisher *vlff_publisher_create(const struct vlff_cfg_publish *pub, const struct vlff_cfg_shm *shm,
                                             const struct vlff_cfg_field *field, const struct vlff_source_hooks *hooks,
                                             char *err, size_t errlen);
void vlff_publisher_destroy(struct vlff_publisher *p);

/* A view's intrinsics and pose within physical bounds (bounds.h; the pose
 * against field.scene_min / max)? 0, or -1 with err saying which value
 * broke which bound; each refusal is counted. */
int vlff_publisher_check_view(struct vlff_publisher *p, const struct vlff_view *v, char *err, size_t errlen);
/* Account an admitted keyframe's measured depth (observed / hit voxels)
 * and average its features into the evidence.
 * The view is checked first (-1 with err, nothing accounted); every ray's
 * march is bounded by the map's size whatever its depth claims. */
int vlff_publisher_observe(struct vlff_publisher *p, const struct vlff_view *v, char *err, size_t errlen);
/* The view the next 2D label image is made for (the latest keyframe); its
 * depth, if any, is read now, not kept. Checked as observe; a refused view
 * leaves the previous camera in place. */
int vlff_publisher_set_camera(struct vlff_publisher *p, const struct vlff_view *v, uint64_t t_ns, long long frame_id,
                              char *err, size_t errlen);
/* True when measured depth of admitted keyframes already ended in the voxel
 * holding world point x (at least twice): a surface the map has seen. */
bool vlff_publisher_surface_known(const struct vlff_publisher *p, const double x[3]);
/* Depth that passes through: a voxel that the rays of two views in a row
 * passed through (well in front of their measured ends: two voxels or a
 * tenth of the ray, whichever is more; through its measured surface, within
 * 0.3 voxel of its points' mean, where it has one) without any of them
 * ending in it
 * loses its measured surface and is published FREE whatever the field's
 * density there, until a ray ends in it again. cleared(): surfaces of at
 * least 8 measured points (a thing, not the depth's stray points in front
 * of a far surface) lost so since create. contradicted(): a stored view (a
 * keyframe) whose measured points end, at 5 % of them or more (at least 16
 * of every fourth pixel each way), in such lost surfaces: it shows what is
 * no longer there. A surface where only rays had passed before is labelled
 * from the evidence alone until 64 rays ended in it (the field's trust
 * there counts what stood there before). */
long long vlff_publisher_cleared(const struct vlff_publisher *p);
bool vlff_publisher_contradicted(const struct vlff_publisher *p, const struct vlff_view *v);
/* The observation grids (what measured depth has seen) are learned state
 * too: saved beside each field checkpoint so a restarted node publishes the
 * same map at once. Save is atomic; load refuses a file of another grid,
 * a truncated or corrupt one, and then leaves the grids untouched. With a
 * growing box, the far map and the far evidence go beside it (path.far,
 * path.evfar), rewritten only when they changed since that path's last
 * save. */
int vlff_publisher_save(struct vlff_publisher *p, const char *path, char *err, size_t errlen);
/* The files a save at path is: path followed by each of these (the grid's
 * own, the far map, the far evidence), for whoever removes a save whole. */
extern const char *const vlff_publisher_files[3];
int vlff_publisher_load(struct vlff_publisher *p, const char *path, char *err, size_t errlen);
/* The evidence observe() averages into (evidence.h), NULL without it
 * (publish.evidence_weight 0): for tests and tools to read. */
const struct vlff_evidence *vlff_publisher_evidence(const struct vlff_publisher *p);
/* Forget observations and evidence (mapping reset). */
void vlff_publisher_reset(struct vlff_publisher *p);
/* Growth (field.grow): the map's grid (publish.voxel_size_m as planned for
 * the first box) and the evidence's grow on their lattices to hold
 * [want_lo, want_hi] (the view with margins ahead; taken together with
 * [lo, hi]) or, each when its cap or memory refuses that, [lo, hi] (what
 * must be held: so the map may hold the wanted box where the evidence holds
 * only the needed one), clipped to +-field.world_limit_m; every voxel keeps what was observed,
 * published and held there; the next publish is whole (readers see the new
 * geometry with it: docs/shm.md "A map that grows"). A grid that would pass
 * its cap is refitted instead: to the voxels that hold something and the
 * box, the empty ones beyond dropped (docs/field.md "Growth"; the voxels
 * are scanned once for both boxes). Where even that passes the cap, the
 * grid slides with the robot (vlff_lattice_window): the voxels it leaves
 * go to the far map (far.h), published beside the grid, and come back
 * when it covers them again; the evidence slides alike (evidence.h). 1
 * grown, 2 grown with the map refitted, 3 slid, 0 when both already held
 * it, -1 with err
 * for a fixed box, a bad box, a grid past shm.map_max_voxels or evidence
 * past its index budget even refitted, a map segment that could not grow to
 * it (vlff_map_reserve), or no memory; what did not grow is unchanged. */
int vlff_publisher_grow(struct vlff_publisher *p, const double want_lo[3], const double want_hi[3],
                        const double lo[3], const double hi[3], char *err, size_t errlen);
/* The map's box now, and its growths so far (grown may be NULL). */
void vlff_publisher_box(const struct vlff_publisher *p, double lo[3], double hi[3], long long *grown);
/* Beyond the caps: the grid's slides so far, and the far map's blocks,
 * bytes, byte limit and blocks dropped for it (all 0 for a fixed box). */
void vlff_publisher_far(const struct vlff_publisher *p, long long *slides, size_t *blocks, size_t *bytes,
                        size_t *limit, long long *dropped);

/* Publication (docs/node.md, "Publishing"). The grid is relabelled through
 * the field in three ways, each published at once to the map segment, whose
 * change log (vlff/shm.h) tells readers which voxels changed:
 *
 * publish: the whole grid, with the 2D label image and the source's scores;
 * the census of lost classes (evidence.h) spans it.
 *
 * publish_changed: only the voxels observe() touched (hit or passed
 * through) since they were last relabelled, as a partial publish logging
 * all of them, without a label image: what an admitted keyframe changed,
 * soon after it was admitted. Nothing touched: nothing published. A whole
 * publish instead when one is owed (nothing published yet, a reset, a
 * load, a failed publish, other prompts).
 *
 * publish_slice: the next consecutive index range of the grid, from where
 * the last slice ended up to the voxel at fraction `to` of the grid (at
 * least one voxel; to >= 1: the rest of the grid), logging only the voxels
 * whose label or confidence changed; the slice that reaches the grid's end
 * ends a round (cycle_done): it also closes the census, owes the round's
 * label image, and the next slice starts from voxel 0. The caller
 * sizes the slices (the trainer: so that a round ends on time, docs/node.md
 * "Publishing"); a slice stops short of `to` after about 40 ms of field
 * queries by the measured speed (set_slice_piece), so that a keyframe
 * admitted meanwhile waits for that, not for a slice over the dense part of
 * the grid: the caller goes on with more slices to `to`. A whole publish instead when one is owed (it restarts the
 * round). refresh_done: the fraction of the grid the current round has
 * refreshed, in [0, 1).
 *
 * publish_image: the next piece of what a round owes after its last slice:
 * its label image at the latest keyframe's view when the round ended,
 * rendered a piece of about 20 ms per call and published, when done, as a
 * version of its own that changes no voxel; then, in a call of its own, the
 * source's scores (scored). In pieces so that a keyframe admitted
 * meanwhile waits for a piece, not for all of it (the trainer publishes
 * keyframes between calls; image_owed says whether a piece is due). Its
 * camera is the one it began with, whatever keyframes set_camera meanwhile;
 * new prompt embeddings halfway make it begin again, at the latest camera.
 * Nothing owed, or a whole publish owed instead: nothing published, 0. */
int vlff_publisher_publish(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                           struct vlff_publish_result *r, char *err, size_t errlen);
int vlff_publisher_publish_changed(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                                   struct vlff_publish_result *r, char *err, size_t errlen);
int vlff_publisher_publish_slice(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                                 double to, struct vlff_publish_result *r, char *err, size_t errlen);
int vlff_publisher_publish_image(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                                 struct vlff_publish_result *r, char *err, size_t errlen);
bool vlff_publisher_image_owed(const struct vlff_publisher *p);
/* publish_image's pieces of exactly `pixels` pixels (at least 1), or 0 (the
 * default): of about 20 ms each, by the measured speed. A fixed size makes
 * the pieces, and so what a test sees between them, the same on a fast
 * host and under emulation. */
void vlff_publisher_set_image_piece(struct vlff_publisher *p, size_t pixels);
/* publish_slice's pieces: at most `voxels` queried voxels (at least 1;
 * SIZE_MAX: none, each slice reaches its target), or 0 (the default):
 * about 40 ms of queries, by the measured speed. */
void vlff_publisher_set_slice_piece(struct vlff_publisher *p, size_t voxels);
double vlff_publisher_refresh_done(const struct vlff_publisher *p);
/* The evidence's memory: what the voxels holding evidence take of
 * publish.evidence_max_mb, and that budget, in bytes (0 and 0 without
 * evidence). */
void vlff_publisher_evidence_memory(const struct vlff_publisher *p, size_t *used, size_t *limit);
/* Evidence a full publish.evidence_max_mb gives up goes to dir/evidence.pages,
 * up to publish.evidence_page_mb (evidence.h, "Paging"); said in the log.
 * 0, or -1 with err (the node goes on without paging). */
int vlff_publisher_page_evidence(struct vlff_publisher *p, const char *dir, char *err, size_t errlen);
/* The paged voxels, those paged out and back in, and those given up for
 * good since the start or the last reset (0 without evidence). */
void vlff_publisher_evidence_paging(const struct vlff_publisher *p, size_t *paged, long long *out, long long *in,
                                    long long *dropped);
/* Voxels observe() touched that no publish has relabelled yet. */
size_t vlff_publisher_pending(const struct vlff_publisher *p);
/* For people: the strip (camera image | segmentation | the source's ground
 * truth when it has one) at the latest keyframe's view, and the labelled
 * voxels coloured by label. The caller writes them (strip.png, map.ply). */
struct vlff_snapshot {
  uint8_t *strip;      /* RGB8 [height][width] */
  int width, height;
  size_t n;            /* labelled voxels: centres, colours, labels (255 = 255 or more) */
  float *xyz;
  uint8_t *rgb, *label;
};
int vlff_publisher_snapshot(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                            struct vlff_snapshot *out, char *err, size_t errlen);
void vlff_snapshot_free(struct vlff_snapshot *s);
/* Tell readers the writer is alive (rate-limited to 10 Hz). */
void vlff_publisher_heartbeat(struct vlff_publisher *p);
/* Replaces the node's status in the map segment (vlff_map_set_status), for
 * controllers. 0, or -1 with the library's message in err. */
int vlff_publisher_set_status(struct vlff_publisher *p, const struct vlff_map_status *st, char *err, size_t errlen);
/* Seconds since the last publish, -1 before the first. */
double vlff_publisher_age_s(const struct vlff_publisher *p);

#endif
