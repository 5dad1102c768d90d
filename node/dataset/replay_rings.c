/*
 * replay_rings.c - vlff-replay's rings, waits and ring errors (replay_rings.h).
 */
#include "replay_rings.h"

#include <errno.h>
#include <stdio.h>
#include <time.h>

#include "cli.h"
#include "vlff/escape.h"

int vlff_replay_ring_error(const char *what, const char *name) {
  fprintf(stderr, "vlff-replay: %s ring %s: %s\n", what, VLFF_Q(name), vlff_shm_last_message());
  return -1;
}

int vlff_replay_rings_open(struct vlff_replay_rings *r, const struct vlff_config *cfg, uint32_t width,
                           uint32_t height, uint32_t color_format, uint32_t depth_format, uint32_t pose_slots,
                           uint32_t dim, uint32_t fh, uint32_t fw) {
  struct vlff_shm_perm perm = {(mode_t)cfg->shm.mode, cfg->shm.group};
  struct vlff_ring_params fp = {VLFF_RECORD_FRAME, (uint32_t)cfg->shm.ring_slots,
                                vlff_frame_slot_size(width, height, color_format, depth_format), perm};
  r->frames = vlff_ring_create(cfg->shm.ring, &fp);
  if (!r->frames) return vlff_replay_ring_error("frame", cfg->shm.ring);
  if (pose_slots) {
    struct vlff_ring_params pp = {VLFF_RECORD_POSE, pose_slots, sizeof(struct vlff_pose_rec), perm};
    r->poses = vlff_ring_create(cfg->shm.pose_ring, &pp);
    if (!r->poses) return vlff_replay_ring_error("pose", cfg->shm.pose_ring);
  }
  if (dim) {
    struct vlff_ring_params xp = {VLFF_RECORD_FEATURE, (uint32_t)cfg->shm.ring_slots,
                                  vlff_feature_slot_size(dim, fh, fw), perm};
    r->feats = vlff_ring_create(cfg->shm.feature_ring, &xp);
    if (!r->feats) return vlff_replay_ring_error("feature", cfg->shm.feature_ring);
  }
  return 0;
}

void vlff_replay_wait_reader(struct vlff_ring *frames, int quiet) {
  int said = 0;
  while (!vlff_cli_stop && vlff_ring_wait_reader(frames, 1000ull * 1000 * 1000) < 0) {
    if (!said && !quiet) fprintf(stderr, "vlff-replay: waiting for a reader of the frame ring\n");
    said = 1;
  }
}

void vlff_replay_sleep_until(uint64_t due_ns) {
  struct timespec ts = {(time_t)(due_ns / 1000000000ull), (long)(due_ns % 1000000000ull)};
  while (!vlff_cli_stop && clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {
  }
}
