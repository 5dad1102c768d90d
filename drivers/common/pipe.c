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
#include "stamps.h"
#include "log.h"

#define TAG "pipe"

struct vlff_pipe {
  struct vlff_config cfg;
  vlff_pix_t pix;
  double k[4];                  /* intrinsics from config or calibration */
  double dist[5];
  bool undistort;
  struct vlff_cv_calib calib;
  bool have_calib;
  /* built for the first frame's size, rebuilt if it changes */
  int w, h;
  struct vlff_cv_undistort *und;
  struct vlff_cv_stereo *stereo;
  uint8_t *scratch;             /* RGB8 of the whole raw image */
  float *depth_scratch;
  uint16_t *u16_scratch;
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

int vlff_camcfg_check(const struct vlff_config *cfg, const char *file, char *err, size_t errlen) {
  const __typeof__(cfg->camera) *c = &cfg->camera;
  if (c->kind != VLFF_CAM_ARAVIS && c->kind != VLFF_CAM_LIBCAMERA)
    BAD("camera.kind", "expected aravis or libcamera (vlff-camd drives real cameras), got sim");
  vlff_pix_t pix = vlff_pix_from_name(c->pixel_format);
  if (pix == VLFF_PIX_INVALID)
    BAD("camera.pixel_format", "expected one of %s, got '%s'", vlff_pix_names(), c->pixel_format);
  if (c->depth == VLFF_DEPTH_STREAM && pix != VLFF_PIX_MONO16)
    BAD("camera.depth", "'stream' needs camera.pixel_format Mono16 (a range image), got '%s'",
        c->pixel_format);
  if (pix == VLFF_PIX_MONO16 && c->depth != VLFF_DEPTH_STREAM)
    BAD("camera.pixel_format", "Mono16 is read as a range image: expected camera.depth: stream");
  if (c->depth == VLFF_DEPTH_STEREO) {
    if (!c->calibration[0])
      BAD("camera.calibration",
          "depth: stereo needs an OpenCV stereo calibration YAML (M1 D1 M2 D2 R T), got none");
    if (c->width % 2)
      BAD("camera.width", "a side-by-side stereo pair needs an even width, got %d", c->width);
  }
  if (c->width && c->width > 2 * cfg->shm.max_width)
    BAD("camera.width", "expected at most shm.max_width (%d), got %d", cfg->shm.max_width, c->width);
  if (c->depth != VLFF_DEPTH_STEREO && c->width > cfg->shm.max_width)
    BAD("camera.width", "expected at most shm.max_width (%d), got %d", cfg->shm.max_width, c->width);
  if (c->height > cfg->shm.max_height)
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

struct vlff_pipe *vlff_pipe_new(const struct vlff_config *cfg, char *err, size_t errlen) {
  if (vlff_camcfg_check(cfg, "config", err, errlen)) return NULL;
  struct vlff_pipe *p = calloc(1, sizeof *p);
  if (!p) {
    snprintf(err, errlen, "out of memory");
    return NULL;
  }
  p->cfg = *cfg;
  p->pix = vlff_pix_from_name(cfg->camera.pixel_format);
  memcpy(p->k, cfg->camera.intrinsics, sizeof p->k);
  memcpy(p->dist, cfg->camera.distortion, sizeof p->dist);
  if (cfg->camera.calibration[0]) {
    char e[512];
    if (vlff_cv_calib_load(cfg->camera.calibration, &p->calib, e, sizeof e)) {
      snprintf(err, errlen, "key 'camera.calibration': %s", e);
      free(p);
      return NULL;
    }
    p->have_calib = true;
    if (cfg->camera.depth == VLFF_DEPTH_STEREO && !p->calib.has_stereo) {
      snprintf(err, errlen,
               "key 'camera.calibration': depth: stereo needs stereo keys M1 D1 M2 D2 R T in %s",
               cfg->camera.calibration);
      free(p);
      return NULL;
    }
    /* The config's own values win: they are the deliberate override. */
    if (p->calib.has_mono && !any_nonzero(p->k, 4)) {
      p->k[0] = p->calib.k[0], p->k[1] = p->calib.k[4], p->k[2] = p->calib.k[2], p->k[3] = p->calib.k[5];
      if (!any_nonzero(p->dist, 5)) memcpy(p->dist, p->calib.dist, sizeof p->dist);
    }
  }
  p->undistort = cfg->camera.depth != VLFF_DEPTH_STEREO && any_nonzero(p->dist, 5);
  return p;
}

void vlff_pipe_free(struct vlff_pipe *p) {
  if (!p) return;
  vlff_cv_undistort_free(p->und);
  vlff_cv_stereo_free(p->stereo);
  free(p->scratch);
  free(p->depth_scratch);
  free(p->u16_scratch);
  free(p);
}

const struct vlff_pipe_stats *vlff_pipe_get_stats(const struct vlff_pipe *p) { return &p->st; }

void vlff_pipe_set_stamps(struct vlff_pipe *p, struct vlff_stamps *q, uint64_t window_ns) {
  p->stamps = q;
  p->stamp_window_ns = window_ns;
}
vlff_pix_t vlff_pipe_pix(const struct vlff_pipe *p) { return p->pix; }

static void drop(struct vlff_pipe *p, uint64_t *counter, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));
static void drop(struct vlff_pipe *p, uint64_t *counter, const char *fmt, ...) {
  (*counter)++;
  /* A broken camera can fail every frame: log the first few, then every
   * 1000th, so the log stays readable and the counters tell the rest. */
  if (p->drops_logged++ < 5 || p->drops_logged % 1000 == 0) {
    char msg[512];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(msg, sizeof msg, fmt, ap);
    va_end(ap);
    VLFF_WARN(TAG, "frame dropped: %s", msg);
  }
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
  free(p->u16_scratch);
  p->w = p->h = 0;
  size_t n = (size_t)raw_w * h;
  p->scratch = malloc(n * 3);
  p->depth_scratch = malloc((size_t)w * h * sizeof(float));
  p->u16_scratch = malloc((size_t)w * h * sizeof(uint16_t));
  if (!p->scratch || !p->depth_scratch || !p->u16_scratch) {
    snprintf(err, errlen, "out of memory for %dx%d scratch images", raw_w, h);
    return -1;
  }
  if (p->have_calib && p->calib.width && (p->calib.width != w || p->calib.height != h)) {
    snprintf(err, errlen, "key 'camera.calibration': calibrated for %dx%d, camera delivers %dx%d",
             p->calib.width, p->calib.height, w, h);
    return -1;
  }
  if (p->cfg.camera.depth == VLFF_DEPTH_STEREO) {
    p->stereo = vlff_cv_stereo_new(&p->calib, w, h, p->cfg.camera.stereo_disparities, err, errlen);
    if (!p->stereo) return -1;
    double b;
    vlff_cv_stereo_geometry(p->stereo, p->k, &b);
    if (p->cfg.camera.stereo_baseline_m > 0 && fabs(b - p->cfg.camera.stereo_baseline_m) > 0.01 * b)
      VLFF_WARN(TAG, "camera.stereo_baseline_m %.4f m disagrees with the calibration's %.4f m; using the calibration",
                p->cfg.camera.stereo_baseline_m, b);
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
  double scale = p->cfg.camera.depth_scale_m;
  for (int y = 0; y < h; y++) {
    const uint16_t *s = (const uint16_t *)((const char *)src + (size_t)y * sstride);
    if (p->cfg.camera.depth_unit == VLFF_DEPTH_UNIT_MM) {
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
  bool stereo = p->cfg.camera.depth == VLFF_DEPTH_STEREO;
  if (stereo && raw->width % 2) {
    drop(p, &p->st.dropped_format, "stereo pair width %d is odd", raw->width);
    return -1;
  }
  int w = stereo ? raw->width / 2 : raw->width, h = raw->height;
  if (prepare(p, raw->width, w, h, err, sizeof err)) {
    drop(p, &p->st.dropped_convert, "%s", err);
    return -1;
  }

  struct vlff_sink_frame f = {.width = w, .height = h};
  f.color_format = p->cfg.camera.depth == VLFF_DEPTH_STREAM ? VLFF_PIX_MONO16 : VLFF_PIX_RGB8;
  if (p->cfg.camera.depth != VLFF_DEPTH_NONE)
    f.depth_format = p->cfg.camera.depth_unit == VLFF_DEPTH_UNIT_MM ? VLFF_DEPTH_FMT_U16_MM : VLFF_DEPTH_FMT_F32_M;
  if (sink->reserve(sink, &f, err, sizeof err)) {
    drop(p, &p->st.dropped_sink, "%s", err);
    return -1;
  }

  int rc = 0;
  if (p->cfg.camera.depth == VLFF_DEPTH_STREAM) {
    for (int y = 0; y < h; y++)
      memcpy(f.color + (size_t)y * f.color_stride, (const char *)raw->data + (size_t)y * raw->stride, (size_t)w * 2);
    if (p->und) {
      rc = vlff_cv_undistort_apply(p->und, raw->data, raw->stride, p->u16_scratch, (size_t)w * 2, 1, 2, err,
                                   sizeof err);
      if (!rc) range_to_depth(p, p->u16_scratch, (size_t)w * 2, f.depth, f.depth_stride, w, h);
    } else {
      range_to_depth(p, raw->data, raw->stride, f.depth, f.depth_stride, w, h);
    }
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
      p->st.trigger_stamped++;
    }
  }
  f.sensor_id = (uint32_t)p->cfg.camera.sensor_id;
  memcpy(f.intrinsics, p->k, sizeof f.intrinsics);
  f.pose_valid = false;
  if (poses && poses->lookup &&
      poses->lookup(poses->ctx, f.host_ns, p->cfg.source.pose_tolerance_s, f.pose, &f.pose_ns,
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
