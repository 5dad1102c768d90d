/*
 * Colour + range camera pairing: frames of two devices into ONE frame
 * record (colour plane + the range image registered into it).
 *
 * The colour camera's pipeline delivers into vlff_pair_color_sink, the range
 * camera's into vlff_pair_depth_sink; each keeps a few frames. A colour and
 * a range frame are paired when each is the other's nearest among the
 * frames held and their times lie within the tolerance of each other:
 *  - either frame stamped from a GPIO trigger (trigger_stamped): the host
 *    stamps, within depth_camera.pair_tolerance_s;
 *  - both free-running (arrival-stamped): within just under half the faster
 *    camera's configured frame period, whatever pair_tolerance_s says (free
 *    cameras keep an arbitrary phase between them), on each frame's device
 *    time moved onto the host clock by its stream's smallest arrival delay
 *    over the latest 32 frames (frames without a device time: arrival), so
 *    that a frame delayed on its way (scheduling, the network) still pairs;
 *    a pair waits for the earlier frame's successor, which could be nearer
 *    (a camera starting up sends frames closer than its period), unless
 *    the later frame's stream holds two more frames meanwhile; two frames
 *    too far apart while either stream's offset comes from one frame alone
 *    (its first, often late: a camera sends it when acquisition starts)
 *    wait for that stream's next frame, which gives its true offset,
 *    unless either stream holds three frames.
 * The config check keeps pair_tolerance_s under half of either camera's
 * frame period, so at most one frame of each stream can qualify: frames are
 * never paired wrongly (and a camera running faster than configured still
 * gets its nearer frame paired), and the oldest frame of either queue that
 * can no longer find a partner (the other stream is already past it by more
 * than the tolerance) is dropped and counted. A queue that overflows (eight
 * frames, the other stream late) drops and counts its oldest frame, or,
 * while it holds a trigger-stamped frame, its oldest free-running one: a
 * triggered camera's frame may arrive many of a free-running camera's
 * frames after its edge, and the frame that edge stamped is its partner.
 *
 * A pair is written into the output sink: the colour frame's pixels,
 * timestamps, ids and pose, the range image registered into the colour
 * camera (depthreg.h, from depth_camera.calibration) as the depth plane,
 * and the registration's output camera as the intrinsics. The record has
 * the colour frame's size, or depth_camera.register_width x register_height
 * when set: then the colour plane is resampled to it (pixel centres kept on
 * pixel centres, as the intrinsics are scaled) and the range image is
 * registered directly at it.
 *
 * Contract
 *  - vlff_pair_new() loads and checks the calibration, and the record size
 *    against the colour camera's aspect when the calibration or the config
 *    gives that camera's size; NULL with err (naming the file and key) on
 *    failure. The output sink is borrowed.
 *  - The two sinks and the stats are used from one thread (camd's loop);
 *    frames of each stream must arrive in time order.
 *  - A pair the output sink refuses, or whose sizes the calibration does not
 *    fit, is dropped and counted (and logged, rate-limited).
 */
#ifndef VLFF_PAIR_H
#define VLFF_PAIR_H

#include <stddef.h>
#include <stdint.h>

#include "config.h"
#include "sink.h"

/* A frame dropped without a partner is counted once, as a start-up frame
 * when the other stream had not begun yet (no frame of it so far, or its
 * first frame more than the tolerance after this one: one camera opens and
 * streams before the other) or no pair was made yet (a camera's first
 * frames need not keep its period), else as unmatched: both were streaming and
 * this frame's partner never came (a frame lost or late on the other side,
 * the other camera lost and reconnecting, a free-running colour camera
 * beside a triggered range camera). */
struct vlff_pair_stats {
  uint64_t pairs;            /* records committed to the output sink */
  uint64_t unmatched_color;  /* colour frames dropped without a range frame, both streaming */
  uint64_t unmatched_depth;  /* range frames dropped without a colour frame, both streaming */
  uint64_t startup_color;    /* colour frames dropped before the range camera's first frame */
  uint64_t startup_depth;    /* range frames dropped before the colour camera's first frame */
  uint64_t dropped;          /* pairs lost: output sink full, registration impossible */
  uint64_t free_pairs;       /* pairs of two free-running frames (the wider tolerance) */
  uint64_t skew_sum_ns, skew_max_ns; /* the pairs' time differences, as matched */
};

struct vlff_pair;
/* From the depth_camera section; the camera section gives the colour
 * camera's size when the calibration file does not. */
struct vlff_pair *vlff_pair_new(const struct vlff_cfg_depth_camera *dcam, const struct vlff_cfg_camera *cam,
                               struct vlff_sink *out, char *err, size_t errlen);
void vlff_pair_free(struct vlff_pair *p);
struct vlff_sink *vlff_pair_color_sink(struct vlff_pair *p);
struct vlff_sink *vlff_pair_depth_sink(struct vlff_pair *p);
const struct vlff_pair_stats *vlff_pair_get_stats(const struct vlff_pair *p);
/* Why the latest pair was dropped ("" before any): camd's report says it. */
const char *vlff_pair_last_error(const struct vlff_pair *p);
/* The host time of the newest colour (depth 0) or range (1) frame committed
 * to the pairing, 0 before the first. */
uint64_t vlff_pair_last_ns(const struct vlff_pair *p, int depth);

#endif
