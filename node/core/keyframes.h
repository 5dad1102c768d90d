/*
 * Keyframe store: the training set of the online learner.
 *
 * Contract
 *  - Holds posed RGB-D keyframes with features at feature resolution in
 *    float16, within a byte budget and a count limit fixed at create.
 *  - Eviction keeps spatial coverage: when an insert would exceed a limit,
 *    the keyframe whose pose is closest to another keyframe's (the most
 *    redundant view) is dropped; the newest `protect` keyframes are never
 *    dropped, so fresh views always get trained on.
 *  - A keyframe that newer depth contradicts is retired on request
 *    (vlff_kfstore_retire), whatever its age, but never the newest.
 *  - vlff_kfstore_views() hands out views pointing into the store; they stay
 *    valid until the next add. Weights favour recent keyframes (half of the
 *    rays go to the newest `recent`) while every keyframe keeps a share.
 *  - Not thread-safe: one owner (the trainer thread).
 */
#ifndef VLFF_KEYFRAMES_H
#define VLFF_KEYFRAMES_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "field.h"

struct vlff_kfstore;

struct vlff_keyframe_in {
  long long id;
  long long t_ns;
  struct vlff_view view; /* its pointers are copied from, not kept */
  int feature_dim;
};

struct vlff_kfstore *vlff_kfstore_create(size_t budget_bytes, int max_count, int protect);
void vlff_kfstore_destroy(struct vlff_kfstore *s);

/* Bytes a keyframe of this shape occupies in the store. */
size_t vlff_kfstore_cost(int w, int h, int fw, int fh, int d, int has_depth);

/* Copy a keyframe in, evicting as needed. Returns 0, or -1 (errno EINVAL when
 * a single keyframe is larger than the whole budget, ENOMEM). */
int vlff_kfstore_add(struct vlff_kfstore *s, const struct vlff_keyframe_in *kf);

int vlff_kfstore_count(const struct vlff_kfstore *s);
size_t vlff_kfstore_bytes(const struct vlff_kfstore *s);
long long vlff_kfstore_evicted(const struct vlff_kfstore *s);

/* Drops every keyframe but the newest for which contradicted(ctx, its
 * view) is true (newer depth shows that what it saw is gone: training on
 * it would keep a moved object at its old place); returns how many,
 * counted in vlff_kfstore_retired. */
int vlff_kfstore_retire(struct vlff_kfstore *s, bool (*contradicted)(void *ctx, const struct vlff_view *v), void *ctx);
long long vlff_kfstore_retired(const struct vlff_kfstore *s);

/* Views and per-view sampling weights for vlff_field_step; returns count. */
int vlff_kfstore_views(struct vlff_kfstore *s, int recent, const struct vlff_view **views, const float **weights);

/* The id of keyframe i in the order views() returns them. */
long long vlff_kfstore_id(const struct vlff_kfstore *s, int i);

/* Pose distance used for redundancy: metres + 0.5 m per radian of rotation. */
double vlff_pose_distance(const double a[16], const double b[16]);

#endif
