/*
 * Where camera drivers deliver frames: a sink with the shape of a ring slot.
 *
 * Contract
 *  - reserve -> fill in place -> commit (or abort). reserve() gets the
 *    frame's size and which planes it has and returns writable plane
 *    pointers and strides; the producer converts straight into them, then
 *    fills the metadata and calls commit(). Exactly one of commit()/abort()
 *    follows every successful reserve(); at most one frame is reserved at a
 *    time per sink.
 *  - reserve() returns 0, or -1 with err filled (frame larger than a slot,
 *    sink closed); the producer drops and counts that frame. A sink never
 *    blocks the producer.
 *  - Plane formats: colour is packed RGB8, or absent (VLFF_PIX_NONE: a
 *    range camera's frame, depth only, on its way to be paired with a
 *    colour camera's); depth is uint16 millimetres or float32 metres, 0
 *    meaning "no valid depth" (the validity mask).
 *  - Timestamps are nanoseconds: device_ns on the camera's clock, host_ns on
 *    this host's CLOCK_MONOTONIC.
 *  - A sink is used from one producer thread; vlff_memsink_* readers may run
 *    only after the producer stopped (it is a test and tool aid).
 */
#ifndef VLFF_SINK_H
#define VLFF_SINK_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

enum vlff_depth_fmt { VLFF_DEPTH_FMT_NONE = 0, VLFF_DEPTH_FMT_U16_MM, VLFF_DEPTH_FMT_F32_M };

struct vlff_sink_frame {
  /* In to reserve(): */
  int width, height;
  int color_format;               /* VLFF_PIX_RGB8, or VLFF_PIX_NONE for a range camera's frame */
  int depth_format;               /* enum vlff_depth_fmt */
  /* Out of reserve(): */
  uint8_t *color;
  size_t color_stride;
  void *depth;
  size_t depth_stride;
  void *slot;                     /* sink-private */
  /* In to commit(): */
  uint64_t device_frame_id;
  uint64_t device_ns, host_ns;
  bool trigger_stamped;           /* host_ns is the trigger pulse's or edge's stamp, not the arrival */
  uint32_t sensor_id;
  double intrinsics[4];           /* fx fy cx cy; zeros = unknown */
  bool pose_valid;                /* false: no pose within tolerance, learner skips */
  bool pose_untrusted;            /* the tracker flagged it (lost / low quality) */
  double pose[16];                /* camera-to-world, row-major */
  uint64_t pose_ns;
};

struct vlff_sink {
  int (*reserve)(struct vlff_sink *s, struct vlff_sink_frame *f, char *err, size_t errlen);
  int (*commit)(struct vlff_sink *s, struct vlff_sink_frame *f);
  void (*abort)(struct vlff_sink *s, struct vlff_sink_frame *f);
  void *ctx;
};

/* Pose lookup by host timestamp (external SLAM through the pose ring).
 * Returns 0 with pose, its timestamp and whether the tracker flagged it
 * untrusted when one lies within tol_s, else -1. */
struct vlff_pose_source {
  int (*lookup)(void *ctx, uint64_t t_ns, double tol_s, double pose[16], uint64_t *pose_ns,
                bool *untrusted);
  void *ctx;
};

/* An in-memory sink of `slots` frames of at most max_w x max_h, kept in
 * commit order (oldest overwritten), for tests and tools. */
struct vlff_memsink;
struct vlff_memsink *vlff_memsink_new(int slots, int max_w, int max_h);
void vlff_memsink_free(struct vlff_memsink *m);
struct vlff_sink *vlff_memsink_sink(struct vlff_memsink *m);
/* Frames committed since creation (including overwritten ones). */
uint64_t vlff_memsink_committed(const struct vlff_memsink *m);
/* The i-th most recent frame (0 = newest) or NULL. Plane pointers stay valid
 * until the next reserve. */
const struct vlff_sink_frame *vlff_memsink_get(const struct vlff_memsink *m, int i);

#endif
