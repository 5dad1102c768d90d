/*
 * The node's watch over its inputs, for what a user sees in --status and
 * the log: whether frames still come, and why a frame found no pose.
 *
 * Frames: the camera counts as lost when no frame came for three of the
 * frames' own mean intervals and at least a second (5 s before the first
 * frame), so a 30 Hz camera that stops shows within a second and a 0.5 Hz
 * one is not lost between its frames. The change either way is logged once,
 * naming the ring.
 *
 * Contract: a vlff_frame_watch is used under the caller's lock (the
 * ingest marks frames, the trainer asks); times are vlff_seconds().
 * vlff_pose_miss_hint() only reads the pose ring.
 */
#ifndef VLFF_WATCH_H
#define VLFF_WATCH_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "vlff/shm.h"

struct vlff_frame_watch {
  double t_start, last_s, gap_s; /* gap_s: the mean interval between frames, 0 before two */
  bool lost;
};

void vlff_frame_watch_init(struct vlff_frame_watch *w, double now);
void vlff_frame_watch_frame(struct vlff_frame_watch *w, double now);
/* Whether the camera counts as lost now; logs the change (ring names the
 * frame ring in the message). */
bool vlff_frame_watch_lost(struct vlff_frame_watch *w, double now, const char *ring);
/* The seconds without a frame after which the camera counts as lost. */
double vlff_frame_watch_limit(const struct vlff_frame_watch *w);

/* Why no two poses of ring (named ring_name) bracket t_ns within tol_s
 * (vlff_pose_lookup's ERANGE): poses on both sides within four tolerances
 * mean the tolerance is below the pose period; poses much further, or
 * only on one side, a gap in the poses or clocks apart. Into why. */
void vlff_pose_miss_hint(struct vlff_ring *ring, const char *ring_name, uint64_t t_ns, double tol_s, char *why,
                         size_t len);

#endif
