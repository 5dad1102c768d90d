/*
 * The frame pipeline every camera backend shares: a raw camera image in,
 * one committed sink frame out (RGB8 colour, optional depth plane,
 * intrinsics, pose).
 *
 * Contract
 *  - vlff_camcfg_check() validates the camera.* and gpio.* combinations a
 *    driver needs (pixel format known, depth mode consistent with it,
 *    calibration present for stereo, ...). Returns 0 or -1 with err naming
 *    the file and the key: "FILE: key 'camera.x': expected ..., got ...".
 *  - vlff_pipe_new() loads the calibration (camera.calibration, or with
 *    camera.depth: stream depth_camera.calibration) and returns
 *    a pipeline, or NULL with err filled. Free with vlff_pipe_free().
 *  - vlff_pipe_push() validates the raw image (format, size, buffer length),
 *    converts it straight into a reserved sink slot and commits. Returns 0
 *    when a frame was committed, -1 when it was dropped; every drop is
 *    counted in the stats by reason and logged (rate-limited).
 *  - One pipeline per producer thread; not thread-safe.
 */
#ifndef VLFF_PIPE_H
#define VLFF_PIPE_H

#include <stddef.h>
#include <stdint.h>

#include "config.h"
#include "pixfmt.h"
#include "sink.h"
struct vlff_stamps;

#ifdef __cplusplus
extern "C" {
#endif

struct vlff_raw_frame {
  const void *data;
  size_t size;            /* bytes available at data */
  size_t stride;          /* bytes per row */
  int width, height;
  vlff_pix_t pix;
  uint64_t device_frame_id;
  uint64_t device_ns, host_ns;
};

struct vlff_pipe_stats {
  uint64_t committed;
  uint64_t dropped_format;   /* wrong pixel format or size for the config */
  uint64_t dropped_short;    /* buffer shorter than its geometry */
  uint64_t dropped_convert;  /* OpenCV refused it */
  uint64_t dropped_sink;     /* no slot (too large) */
  uint64_t no_pose;          /* committed but marked without a trustworthy pose */
  uint64_t trigger_stamped;  /* host time taken from a matched GPIO pulse/edge */
};

int vlff_camcfg_check(const struct vlff_config *cfg, const char *file, char *err, size_t errlen);

/* The camera.* section of the range camera (depth_camera.*), for opening
 * it with a camera backend. */
void vlff_depth_camera_config(const struct vlff_config *cfg, struct vlff_cfg_camera *out);

struct vlff_pipe;
/* The colour camera's pipeline. With camera.depth: stream its frames carry
 * colour only (the pairing adds the depth plane) and its intrinsics and
 * distortion come from the depth-to-colour calibration's colour camera.
 * The whole config is checked (vlff_camcfg_check); the pipeline keeps only
 * its camera's section and source.pose_tolerance_s. */
struct vlff_pipe *vlff_pipe_new(const struct vlff_config *cfg, char *err, size_t errlen);
/* The range camera's pipeline (camera.depth: stream): 16-bit counts times
 * depth_camera.scale_m into a uint16 millimetre depth plane, no colour
 * plane; undistortion is left to the registration. */
struct vlff_pipe *vlff_pipe_new_depth(const struct vlff_config *cfg, char *err, size_t errlen);
void vlff_pipe_free(struct vlff_pipe *p);
/* poses may be NULL: frames are then committed without a pose. */
int vlff_pipe_push(struct vlff_pipe *p, const struct vlff_raw_frame *raw, struct vlff_sink *sink,
                   const struct vlff_pose_source *poses);
/* Stamp frames with the trigger (GPIO pulse or edge) that exposed them: the
 * newest stamp within window_ns before a frame's arrival replaces its host
 * timestamp. q is borrowed and must outlive the pipeline. */
void vlff_pipe_set_stamps(struct vlff_pipe *p, struct vlff_stamps *q, uint64_t window_ns);
const struct vlff_pipe_stats *vlff_pipe_get_stats(const struct vlff_pipe *p);
/* The pixel format the camera is configured to deliver. */
vlff_pix_t vlff_pipe_pix(const struct vlff_pipe *p);

#ifdef __cplusplus
}
#endif

#endif
