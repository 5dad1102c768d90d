/*
 * What a scene source gives the node besides the frames in the ring.
 *
 * The node's core reads frames, poses and features from shared memory and
 * knows nothing of where they come from. A source that knows more about its
 * scene than a camera does (the simulator: the features of each frame, the
 * text encoder its features were made with, the ground truth) offers it
 * through these hooks; node/sim/sim_source.h fills them for vlff-sim. A camera
 * rig gives none: every member NULL.
 *
 * Frame ids are the ring's (vlff_frame_hdr.frame_id); a source that loops
 * its scene maps them onto its own frames.
 *
 * Contract: features() is called from the ingest thread, the others from the
 * trainer thread, never two at once from one thread; ctx belongs to the
 * source's creator and outlives the node. Functions returning int give 0, or
 * -1 with err filled.
 */
#ifndef VLFF_SOURCE_H
#define VLFF_SOURCE_H

#include <stddef.h>
#include <stdint.h>

#include "vlff/shm.h"

/* A published map as an observer sees it. */
struct vlff_map_seen {
  const struct vlff_map_grid *grid;
  const int *image_labels;       /* [height][width] prompt index, -1 = none; NULL when no label image */
  int width, height;
  long long frame_id;            /* the label image's camera frame */
  const char *const *prompts;
  int prompt_count;
};

struct vlff_source_hooks {
  void *ctx;
  /* Feature map of a frame, float16 [feat_height][feat_width][D] with D the
   * field's feature dimension. NULL: the source gives no features. */
  int (*features)(void *ctx, long long frame_id, uint16_t *out, char *err, size_t errlen);
  int feat_width, feat_height;
  /* The embedding (D floats) of a prompt text. NULL: none. */
  int (*embed)(void *ctx, const char *text, float *out, char *err, size_t errlen);
  /* Scores a published map against the source's ground truth: mIoU in
   * percent, -1 where unknown. NULL: no ground truth. */
  void (*observe)(void *ctx, const struct vlff_map_seen *m, double *miou2d, double *miou3d);
  /* Snapshot panels of a frame at width x height: the scene's camera image
   * and its ground truth in label colours, RGB8 each. NULL: none. */
  int (*panels)(void *ctx, long long frame_id, int width, int height, uint8_t *image, uint8_t *truth);
  /* The colour of a prompt in the source's ground-truth palette, NULL when
   * the prompt names none of its classes. NULL: no palette. */
  const uint8_t *(*color)(void *ctx, const char *prompt);
};

#endif
