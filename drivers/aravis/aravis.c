/*
 * Aravis backend: open and configure a camera, stream through a buffer pool
 * polled with arv_stream_timeout_pop_buffer, hand complete buffers to the
 * frame pipeline.
 *
 * Loss detection: Aravis' GigE heartbeat emits "control-lost" from its own
 * thread when the control channel dies; we latch it in an atomic flag. A
 * camera that silently stops sending (cable pulled mid-stream) shows up as
 * grab timeouts; after a second of silence we probe the control channel by
 * reading a register, which fails quickly for a dead camera. Trigger modes
 * wait indefinitely for triggers, so for them silence alone is not loss.
 */
#include "aravis.h"
#include "clock.h"

#include <arv.h>
#include <errno.h>
#include <stdbool.h>
#include <math.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "log.h"

#define TAG "aravis"
#define POOL 8

struct vlff_arv {
  ArvCamera *cam;
  ArvStream *stream;
  gulong lost_handler;
  atomic_bool lost;
  struct vlff_cfg_camera cfg;
  char name[VLFF_CFG_STR];
  int w, h;
  size_t payload;
  uint64_t silent_since_ns;
  bool gone; /* its control channel did not answer: closing skips the device */
  struct vlff_arv_stats st;
};

static void on_control_lost(ArvDevice *dev, gpointer data) {
  (void)dev;
  atomic_store(&((struct vlff_arv *)data)->lost, true);
}

/* A GError from setting a feature becomes "key: message" and frees it. */
static int open_errno; /* why the last open failed: ENODEV (retry) or EINVAL */

static int gfail(GError **e, char *err, size_t errlen, const char *key, const char *what) {
  snprintf(err, errlen, "key '%s': %s: %s", key, what, *e ? (*e)->message : "failed");
  /* A camera that stops answering mid-configuration is gone, not misconfigured. */
  bool gone = *e && (*e)->domain == ARV_DEVICE_ERROR &&
              ((*e)->code == ARV_DEVICE_ERROR_TIMEOUT || (*e)->code == ARV_DEVICE_ERROR_NOT_CONNECTED ||
               (*e)->code == ARV_DEVICE_ERROR_TRANSFER_ERROR);
  open_errno = gone ? ENODEV : EINVAL;
  g_clear_error(e);
  return -1;
}

/* A numeric feature the camera may lack (exposure, gain, frame rate): when it
 * has it, the configured value must lie within the camera's own bounds and
 * is then set. 0, or -1 with err naming the key. */
static int set_bounded(ArvCamera *cam, gboolean (*available)(ArvCamera *, GError **),
                       void (*bounds)(ArvCamera *, double *, double *, GError **),
                       void (*set)(ArvCamera *, double, GError **), double value, const char *key,
                       const char *refused, char *err, size_t errlen) {
  if (!available(cam, NULL)) return 0;
  GError *e = NULL;
  double lo, hi;
  bounds(cam, &lo, &hi, &e);
  if (!e && (value < lo || value > hi))
    return snprintf(err, errlen, "key '%s': expected [%g, %g] for this camera, got %g", key, lo, hi, value), -1;
  g_clear_error(&e);
  set(cam, value, &e);
  if (e) return gfail(&e, err, errlen, key, refused);
  return 0;
}


static ArvCamera *connect(const char *device, char *err, size_t errlen) {
  GError *e = NULL;
  const char *id = device[0] ? device : NULL;
  if (!strcmp(device, "Fake")) {
    arv_enable_interface("Fake");
    arv_update_device_list();
    id = "Fake_1";
  }
  /* An IP address or a known id opens directly in milliseconds; only ids
   * Aravis has not seen yet need the (~1 s) discovery first. */
  ArvCamera *cam = arv_camera_new(id, &e);
  if (!cam && id) {
    g_clear_error(&e);
    arv_update_device_list();
    cam = arv_camera_new(id, &e);
  }
  if (!cam) {
    snprintf(err, errlen, "key 'camera.device': cannot open camera '%s': %s", device[0] ? device : "(first found)",
             e ? e->message : "not found");
    g_clear_error(&e);
  }
  return cam;
}

static int configure(struct vlff_arv *a, char *err, size_t errlen) {
  const struct vlff_cfg_camera *c = &a->cfg;
  ArvCamera *cam = a->cam;
  GError *e = NULL;

  /* A previous session may have crashed while streaming. */
  arv_camera_stop_acquisition(cam, NULL);

  arv_camera_set_pixel_format_from_string(cam, c->pixel_format, &e);
  if (e) return gfail(&e, err, errlen, "camera.pixel_format", "camera refused the pixel format");
  const char *pf = arv_camera_get_pixel_format_as_string(cam, &e);
  if (e || !pf || strcmp(pf, c->pixel_format)) {
    g_clear_error(&e);
    snprintf(err, errlen, "key 'camera.pixel_format': camera does not offer %s (it reports %s)",
             c->pixel_format, pf ? pf : "nothing");
    return -1;
  }

  if (arv_camera_is_binning_available(cam, NULL)) {
    arv_camera_set_binning(cam, 1, 1, &e);
    g_clear_error(&e); /* some cameras expose binning read-only */
  }

  int sw = 0, sh = 0;
  arv_camera_get_sensor_size(cam, &sw, &sh, &e);
  if (e) return gfail(&e, err, errlen, "camera.width", "cannot read the sensor size");
  int w = c->width ? c->width : sw, h = c->height ? c->height : sh;
  if (c->offset_x + w > sw)
    return snprintf(err, errlen,
                    "key 'camera.offset_x': ROI x %d + width %d exceeds the sensor width %d of '%s'",
                    c->offset_x, w, sw, a->name),
           -1;
  if (c->offset_y + h > sh)
    return snprintf(err, errlen,
                    "key 'camera.offset_y': ROI y %d + height %d exceeds the sensor height %d of '%s'",
                    c->offset_y, h, sh, a->name),
           -1;
  /* Offsets first to 0 so any width/height within the sensor is legal,
   * then the real region. */
  arv_camera_set_region(cam, 0, 0, w, h, &e);
  if (e) return gfail(&e, err, errlen, "camera.width", "camera refused the ROI size");
  arv_camera_set_region(cam, c->offset_x, c->offset_y, w, h, &e);
  if (e) return gfail(&e, err, errlen, "camera.offset_x", "camera refused the ROI offset");
  int rx, ry, rw, rh;
  arv_camera_get_region(cam, &rx, &ry, &rw, &rh, &e);
  if (e) return gfail(&e, err, errlen, "camera.width", "cannot read the ROI back");
  if (rx != c->offset_x || ry != c->offset_y || rw != w || rh != h)
    return snprintf(err, errlen,
                    "key 'camera.width': camera adjusted the ROI %dx%d+%d+%d to %dx%d+%d+%d "
                    "(choose values on its increment grid)",
                    w, h, c->offset_x, c->offset_y, rw, rh, rx, ry),
           -1;
  a->w = w;
  a->h = h;

  if (arv_camera_is_exposure_auto_available(cam, NULL)) {
    arv_camera_set_exposure_time_auto(cam, ARV_AUTO_OFF, &e);
    if (e) return gfail(&e, err, errlen, "camera.exposure_us", "cannot turn auto exposure off");
  }
  if (set_bounded(cam, arv_camera_is_exposure_time_available, arv_camera_get_exposure_time_bounds,
                  arv_camera_set_exposure_time, c->exposure_us, "camera.exposure_us", "camera refused the exposure",
                  err, errlen))
    return -1;
  if (arv_camera_is_gain_auto_available(cam, NULL)) {
    arv_camera_set_gain_auto(cam, ARV_AUTO_OFF, &e);
    if (e) return gfail(&e, err, errlen, "camera.gain_db", "cannot turn auto gain off");
  }
  if (set_bounded(cam, arv_camera_is_gain_available, arv_camera_get_gain_bounds, arv_camera_set_gain, c->gain_db,
                  "camera.gain_db", "camera refused the gain", err, errlen))
    return -1;
  if (set_bounded(cam, arv_camera_is_frame_rate_available, arv_camera_get_frame_rate_bounds,
                  arv_camera_set_frame_rate, c->frame_rate, "camera.frame_rate", "camera refused the frame rate", err,
                  errlen))
    return -1;

  if (arv_camera_is_gv_device(cam)) {
    if (c->packet_size > 0)
      arv_camera_gv_set_packet_size(cam, c->packet_size, &e);
    else
      arv_camera_gv_auto_packet_size(cam, &e);
    if (e) return gfail(&e, err, errlen, "camera.packet_size", "cannot set the packet size");
  }

  switch (c->trigger) {
  case VLFF_TRIG_FREERUN: arv_camera_clear_triggers(cam, &e); break;
  case VLFF_TRIG_SOFTWARE: arv_camera_set_trigger(cam, "Software", &e); break;
  case VLFF_TRIG_HARDWARE: arv_camera_set_trigger(cam, c->trigger_line, &e); break;
  }
  if (e)
    return gfail(&e, err, errlen, c->trigger == VLFF_TRIG_HARDWARE ? "camera.trigger_line" : "camera.trigger",
                 "camera refused the trigger mode");

  arv_camera_set_acquisition_mode(cam, ARV_ACQUISITION_MODE_CONTINUOUS, &e);
  if (e) return gfail(&e, err, errlen, "camera.trigger", "cannot set continuous acquisition");
  return 0;
}

struct vlff_arv *vlff_arv_open(const struct vlff_cfg_camera *cfg, char *err, size_t errlen) {
  struct vlff_arv *a = calloc(1, sizeof *a);
  if (!a) {
    snprintf(err, errlen, "out of memory");
    return NULL;
  }
  a->cfg = *cfg;
  snprintf(a->name, sizeof a->name, "%s", cfg->device[0] ? cfg->device : "(first found)");
  atomic_init(&a->lost, false);
  GError *e = NULL;
  open_errno = EINVAL;
  a->cam = connect(cfg->device, err, errlen);
  if (!a->cam) {
    open_errno = ENODEV;
    goto fail;
  }
  ArvDevice *dev = arv_camera_get_device(a->cam);
  a->lost_handler = g_signal_connect(dev, "control-lost", G_CALLBACK(on_control_lost), a);
  if (configure(a, err, errlen)) goto fail;
  a->payload = (size_t)arv_camera_get_payload(a->cam, &e);
  if (e || !a->payload) {
    gfail(&e, err, errlen, "camera.pixel_format", "cannot read the payload size");
    goto fail;
  }
  a->stream = arv_camera_create_stream(a->cam, NULL, NULL, &e);
  if (!a->stream) {
    gfail(&e, err, errlen, "camera.device", "cannot create the stream");
    goto fail;
  }
  for (int i = 0; i < POOL; i++) arv_stream_push_buffer(a->stream, arv_buffer_new(a->payload, NULL));
  arv_camera_start_acquisition(a->cam, &e);
  if (e) {
    gfail(&e, err, errlen, "camera.device", "cannot start acquisition");
    goto fail;
  }
  a->silent_since_ns = vlff_now_ns();
  VLFF_INFO(TAG, "'%s' (%s %s) streaming %dx%d %s, trigger %s, payload %zu bytes", a->name,
            arv_camera_get_vendor_name(a->cam, NULL), arv_camera_get_model_name(a->cam, NULL), a->w, a->h,
            cfg->pixel_format,
            cfg->trigger == VLFF_TRIG_FREERUN    ? "freerun"
            : cfg->trigger == VLFF_TRIG_SOFTWARE ? "software"
                                                        : cfg->trigger_line,
            a->payload);
  return a;
fail:
  vlff_arv_close(a);
  errno = open_errno;
  return NULL;
}

void vlff_arv_close(struct vlff_arv *a) {
  if (!a) return;
  if (a->cam) {
    /* Stopping a camera that is gone costs the GVCP retries of every
     * register written (seconds) for nothing. */
    if (a->stream && !a->gone && !atomic_load(&a->lost)) arv_camera_stop_acquisition(a->cam, NULL);
    if (a->lost_handler) g_signal_handler_disconnect(arv_camera_get_device(a->cam), a->lost_handler);
  }
  if (a->stream) g_object_unref(a->stream);
  if (a->cam) g_object_unref(a->cam);
  free(a);
}

void vlff_arv_shutdown(void) { arv_shutdown(); }

const struct vlff_arv_stats *vlff_arv_stats(const struct vlff_arv *a) { return &a->st; }

int vlff_arv_software_trigger(struct vlff_arv *a, char *err, size_t errlen) {
  GError *e = NULL;
  arv_camera_software_trigger(a->cam, &e);
  if (e) {
    snprintf(err, errlen, "software trigger on '%s': %s", a->name, e->message);
    g_clear_error(&e);
    return -1;
  }
  a->st.triggers++;
  return 0;
}

static vlff_pix_t from_arv(ArvPixelFormat f) {
  switch (f) {
  case ARV_PIXEL_FORMAT_MONO_8: return VLFF_PIX_MONO8;
  case ARV_PIXEL_FORMAT_MONO_16:
  case ARV_PIXEL_FORMAT_COORD3D_C_16: return VLFF_PIX_MONO16;
  case ARV_PIXEL_FORMAT_RGB_8_PACKED: return VLFF_PIX_RGB8;
  case ARV_PIXEL_FORMAT_BGR_8_PACKED: return VLFF_PIX_BGR8;
  case ARV_PIXEL_FORMAT_BAYER_RG_8: return VLFF_PIX_BAYER_RG8;
  case ARV_PIXEL_FORMAT_BAYER_BG_8: return VLFF_PIX_BAYER_BG8;
  case ARV_PIXEL_FORMAT_BAYER_GR_8: return VLFF_PIX_BAYER_GR8;
  case ARV_PIXEL_FORMAT_BAYER_GB_8: return VLFF_PIX_BAYER_GB8;
  default: return VLFF_PIX_NONE;
  }
}

static const char *status_name(ArvBufferStatus s) {
  switch (s) {
  case ARV_BUFFER_STATUS_SUCCESS: return "success";
  case ARV_BUFFER_STATUS_CLEARED: return "cleared";
  case ARV_BUFFER_STATUS_TIMEOUT: return "timeout";
  case ARV_BUFFER_STATUS_MISSING_PACKETS: return "missing packets";
  case ARV_BUFFER_STATUS_WRONG_PACKET_ID: return "wrong packet id";
  case ARV_BUFFER_STATUS_SIZE_MISMATCH: return "size mismatch";
  case ARV_BUFFER_STATUS_FILLING: return "filling";
  case ARV_BUFFER_STATUS_ABORTED: return "aborted";
  default: return "unknown";
  }
}

/* Is the camera still there? One register read goes over the control
 * channel and fails after Aravis' GVCP retries (5 of 500 ms) when nobody
 * answers: the bootstrap's first register (the GigE Vision version, the
 * GenCP version on USB3 Vision), which every device has. A feature read
 * instead (the payload size) goes through several registers, each with
 * its own retries: 10 s for a camera that is gone. */
static bool probe(struct vlff_arv *a) {
  GError *e = NULL;
  guint32 v = 0;
  arv_device_read_register(arv_camera_get_device(a->cam), 0, &v, &e);
  if (e) {
    VLFF_WARN(TAG, "'%s' does not answer: %s", a->name, e->message);
    g_clear_error(&e);
    a->gone = true;
    return false;
  }
  return true;
}

int vlff_arv_grab(struct vlff_arv *a, int timeout_ms, struct vlff_pipe *pipe, struct vlff_sink *sink,
                  const struct vlff_pose_source *poses) {
  if (atomic_load(&a->lost)) {
    VLFF_WARN(TAG, "'%s': control channel lost", a->name);
    return -1;
  }
  ArvBuffer *b = arv_stream_timeout_pop_buffer(a->stream, (guint64)timeout_ms * 1000);
  uint64_t now = vlff_now_ns();
  if (!b) {
    a->st.timeouts++;
    if (atomic_load(&a->lost)) return -1;
    if (now - a->silent_since_ns > 1000000000u) {
      a->silent_since_ns = now;
      if (!probe(a)) return -1;
    }
    return 0;
  }
  a->silent_since_ns = now;
  a->st.buffers++;
  int rc = 0;
  ArvBufferStatus s = arv_buffer_get_status(b);
  if (s != ARV_BUFFER_STATUS_SUCCESS) {
    vlff_warn_limited(&a->st.incomplete, TAG, "'%s': dropped buffer %llu (%s); %llu incomplete so far", a->name,
                      (unsigned long long)arv_buffer_get_frame_id(b), status_name(s),
                      (unsigned long long)a->st.incomplete + 1);
  } else if (arv_buffer_get_payload_type(b) != ARV_BUFFER_PAYLOAD_TYPE_IMAGE &&
             arv_buffer_get_payload_type(b) != ARV_BUFFER_PAYLOAD_TYPE_EXTENDED_CHUNK_DATA) {
    a->st.incomplete++;
    VLFF_WARN(TAG, "'%s': dropped a buffer that is not an image (payload type %d)", a->name,
              (int)arv_buffer_get_payload_type(b));
  } else {
    size_t size = 0;
    const void *data = arv_buffer_get_data(b, &size);
    struct vlff_raw_frame raw = {
        .data = data,
        .size = size,
        .width = arv_buffer_get_image_width(b),
        .height = arv_buffer_get_image_height(b),
        .pix = from_arv(arv_buffer_get_image_pixel_format(b)),
        .device_frame_id = arv_buffer_get_frame_id(b),
        .device_ns = arv_buffer_get_timestamp(b),
    };
    raw.stride = raw.width > 0 ? (size_t)raw.width * vlff_pix_bytes(raw.pix) : 0;
    /* Aravis stamps buffer arrival with the wall clock; move it onto
     * CLOCK_MONOTONIC through the current offset between the two, read
     * bracketed (clock.h: two reads back to back are off by however long
     * the thread was preempted between them). Fall back to "now" when that
     * is not plausible (no stamp, or a clock step). */
    const uint64_t sys = arv_buffer_get_system_timestamp(b);
    const int64_t t = (int64_t)sys + vlff_mono_minus_wall_ns();
    raw.host_ns = sys && t > 0 && (uint64_t)t <= now && now - (uint64_t)t < 1000000000u ? (uint64_t)t : now;
    rc = vlff_pipe_push(pipe, &raw, sink, poses) == 0 ? 1 : 0;
  }
  arv_stream_push_buffer(a->stream, b);
  return rc;
}
