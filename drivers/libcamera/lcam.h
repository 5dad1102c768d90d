/*
 * libcamera backend (CSI and UVC cameras on embedded boards), a C interface
 * over one C++ file.
 *
 * Contract
 *  - vlff_lcam_open() starts libcamera's camera manager, picks the camera
 *    named by camera.device (a libcamera id, or an index into its list; ""
 *    = the first), configures one stream of camera.width x camera.height in
 *    camera.pixel_format (GenICam names mapped to libcamera's formats),
 *    allocates buffers, queues one request per buffer and starts. Returns
 *    NULL with err filled and errno set: ENODEV when there is no such camera
 *    (none at all: the message says so), EINVAL when the camera cannot do
 *    the configuration (the message names the key and what it offers).
 *  - vlff_lcam_grab() waits up to timeout_ms for a completed request, passes
 *    the frame (sensor timestamp, CLOCK_MONOTONIC) through the pipeline into
 *    the sink and requeues the request. Returns 1 committed, 0 nothing or
 *    dropped (counted), -1 camera disconnected.
 *  - vlff_lcam_close() stops the camera, waits for outstanding requests,
 *    frees everything; NULL accepted. One camera per process.
 *  - No C++ exception crosses this header. One thread uses an object.
 */
#ifndef VLFF_LCAM_H
#define VLFF_LCAM_H

#include <stddef.h>
#include <stdint.h>

#include "config.h"
#include "pipe.h"
#include "sink.h"

#ifdef __cplusplus
extern "C" {
#endif

struct vlff_lcam;
struct vlff_lcam *vlff_lcam_open(const struct vlff_cfg_camera *cfg, char *err, size_t errlen);
int vlff_lcam_grab(struct vlff_lcam *c, int timeout_ms, struct vlff_pipe *pipe, struct vlff_sink *sink,
                   const struct vlff_pose_source *poses);
void vlff_lcam_close(struct vlff_lcam *c);
void vlff_lcam_counters(const struct vlff_lcam *c, uint64_t *incomplete, uint64_t *timeouts);

#ifdef __cplusplus
}
#endif

#endif
