/*
 * A frame's stages on the ingest thread: frame_checks (the record, its size,
 * colour format and intrinsics), frame_pose (from the frame or the pose
 * ring), frame_admit (depth, keyframe selection, downscaling, features or a
 * place in the pending list), the frame held for its pose, and the refusal
 * log that counts and explains every frame refused.
 *
 * Thread: ingest only (called from ingest_main, ingest.c).
 * State: the struct ingest passed in (refusal log, selector, pose ring,
 * held frame, pending list).
 * Locks: slock for the refusal counts and the last good pose time, qlock
 * through queue_push (short, never across work; node_internal.h).
 */
#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "bounds.h"
#include "clock.h"
#include "feature_join.h"
#include "log.h"
#include "mem.h"
#include "node_internal.h"
#include "select.h"
#include "vlff/escape.h"
#include "vlff/shm.h"

/* Area-average downscale by an integer factor, or nearest for any other. */
static void resample_rgb(const uint8_t *src, int sw, int sh, size_t sstride, int ch, uint8_t *dst,
                         int dw, int dh) {
  int fx = sw / dw, fy = sh / dh;
  bool box = fx * dw == sw && fy * dh == sh;
  for (int y = 0; y < dh; y++)
    for (int x = 0; x < dw; x++) {
      unsigned acc[3] = {0, 0, 0};
      int cnt = 0;
      int y0 = box ? y * fy : (int)((y + 0.5) * sh / dh), x0 = box ? x * fx : (int)((x + 0.5) * sw / dw);
      int ny = box ? fy : 1, nx = box ? fx : 1;
      for (int yy = 0; yy < ny; yy++)
        for (int xx = 0; xx < nx; xx++) {
          const uint8_t *p = src + (size_t)(y0 + yy) * sstride + (size_t)(x0 + xx) * ch;
          for (int c = 0; c < 3; c++) acc[c] += p[ch == 1 ? 0 : c];
          cnt++;
        }
      for (int c = 0; c < 3; c++) dst[((size_t)y * dw + x) * 3 + c] = (uint8_t)(acc[c] / cnt);
    }
}

/* Depth is sampled, never averaged: averaging across an edge invents
 * surfaces floating between foreground and background. */
static size_t resample_depth(const void *src, uint32_t fmt, int sw, int sh, size_t sstride, float *dst,
                             int dw, int dh, float *max) {
  size_t valid = 0;
  for (int y = 0; y < dh; y++)
    for (int x = 0; x < dw; x++) {
      int sy = (int)((y + 0.5) * sh / dh), sx = (int)((x + 0.5) * sw / dw);
      const uint8_t *row = (const uint8_t *)src + (size_t)sy * sstride;
      float d;
      if (fmt == VLFF_PIX_DEPTH_U16_MM) {
        uint16_t mm;
        memcpy(&mm, row + (size_t)sx * 2, 2);
        d = mm * 1e-3f;
      } else {
        memcpy(&d, row + (size_t)sx * 4, 4);
      }
      if (!(d > 0 && d <= VLFF_DEPTH_MAX_M)) d = 0; /* none, NaN, or beyond any sensor (bounds.h) */
      valid += d > 0;
      if (d > *max) *max = d;
      dst[(size_t)y * dw + x] = d;
    }
  return valid;
}

/* ---- refused frames ----------------------------------------------------- */

static const char *const refusal_names[VLFF_REFUSED_COUNT] = {
    [VLFF_REFUSED_NONE] = "none",
    [VLFF_REFUSED_MALFORMED] = "malformed",
    [VLFF_REFUSED_OVERSIZE] = "oversize",
    [VLFF_REFUSED_PIXEL_FORMAT] = "pixel format",
    [VLFF_REFUSED_NO_INTRINSICS] = "no intrinsics",
    [VLFF_REFUSED_BAD_INTRINSICS] = "bad intrinsics",
    [VLFF_REFUSED_NO_POSE] = "no pose",
    [VLFF_REFUSED_BAD_POSE] = "bad pose",
    [VLFF_REFUSED_POSE_RANGE] = "pose out of range",
    [VLFF_REFUSED_NO_DEPTH] = "no depth",
    [VLFF_REFUSED_EMPTY_DEPTH] = "empty depth",
    [VLFF_REFUSED_TOO_SMALL] = "too small",
    [VLFF_REFUSED_NO_FEATURES] = "no features",
    [VLFF_REFUSED_FUTURE_POSE] = "future pose",
    [VLFF_REFUSED_FEATURES_LATE] = "features late",
    [VLFF_REFUSED_FUTURE_FRAME] = "future frame",
};

const char *vlff_refusal_name(int reason) {
  return reason > 0 && reason < VLFF_REFUSED_COUNT ? refusal_names[reason] : "unknown";
}

void refuse(struct vlff_node *n, struct refusal_log *rl, int reason, long long id, const char *fmt, ...) {
  long long total;
  pthread_mutex_lock(&n->slock);
  n->st.frames_invalid++;
  total = ++n->st.refused[reason];
  n->st.last_refusal = reason;
  pthread_mutex_unlock(&n->slock);
  char detail[384];
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(detail, sizeof detail, fmt, ap);
  va_end(ap);
  rl->since[reason]++;
  if (!rl->seen[reason]) {
    rl->seen[reason] = true;
    VLFF_INFO(TAG, "frame %lld refused, %s: %s (further frames refused for this reason are counted in --status "
              "and summarised here every %.0f s)", id, refusal_names[reason], detail, REFUSAL_REPORT_S);
  } else {
    VLFF_DEBUG(TAG, "frame %lld refused, %s: %s (%lld so far)", id, refusal_names[reason], detail, total);
  }
}

void refusal_summary(struct vlff_node *n, struct refusal_log *rl, double now) {
  if (now - rl->last_report_s < REFUSAL_REPORT_S) return;
  char line[768];
  size_t len = 0;
  line[0] = 0;
  long long totals[VLFF_REFUSED_COUNT];
  pthread_mutex_lock(&n->slock);
  memcpy(totals, n->st.refused, sizeof totals);
  pthread_mutex_unlock(&n->slock);
  for (int r = 1; r < VLFF_REFUSED_COUNT; r++) {
    if (!rl->since[r] || len >= sizeof line) continue;
    len += (size_t)snprintf(line + len, sizeof line - len, "%s%s %lld (%lld in all)", len ? ", " : "",
                            refusal_names[r], rl->since[r], totals[r]);
    rl->since[r] = 0;
  }
  if (line[0]) VLFF_INFO(TAG, "frames refused in the last %.0f s: %s", now - rl->last_report_s, line);
  rl->last_report_s = now;
}

/* Why the pose ring gave no pose for a frame stamped t_ns: says what a user
 * can act on (nothing writes poses, clocks apart, the source lags). */
static void no_pose_detail(const struct vlff_config *cfg, struct vlff_ring *poses, int lookup_errno, uint64_t t_ns,
                           bool untrusted, char *why, size_t len) {
  if (!poses) {
    snprintf(why, len, "the frame carries no pose and the pose ring cannot be attached: %s (start vlff-pose or the "
             "SLAM adapter that writes it)", vlff_shm_last_message());
    return;
  }
  if (untrusted) {
    snprintf(why, len, "the pose source flagged the pose at this time untrusted (tracking lost)");
    return;
  }
  struct vlff_pose_rec last;
  if (vlff_ring_read_latest(poses, &last, sizeof last, NULL) != (ssize_t)sizeof last) {
    snprintf(why, len, "the pose ring %s holds no pose yet", cfg->shm.pose_ring);
    return;
  }
  double dt = ((double)last.t_ns - (double)t_ns) * 1e-9;
  if (lookup_errno == EAGAIN)
    snprintf(why, len, "frame stamped %.6f s is newer than the newest pose in %s (%.3f s older): the pose source "
             "lags or stopped", (double)t_ns * 1e-9, cfg->shm.pose_ring, -dt);
  else
    vlff_pose_miss_hint(poses, cfg->shm.pose_ring, t_ns, cfg->source.pose_tolerance_s, why, len);
}

/* Whether a stamp (CLOCK_MONOTONIC ns) lies ahead of the clock by more than
 * pose.future_tolerance_s (0: never), by *ahead_s seconds: frames and poses
 * are stamped when taken, so neither can. */
static bool ahead_of_clock(const struct vlff_config *cfg, uint64_t t_ns, double *ahead_s) {
  *ahead_s = ((double)t_ns - (double)vlff_now_ns()) * 1e-9;
  return cfg->pose.future_tolerance_s > 0 && *ahead_s > cfg->pose.future_tolerance_s;
}

/* Stage 1: the record, its size, its colour format, its intrinsics. */
static bool frame_checks(struct ingest *ig, const void *buf, ssize_t len) {
  struct vlff_node *n = ig->n;
  const struct vlff_config *cfg = ig->cfg;
  const struct vlff_frame_hdr *h = buf;
  long long id = (long long)h->frame_id;
  if (vlff_frame_validate(buf, (size_t)len) != 0) {
    refuse(n, &ig->rl, VLFF_REFUSED_MALFORMED, id, "record of %zd bytes is not a well-formed frame (sizes, formats, "
           "planes, non-finite intrinsics or pose)", len);
    return false;
  }
  /* A frame is stamped when it is taken, before it reaches the ring: one
   * stamped ahead of the clock (beyond pose.future_tolerance_s, the pose
   * stamps' bound) has a wrong clock, and its time would sort it after
   * every frame to come (one such frame stopped keyframe selection). */
  double ahead_s;
  if (ahead_of_clock(cfg, h->t_host_ns, &ahead_s)) {
    refuse(n, &ig->rl, VLFF_REFUSED_FUTURE_FRAME, id, "stamped %.3f s ahead of the clock (pose.future_tolerance_s "
           "%g s): the camera driver's clock or clock offset is wrong", ahead_s, cfg->pose.future_tolerance_s);
    return false;
  }
  const struct vlff_plane *cp = &h->plane[VLFF_PLANE_COLOR];
  if ((int)cp->width > cfg->shm.max_width || (int)cp->height > cfg->shm.max_height) {
    refuse(n, &ig->rl, VLFF_REFUSED_OVERSIZE, id, "%ux%u is larger than shm.max_width x shm.max_height (%dx%d)",
           cp->width, cp->height, cfg->shm.max_width, cfg->shm.max_height);
    return false;
  }
  if (cp->format != VLFF_PIX_RGB8 && cp->format != VLFF_PIX_MONO8) {
    refuse(n, &ig->rl, VLFF_REFUSED_PIXEL_FORMAT, id, "colour plane is %s, expected RGB8 or Mono8",
           vlff_pixfmt_name(cp->format));
    return false;
  }
  char why[384];
  if (!(h->flags & VLFF_FRAME_INTRINSICS_VALID) || !isfinite(h->fx) || !isfinite(h->fy) || !isfinite(h->cx) ||
      !isfinite(h->cy)) {
    refuse(n, &ig->rl, VLFF_REFUSED_NO_INTRINSICS, id, "%s (set camera.intrinsics or camera.calibration)",
           (h->flags & VLFF_FRAME_INTRINSICS_VALID) ? "intrinsics not finite" : "the frame is not flagged with intrinsics");
    return false;
  }
  /* The physical bounds every camera in vlff is held to (bounds.h). */
  if (vlff_intrinsics_plausible((int)cp->width, (int)cp->height, h->fx, h->fy, h->cx, h->cy, why, sizeof why)) {
    refuse(n, &ig->rl, VLFF_REFUSED_BAD_INTRINSICS, id, "%s (millimetres, or another image size's values?)", why);
    return false;
  }
  return true;
}

enum pose_result { POSE_FOUND, POSE_REFUSED, POSE_LATER };

/* Stage 2: the frame's pose, from the frame or the pose ring, checked.
 * POSE_LATER (nothing refused) when may_wait and the frame is newer than
 * every pose: its pose may still come. waited_s > 0 says how long a held
 * frame waited, for the refusal's detail. */
static int frame_pose(struct ingest *ig, const struct vlff_frame_hdr *h, bool may_wait, double waited_s,
                      double pose[16]) {
  struct vlff_node *n = ig->n;
  const struct vlff_config *cfg = ig->cfg;
  long long id = (long long)h->frame_id;
  bool have_pose = false, untrusted = false;
  int lookup_errno = 0;
  char why[384];
  const bool in_frame = (h->flags & VLFF_FRAME_POSE_VALID) && !(h->flags & VLFF_FRAME_POSE_UNTRUSTED);
  if (in_frame) {
    memcpy(pose, h->pose, 16 * sizeof pose[0]);
    have_pose = true;
  } else {
    /* Attached when a frame needs it, not before waiting for the frame:
     * a pose source that starts meanwhile poses that frame already. A
     * failed lookup re-attaches (at most once a second), so a pose
     * source restarted with another ring geometry, which abandons the
     * old segment, is followed. */
    double t_now = vlff_seconds();
    if (!ig->poses || (ig->pose_miss && t_now - ig->pose_reattach_s >= 1.0)) {
      vlff_ring_close(ig->poses);
      ig->poses = attach_input(n, cfg->shm.pose_ring, VLFF_RECORD_POSE);
      ig->pose_reattach_s = t_now;
      ig->pose_miss = false;
    }
    if (ig->poses) {
      struct vlff_pose_rec pr;
      if (vlff_pose_lookup(ig->poses, h->t_host_ns, (uint64_t)(cfg->source.pose_tolerance_s * 1e9), &pr) == 0) {
        untrusted = (pr.flags & VLFF_FRAME_POSE_UNTRUSTED) != 0;
        if (!untrusted) {
          memcpy(pose, pr.pose, 16 * sizeof pose[0]);
          have_pose = true;
        }
      } else {
        lookup_errno = errno;
        ig->pose_miss = true;
      }
    }
  }
  if (!have_pose) {
    if (may_wait && lookup_errno == EAGAIN) return POSE_LATER;
    no_pose_detail(cfg, ig->poses, lookup_errno, h->t_host_ns, untrusted, why, sizeof why);
    if (waited_s > 0)
      refuse(n, &ig->rl, VLFF_REFUSED_NO_POSE, id, "after waiting %.3f s (source.pose_wait_s): %s", waited_s, why);
    else
      refuse(n, &ig->rl, VLFF_REFUSED_NO_POSE, id, "%s", why);
    return POSE_REFUSED;
  }
  /* A pose is computed after its image: one stamped ahead of the clock
   * (beyond pose.future_tolerance_s) says the pose source's clock or offset
   * is wrong, and every frame would take a pose from that much earlier. */
  struct vlff_pose_rec newest;
  uint64_t pose_t = in_frame ? h->pose_t_ns
                    : vlff_ring_read_latest(ig->poses, &newest, sizeof newest, NULL) == (ssize_t)sizeof newest
                        ? newest.t_ns : 0;
  double ahead_s;
  if (ahead_of_clock(cfg, pose_t, &ahead_s)) {
    refuse(n, &ig->rl, VLFF_REFUSED_FUTURE_POSE, id, "%s stamped %.3f s ahead of the clock (pose.future_tolerance_s "
           "%g s): the pose source's clock or clock offset is wrong",
           in_frame ? "the frame's pose is" : "the newest pose in the pose ring is", ahead_s, cfg->pose.future_tolerance_s);
    return POSE_REFUSED;
  }
  if (!vlff_pose_valid(pose)) {
    refuse(n, &ig->rl, VLFF_REFUSED_BAD_POSE, id, "pose is not a rigid transform (NaN, or rotation not orthonormal)");
    return POSE_REFUSED;
  }
  if (vlff_field_pose_plausible(&cfg->field, pose, why, sizeof why)) {
    refuse(n, &ig->rl, VLFF_REFUSED_POSE_RANGE, id, "%s: poses in millimetres or in another world frame?", why);
    return POSE_REFUSED;
  }
  pthread_mutex_lock(&n->slock);
  n->last_pose_ok_s = vlff_seconds();
  pthread_mutex_unlock(&n->slock);
  return POSE_FOUND;
}

/* Stage 3: depth, keyframe selection, the candidate and its features. */
static void frame_admit(struct ingest *ig, const void *buf, const double pose[16], double now) {
  struct vlff_node *n = ig->n;
  const struct vlff_config *cfg = ig->cfg;
  const struct vlff_frame_hdr *h = buf;
  long long id = (long long)h->frame_id;
  const struct vlff_plane *cp = &h->plane[VLFF_PLANE_COLOR];
  const struct vlff_plane *dp = h->nplanes > 1 ? &h->plane[VLFF_PLANE_DEPTH] : NULL;
  if (!dp || (dp->format != VLFF_PIX_DEPTH_U16_MM && dp->format != VLFF_PIX_DEPTH_F32_M) ||
      dp->width != cp->width || dp->height != cp->height) {
    if (!dp)
      refuse(n, &ig->rl, VLFF_REFUSED_NO_DEPTH, id, "the frame has no depth plane (camera.depth: none?)");
    else
      refuse(n, &ig->rl, VLFF_REFUSED_NO_DEPTH, id, "depth plane is %s %ux%u, expected DEPTH_U16_MM or DEPTH_F32_M "
             "of the colour plane's %ux%u", vlff_pixfmt_name(dp->format), dp->width, dp->height, cp->width,
             cp->height);
    return;
  }
  if (!vlff_kf_selector_offer(&ig->sel, (long long)h->t_host_ns, pose)) return;

  int dw = (int)lround(cp->width * cfg->train.image_scale), dh = (int)lround(cp->height * cfg->train.image_scale);
  if (dw < 4 || dh < 4) {
    refuse(n, &ig->rl, VLFF_REFUSED_TOO_SMALL, id, "%ux%u is %dx%d at train.image_scale %g, under 4x4", cp->width,
           cp->height, dw, dh, cfg->train.image_scale);
    return;
  }
  struct candidate *c = calloc(1, sizeof *c);
  if (!c) return;
  c->id = id;
  c->t_host_ns = h->t_host_ns;
  c->rgb = malloc((size_t)dw * dh * 3);
  c->depth = malloc((size_t)dw * dh * sizeof(float));
  if (!c->rgb || !c->depth) {
    candidate_free(c);
    return;
  }
  resample_rgb(vlff_frame_plane(buf, VLFF_PLANE_COLOR), (int)cp->width, (int)cp->height, cp->stride,
               cp->format == VLFF_PIX_RGB8 ? 3 : 1, c->rgb, dw, dh);
  float depth_max = 0;
  size_t valid = resample_depth(vlff_frame_plane(buf, VLFF_PLANE_DEPTH), dp->format, (int)dp->width,
                                (int)dp->height, dp->stride, c->depth, dw, dh, &depth_max);
  if (valid == 0) {
    candidate_free(c);
    refuse(n, &ig->rl, VLFF_REFUSED_EMPTY_DEPTH, id, "the depth plane has no valid pixel (all 0, NaN or beyond %g m)",
           VLFF_DEPTH_MAX_M);
    return;
  }
  /* Poses in millimetres pass any world-sized bound until the robot has
   * gone far, but every step between candidates is then longer than the
   * depth can reach. The next candidate is measured from this one whatever
   * becomes of it, so that a tracker's one jump (a relocalisation, a
   * replayed loop starting over) costs one frame, not all that follow. */
  char why[192];
  bool step_ok = !ig->have_prev || !vlff_pose_step_plausible(ig->prev_c2w, ig->prev_depth_max_m, pose, depth_max,
                                                             why, sizeof why);
  memcpy(ig->prev_c2w, pose, sizeof ig->prev_c2w);
  ig->prev_depth_max_m = depth_max;
  ig->have_prev = true;
  if (!step_ok) {
    candidate_free(c);
    refuse(n, &ig->rl, VLFF_REFUSED_POSE_RANGE, id, "%s: poses in millimetres, or a jump of the tracker?", why);
    return;
  }
  double sx = (double)dw / cp->width, sy = (double)dh / cp->height;
  struct vlff_view *v = &c->view;
  v->width = dw;
  v->height = dh;
  v->rgb = c->rgb;
  v->depth = c->depth;
  v->fx = h->fx * sx;
  v->fy = h->fy * sy;
  v->cx = h->cx * sx;
  v->cy = h->cy * sy;
  memcpy(v->c2w, pose, sizeof v->c2w);

  if (n->hooks.features) {
    const struct vlff_source_hooks *src = &n->hooks;
    char err[256] = "no memory";
    c->features = malloc((size_t)src->feat_width * src->feat_height * cfg->field.feature_dim * sizeof(uint16_t));
    if (!c->features || src->features(src->ctx, id, c->features, err, sizeof err)) {
      candidate_free(c);
      refuse(n, &ig->rl, VLFF_REFUSED_NO_FEATURES, id, "the source's features unavailable: %s", err);
      return;
    }
    v->features = c->features;
    v->feat_width = src->feat_width;
    v->feat_height = src->feat_height;
    v->feature_dim = cfg->field.feature_dim;
    queue_push(n, c);
  } else {
    c->deadline_s = now + cfg->vlm.feature_timeout_s;
    if (ig->npend == PENDING_CAP) {
      STAT_ADD(n, features_timeout, 1);
      refuse(n, &ig->rl, VLFF_REFUSED_FEATURES_LATE, ig->pending[0]->id, "%d newer keyframes wait for their "
             "features: the feature source is slower than the keyframes come", PENDING_CAP);
      candidate_free(ig->pending[0]);
      pending_remove(ig->pending, &ig->npend, 0);
    }
    char jerr[256];
    if (ig->join) vlff_feature_join_add_frame(ig->join, (uint64_t)id, vlff_now_ns(), jerr, sizeof jerr);
#ifdef VLFF_HAVE_VLM
    if (n->image_worker)
      vlff_image_worker_submit(n->image_worker, (uint64_t)id, vlff_frame_plane(buf, VLFF_PLANE_COLOR),
                               (int)cp->width, (int)cp->height, cp->stride);
#endif
    ig->pending[ig->npend++] = c;
  }
}

/* The held frame goes on once its pose is there, or is refused when
 * source.pose_wait_s has passed. */
void ingest_held(struct ingest *ig, double now) {
  if (!ig->holding) return;
  double waited = now - ig->held_since_s;
  double pose[16];
  int r = frame_pose(ig, ig->held, waited < ig->cfg->source.pose_wait_s, waited, pose);
  if (r == POSE_LATER) return;
  ig->holding = false;
  if (r == POSE_FOUND) frame_admit(ig, ig->held, pose, now);
}

/* One record from the ring through the stages. A frame whose pose may
 * still come is held when it would be a keyframe by time and none is held
 * yet; other such frames are not needed as keyframes and pass unrefused. */
void ingest_frame(struct ingest *ig, const void *buf, ssize_t len, double now) {
  ingest_held(ig, now); /* an older frame's pose may have come with this one's */
  if (!frame_checks(ig, buf, len)) return;
  const struct vlff_frame_hdr *h = buf;
  double pose[16];
  int r = frame_pose(ig, h, ig->cfg->source.pose_wait_s > 0, 0, pose);
  if (r == POSE_LATER) {
    if (!ig->holding && vlff_kf_selector_due(&ig->sel, (long long)h->t_host_ns)) {
      memcpy(ig->held, buf, (size_t)len);
      ig->held_len = (size_t)len;
      ig->held_since_s = now;
      ig->holding = true;
    } else {
      VLFF_DEBUG(TAG, "frame %llu skipped: its pose is not there yet and %s", (unsigned long long)h->frame_id,
                 ig->holding ? "an earlier keyframe candidate waits for its own" : "it is no keyframe by time");
    }
    return;
  }
  if (r == POSE_FOUND) frame_admit(ig, buf, pose, now);
}
