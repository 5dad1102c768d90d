/*
 * vlff_feature_join: pairs keyframes with the features an external
 * extractor publishes for them (feature ring, libvlff-shm), by frame id.
 *
 * The node registers each keyframe it wants features for; records read from
 * the feature ring are validated (vlff_feature_validate, float16, D = the
 * configured dimension, size limits) and converted from the ring's [D][h][w]
 * to the field's [h][w][D]. A keyframe whose features have not arrived
 * vlm.feature_timeout_s after it was registered expires: it is reported
 * once and counted, so the node drops it instead of waiting forever.
 * Features for frames nobody registered are kept for a while (they may
 * arrive before the keyframe decision) and evicted oldest first.
 *
 * Contract
 *  - int functions return >= 0 on success, -1 on error with one line in
 *    err. A bad feature record is refused and counted; the join's state is
 *    unchanged by it. Values must be finite and within +-VLFF_FEATURE_MAX_ABS
 *    (no vision-language model's features come near it). The latest bad
 *    record's reason is kept for the caller's log
 *    (vlff_feature_join_last_bad).
 *  - The caller owns the join (vlff_feature_join_destroy). One thread at a
 *    time.
 */
#ifndef VLFF_FEATURE_JOIN_H
#define VLFF_FEATURE_JOIN_H

#include <stddef.h>
#include <stdint.h>

#include "bounds.h" /* VLFF_FEATURE_MAX_ABS */

struct vlff_ring;
struct vlff_feature_join;

struct vlff_feature_join_stats {
  uint64_t joined, expired, bad_records, orphans_evicted, frames_refused;
  uint64_t stale; /* records of frames stamped before vlff_feature_join_not_before's time */
};

/* capacity: keyframes waiting and feature maps held, each; dim: D;
 * max_h/max_w: the largest feature map accepted. */
struct vlff_feature_join *vlff_feature_join_create(int capacity, double timeout_s, int dim, int max_h, int max_w,
                                                   char *err, size_t errlen);
void vlff_feature_join_destroy(struct vlff_feature_join *j);

/* A keyframe now waiting for its features (now_ns: CLOCK_MONOTONIC). A full
 * join refuses it (-1, counted). */
int vlff_feature_join_add_frame(struct vlff_feature_join *j, uint64_t frame_id, uint64_t now_ns, char *err,
                                size_t errlen);

/* One feature record (as read from the ring): 0 taken, 1 passed over as
 * stale (its frame stamped before vlff_feature_join_not_before's time). */
int vlff_feature_join_add_record(struct vlff_feature_join *j, const void *record, size_t len, char *err,
                                 size_t errlen);

/* Read every record waiting in the feature ring (never blocks). Returns the
 * number accepted; bad records are counted and skipped. -1 with EPIPE when
 * the ring was replaced or truncated under the handle (what it held before is
 * taken): close it and attach again. */
int vlff_feature_join_pump(struct vlff_feature_join *j, struct vlff_ring *ring);

/* Why the latest bad record was refused ("" before any). */
const char *vlff_feature_join_last_bad(const struct vlff_feature_join *j);

/* Records of frames stamped (t_host_ns, CLOCK_MONOTONIC) before t_ns are
 * passed over and counted (stats.stale): a reader that starts at the
 * oldest record a ring holds takes the maps of frames it may still read,
 * not those of an earlier session whose frame ids may come again. */
void vlff_feature_join_not_before(struct vlff_feature_join *j, uint64_t t_ns);

enum vlff_join_result { VLFF_JOIN_NONE = 0, VLFF_JOIN_READY = 1, VLFF_JOIN_EXPIRED = 2 };

/* Next event: READY fills *frame_id, *h, *w and out (h * w * D float16,
 * capacity max_h * max_w * D); EXPIRED fills *frame_id only. */
int vlff_feature_join_poll(struct vlff_feature_join *j, uint64_t now_ns, uint64_t *frame_id, uint16_t *out,
                           int *h, int *w);

void vlff_feature_join_stats(const struct vlff_feature_join *j, struct vlff_feature_join_stats *st);

#endif
