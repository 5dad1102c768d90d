/*
 * replay_mcap.h - vlff-replay's player of MCAP recordings of the node's
 * inputs (vlff-record's files; the channels are node/view/inputs.h's).
 *
 * The whole recording is read and every message validated (inputs.h: sizes,
 * intrinsics, finite unit-quaternion poses, feature shapes, monotone stamps)
 * before the rings are created, so a bad file is refused before anything is
 * published, with an error naming the channel and the message's index. It is
 * then played in file order: a pose into the pose ring, a frame (colour, depth,
 * intrinsics) into the frame ring, a feature map into the feature ring with the
 * id and host time the replay gave its frame (found by the frame's recorded
 * stamp). Times: every record at base + (its stamp - the first played
 * frame's) / rate, so that a pose recorded at a frame's stamp is published at
 * that frame's new host time and the node's lookup finds it exactly.
 *
 * Contract: vlff_replay_mcap returns vlff-replay's exit status (0 every frame
 * published, 1 an unreadable or invalid recording or a ring failure, 2 an
 * option the recording cannot honour), having said why on stderr. Not
 * thread-safe (the process's stop flag, vlff_cli_stop, ends it).
 */
#ifndef VLFF_REPLAY_MCAP_H
#define VLFF_REPLAY_MCAP_H

#include "config.h"

struct vlff_replay_opts {
  double fps;      /* > 0: scale time so the recording's mean frame rate is fps */
  double rate;     /* play at rate times the recorded pace */
  int loop, backpressure, wait_reader, quiet, features;
  long long count; /* frames; 0 = all */
  int start;       /* first frame played */
  int pose_slots;  /* the pose ring's slots */
};

/* 1 when path is a regular file starting with the MCAP magic, else 0. */
int vlff_replay_is_mcap(const char *path);
int vlff_replay_mcap(const char *path, const struct vlff_config *cfg, const struct vlff_replay_opts *o);

#endif
