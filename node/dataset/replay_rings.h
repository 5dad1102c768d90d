/*
 * replay_rings.h - what vlff-replay's two players share: the three rings
 * made for a recording's sizes, waiting for the frame ring's reader,
 * sleeping to a deadline, and a ring's failure said on stderr. One copy for
 * scenes (vlff_replay_main.c) and MCAP recordings (replay_mcap.c).
 *
 * Contract: one thread (vlff-replay's); every wait ends early on
 * vlff_cli_stop.
 */
#ifndef VLFF_REPLAY_RINGS_H
#define VLFF_REPLAY_RINGS_H

#include <stdint.h>

#include "config.h"
#include "vlff/shm.h"

struct vlff_replay_rings {
  struct vlff_ring *frames, *poses, *feats; /* poses, feats: NULL when not made */
};

/* Prints "vlff-replay: WHAT ring NAME: <libvlff-shm's last message>"; -1. */
int vlff_replay_ring_error(const char *what, const char *name);
/* The frame ring for width x height frames of the two pixel formats, the
 * pose ring with pose_slots slots (0: none), the feature ring for dim x fh x
 * fw maps (dim 0: none), named, sized and permitted by cfg's shm section.
 * 0, or -1 said on stderr (the rings made so far are left in r). */
int vlff_replay_rings_open(struct vlff_replay_rings *r, const struct vlff_config *cfg, uint32_t width,
                           uint32_t height, uint32_t color_format, uint32_t depth_format, uint32_t pose_slots,
                           uint32_t dim, uint32_t fh, uint32_t fw);
/* Waits until the frame ring has a reader (saying once that it waits,
 * unless quiet). */
void vlff_replay_wait_reader(struct vlff_ring *frames, int quiet);
/* Sleeps until due (vlff_now_ns's clock). */
void vlff_replay_sleep_until(uint64_t due_ns);

#endif
