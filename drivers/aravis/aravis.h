/*
 * Aravis (GigE Vision / USB3 Vision) camera backend.
 *
 * Contract
 *  - vlff_arv_open() connects to camera.device (an IP address, a device id
 *    or serial as Aravis lists it, or "Fake" for Aravis' in-process fake
 *    camera), sets every feature from the config explicitly (cameras keep
 *    register values across connections), allocates the buffer pool and
 *    starts acquisition. Returns NULL with err filled; errors about a value
 *    name the config key ("camera.offset_x: ..."). errno tells the caller
 *    what to do: ENODEV = camera unreachable (retry later), EINVAL = the
 *    camera refuses the configuration (retrying will not help).
 *  - vlff_arv_grab() waits up to timeout_ms for one buffer and passes a
 *    complete one through the pipeline into the sink. Returns 1 (frame
 *    committed), 0 (nothing, or a dropped frame; see the stats), or -1 when
 *    the camera is lost (control channel gone, or it stopped answering):
 *    close it and open again.
 *  - No GLib main loop is needed: buffers are polled.
 *  - One thread uses an object at a time, except vlff_arv_software_trigger()
 *    which may be called from a second thread (Aravis serialises control
 *    access per device).
 */
#ifndef VLFF_ARAVIS_H
#define VLFF_ARAVIS_H

#include <stddef.h>
#include <stdint.h>

#include "config.h"
#include "pipe.h"
#include "sink.h"

struct vlff_arv_stats {
  uint64_t buffers;       /* buffers popped */
  uint64_t incomplete;    /* dropped: missing packets, size mismatch, aborted ... */
  uint64_t timeouts;      /* grab waits that saw nothing */
  uint64_t triggers;      /* software triggers sent */
};

struct vlff_arv;
struct vlff_arv *vlff_arv_open(const struct vlff_cfg_camera *cfg, char *err, size_t errlen);
void vlff_arv_close(struct vlff_arv *a);
int vlff_arv_grab(struct vlff_arv *a, int timeout_ms, struct vlff_pipe *pipe, struct vlff_sink *sink,
                  const struct vlff_pose_source *poses);
int vlff_arv_software_trigger(struct vlff_arv *a, char *err, size_t errlen);
const struct vlff_arv_stats *vlff_arv_stats(const struct vlff_arv *a);
/* Releases Aravis' global state; call once at process exit. */
void vlff_arv_shutdown(void);

#endif
