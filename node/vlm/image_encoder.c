/*
 * Image encoder: preprocessing in C, inference through the DNN shim, and a
 * worker thread so the keyframe path never waits for a network.
 *
 * The worker keeps two small rings under one mutex: pending frames (copied
 * in by submit, newest wins when full) and finished results (oldest first).
 * Inference runs with the mutex released, so submit and poll only ever wait
 * for a memcpy.
 */
#include "image_encoder.h"
#include "bounds.h" /* VLFF_FEATURE_MAX_ABS */

#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "dnn_shim.h"
#include "field.h"
#include "files.h"
#include "log.h"
#include "mem.h"

struct vlff_image_encoder {
  struct vlff_dnn *net;
  char path[VLFF_CFG_PATH];
  int in_w, in_h;
  float mean[3], inv_std[3];
  bool bgr, normalize, cuda;
  int dim, out_h, out_w;
  uint8_t *resized;  /* in_w * in_h * 3 */
  float *blob;       /* 3 * in_h * in_w */
};


static int infer(struct vlff_image_encoder *e, const uint8_t *rgb, int width, int height, size_t stride,
                 struct vlff_tensor *t, char *err, size_t errlen) {
  const uint8_t *src = rgb;
  uint8_t *packed = NULL;
  if (stride != (size_t)width * 3) { /* the shim takes packed rows */
    packed = malloc((size_t)width * height * 3);
    if (!packed) {
      vlff_errf(err, errlen, "%s: out of memory", e->path);
      return -1;
    }
    for (int y = 0; y < height; y++) memcpy(packed + (size_t)y * width * 3, rgb + (size_t)y * stride, (size_t)width * 3);
    src = packed;
  }
  int rc = 0;
  if (width == e->in_w && height == e->in_h) memcpy(e->resized, src, (size_t)width * height * 3);
  else rc = vlff_dnn_resize(src, width, height, 3, e->resized, e->in_w, e->in_h, err, errlen);
  free(packed);
  if (rc) return -1;
  size_t plane = (size_t)e->in_w * e->in_h;
  for (int c = 0; c < 3; c++) {
    int srcc = e->bgr ? 2 - c : c;
    float m = e->mean[srcc], is = e->inv_std[srcc];
    float *dst = e->blob + (size_t)c * plane;
    for (size_t i = 0; i < plane; i++) dst[i] = ((float)e->resized[i * 3 + srcc] * (1.0f / 255.0f) - m) * is;
  }
  int shape[4] = {1, 3, e->in_h, e->in_w};
  int n = vlff_dnn_run(e->net, e->blob, shape, 4, t, 1, err, errlen);
  return n == 1 ? 0 : -1;
}

struct vlff_image_encoder *vlff_image_encoder_open(const struct vlff_cfg_vlm *vlm, int feature_dim, char *err,
                                                   size_t errlen) {
  const char *path = vlm->image_model;
  if (!path[0]) {
    vlff_errf(err, errlen, "vlm.image_model: no image model configured");
    return NULL;
  }
  struct vlff_image_encoder *e = calloc(1, sizeof *e);
  if (!e) {
    vlff_errf(err, errlen, "%s: out of memory", path);
    return NULL;
  }
  snprintf(e->path, sizeof e->path, "%s", path);
  e->in_w = vlm->input_width;
  e->in_h = vlm->input_height;
  for (int c = 0; c < 3; c++) {
    e->mean[c] = (float)vlm->mean[c];
    e->inv_std[c] = (float)(1.0 / vlm->std[c]);
  }
  e->bgr = vlm->bgr;
  e->normalize = vlm->normalize;
  e->resized = malloc((size_t)e->in_w * e->in_h * 3);
  e->blob = malloc((size_t)e->in_w * e->in_h * 3 * sizeof *e->blob);
  if (!e->resized || !e->blob) {
    vlff_errf(err, errlen, "%s: out of memory", path);
    goto fail;
  }
  if (vlff_check_regular(path, err, errlen)) goto fail;
  e->net = vlff_dnn_open(path, vlm->cuda, &e->cuda, err, errlen);
  if (!e->net) goto fail;
  if (vlm->cuda && !e->cuda) VLFF_WARN("vlm", "%s: vlm.cuda set but OpenCV has no CUDA device; running on the CPU", path);

  /* Probe: a mid-grey frame must give [1, D, h, w] finite features. */
  memset(e->resized, 128, (size_t)e->in_w * e->in_h * 3);
  struct vlff_tensor t;
  char why[384];
  if (infer(e, e->resized, e->in_w, e->in_h, (size_t)e->in_w * 3, &t, why, sizeof why)) {
    vlff_errf(err, errlen, "%s: probe inference at %dx%d (vlm.input_width/height) failed: %s", path, e->in_w, e->in_h,
            why);
    goto fail;
  }
  if (t.ndim != 4 || t.shape[0] != 1 || t.shape[2] < 1 || t.shape[3] < 1) {
    char s[96] = "";
    for (int i = 0, o = 0; i < t.ndim && o < 80; i++) o += snprintf(s + o, sizeof s - (size_t)o, "%s%d", i ? "," : "", t.shape[i]);
    vlff_errf(err, errlen, "%s: output shape [%s], expected [1,D,h,w] dense features", path, s);
    goto fail;
  }
  if (t.shape[1] != feature_dim) {
    vlff_errf(err, errlen, "%s: features have D=%d, but field.feature_dim is %d", path, t.shape[1],
            feature_dim);
    goto fail;
  }
  for (size_t i = 0; i < t.count; i++)
    if (!isfinite(t.data[i])) {
      vlff_errf(err, errlen, "%s: probe inference gave non-finite features (corrupt weights?)", path);
      goto fail;
    }
  e->dim = t.shape[1];
  e->out_h = t.shape[2];
  e->out_w = t.shape[3];
  VLFF_INFO("vlm", "%s: %dx%d -> [%d,%d,%d] features on %s", path, e->in_w, e->in_h, e->dim, e->out_h, e->out_w,
            e->cuda ? "CUDA" : "CPU");
  return e;
fail:
  vlff_image_encoder_close(e);
  return NULL;
}

void vlff_image_encoder_close(struct vlff_image_encoder *e) {
  if (!e) return;
  vlff_dnn_close(e->net);
  free(e->resized);
  free(e->blob);
  free(e);
}

void vlff_image_encoder_shape(const struct vlff_image_encoder *e, int *dim, int *height, int *width) {
  if (dim) *dim = e->dim;
  if (height) *height = e->out_h;
  if (width) *width = e->out_w;
}

int vlff_image_encoder_run(struct vlff_image_encoder *e, const uint8_t *rgb, int width, int height, size_t stride,
                           uint16_t *out, char *err, size_t errlen) {
  if (!e || !rgb || !out || width < 1 || height < 1 || width > 16384 || height > 16384 || stride < (size_t)width * 3) {
    vlff_errf(err, errlen, "image encoder: invalid frame %dx%d (stride %zu)", width, height, stride);
    return -1;
  }
  struct vlff_tensor t;
  if (infer(e, rgb, width, height, stride, &t, err, errlen)) return -1;
  if (t.ndim != 4 || t.shape[1] != e->dim || t.shape[2] != e->out_h || t.shape[3] != e->out_w) {
    vlff_errf(err, errlen, "%s: output shape changed between frames", e->path);
    return -1;
  }
  size_t hw = (size_t)e->out_h * e->out_w;
  const float *f = t.data;
  for (size_t p = 0; p < hw; p++) {
    double ss = 0;
    for (int d = 0; d < e->dim; d++) {
      float v = f[(size_t)d * hw + p];
      if (!isfinite(v)) {
        vlff_errf(err, errlen, "%s: non-finite feature at pixel %zu, channel %d", e->path, p, d);
        return -1;
      }
      ss += (double)v * v;
    }
    float s = (e->normalize && ss > 0) ? (float)(1.0 / sqrt(ss)) : 1.0f;
    uint16_t *o = out + p * (size_t)e->dim;
    for (int d = 0; d < e->dim; d++) {
      const float v = f[(size_t)d * hw + p] * s;
      if (!(fabsf(v) <= VLFF_FEATURE_MAX_ABS)) { /* the feature ring's bound */
        vlff_errf(err, errlen, "%s: feature %g at pixel %zu, channel %d, beyond +-%g", e->path, (double)v, p, d,
                  VLFF_FEATURE_MAX_ABS);
        return -1;
      }
      o[d] = vlff_f32_to_f16(v);
    }
  }
  return 0;
}

/* ---- worker ------------------------------------------------------------- */

struct pending {
  uint64_t id;
  int width, height;
  uint8_t *rgb; /* capacity cap_bytes */
  size_t cap_bytes;
};

struct result {
  uint64_t id;
  int ok;
  char err[160];
  uint16_t *feat;
};

struct vlff_image_worker {
  struct vlff_image_encoder *enc;
  pthread_t thread;
  pthread_mutex_t mu;
  pthread_cond_t cv;
  bool stop;
  int depth;
  struct pending *frames; /* ring of depth */
  int f_head, f_count;
  struct result *results; /* ring of depth */
  int r_head, r_count;
  size_t feat_count;
  struct pending work;    /* owned by the thread while encoding */
  uint16_t *work_feat;
  struct vlff_image_worker_stats st;
};

static void *worker_main(void *arg) {
  struct vlff_image_worker *w = arg;
  pthread_mutex_lock(&w->mu);
  for (;;) {
    while (!w->stop && !w->f_count) pthread_cond_wait(&w->cv, &w->mu);
    if (w->stop) break;
    /* Swap buffers with the oldest pending slot: no copy under the lock. */
    struct pending tmp = w->frames[w->f_head];
    w->frames[w->f_head] = w->work;
    w->work = tmp;
    w->f_head = (w->f_head + 1) % w->depth;
    w->f_count--;
    pthread_mutex_unlock(&w->mu);

    char err[160] = "";
    int rc = vlff_image_encoder_run(w->enc, w->work.rgb, w->work.width, w->work.height, (size_t)w->work.width * 3,
                                    w->work_feat, err, sizeof err);
    pthread_mutex_lock(&w->mu);
    if (w->r_count == w->depth) { /* nobody polled: the oldest result goes */
      w->r_head = (w->r_head + 1) % w->depth;
      w->r_count--;
      w->st.dropped_results++;
    }
    struct result *r = &w->results[(w->r_head + w->r_count) % w->depth];
    uint16_t *t = r->feat;
    r->feat = w->work_feat;
    w->work_feat = t;
    r->id = w->work.id;
    r->ok = rc == 0;
    snprintf(r->err, sizeof r->err, "%s", err);
    w->r_count++;
    if (rc == 0) w->st.encoded++;
    else w->st.failed++;
  }
  pthread_mutex_unlock(&w->mu);
  return NULL;
}

struct vlff_image_worker *vlff_image_worker_start(struct vlff_image_encoder *enc, int depth, char *err,
                                                  size_t errlen) {
  if (!enc || depth < 1 || depth > 64) {
    vlff_errf(err, errlen, "image worker: depth %d outside 1..64", depth);
    vlff_image_encoder_close(enc);
    return NULL;
  }
  struct vlff_image_worker *w = calloc(1, sizeof *w);
  if (!w) goto oom;
  w->enc = enc;
  w->depth = depth;
  w->feat_count = (size_t)enc->dim * enc->out_h * enc->out_w;
  w->frames = calloc((size_t)depth, sizeof *w->frames);
  w->results = calloc((size_t)depth, sizeof *w->results);
  w->work_feat = malloc(w->feat_count * sizeof *w->work_feat);
  if (!w->frames || !w->results || !w->work_feat) goto oom;
  for (int i = 0; i < depth; i++)
    if (!(w->results[i].feat = malloc(w->feat_count * sizeof(uint16_t)))) goto oom;
  pthread_mutex_init(&w->mu, NULL);
  pthread_cond_init(&w->cv, NULL);
  if (pthread_create(&w->thread, NULL, worker_main, w)) {
    vlff_errf(err, errlen, "image worker: cannot start thread");
    pthread_mutex_destroy(&w->mu);
    pthread_cond_destroy(&w->cv);
    goto free_all;
  }
  return w;
oom:
  vlff_errf(err, errlen, "image worker: out of memory");
  if (!w) {
    vlff_image_encoder_close(enc);
    return NULL;
  }
free_all:
  for (int i = 0; w->results && i < depth; i++) free(w->results[i].feat);
  VLFF_FREE_ALL(w->results, w->frames, w->work_feat, w);
  vlff_image_encoder_close(enc);
  return NULL;
}

void vlff_image_worker_stop(struct vlff_image_worker *w) {
  if (!w) return;
  pthread_mutex_lock(&w->mu);
  w->stop = true;
  pthread_cond_signal(&w->cv);
  pthread_mutex_unlock(&w->mu);
  pthread_join(w->thread, NULL);
  pthread_mutex_destroy(&w->mu);
  pthread_cond_destroy(&w->cv);
  for (int i = 0; i < w->depth; i++) {
    free(w->frames[i].rgb);
    free(w->results[i].feat);
  }
  VLFF_FREE_ALL(w->work.rgb, w->work_feat, w->frames, w->results);
  vlff_image_encoder_close(w->enc);
  free(w);
}

int vlff_image_worker_submit(struct vlff_image_worker *w, uint64_t frame_id, const uint8_t *rgb, int width,
                             int height, size_t stride) {
  if (!w || !rgb || width < 1 || height < 1 || width > 16384 || height > 16384 || stride < (size_t)width * 3)
    return -1;
  size_t bytes = (size_t)width * height * 3;
  pthread_mutex_lock(&w->mu);
  if (w->f_count == w->depth) {
    w->f_head = (w->f_head + 1) % w->depth;
    w->f_count--;
    w->st.dropped_frames++;
  }
  struct pending *p = &w->frames[(w->f_head + w->f_count) % w->depth];
  if (p->cap_bytes < bytes) {
    uint8_t *nb = realloc(p->rgb, bytes);
    if (!nb) {
      pthread_mutex_unlock(&w->mu);
      return -1;
    }
    p->rgb = nb;
    p->cap_bytes = bytes;
  }
  for (int y = 0; y < height; y++) memcpy(p->rgb + (size_t)y * width * 3, rgb + (size_t)y * stride, (size_t)width * 3);
  p->id = frame_id;
  p->width = width;
  p->height = height;
  w->f_count++;
  w->st.submitted++;
  pthread_cond_signal(&w->cv);
  pthread_mutex_unlock(&w->mu);
  return 0;
}

int vlff_image_worker_poll(struct vlff_image_worker *w, uint64_t *frame_id, uint16_t *out, char *err,
                           size_t errlen) {
  pthread_mutex_lock(&w->mu);
  if (!w->r_count) {
    pthread_mutex_unlock(&w->mu);
    return 0;
  }
  struct result *r = &w->results[w->r_head];
  *frame_id = r->id;
  int rc = r->ok ? 1 : -1;
  if (r->ok) memcpy(out, r->feat, w->feat_count * sizeof *out);
  else vlff_errf(err, errlen, "%s", r->err);
  w->r_head = (w->r_head + 1) % w->depth;
  w->r_count--;
  pthread_mutex_unlock(&w->mu);
  return rc;
}

void vlff_image_worker_stats(struct vlff_image_worker *w, struct vlff_image_worker_stats *st) {
  pthread_mutex_lock(&w->mu);
  *st = w->st;
  pthread_mutex_unlock(&w->mu);
}
