/*
 * Colour + range pairing (see pair.h). Each stream has a small FIFO of
 * frames whose pixels the pipelines convert straight into; a commit on
 * either side runs the matcher over the two oldest frames.
 */
#include "pair.h"

#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "cvshim.h"
#include "depthreg.h"
#include "log.h"
#include "pixfmt.h"

#define TAG "pair"
/* Frames kept per stream: they cover the arrival skew of two devices. A
 * triggered GigE range camera on a loaded host (the VM's camd_lcam_pair
 * case under emulation) delivered its frame more than four of a 30 Hz
 * colour camera's frames after the edge; with four held, the colour frame
 * of that edge was gone by then and the edge gave no record (2 runs in 8). */
#define HOLD 8

struct held {
  struct vlff_sink_frame meta;
  void *px;
  size_t cap;
};

/* Frames whose device clock maps each arrival back to its exposure: the
 * least-delayed of the last OFFSETS frames gives the device-to-host offset
 * (the delay's floor), so a frame delayed in the scene server, the network
 * or the host's scheduler keeps its device time on the host clock. */
#define OFFSETS 32

struct fifo {
  struct held f[HOLD];
  int head, n;
  bool reserved;
  bool started;      /* a frame of this stream was committed */
  uint64_t first_ns; /* the first one's time */
  int64_t off[OFFSETS]; /* host_ns - device_ns of the latest frames */
  int noff, off_next;
  uint64_t last_ns;  /* the newest frame's host time */
};

struct vlff_pair {
  struct vlff_sink color_sink, depth_sink, *out;
  struct fifo color, depth;
  struct vlff_rgbd_calib calib;
  struct vlff_depthreg *reg;
  int reg_dw, reg_dh, reg_cw, reg_ch;
  int out_w, out_h; /* the record's size, 0 x 0 = the colour frames' */
  uint64_t tol_ns;      /* depth_camera.pair_tolerance_s: trigger-stamped pairs */
  uint64_t free_tol_ns; /* free-running pairs: under half the faster camera's period */
  struct vlff_pair_stats st;
  bool paired;     /* a pair was matched: the streams are in step */
  uint64_t logged; /* drops warned of (vlff_warn_limited) */
  char last_error[512]; /* as large as the messages it keeps */
};

static struct held *oldest(struct fifo *q) { return q->n ? &q->f[q->head] : NULL; }
static void pop(struct fifo *q) { q->head = (q->head + 1) % HOLD, q->n--; }

/* Drops q's frame i (0: its oldest), which found no partner in the other
 * stream. It is counted as a start-up frame when the other stream had not begun
 * (nothing from it yet, or its first frame came more than the tolerance
 * after this one: no frame of it could have been this one's partner) or no
 * pair was made yet (a camera's first frames after it starts streaming
 * need not keep its period: Aravis' fake camera sends its first at once,
 * off the grid of the later ones), as unmatched otherwise. */
static void drop_at(struct vlff_pair *p, struct fifo *q, int i) {
  const bool color = q == &p->color;
  const struct fifo *other = color ? &p->depth : &p->color;
  const struct held *h = &q->f[(q->head + i) % HOLD];
  const uint64_t t = h->meta.host_ns;
  const uint64_t tol = !h->meta.trigger_stamped && p->free_tol_ns > p->tol_ns ? p->free_tol_ns : p->tol_ns;
  if (!p->paired || !other->started || t + tol < other->first_ns)
    (*(color ? &p->st.startup_color : &p->st.startup_depth))++;
  else
    (*(color ? &p->st.unmatched_color : &p->st.unmatched_depth))++;
  /* The frames before it move back one place and the head past its
   * buffer, which becomes the slot before the head: the slot after the
   * queue (head + n), which a reservation may hold open, stays where it
   * is. */
  struct held gone = *h;
  for (int j = i; j > 0; j--) q->f[(q->head + j) % HOLD] = q->f[(q->head + j - 1) % HOLD];
  q->f[q->head] = gone;
  pop(q);
}

static void drop_oldest(struct vlff_pair *p, struct fifo *q) { drop_at(p, q, 0); }

/* The frame a full queue gives up: its oldest, unless the queue holds a
 * frame stamped by a trigger. A triggered camera's frame can reach the host
 * long after its edge on a loaded host (the VM's GigE range camera, later
 * than the eight frames a 30 Hz colour camera sends meanwhile), and the
 * colour frame that edge stamped is its partner: then the oldest frame not
 * stamped goes first. A free-running frame pairs with a triggered one only
 * when it began within the tolerance before that edge and no frame carries
 * the edge's stamp, so the oldest of them is the one least likely to be
 * wanted. */
static int victim(const struct fifo *q) {
  bool stamped = false;
  for (int i = 0; i < q->n; i++) stamped |= q->f[(q->head + i) % HOLD].meta.trigger_stamped;
  if (!stamped) return 0;
  for (int i = 0; i < q->n; i++)
    if (!q->f[(q->head + i) % HOLD].meta.trigger_stamped) return i;
  return 0;
}

/* The slot a new frame goes into; a full queue gives up a frame that no
 * frame of the other stream has claimed in time (victim). */
static struct held *reserve_slot(struct vlff_pair *p, struct fifo *q, size_t bytes, char *err, size_t errlen) {
  if (q->n == HOLD) drop_at(p, q, victim(q));
  struct held *h = &q->f[(q->head + q->n) % HOLD];
  if (h->cap < bytes) {
    void *np = realloc(h->px, bytes);
    if (!np) {
      snprintf(err, errlen, "pairing: out of memory for a %zu-byte frame", bytes);
      return NULL;
    }
    h->px = np, h->cap = bytes;
  }
  q->reserved = true;
  return h;
}

/* A pair lost on the way out: counted, its reason kept for camd's
 * periodic report and warned of (rate-limited). */
static void lost_pair(struct vlff_pair *p, const char *why) {
  p->st.dropped++;
  snprintf(p->last_error, sizeof p->last_error, "%s", why);
  vlff_warn_limited(&p->logged, TAG, "pair dropped: %s", why);
}

static void emit(struct vlff_pair *p, const struct held *c, const struct held *d) {
  const struct vlff_sink_frame *cm = &c->meta, *dm = &d->meta;
  char err[512];
  if (!p->reg || p->reg_dw != dm->width || p->reg_dh != dm->height || p->reg_cw != cm->width ||
      p->reg_ch != cm->height) {
    vlff_depthreg_free(p->reg);
    p->reg = vlff_depthreg_new(&p->calib, dm->width, dm->height, cm->width, cm->height, p->out_w, p->out_h, err,
                               sizeof err);
    p->reg_dw = dm->width, p->reg_dh = dm->height, p->reg_cw = cm->width, p->reg_ch = cm->height;
    if (!p->reg) {
      lost_pair(p, err);
      return;
    }
  }
  int ow, oh;
  double k[4];
  vlff_depthreg_intrinsics(p->reg, k, &ow, &oh);
  struct vlff_sink_frame f = {.width = ow, .height = oh, .color_format = VLFF_PIX_RGB8,
                              .depth_format = VLFF_DEPTH_FMT_U16_MM};
  if (p->out->reserve(p->out, &f, err, sizeof err)) {
    lost_pair(p, err);
    return;
  }
  /* At another size the colour plane is resampled to the registration's
   * output camera: the same scaling about pixel centres as its intrinsics. */
  if (ow == cm->width && oh == cm->height) {
    for (int y = 0; y < oh; y++)
      memcpy(f.color + (size_t)y * f.color_stride, (const uint8_t *)c->px + (size_t)y * cm->width * 3,
             (size_t)cm->width * 3);
  } else if (vlff_cv_resize_rgb(c->px, (size_t)cm->width * 3, cm->width, cm->height, f.color, f.color_stride, ow,
                                oh, err, sizeof err)) {
    p->out->abort(p->out, &f);
    lost_pair(p, err);
    return;
  }
  if (vlff_depthreg_apply(p->reg, d->px, (size_t)dm->width * 2, 0.001, f.depth, f.depth_stride, err, sizeof err) <
      0) {
    p->out->abort(p->out, &f);
    lost_pair(p, err);
    return;
  }
  f.device_frame_id = cm->device_frame_id;
  f.device_ns = cm->device_ns;
  f.host_ns = cm->host_ns;
  f.sensor_id = cm->sensor_id;
  memcpy(f.intrinsics, k, sizeof f.intrinsics);
  f.pose_valid = cm->pose_valid;
  f.pose_untrusted = cm->pose_untrusted;
  memcpy(f.pose, cm->pose, sizeof f.pose);
  f.pose_ns = cm->pose_ns;
  if (p->out->commit(p->out, &f)) {
    lost_pair(p, "the output refused the commit");
    return;
  }
  p->st.pairs++;
}

static uint64_t dist(uint64_t a, uint64_t b) { return a > b ? a - b : b - a; }

/* A stream whose device-to-host offset comes from one frame alone (its
 * first, or its first after a clock reset): that offset is that frame's
 * delay, which at a stream's start is often long (a camera sends its first
 * frame at once when acquisition starts, or late). */
static bool young(const struct fifo *q) { return q->noff == 1; }

/* The device-to-host offset of q's stream: the smallest host - device of the
 * latest frames; a jump of more than a second (the camera's clock reset, a
 * reconnect) starts the window afresh. */
static void track_offset(struct fifo *q, const struct vlff_sink_frame *f) {
  if (!f->device_ns || f->trigger_stamped) return;
  int64_t o = (int64_t)(f->host_ns - f->device_ns), lo = INT64_MAX;
  for (int i = 0; i < q->noff; i++) lo = q->off[i] < lo ? q->off[i] : lo;
  if (q->noff && (o < lo - 1000000000ll || o > lo + 1000000000ll)) q->noff = 0, q->off_next = 0;
  q->off[q->off_next] = o;
  q->off_next = (q->off_next + 1) % OFFSETS;
  if (q->noff < OFFSETS) q->noff++;
}

/* A held frame's time for matching against a frame of the other stream:
 * both free-running (arrival-stamped), the device time on the host clock
 * when the camera stamps its frames; else the host stamp. */
static uint64_t when(const struct fifo *q, const struct held *h, bool free_pair) {
  if (!free_pair || !h->meta.device_ns || !q->noff) return h->meta.host_ns;
  int64_t lo = INT64_MAX;
  for (int i = 0; i < q->noff; i++) lo = q->off[i] < lo ? q->off[i] : lo;
  uint64_t t = h->meta.device_ns + (uint64_t)lo;
  return t <= h->meta.host_ns ? t : h->meta.host_ns;
}

/* Frames arrive in time order per stream, so an oldest frame more than the
 * tolerance before the other stream's oldest can never be paired. Within the
 * tolerance the pair must also be mutually nearest among the frames held: a
 * camera running faster than configured can put two frames near one of the
 * other's, and only the nearer is its partner. Two free-running frames
 * (neither stamped by a trigger) pair within just under half the faster
 * camera's period: free-running cameras keep an arbitrary phase between
 * them, and mutual nearness alone keeps each frame to its one partner. */
static void match(struct vlff_pair *p) {
  struct held *c, *d;
  while ((c = oldest(&p->color)) && (d = oldest(&p->depth))) {
    const bool fr = !c->meta.trigger_stamped && !d->meta.trigger_stamped;
    const uint64_t tol = fr && p->free_tol_ns > p->tol_ns ? p->free_tol_ns : p->tol_ns;
    uint64_t tc = when(&p->color, c, fr), td = when(&p->depth, d, fr);
    if (dist(tc, td) <= tol) {
      const struct held *c2 = p->color.n > 1 ? &p->color.f[(p->color.head + 1) % HOLD] : NULL;
      const struct held *d2 = p->depth.n > 1 ? &p->depth.f[(p->depth.head + 1) % HOLD] : NULL;
      /* Free-running frames: the earlier one's stream may still send a
       * frame nearer the later one (a camera starting up sends its first
       * frames off its period's grid, one 18 ms before the next in the e2e
       * rig), so the pair waits for that successor, unless the later
       * one's stream has moved on by two frames meanwhile (the earlier
       * camera stopped). Frames stamped at the same instant have no nearer
       * partner to wait for. */
      if (fr && tc != td && (tc < td ? !c2 : !d2) && (tc < td ? p->depth.n : p->color.n) < 3) break;
      if (c2 && dist(when(&p->color, c2, fr), td) < dist(tc, td)) {
        drop_oldest(p, &p->color);
      } else if (d2 && dist(tc, when(&p->depth, d2, fr)) < dist(tc, td)) {
        drop_oldest(p, &p->depth);
      } else {
        uint64_t skew = dist(tc, td);
        p->st.skew_sum_ns += skew;
        if (skew > p->st.skew_max_ns) p->st.skew_max_ns = skew;
        if (fr) p->st.free_pairs++;
        p->paired = true;
        emit(p, c, d);
        pop(&p->color), pop(&p->depth);
      }
    } else if (fr && (young(&p->color) || young(&p->depth)) && p->color.n < 3 && p->depth.n < 3) {
      /* Too far apart by an offset from one frame: the next frame of that
       * stream gives its true offset, which may bring the two together.
       * Bounded: either stream holding three frames decides. */
      break;
    } else if (tc < td) {
      drop_oldest(p, &p->color);
    } else {
      drop_oldest(p, &p->depth);
    }
  }
}

static int color_reserve(struct vlff_sink *s, struct vlff_sink_frame *f, char *err, size_t errlen) {
  struct vlff_pair *p = s->ctx;
  if (f->color_format != VLFF_PIX_RGB8 || f->depth_format != VLFF_DEPTH_FMT_NONE || f->width <= 0 ||
      f->height <= 0) {
    snprintf(err, errlen, "pairing: the colour camera must deliver RGB8 without depth");
    return -1;
  }
  struct held *h = reserve_slot(p, &p->color, (size_t)f->width * f->height * 3, err, errlen);
  if (!h) return -1;
  f->color = h->px, f->color_stride = (size_t)f->width * 3;
  f->depth = NULL, f->depth_stride = 0;
  f->slot = h;
  return 0;
}

static int depth_reserve(struct vlff_sink *s, struct vlff_sink_frame *f, char *err, size_t errlen) {
  struct vlff_pair *p = s->ctx;
  if (f->color_format != VLFF_PIX_NONE || f->depth_format != VLFF_DEPTH_FMT_U16_MM || f->width <= 0 ||
      f->height <= 0) {
    snprintf(err, errlen, "pairing: the range camera must deliver uint16 millimetres without colour");
    return -1;
  }
  struct held *h = reserve_slot(p, &p->depth, (size_t)f->width * f->height * 2, err, errlen);
  if (!h) return -1;
  f->color = NULL, f->color_stride = 0;
  f->depth = h->px, f->depth_stride = (size_t)f->width * 2;
  f->slot = h;
  return 0;
}

static int commit_to(struct vlff_pair *p, struct fifo *q, struct vlff_sink_frame *f) {
  if (!q->reserved) return -1;
  struct held *h = f->slot;
  h->meta = *f;
  q->reserved = false;
  if (!q->started) q->started = true, q->first_ns = f->host_ns;
  q->last_ns = f->host_ns;
  track_offset(q, f);
  q->n++;
  match(p);
  return 0;
}

static int color_commit(struct vlff_sink *s, struct vlff_sink_frame *f) {
  struct vlff_pair *p = s->ctx;
  return commit_to(p, &p->color, f);
}
static int depth_commit(struct vlff_sink *s, struct vlff_sink_frame *f) {
  struct vlff_pair *p = s->ctx;
  return commit_to(p, &p->depth, f);
}
static void color_abort(struct vlff_sink *s, struct vlff_sink_frame *f) {
  (void)f;
  ((struct vlff_pair *)s->ctx)->color.reserved = false;
}
static void depth_abort(struct vlff_sink *s, struct vlff_sink_frame *f) {
  (void)f;
  ((struct vlff_pair *)s->ctx)->depth.reserved = false;
}

struct vlff_pair *vlff_pair_new(const struct vlff_cfg_depth_camera *dcam, const struct vlff_cfg_camera *cam,
                               struct vlff_sink *out, char *err, size_t errlen) {
  struct vlff_pair *p = calloc(1, sizeof *p);
  if (!p) {
    snprintf(err, errlen, "pairing: out of memory");
    return NULL;
  }
  char e[512];
  if (vlff_rgbd_calib_load(dcam->calibration, &p->calib, e, sizeof e)) {
    snprintf(err, errlen, "key 'depth_camera.calibration': %s", e);
    free(p);
    return NULL;
  }
  /* A record size whose aspect cannot be the colour camera's is refused
   * here when the calibration or the config names the camera's size; else
   * the first pair finds out (and every pair is dropped, said in the log). */
  const struct vlff_cfg_depth_camera *d = dcam;
  int cw = p->calib.color_w ? p->calib.color_w : cam->width;
  int ch = p->calib.color_w ? p->calib.color_h : cam->height;
  if (d->register_width && cw && ch && !vlff_depthreg_aspect_ok(d->register_width, d->register_height, cw, ch)) {
    snprintf(err, errlen,
             "key 'depth_camera.register_width': %dx%d is not the colour camera's aspect (%dx%d, within %g %%): "
             "another aspect would stretch the image; crop the colour camera with its ROI instead",
             d->register_width, d->register_height, cw, ch, 100 * VLFF_DEPTHREG_ASPECT_TOL);
    free(p);
    return NULL;
  }
  p->out_w = d->register_width, p->out_h = d->register_height;
  p->out = out;
  p->tol_ns = (uint64_t)(dcam->pair_tolerance_s * 1e9);
  const double rate = cam->frame_rate > dcam->frame_rate ? cam->frame_rate : dcam->frame_rate;
  p->free_tol_ns = rate > 0 ? (uint64_t)(0.5e9 / rate) - 1 : p->tol_ns;
  p->color_sink = (struct vlff_sink){color_reserve, color_commit, color_abort, p};
  p->depth_sink = (struct vlff_sink){depth_reserve, depth_commit, depth_abort, p};
  return p;
}

void vlff_pair_free(struct vlff_pair *p) {
  if (!p) return;
  for (int i = 0; i < HOLD; i++) free(p->color.f[i].px), free(p->depth.f[i].px);
  vlff_depthreg_free(p->reg);
  free(p);
}

struct vlff_sink *vlff_pair_color_sink(struct vlff_pair *p) { return &p->color_sink; }
struct vlff_sink *vlff_pair_depth_sink(struct vlff_pair *p) { return &p->depth_sink; }
const struct vlff_pair_stats *vlff_pair_get_stats(const struct vlff_pair *p) { return &p->st; }
const char *vlff_pair_last_error(const struct vlff_pair *p) { return p->last_error; }
uint64_t vlff_pair_last_ns(const struct vlff_pair *p, int depth) { return depth ? p->depth.last_ns : p->color.last_ns; }
