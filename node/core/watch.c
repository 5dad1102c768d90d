/* The node's watch over its inputs (see watch.h). */
#include "watch.h"

#include <math.h>
#include <stdio.h>

#include "log.h"

#define TAG "node"

void vlff_frame_watch_init(struct vlff_frame_watch *w, double now) {
  *w = (struct vlff_frame_watch){.t_start = now};
}

void vlff_frame_watch_frame(struct vlff_frame_watch *w, double now) {
  if (w->last_s > 0) {
    /* A mean over the latest dozen or so intervals: a camera's rate may
     * change (reconfigured, throttled), a single late frame should not. */
    double gap = now - w->last_s;
    w->gap_s = w->gap_s > 0 ? 0.9 * w->gap_s + 0.1 * gap : gap;
  }
  if (w->lost && w->last_s > 0)
    VLFF_INFO(TAG, "frames again after %.1f s without", now - w->last_s);
  w->lost = false;
  w->last_s = now;
}

double vlff_frame_watch_limit(const struct vlff_frame_watch *w) {
  if (w->last_s <= 0) return 5.0;
  return fmax(1.0, 3 * w->gap_s);
}

bool vlff_frame_watch_lost(struct vlff_frame_watch *w, double now, const char *ring) {
  double since = now - (w->last_s > 0 ? w->last_s : w->t_start);
  bool lost = since > vlff_frame_watch_limit(w);
  if (lost && !w->lost && w->last_s > 0)
    VLFF_WARN(TAG, "no frame from ring %s for %.1f s (frames came every %.2f s): the camera stopped or is lost; "
              "the driver's log (vlff-camd) says which", ring, since, w->gap_s);
  else if (lost && !w->lost)
    VLFF_WARN(TAG, "no frame from ring %s yet, %.1f s after the start: is the camera driver (vlff-camd) running?",
              ring, since);
  w->lost = lost;
  return lost;
}

void vlff_pose_miss_hint(struct vlff_ring *ring, const char *ring_name, uint64_t t_ns, double tol_s, char *why,
                         size_t len) {
  struct vlff_pose_rec pr, last;
  const uint64_t tol_ns = (uint64_t)(tol_s * 1e9);
  if (vlff_pose_lookup(ring, t_ns, 4 * tol_ns, &pr) == 0) {
    snprintf(why, len,
             "poses in %s lie on both sides of the frame's stamp %.6f s, but not both within "
             "source.pose_tolerance_s %g s: the tolerance is below the pose period (set it to at least the "
             "tracker's pose period, about 1.2 periods: 0.04 s for 30 Hz; docs/pose.md)",
             ring_name, (double)t_ns * 1e-9, tol_s);
    return;
  }
  double dt = 0;
  if (vlff_ring_read_latest(ring, &last, sizeof last, NULL) == (ssize_t)sizeof last)
    dt = ((double)last.t_ns - (double)t_ns) * 1e-9;
  snprintf(why, len,
           "no two poses in %s bracket the frame's stamp %.6f s within source.pose_tolerance_s %g s, nor within "
           "four times it (newest pose %+.3f s from it): a gap in the poses, or the clocks apart (pose stamps "
           "on another clock than the frames': docs/pose.md)",
           ring_name, (double)t_ns * 1e-9, tol_s, dt);
}
