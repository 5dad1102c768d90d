/*
 * Keyframe store: the training set of the online learner.
 *
 * Contract
 *  - Holds posed RGB-D keyframes with features at feature resolution in
 *    float16, within a byte budget and a count limit fixed at create.
 *  - Eviction keeps spatial coverage: when an insert would exceed a limit,
 *    the keyframe whose pose is closest to another keyframe's (the most
 *    redundant view) is evicted (paged out, see "Paging"); the newest
 *    `protect` keyframes are never evicted, so fresh views always get
 *    trained on.
 *  - A keyframe that newer depth contradicts is retired on request
 *    (vlff_kfstore_retire), whatever its age, but never the newest.
 *  - vlff_kfstore_views() hands out views pointing into the store; they stay
 *    valid until the next add, retire or page-in. Weights favour recent
 *    keyframes (half of the rays go to the newest `recent`) while every
 *    keyframe keeps a share.
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

/* Paging. Without a page file an evicted keyframe is dropped. With one
 * (vlff_kfstore_page_to: a path in the node's state directory, made anew,
 * and a byte budget), an evicted keyframe is written there instead, whole
 * (pixels, depth, features, pose, intrinsics), and its pose kept in
 * memory; it is dropped only when the file is full or a write fails. Views
 * of one place (vlff_pose_distance under 0.05: 5 cm, or 0.1 rad) count
 * once: an evicted view of the place of a view kept (or of the one coming
 * in) is not paged, and one of the place of a paged view overwrites it.
 * vlff_kfstore_page_in(c2w, radius) brings back the paged keyframe nearest
 * to the camera pose c2w within radius when, the eviction victim gone for
 * it, it would not be the next to go (its nearest view farther than every
 * other candidate's), so that one page-in does not undo itself at the
 * next add. It joins as the oldest view (not protected, not recent),
 * evicting (paging out) as an add does. Returns 1 when one came back, 0
 * when none qualified (or no memory for it), -1 when its read failed (it
 * is then dropped, counted). The file holds one store's life: page_to
 * replaces any file of that name, and the store's destroy removes its own
 * (not a newer store's of the same name). Why: a building's keyframes do
 * not fit a robot's memory; without paging, a robot that returns to a flat
 * trains on none of its earlier views of it (docs/node.md, "Memory"). */
int vlff_kfstore_page_to(struct vlff_kfstore *s, const char *path, size_t max_bytes, char *err, size_t errlen);
int vlff_kfstore_page_in(struct vlff_kfstore *s, const double c2w[16], double radius);
/* Keyframes in the page file now; written there and brought back since
 * create; evicted with nowhere to go (no page file, it full, an I/O
 * error); the file's bytes in use and its byte budget (0 without a page
 * file); its last error ("" when none). */
long long vlff_kfstore_paged(const struct vlff_kfstore *s);
long long vlff_kfstore_paged_out(const struct vlff_kfstore *s);
long long vlff_kfstore_paged_in(const struct vlff_kfstore *s);
long long vlff_kfstore_dropped(const struct vlff_kfstore *s);
size_t vlff_kfstore_page_bytes(const struct vlff_kfstore *s);
size_t vlff_kfstore_page_limit(const struct vlff_kfstore *s);
const char *vlff_kfstore_page_error(const struct vlff_kfstore *s);

/* Pose distance used for redundancy: metres + 0.5 m per radian of rotation. */
double vlff_pose_distance(const double a[16], const double b[16]);

#endif
