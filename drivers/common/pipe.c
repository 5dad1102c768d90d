/*
 * Raw camera image -> sink slot. The common case (no undistortion, no
 * depth) converts straight into the reserved slot: one pass over the
 * pixels, no intermediate copy. Undistortion and stereo need a scratch RGB
 * image first because OpenCV's remap cannot work in place.
 */
#include "pipe.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "cvshim.h"
#include "depthreg.h"
#include "stamps.h"
#include "log.h"
#include "vlff/escape.h"

#define TAG "pipe"

struct vlff_pipe {
  struct vlff_cfg_camera cam;   /* this camera's section (the range camera's: vlff_depth_camera_config) */
  double pose_tolerance_s;      /* source.pose_tolerance_s */
  vlff_pix_t pix;
  double k[4];                  /* intrinsics from config or calibration */
  double dist[5];
  bool undistort;
  struct vlff_cv_calib calib;
  bool have_calib;
  bool range;                   /* the range camera of a pair: depth plane only */
  /* built for the first frame's size, rebuilt if it changes */
  int w, h;
  struct vlff_cv_undistort *und;
  struct vlff_cv_stereo *stereo;
  uint8_t *scratch;             /* RGB8 of the whole raw image */
  float *depth_scratch;
  size_t scratch_size;
  struct vlff_pipe_stats st;
  struct vlff_stamps *stamps;
  uint64_t stamp_window_ns;
  uint64_t drops_logged;
};

static bool any_nonzero(const double *v, int n) {
  for (int i = 0; i < n; i++)
    if (v[i] != 0) return true;
  return false;
}

#define BAD(key, ...)                                                  \
  do {                                                                 \
    char what_[256];                                                   \
    snprintf(what_, sizeof what_, __VA_ARGS__);                        \
    snprintf(err, errlen, "%s: key '%s': %s", file, key, what_);       \
    return -1;                                                         \
  } while (0)

/* camera.depth: stream: a range camera (depth_camera.*) paired with the
 * colour camera by time, its depth registered into it. */
static int check_depth_camera(const struct vlff_config *cfg, const char *file, char *err, size_t errlen) {
  const struct vlff_cfg_depth_camera *d = &cfg->depth_camera;
  if (d->kind == VLFF_DCAM_NONE)
    BAD("camera.depth", "'stream' pairs the colour camera with a range camera: set depth_camera.kind "
                        "(aravis) and depth_camera.device");
  if (vlff_pix_from_name(d->pixel_format) != VLFF_PIX_MONO16)
    BAD("depth_camera.pixel_format", "expected a 16-bit range format (Mono16 or Coord3D_C16), got '%s'",
        d->pixel_format);
  if (!d->calibration[0])
    BAD("depth_camera.calibration",
        "expected the depth-to-colour calibration (OpenCV FileStorage: K1 D1 K2 D2 R T), got none");
  if (cfg->camera.calibration[0] || any_nonzero(cfg->camera.intrinsics, 4) || any_nonzero(cfg->camera.distortion, 5))
    BAD(cfg->camera.calibration[0] ? "camera.calibration" : "camera.intrinsics",
        "with camera.depth: stream the colour camera's intrinsics come from depth_camera.calibration (K2, D2): "
        "expected none here");
  if (cfg->camera.depth_unit != VLFF_DEPTH_UNIT_MM)
    BAD("camera.depth_unit", "registered depth is uint16 millimetres: expected mm");
  /* Two frames of one camera within the tolerance of a frame of the other
   * would make the pairing ambiguous: under half a period, none can be. */
  double half = 0.5 / fmax(cfg->camera.frame_rate, d->frame_rate);
  if (!(d->pair_tolerance_s < half))
    BAD("depth_camera.pair_tolerance_s",
        "expected less than half the faster camera's frame period (%.4f s), so that no frame has two "
        "candidates, got %g", half, d->pair_tolerance_s);
  /* The record's size: the colour camera's, or one both planes are
   * resampled/registered at. The ring holds it, so the ring's bounds apply
   * to it rather than to the colour camera. */
  const int rw = d->register_width, rh = d->register_height;
  if (!rw != !rh)
    BAD(rw ? "depth_camera.register_height" : "depth_camera.register_width",
        "expected both register_width and register_height (or both 0: the colour camera's size), got %dx%d", rw,
        rh);
  if (rw && (rw < 16 || rw > cfg->shm.max_width))
    BAD("depth_camera.register_width", "expected 16..shm.max_width (%d), got %d", cfg->shm.max_width, rw);
  if (rh && (rh < 16 || rh > cfg->shm.max_height))
    BAD("depth_camera.register_height", "expected 16..shm.max_height (%d), got %d", cfg->shm.max_height, rh);
  if (rw && cfg->camera.width && cfg->camera.height &&
      !vlff_depthreg_aspect_ok(rw, rh, cfg->camera.width, cfg->camera.height))
    BAD("depth_camera.register_width",
        "expected the colour camera's aspect (camera.width x camera.height = %dx%d, within %g %%), got %dx%d: "
        "another aspect would stretch the image; crop the colour camera with its ROI instead",
        cfg->camera.width, cfg->camera.height, 100 * VLFF_DEPTHREG_ASPECT_TOL, rw, rh);
  return 0;
}

int vlff_camcfg_check(const struct vlff_config *cfg, const char *file, char *err, size_t errlen) {
  const struct vlff_cfg_camera *c = &cfg->camera;
  vlff_pix_t pix = vlff_pix_from_name(c->pixel_format);
  if (pix == VLFF_PIX_INVALID)
    BAD("camera.pixel_format", "expected one of %s, got '%s'", vlff_pix_names(), c->pixel_format);
  if (pix == VLFF_PIX_MONO16)
    BAD("camera.pixel_format",
        "%s is a range image, not colour: a range camera goes in depth_camera.* beside a colour camera, "
        "with camera.depth: stream", c->pixel_format);
  if (c->depth == VLFF_DEPTH_STREAM && check_depth_camera(cfg, file, err, errlen)) return -1;
  if (cfg->depth_camera.kind != VLFF_DCAM_NONE && c->depth != VLFF_DEPTH_STREAM)
    BAD("depth_camera.kind", "a range camera is paired with the colour camera only with camera.depth: stream");
  if (c->depth == VLFF_DEPTH_STEREO) {
    if (!c->calibration[0])
      BAD("camera.calibration",
          "depth: stereo needs an OpenCV stereo calibration YAML (M1 D1 M2 D2 R T), got none");
    if (c->width % 2)
      BAD("camera.width", "a side-by-side stereo pair needs an even width, got %d", c->width);
  }
  /* The ring holds the camera's image, except a pair's registered to its
   * own size (checked above). */
  bool ring_sized = !(c->depth == VLFF_DEPTH_STREAM && cfg->depth_camera.register_width);
  if (ring_sized && c->width && c->width > 2 * cfg->shm.max_width)
    BAD("camera.width", "expected at most shm.max_width (%d), got %d", cfg->shm.max_width, c->width);
  if (ring_sized && c->depth != VLFF_DEPTH_STEREO && c->width > cfg->shm.max_width)
    BAD("camera.width", "expected at most shm.max_width (%d), got %d", cfg->shm.max_width, c->width);
  if (ring_sized && c->height > cfg->shm.max_height)
    BAD("camera.height", "expected at most shm.max_height (%d), got %d", cfg->shm.max_height, c->height);
  if ((c->offset_x || c->offset_y) && (!c->width || !c->height))
    BAD(c->offset_x ? "camera.offset_x" : "camera.offset_y",
        "an ROI offset needs camera.width and camera.height set");
  bool k_any = any_nonzero(c->intrinsics, 4);
  for (int i = 0; i < 4 && k_any; i++)
    if (c->intrinsics[i] == 0)
      BAD("camera.intrinsics", "expected all of fx fy cx cy or all zeros, got 0 at index %d", i);
  if (k_any && (c->intrinsics[0] <= 0 || c->intrinsics[1] <= 0))
    BAD("camera.intrinsics", "expected positive focal lengths");
  if (any_nonzero(c->distortion, 5) && !k_any && !c->calibration[0])
    BAD("camera.distortion", "undistortion needs camera.intrinsics or camera.calibration");
  if (c->kind == VLFF_CAM_LIBCAMERA && c->trigger != VLFF_TRIG_FREERUN)
    BAD("camera.trigger", "libcamera cameras free-run: expected freerun, got %s",
        c->trigger == VLFF_TRIG_SOFTWARE ? "software" : "hardware");
  if (c->trigger == VLFF_TRIG_HARDWARE && !c->trigger_line[0])
    BAD("camera.trigger_line", "hardware triggering needs the camera's input line, got none");
  if (cfg->gpio.mode == VLFF_GPIO_OUTPUT && cfg->gpio.pulse_us * 1e-6 >= 1.0 / cfg->gpio.rate_hz)
    BAD("gpio.pulse_us", "expected a pulse shorter than the period 1/gpio.rate_hz (%.0f us), got %.0f",
        1e6 / cfg->gpio.rate_hz, cfg->gpio.pulse_us);
  if (cfg->gpio.mode != VLFF_GPIO_OFF && !cfg->gpio.line[0])
    BAD("gpio.line", "expected a line name or number, got none");
  if (cfg->gpio.mode != VLFF_GPIO_OFF && !cfg->gpio.chip[0])
    BAD("gpio.chip", "expected a chip name, path or number, got none");
  return 0;
}

void vlff_depth_camera_config(const struct vlff_config *cfg, struct vlff_cfg_camera *out) {
  const struct vlff_cfg_depth_camera *d = &cfg->depth_camera;
  *out = cfg->camera;
  struct vlff_cfg_camera *c = out;
  c->kind = VLFF_CAM_ARAVIS;
  snprintf(c->device, sizeof c->device, "%s", d->device);
  snprintf(c->pixel_format, sizeof c->pixel_format, "%s", d->pixel_format);
  c->width = d->width, c->height = d->height, c->offset_x = c->offset_y = 0;
  c->exposure_us = d->exposure_us, c->gain_db = 0, c->frame_rate = d->frame_rate;
  c->packet_size = d->packet_size, c->trigger = d->trigger;
  snprintf(c->trigger_line, sizeof c->trigger_line, "%s", d->trigger_line);
  memset(c->intrinsics, 0, sizeof c->intrinsics);
  memset(c->distortion, 0, sizeof c->distortion);
  c->calibration[0] = 0;
  c->depth = VLFF_DEPTH_STREAM, c->depth_unit = VLFF_DEPTH_UNIT_MM, c->depth_scale_m = d->scale_m;
}

/* A pipeline for the camera section cam; pair: the range camera a colour
 * camera is paired with (its depth-to-colour calibration), else NULL. */
static struct vlff_pipe *pipe_create(const struct vlff_cfg_camera *cam, const struct vlff_cfg_depth_camera *pair,
                                     double pose_tolerance_s, bool range, char *err, size_t errlen) {
  struct vlff_pipe *p = calloc(1, sizeof *p);
  if (!p) {
    snprintf(err, errlen, "out of memory");
    return NULL;
  }
  p->cam = *cam;
  p->pose_tolerance_s = pose_tolerance_s;
  p->range = range;
  p->pix = vlff_pix_from_name(cam->pixel_format);
  memcpy(p->k, cam->intrinsics, sizeof p->k);
  memcpy(p->dist, cam->distortion, sizeof p->dist);
  if (!range && pair) {
    /* The registration projects into the colour camera of the calibration:
     * the colour image must be undistorted with that camera's own model. */
    struct vlff_rgbd_calib rc;
    char e[512];
    if (vlff_rgbd_calib_load(pair->calibration, &rc, e, sizeof e)) {
      snprintf(err, errlen, "key 'depth_camera.calibration': %s", e);
      free(p);
      return NULL;
    }
    /* Both sizes in the config and in the file: they must agree, or the
     * first pair would find out and every pair be dropped. */
    const struct vlff_cfg_depth_camera *dc = pair;
    bool color_off = rc.color_w && cam->width && cam->height && (rc.color_w != cam->width || rc.color_h != cam->height);
    if (color_off || (rc.depth_w && dc->width && dc->height && (rc.depth_w != dc->width || rc.depth_h != dc->height))) {
      snprintf(err, errlen, "key 'depth_camera.calibration': %s is calibrated for %s %dx%d, but %s say %dx%d",
               VLFF_Q(pair->calibration), color_off ? "colour" : "depth",
               color_off ? rc.color_w : rc.depth_w, color_off ? rc.color_h : rc.depth_h,
               color_off ? "camera.width/height" : "depth_camera.width/height",
               color_off ? cam->width : dc->width, color_off ? cam->height : dc->height);
      free(p);
      return NULL;
    }
    if (rc.nc > 5 && any_nonzero(rc.dc + 5, rc.nc - 5)) {
      snprintf(err, errlen, "key 'depth_camera.calibration': %s: the colour camera's rational distortion (D2 "
               "k4..k6) is not supported by the colour pipeline; calibrate it with 5 coefficients",
               pair->calibration);
      free(p);
      return NULL;
    }
    p->k[0] = rc.kc[0], p->k[1] = rc.kc[4], p->k[2] = rc.kc[2], p->k[3] = rc.kc[5];
    memset(p->dist, 0, sizeof p->dist);
    memcpy(p->dist, rc.dc, sizeof(double) * (size_t)(rc.nc < 5 ? rc.nc : 5));
  }
  if (cam->calibration[0]) {
    char e[512];
    if (vlff_cv_calib_load(cam->calibration, &p->calib, e, sizeof e)) {
      snprintf(err, errlen, "key 'camera.calibration': %s", e);
      free(p);
      return NULL;
    }
    p->have_calib = true;
    if (cam->depth != VLFF_DEPTH_STEREO && p->calib.width && cam->width && cam->height &&
        (p->calib.width != cam->width || p->calib.height != cam->height)) {
      snprintf(err, errlen, "key 'camera.calibration': %s is calibrated for %dx%d images (image_width/height), but "
               "camera.width/height say %dx%d", VLFF_Q(cam->calibration), p->calib.width, p->calib.height,
               cam->width, cam->height);
      free(p);
      return NULL;
    }
    if (cam->depth == VLFF_DEPTH_STEREO && !p->calib.has_stereo) {
      snprintf(err, errlen,
               "key 'camera.calibration': depth: stereo needs stereo keys M1 D1 M2 D2 R T in %s",
               cam->calibration);
      free(p);
      return NULL;
    }
    /* The config's own values win: they are the deliberate override. */
    if (p->calib.has_mono && !any_nonzero(p->k, 4)) {
      p->k[0] = p->calib.k[0], p->k[1] = p->calib.k[4], p->k[2] = p->calib.k[2], p->k[3] = p->calib.k[5];
      if (!any_nonzero(p->dist, 5)) memcpy(p->dist, p->calib.dist, sizeof p->dist);
    }
  }
  p->undistort = !range && cam->depth != VLFF_DEPTH_STEREO && any_nonzero(p->dist, 5);
  return p;
}

struct vlff_pipe *vlff_pipe_new(const struct vlff_config *cfg, char *err, size_t errlen) {
  if (vlff_camcfg_check(cfg, "config", err, errlen)) return NULL;
  const struct vlff_cfg_depth_camera *pair = cfg->camera.depth == VLFF_DEPTH_STREAM ? &cfg->depth_camera : NULL;
  return pipe_create(&cfg->camera, pair, cfg->source.pose_tolerance_s, false, err, errlen);
}

struct vlff_pipe *vlff_pipe_new_depth(const struct vlff_config *cfg, char *err, size_t errlen) {
  if (vlff_camcfg_check(cfg, "config", err, errlen)) return NULL;
  if (cfg->camera.depth != VLFF_DEPTH_STREAM) {
    snprintf(err, errlen, "key 'camera.depth': a range camera's pipeline needs camera.depth: stream");
    return NULL;
  }
  struct vlff_cfg_camera d;
  vlff_depth_camera_config(cfg, &d);
  return pipe_create(&d, NULL, cfg->source.pose_tolerance_s, true, err, errlen);
}

void vlff_pipe_free(struct vlff_pipe *p) {
  if (!p) return;
  vlff_cv_undistort_free(p->und);
  vlff_cv_stereo_free(p->stereo);
  free(p->scratch);
  free(p->depth_scratch);
  free(p);
}

const struct vlff_pipe_stats *vlff_pipe_get_stats(const struct vlff_pipe *p) { return &p->st; }

void vlff_pipe_set_stamps(struct vlff_pipe *p, struct vlff_stamps *q, uint64_t window_ns) {
  p->stamps = q;
  p->stamp_window_ns = window_ns;
}
vlff_pix_t vlff_pipe_pix(const struct vlff_pipe *p) { return p->pix; }

/* A frame dropped: counted, and logged so that a broken camera failing
 * every frame still leaves the log readable (vlff_warn_limited). */
static void drop(struct vlff_pipe *p, uint64_t *counter, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
static void drop(struct vlff_pipe *p, uint64_t *counter, const char *fmt, ...) {
  (*counter)++;
  char msg[512];
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(msg, sizeof msg, fmt, ap);
  va_end(ap);
  vlff_warn_limited(&p->drops_logged, TAG, "frame dropped: %s", msg);
}

/* (Re)build size-dependent state; w,h is the output (per-eye) size. */
static int prepare(struct vlff_pipe *p, int raw_w, int w, int h, char *err, size_t errlen) {
  if (p->w == w && p->h == h) return 0;
  vlff_cv_undistort_free(p->und);
  vlff_cv_stereo_free(p->stereo);
  p->und = NULL;
  p->stereo = NULL;
  free(p->scratch);
  free(p->depth_scratch);
  p->w = p->h = 0;
  size_t n = (size_t)raw_w * h;
  p->scratch = malloc(n * 3);
  p->depth_scratch = malloc((size_t)w * h * sizeof(float));
  if (!p->scratch || !p->depth_scratch) {
    snprintf(err, errlen, "out of memory for %dx%d scratch images", raw_w, h);
    return -1;
  }
  if (p->have_calib && p->calib.width && (p->calib.width != w || p->calib.height != h)) {
    snprintf(err, errlen, "key 'camera.calibration': calibrated for %dx%d, camera delivers %dx%d",
             p->calib.width, p->calib.height, w, h);
    return -1;
  }
  if (p->cam.depth == VLFF_DEPTH_STEREO) {
    p->stereo = vlff_cv_stereo_new(&p->calib, w, h, p->cam.stereo_disparities, err, errlen);
    if (!p->stereo) return -1;
    double b;
    vlff_cv_stereo_geometry(p->stereo, p->k, &b);
    if (p->cam.stereo_baseline_m > 0 && fabs(b - p->cam.stereo_baseline_m) > 0.01 * b)
      VLFF_WARN(TAG, "camera.stereo_baseline_m %.4f m disagrees with the calibration's %.4f m; using the calibration",
                p->cam.stereo_baseline_m, b);
  } else if (p->undistort) {
    if (!any_nonzero(p->k, 4)) {
      snprintf(err, errlen, "key 'camera.distortion': undistortion needs intrinsics");
      return -1;
    }
    p->und = vlff_cv_undistort_new(w, h, p->k, p->dist, err, errlen);
    if (!p->und) return -1;
  }
  p->w = w;
  p->h = h;
  return 0;
}

/* Range counts -> depth plane. 0 counts stays 0 (invalid); a value that
 * does not fit uint16 millimetres is invalid too rather than clamped. */
static void range_to_depth(const struct vlff_pipe *p, const uint16_t *src, size_t sstride, void *dst,
                           size_t dstride, int w, int h) {
  double scale = p->cam.depth_scale_m;
  for (int y = 0; y < h; y++) {
    const uint16_t *s = (const uint16_t *)((const char *)src + (size_t)y * sstride);
    if (p->cam.depth_unit == VLFF_DEPTH_UNIT_MM) {
      uint16_t *d = (uint16_t *)((char *)dst + (size_t)y * dstride);
      for (int x = 0; x < w; x++) {
        double mm = s[x] * scale * 1000.0 + 0.5;
        d[x] = mm < 65535.5 ? (uint16_t)mm : 0;
      }
    } else {
      float *d = (float *)((char *)dst + (size_t)y * dstride);
      for (int x = 0; x < w; x++) d[x] = (float)(s[x] * scale);
    }
  }
}

int vlff_pipe_push(struct vlff_pipe *p, const struct vlff_raw_frame *raw, struct vlff_sink *sink,
                   const struct vlff_pose_source *poses) {
  char err[512];
  if (raw->pix != p->pix) {
    drop(p, &p->st.dropped_format, "camera sent %s, configured %s", vlff_pix_name(raw->pix),
         vlff_pix_name(p->pix));
    return -1;
  }
  size_t bpp = vlff_pix_bytes(raw->pix);
  if (raw->width <= 0 || raw->height <= 0 || raw->stride < (size_t)raw->width * bpp) {
    drop(p, &p->st.dropped_format, "bad geometry %dx%d stride %zu", raw->width, raw->height, raw->stride);
    return -1;
  }
  if (!raw->data || raw->size < raw->stride * (size_t)(raw->height - 1) + (size_t)raw->width * bpp) {
    drop(p, &p->st.dropped_short, "buffer of %zu bytes is short for %dx%d %s", raw->size, raw->width,
         raw->height, vlff_pix_name(raw->pix));
    return -1;
  }
  bool stereo = p->cam.depth == VLFF_DEPTH_STEREO;
  if (stereo && raw->width % 2) {
    drop(p, &p->st.dropped_format, "stereo pair width %d is odd", raw->width);
    return -1;
  }
  int w = stereo ? raw->width / 2 : raw->width, h = raw->height;
  if (prepare(p, raw->width, w, h, err, sizeof err)) {
    drop(p, &p->st.dropped_convert, "%s", err);
    return -1;
  }

  /* A range camera's frame is depth only; the colour camera of a pair
   * sends colour only (the pairing adds the registered depth); a stereo
   * pair computes both. */
  struct vlff_sink_frame f = {.width = w, .height = h};
  f.color_format = p->range ? VLFF_PIX_NONE : VLFF_PIX_RGB8;
  if (p->range || p->cam.depth == VLFF_DEPTH_STEREO)
    f.depth_format = p->cam.depth_unit == VLFF_DEPTH_UNIT_MM ? VLFF_DEPTH_FMT_U16_MM : VLFF_DEPTH_FMT_F32_M;
  if (sink->reserve(sink, &f, err, sizeof err)) {
    drop(p, &p->st.dropped_sink, "%s", err);
    return -1;
  }

  int rc = 0;
  if (p->range) {
    range_to_depth(p, raw->data, raw->stride, f.depth, f.depth_stride, w, h);
  } else if (stereo) {
    size_t ss = (size_t)raw->width * 3;
    rc = vlff_cv_to_rgb(raw->data, raw->stride, raw->width, h, raw->pix, p->scratch, ss, err, sizeof err);
    bool f32 = f.depth_format == VLFF_DEPTH_FMT_F32_M;
    float *dd = f32 ? f.depth : p->depth_scratch;
    size_t ds = f32 ? f.depth_stride : (size_t)w * sizeof(float);
    if (!rc)
      rc = vlff_cv_stereo_compute(p->stereo, p->scratch, ss, p->scratch + (size_t)w * 3, ss, f.color,
                                  f.color_stride, dd, ds, err, sizeof err);
    if (!rc && !f32)
      for (int y = 0; y < h; y++) {
        uint16_t *o = (uint16_t *)((char *)f.depth + (size_t)y * f.depth_stride);
        const float *s = p->depth_scratch + (size_t)y * w;
        for (int x = 0; x < w; x++) {
          double mm = s[x] * 1000.0 + 0.5;
          o[x] = s[x] > 0 && mm < 65535.5 ? (uint16_t)mm : 0;
        }
      }
  } else if (p->und) {
    size_t ss = (size_t)w * 3;
    rc = vlff_cv_to_rgb(raw->data, raw->stride, w, h, raw->pix, p->scratch, ss, err, sizeof err);
    if (!rc)
      rc = vlff_cv_undistort_apply(p->und, p->scratch, ss, f.color, f.color_stride, 3, 1, err, sizeof err);
  } else {
    rc = vlff_cv_to_rgb(raw->data, raw->stride, w, h, raw->pix, f.color, f.color_stride, err, sizeof err);
  }
  if (rc) {
    sink->abort(sink, &f);
    drop(p, &p->st.dropped_convert, "%s", err);
    return -1;
  }

  f.device_frame_id = raw->device_frame_id;
  f.device_ns = raw->device_ns;
  f.host_ns = raw->host_ns;
  if (p->stamps) {
    uint64_t t = vlff_stamps_match(p->stamps, raw->host_ns, p->stamp_window_ns);
    if (t) {
      f.host_ns = t;
      f.trigger_stamped = true;
      p->st.trigger_stamped++;
    }
  }
  f.sensor_id = (uint32_t)p->cam.sensor_id;
  memcpy(f.intrinsics, p->k, sizeof f.intrinsics);
  f.pose_valid = false;
  if (poses && poses->lookup &&
      poses->lookup(poses->ctx, f.host_ns, p->pose_tolerance_s, f.pose, &f.pose_ns,
                    &f.pose_untrusted) == 0) {
    f.pose_valid = true;
    if (f.pose_untrusted) p->st.no_pose++;
  } else {
    p->st.no_pose++;
    memset(f.pose, 0, sizeof f.pose);
    f.pose_ns = 0;
  }
  if (sink->commit(sink, &f)) {
    drop(p, &p->st.dropped_sink, "commit refused");
    return -1;
  }
  p->st.committed++;
  return 0;
}
