/*
 * The frame ring as a sink (see sink.h), and the pose ring as a pose source.
 *
 * Contract
 *  - vlff_ringsink_new() creates (or takes over from a dead creator) the
 *    frame ring shm.ring with shm.ring_slots slots sized for shm.max_width x
 *    shm.max_height RGB8 plus the depth plane camera.depth asks for. NULL
 *    with err (the shm library's message) on failure.
 *  - The pose source attaches to shm.pose_ring lazily: a missing pose ring
 *    (no SLAM running yet) is retried at most once a second and frames go
 *    out marked "no pose" meanwhile.
 *  - One producer thread; frees with vlff_ringsink_free (the segment stays
 *    for consumers; a restarted driver takes it over).
 */
#ifndef VLFF_RINGSINK_H
#define VLFF_RINGSINK_H

#include <stddef.h>

#include "config.h"
#include "sink.h"

struct vlff_ringsink;
/* shm: the segments (shm.*); camera: the colour camera, whose depth
 * settings fix the ring's depth plane. */
struct vlff_ringsink *vlff_ringsink_new(const struct vlff_cfg_shm *shm, const struct vlff_cfg_camera *camera, char *err,
                                        size_t errlen);
void vlff_ringsink_free(struct vlff_ringsink *r);
struct vlff_sink *vlff_ringsink_sink(struct vlff_ringsink *r);
struct vlff_pose_source *vlff_ringsink_poses(struct vlff_ringsink *r);

#endif
