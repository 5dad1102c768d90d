/*
 * vlff-eval --online: the running node scored as a robot gets it.
 *
 * A recorded scene is played by vlff-replay through the real rings into a
 * real vlff-node (a fresh state directory, segments of names of its own),
 * at the recording's rate; the published map is copied with
 * vlff_map_snapshot_take every interval_s from the replay's start and
 * scored at the scene's labelled points (metrics.h, standard protocol): a
 * point takes the class of the prompt its voxel holds, free and unknown
 * voxels are "no prediction". The run ends after_s seconds after the replay
 * ended, with a last sample there.
 *
 * The node's config is the evaluation's (the scene's box, feature dimension
 * and every other key as vlff-eval loaded them) with the source, shm names,
 * state directory and prompts made for the run: the prompts are the scene's
 * embeddings file in its order (no prompts.sets), the classes vlff-eval
 * scores. Files go to <out>/online/: node.yaml, node.log, replay.log,
 * curve.tsv.
 *
 * Contract: 0 with res filled, or -1 with err naming the step that failed;
 * every child is stopped and reaped and every segment of the run removed
 * before return, whatever happened. Bounded: the node must publish its map
 * segment within 60 s of start, and a replay still running after
 * replay_limit_s fails the run.
 */
#ifndef VLFF_EVAL_ONLINE_H
#define VLFF_EVAL_ONLINE_H

#include <stddef.h>
#include <stdint.h>

#include "config.h"
#include "dataset.h"

struct vlff_online_opts {
  const char *scene;       /* the scene directory (or .sens) vlff-replay plays */
  const char *embeddings;  /* the prompts' file, in the order of the classes */
  const char *out;         /* report directory */
  const char *node_bin, *replay_bin; /* NULL: found beside this program */
  double interval_s, after_s;
  double replay_limit_s;   /* the replay may take this long at most */
  int width, height;       /* the scene's frame size (the rings' bounds) */
  int quiet;
};

struct vlff_online_result {
  double miou3d, macc3d;   /* at after_s past the replay's end, 0..1; -1 before any map */
  double coverage;         /* of the labelled points seen by a training frame: labelled by the map */
  double publish_interval_s; /* mean over the run; -1 with fewer than two versions */
  uint64_t version;
  int samples;
};

/* pts: the labelled points; seen[i] != 0 when a training frame saw point i
 * (NULL: every point); names: the K classes, the map's prompts matched to
 * them by text. */
int vlff_eval_online(const struct vlff_online_opts *o, const struct vlff_config *cfg, const struct vlff_points *pts,
                     const uint8_t *seen, int k, const char (*names)[VLFF_PROMPT_LEN], struct vlff_online_result *res,
                     char *err, size_t errlen);

#endif
