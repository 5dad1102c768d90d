/*
 * The online learner: threads, queues and policies around the field.
 *
 * Two threads do the work. The ingest thread never touches the field: it
 * turns ring records into candidate keyframes (validated, posed, downscaled,
 * with features) and hands them over through a small queue that drops the
 * oldest candidate rather than ever blocking the ring. The trainer thread
 * owns the field, the keyframe store and the map writer; it interleaves pose
 * checks, optimisation steps, publishes and checkpoints, so none of them
 * needs a lock around the model.
 */
#include "node.h"

#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "bounds.h"
#include "clock.h"
#include "embeddings.h"
#include "feature_join.h"
#include "field.h"
#include "files.h"
#include "keyframes.h"
#include "log.h"
#include "mem.h"
#include "publish.h"
#include "select.h"
#include "source.h"
#include "watch.h"
#include "vlff/escape.h"
#include "vlff/shm.h"
#ifdef VLFF_HAVE_VLM
#include "image_encoder.h"
#include "text_encoder.h"
#endif

/* Steps in a row with a non-finite loss on a finite field before it is
 * rolled back all the same (step_not_finite). */
#define NONFINITE_RUN_MAX 20
/* Steps between two scans of the whole learned state (vlff_field_check). */
#define FIELD_SCAN_STEPS 200
#define TAG "node"
#define QUEUE_CAP 4
#define PENDING_CAP 16
#define LAT_CAP 4096
#define KF_PROTECT 8  /* newest keyframes never evicted */
#define KF_HISTORY 32 /* admitted keyframes the pose check compares against */

struct candidate {
  long long id;
  uint64_t t_host_ns;
  struct vlff_view view; /* points into the buffers below */
  uint8_t *rgb;
  float *depth;
  uint16_t *features;
  double deadline_s;     /* features must arrive by then (feature ring) */
};

struct vlff_node {
  struct vlff_config cfg;
  struct vlff_field *field;
  struct vlff_kfstore *store;
  struct vlff_source_hooks hooks;     /* what the source gives beyond the ring (source.h) */
  struct vlff_embeddings *emb_file;   /* prompts.embeddings */
#ifdef VLFF_HAVE_VLM
  struct vlff_text_encoder *text_enc; /* vlm.text_model */
  struct vlff_image_worker *image_worker; /* source.features: model */
#endif
  int model_h, model_w;               /* largest feature map accepted */
  struct vlff_publisher *pub;
  struct vlff_prompts *mailbox;
  /* vlff_warn_limited's counters, one per line that can come with every frame,
   * keyframe, iteration or request (each used by one thread). */
  struct {
    uint64_t mailbox, mailbox_refused, mailbox_answer, map_status, publish, feature_ring, encoder, features_late,
        kf_rejected, kf_refused, kf_store, step_failed, nonfinite, rollback;
  } warned;

  pthread_t ingest_thread, trainer_thread;
  bool ingest_started, trainer_started, joined;
  atomic_bool stop;
  atomic_bool finished;
  double t_start;

  /* ingest -> trainer */
  pthread_mutex_t qlock;
  pthread_cond_t qcond;
  struct candidate *queue[QUEUE_CAP];
  int qlen;

  /* commands -> trainer */
  pthread_mutex_t clock;
  int cmds[16][2];
  int ncmds;

  /* status (short critical sections, never held across work) */
  pthread_mutex_t slock;
  struct vlff_node_status st;
  double last_frame_s, last_pose_ok_s, last_lapped_s;
  struct vlff_frame_watch fwatch; /* under slock */

  /* trainer-private */
  float *prompt_emb;           /* [k][D] */
  int prompt_k;
  char prompt_text[VLFF_MAX_PROMPTS][VLFF_PROMPT_LEN];
  bool mapping;
  bool resumed;                /* the field came from a checkpoint: no batch warm-up */
  long long ckpt_steps;        /* field steps in the newest checkpoint (or at start) */
  /* Monotonic ns of each thread's last loop pass: the service watchdog is
   * fed only while both move (vlff_node_status). */
  _Atomic uint64_t ingest_beat_ns, trainer_beat_ns;
  int ckpt_slot;
  int nonfinite_run;          /* trainer: steps in a row whose loss was not finite */
  long long scanned_step;     /* trainer: the step of the last vlff_field_check */
  unsigned rollback_tried;    /* trainer: slots the field was loaded from since its last save */
  double lat_ms[LAT_CAP];
  int lat_n;
  uint64_t pending_t_host[64];
  int pending_lat;
  float accepted_res[KF_HISTORY]; /* pose evidence of recently admitted keyframes */
  float accepted_inl[KF_HISTORY];
  int n_accepted;
};


static void candidate_free(struct candidate *c) {
  if (!c) return;
  VLFF_FREE_ALL(c->rgb, c->depth, c->features, c);
}

#define STAT_ADD(n, field, v)          \
  do {                                 \
    pthread_mutex_lock(&(n)->slock);   \
    (n)->st.field += (v);              \
    pthread_mutex_unlock(&(n)->slock); \
  } while (0)

/* ---- prompts ------------------------------------------------------------ */

/* Embeddings for prompt texts, from the first source configured: the
 * precomputed file, the in-node text encoder, or the source's own encoder
 * (the simulator's, source.h). */
static int embed_prompts(struct vlff_node *n, const char texts[][VLFF_PROMPT_LEN], int k,
                         float *out, char *err, size_t errlen) {
  int d = n->cfg.field.feature_dim;
  for (int i = 0; i < k; i++) {
    float *o = out + (size_t)i * d;
    if (n->emb_file) {
      const float *v = vlff_embeddings_lookup(n->emb_file, texts[i]);
      if (!v) {
        snprintf(err, errlen, "prompt '%s': not in the embeddings file %s", VLFF_Q(texts[i]),
                 VLFF_Q(n->cfg.prompts.embeddings));
        return -1;
      }
      memcpy(o, v, (size_t)d * sizeof(float));
#ifdef VLFF_HAVE_VLM
    } else if (n->text_enc) {
      if (vlff_text_encoder_encode(n->text_enc, texts[i], o, err, errlen)) return -1;
#endif
    } else if (n->hooks.embed) {
      if (n->hooks.embed(n->hooks.ctx, texts[i], o, err, errlen)) return -1;
    } else {
      snprintf(err, errlen, "prompt '%s': no text encoder (set prompts.embeddings or vlm.text_model)",
               VLFF_Q(texts[i]));
      return -1;
    }
  }
  return 0;
}

static int apply_prompts(struct vlff_node *n, const char texts[][VLFF_PROMPT_LEN], int k, int set_index,
                         char *err, size_t errlen) {
  if (k < 1 || k > VLFF_MAX_PROMPTS) {
    snprintf(err, errlen, "prompt set of %d prompts (expected 1..%d)", k, VLFF_MAX_PROMPTS);
    return -1;
  }
  float *emb = malloc((size_t)k * n->cfg.field.feature_dim * sizeof(float));
  if (!emb) return snprintf(err, errlen, "out of memory"), -1;
  if (embed_prompts(n, texts, k, emb, err, errlen) ||
      vlff_field_set_prompts(n->field, emb, k, err, errlen)) {
    free(emb);
    return -1;
  }
  free(n->prompt_emb);
  n->prompt_emb = emb;
  n->prompt_k = k;
  for (int i = 0; i < k; i++) snprintf(n->prompt_text[i], VLFF_PROMPT_LEN, "%s", texts[i]);
  pthread_mutex_lock(&n->slock);
  n->st.prompt_set = set_index;
  n->st.prompt_count = k;
  pthread_mutex_unlock(&n->slock);
  VLFF_INFO(TAG, "prompts: %d (%s%s)", k, set_index >= 0 ? "set " : "posted texts",
            set_index >= 0 ? n->cfg.prompts.sets[set_index].name : "");
  return 0;
}

static int apply_prompt_set(struct vlff_node *n, int idx, char *err, size_t errlen) {
  if (idx < 0 || idx >= n->cfg.prompts.set_count) {
    snprintf(err, errlen, "prompt set %d does not exist (have %d)", idx, n->cfg.prompts.set_count);
    return -1;
  }
  const struct vlff_prompt_set *s = &n->cfg.prompts.sets[idx];
  return apply_prompts(n, (const char(*)[VLFF_PROMPT_LEN])s->text, s->count, idx, err, errlen);
}

/* ---- ingest ------------------------------------------------------------- */

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
                             int dw, int dh) {
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
      if (!(d > 0) || !isfinite(d)) d = 0;
      valid += d > 0;
      dst[(size_t)y * dw + x] = d;
    }
  return valid;
}

static void queue_push(struct vlff_node *n, struct candidate *c) {
  struct candidate *dropped = NULL;
  pthread_mutex_lock(&n->qlock);
  if (n->qlen == QUEUE_CAP) {
    dropped = n->queue[0];
    memmove(n->queue, n->queue + 1, (QUEUE_CAP - 1) * sizeof n->queue[0]);
    n->qlen--;
  }
  n->queue[n->qlen++] = c;
  pthread_cond_signal(&n->qcond);
  pthread_mutex_unlock(&n->qlock);
  if (dropped) {
    STAT_ADD(n, candidates_dropped, 1);
    candidate_free(dropped);
  }
}

/* A keyframe waiting for its features leaves the pending list either
 * with them (queued for the trainer) or without (dropped and counted). */
static int pending_find(struct candidate **pending, int npend, uint64_t id) {
  for (int i = 0; i < npend; i++)
    if ((uint64_t)pending[i]->id == id) return i;
  return -1;
}

static void pending_remove(struct candidate **pending, int *npend, int i) {
  memmove(pending + i, pending + i + 1, (size_t)(*npend - i - 1) * sizeof *pending);
  (*npend)--;
}

static void pending_complete(struct vlff_node *n, struct candidate **pending, int *npend, uint64_t id,
                             const uint16_t *feat, int fh, int fw) {
  int i = pending_find(pending, *npend, id);
  if (i < 0) return;
  struct candidate *c = pending[i];
  pending_remove(pending, npend, i);
  int d = n->cfg.field.feature_dim;
  size_t bytes = (size_t)fh * fw * d * sizeof(uint16_t);
  c->features = feat ? malloc(bytes) : NULL;
  if (!c->features) {
    STAT_ADD(n, features_timeout, 1);
    candidate_free(c);
    return;
  }
  memcpy(c->features, feat, bytes);
  c->view.features = c->features;
  c->view.feat_width = fw;
  c->view.feat_height = fh;
  c->view.feature_dim = d;
  queue_push(n, c);
}

static mode_t shm_mode(const struct vlff_node *n) {
  return n->cfg.shm.mode ? (mode_t)n->cfg.shm.mode : 0640;
}

/* Why an input ring cannot be attached, logged once per reason as it changes
 * (missing, another owner or a wider mode, another kind, truncated, not a vlff
 * segment: libvlff-shm's error code), so that a user sees why the node waits,
 * and sees it again when the reason moves on, without a line per retry.
 * *last holds the code logged last (0: none since the last attach). */
static void attach_refused(int *last, const char *what, const char *name) {
  int code = vlff_shm_last_error();
  if (code == *last) return;
  *last = code;
  VLFF_WARN(TAG, "waiting for %s %s: %s", what, VLFF_Q(name), vlff_shm_last_message());
}

/* Only rings of this node's uid, within the configured mode: anyone else able
 * to write one could forge its records. */
static struct vlff_ring *attach_input(struct vlff_node *n, const char *name, uint32_t kind) {
  return vlff_ring_attach_owned(name, kind, geteuid(), shm_mode(n));
}

static struct vlff_ring *attach_retry(struct vlff_node *n, const char *name, uint32_t kind) {
  int refused = 0;
  while (!atomic_load(&n->stop)) {
    atomic_store(&n->ingest_beat_ns, vlff_shm_now_ns());
    struct vlff_ring *r = attach_input(n, name, kind);
    if (r) {
      VLFF_INFO(TAG, "attached to ring %s (%u slots of %llu bytes)", VLFF_Q(name), vlff_ring_slots(r),
                (unsigned long long)vlff_ring_slot_size(r));
      return r;
    }
    attach_refused(&refused, "ring", name);
    struct timespec ts = {0, 100 * 1000 * 1000};
    nanosleep(&ts, NULL);
  }
  return NULL;
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
};

const char *vlff_refusal_name(int reason) {
  return reason > 0 && reason < VLFF_REFUSED_COUNT ? refusal_names[reason] : "unknown";
}

/* A camera that lacks something lacks it on every frame: the first refusal
 * of each reason is logged at info with its detail, later ones only at
 * debug, and a summary of the counts every REFUSAL_REPORT_S while refusals
 * go on, so the log says why without a line per frame. */
#define REFUSAL_REPORT_S 5.0

struct refusal_log {
  bool seen[VLFF_REFUSED_COUNT];
  long long since[VLFF_REFUSED_COUNT]; /* since the last summary */
  double last_report_s;
};

static void refuse(struct vlff_node *n, struct refusal_log *rl, int reason, long long id, const char *fmt, ...)
    __attribute__((format(printf, 5, 6)));

static void refuse(struct vlff_node *n, struct refusal_log *rl, int reason, long long id, const char *fmt, ...) {
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

static void refusal_summary(struct vlff_node *n, struct refusal_log *rl, double now) {
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

/* The ingest thread's state, shared by a frame's stages. */
struct ingest {
  struct vlff_node *n;
  const struct vlff_config *cfg;
  struct refusal_log rl;
  struct vlff_kf_selector sel;
  struct candidate *pending[PENDING_CAP]; /* keyframes waiting for their features */
  int npend;
  struct vlff_feature_join *join;
  int feats_refused; /* attach_refused's last code for the feature ring */
  struct vlff_ring *poses;
  double pose_reattach_s;
  bool pose_miss;
  /* One keyframe candidate waiting for its pose (source.pose_wait_s): a
   * tracker that poses the node's own frames publishes each pose after its
   * frame reached the ring. */
  void *held;
  size_t held_len;
  double held_since_s;
  bool holding;
};

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
  if ((h->flags & VLFF_FRAME_POSE_VALID) && !(h->flags & VLFF_FRAME_POSE_UNTRUSTED)) {
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
  if (!vlff_pose_valid(pose)) {
    refuse(n, &ig->rl, VLFF_REFUSED_BAD_POSE, id, "pose is not a rigid transform (NaN, or rotation not orthonormal)");
    return POSE_REFUSED;
  }
  if (vlff_pose_plausible(pose, cfg->field.scene_min, cfg->field.scene_max, why, sizeof why)) {
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
  size_t valid = resample_depth(vlff_frame_plane(buf, VLFF_PLANE_DEPTH), dp->format, (int)dp->width,
                                (int)dp->height, dp->stride, c->depth, dw, dh);
  if (valid == 0) {
    candidate_free(c);
    refuse(n, &ig->rl, VLFF_REFUSED_EMPTY_DEPTH, id, "the depth plane has no valid pixel (all 0 or NaN)");
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
      candidate_free(ig->pending[0]);
      pending_remove(ig->pending, &ig->npend, 0);
    }
    char jerr[256];
    if (ig->join) vlff_feature_join_add_frame(ig->join, (uint64_t)id, vlff_shm_now_ns(), jerr, sizeof jerr);
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
static void ingest_held(struct ingest *ig, double now) {
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
/* Events per second over windows of at least a second (frames in, training
 * steps): once a window is over, its rate goes into *out under the status
 * lock and a new window starts. */
struct rate_meter {
  double t0;
  long long count;
};

static void rate_publish(struct rate_meter *r, double now, struct vlff_node *n, double *out) {
  if (now - r->t0 < 1.0) return;
  pthread_mutex_lock(&n->slock);
  *out = r->count / (now - r->t0);
  pthread_mutex_unlock(&n->slock);
  r->t0 = now;
  r->count = 0;
}

static void ingest_frame(struct ingest *ig, const void *buf, ssize_t len, double now) {
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

/* Features that arrived (external extractor or in-node model) complete
 * their waiting keyframes; keyframes whose features never come expire. */
static void ingest_features(struct ingest *ig, struct vlff_ring **feats, uint16_t *fbuf, int model_h, int model_w) {
  struct vlff_node *n = ig->n;
  const struct vlff_config *cfg = ig->cfg;
  if (ig->join && !*feats) {
    *feats = attach_input(n, cfg->shm.feature_ring, VLFF_RECORD_FEATURE);
    if (*feats && ig->feats_refused)
      VLFF_INFO(TAG, "attached to feature ring %s", cfg->shm.feature_ring);
    if (*feats)
      ig->feats_refused = 0;
    else
      attach_refused(&ig->feats_refused, "feature ring", cfg->shm.feature_ring);
  }
  if (ig->join) {
    /* A producer that replaced its ring (restarted with another geometry, or
     * after the file was truncated) is followed on the next pass. */
    if (*feats && vlff_feature_join_pump(ig->join, *feats) < 0 && errno == EPIPE) {
      vlff_warn_limited(&n->warned.feature_ring, TAG, "feature ring: %s; attaching again", vlff_shm_last_message());
      vlff_ring_close(*feats);
      *feats = NULL;
      ig->feats_refused = -1; /* no refusal code: the next attach is logged either way */
    }
    uint64_t fid;
    int fh, fw, ev;
    while ((ev = vlff_feature_join_poll(ig->join, vlff_shm_now_ns(), &fid, fbuf, &fh, &fw)) != VLFF_JOIN_NONE) {
      if (ev == VLFF_JOIN_READY) pending_complete(n, ig->pending, &ig->npend, fid, fbuf, fh, fw);
    }
  }
#ifdef VLFF_HAVE_VLM
  if (n->image_worker) {
    uint64_t fid;
    char werr[256];
    int r;
    while ((r = vlff_image_worker_poll(n->image_worker, &fid, fbuf, werr, sizeof werr)) != 0) {
      if (r > 0) {
        pending_complete(n, ig->pending, &ig->npend, fid, fbuf, model_h, model_w);
      } else {
        vlff_warn_limited(&n->warned.encoder, TAG, "frame %llu: image encoder failed: %s", (unsigned long long)fid,
                          werr);
        int i = pending_find(ig->pending, ig->npend, fid);
        if (i >= 0) {
          STAT_ADD(n, features_timeout, 1);
          candidate_free(ig->pending[i]);
          pending_remove(ig->pending, &ig->npend, i);
        }
      }
    }
  }
#else
  (void)model_h;
  (void)model_w;
#endif
  for (int i = 0; i < ig->npend; i++)
    if (vlff_seconds() > ig->pending[i]->deadline_s) {
      STAT_ADD(n, features_timeout, 1);
      vlff_warn_limited(&n->warned.features_late, TAG, "frame %lld: features did not arrive within %.1f s",
                        ig->pending[i]->id, cfg->vlm.feature_timeout_s);
      candidate_free(ig->pending[i]);
      pending_remove(ig->pending, &ig->npend, i);
      i--;
    }
}

static void *ingest_main(void *arg) {
  /* Named so that ps -L, top -H and a debugger tell the threads apart, and a
   * test can freeze this one alone (the watchdog must then go unfed). */
  pthread_setname_np(pthread_self(), "vlff-ingest");
  struct vlff_node *n = arg;
  const struct vlff_config *cfg = &n->cfg;
  struct ingest ig = {.n = n, .cfg = cfg, .rl = {.last_report_s = vlff_seconds()}};
  struct vlff_ring *ring = attach_retry(n, cfg->shm.ring, VLFF_RECORD_FRAME);
  struct vlff_ring *feats = NULL;
  size_t cap = ring ? vlff_ring_slot_size(ring) : 0;
  void *buf = cap ? malloc(cap) : NULL;
  ig.held = cap ? malloc(cap) : NULL;
  int dim = cfg->field.feature_dim;
  /* Feature maps are at most the model input's size (the extractor's
   * contract); the join and the image worker hand results out through fbuf. */
  int model_h = n->model_h, model_w = n->model_w;
  uint16_t *fbuf = malloc((size_t)model_h * model_w * dim * sizeof(uint16_t));
  if (cfg->source.features == VLFF_FEAT_RING) {
    char jerr[256];
    ig.join = vlff_feature_join_create(PENDING_CAP, cfg->vlm.feature_timeout_s, dim, model_h, model_w, jerr,
                                       sizeof jerr);
    if (!ig.join) VLFF_ERROR(TAG, "feature join: %s", jerr);
  }
  vlff_kf_selector_init(&ig.sel, cfg->keyframes.rate_hz, cfg->keyframes.min_translation_m,
                        cfg->keyframes.min_rotation_deg);
  uint64_t lost_seen = 0;
  struct rate_meter fps = {vlff_seconds(), 0};
  while (ring && buf && ig.held && fbuf && !atomic_load(&n->stop)) {
    atomic_store(&n->ingest_beat_ns, vlff_shm_now_ns());
    ingest_features(&ig, &feats, fbuf, model_h, model_w);
    ingest_held(&ig, vlff_seconds());
    refusal_summary(n, &ig.rl, vlff_seconds());
    struct vlff_ring_view info;
    /* A held frame is looked at again soon after each short wait. */
    uint64_t wait_ns = ig.holding ? 5 * 1000 * 1000ull : 50 * 1000 * 1000ull;
    ssize_t len = vlff_ring_read_copy(ring, buf, cap, &info, wait_ns);
    uint64_t lost = vlff_ring_lost(ring);
    if (lost != lost_seen) {
      pthread_mutex_lock(&n->slock);
      n->st.frames_lost += (long long)(lost - lost_seen);
      n->last_lapped_s = vlff_seconds();
      pthread_mutex_unlock(&n->slock);
      lost_seen = lost;
    }
    if (len < 0) {
      if (errno == EPIPE) { /* the producer replaced the ring: follow it */
        vlff_ring_close(ring);
        ring = attach_retry(n, cfg->shm.ring, VLFF_RECORD_FRAME);
        lost_seen = 0;
        if (ring && vlff_ring_slot_size(ring) > cap) {
          cap = vlff_ring_slot_size(ring);
          void *nb = realloc(buf, cap), *nh = nb ? realloc(ig.held, cap) : NULL;
          if (nb) buf = nb;
          if (nh) ig.held = nh;
          if (!nb || !nh) break;
        }
      } else if (errno == EMSGSIZE) {
        refuse(n, &ig.rl, VLFF_REFUSED_MALFORMED, -1, "record larger than the ring's slot size %zu", cap);
      }
      continue;
    }
    double now = vlff_seconds();
    pthread_mutex_lock(&n->slock);
    n->st.frames_in++;
    n->last_frame_s = now;
    vlff_frame_watch_frame(&n->fwatch, now);
    pthread_mutex_unlock(&n->slock);
    fps.count++;
    rate_publish(&fps, now, n, &n->st.fps_in);
    ingest_frame(&ig, buf, len, now);
  }
  for (int i = 0; i < ig.npend; i++) candidate_free(ig.pending[i]);
  free(buf);
  free(ig.held);
  free(fbuf);
  vlff_feature_join_destroy(ig.join);
  vlff_ring_close(ring);
  vlff_ring_close(ig.poses);
  vlff_ring_close(feats);
  return NULL;
}

/* ---- trainer ------------------------------------------------------------ */

static void ckpt_path(const struct vlff_node *n, int slot, char *out, size_t len) {
  snprintf(out, len, "%s/field.%d.ckpt", n->cfg.node.state_dir, slot);
}

static void obs_path(const struct vlff_node *n, int slot, char *out, size_t len) {
  snprintf(out, len, "%s/map.%d.obs", n->cfg.node.state_dir, slot);
}

/* The field's own state went non-finite or out of the bounds of field.h (why
 * names where): back to the newest checkpoint that loads, or to a new field
 * when none does. The keyframes stay, so it learns again from what it has. */
static void roll_back(struct vlff_node *n, const char *why) {
  char path[2][VLFF_CFG_PATH + 32], err[640];
  const char *paths[2];
  int slot_of[2], np = 0;
  /* A checkpoint that loads but diverged again before anything new was
   * saved (values within the bounds that overflow together) is not taken
   * twice: then the other slot, then a new field. */
  for (int i = 0; i < 2; i++) {
    if (n->rollback_tried & (1u << i)) continue;
    ckpt_path(n, i, path[np], sizeof path[np]);
    paths[np] = path[np];
    slot_of[np++] = i;
  }
  err[0] = 0;
  int k = vlff_field_rollback(n->field, paths, np, err, sizeof err);
  STAT_ADD(n, field_rollbacks, 1);
  if (k >= 0) {
    int slot = slot_of[k];
    n->rollback_tried |= 1u << slot;
    /* The next checkpoint goes to the other slot: the good one stays. */
    n->ckpt_steps = vlff_field_steps(n->field);
    n->ckpt_slot = slot ^ 1;
    vlff_warn_limited(&n->warned.rollback, TAG, "the field diverged (%s): rolled back to %s at step %lld%s%s", why,
                      VLFF_Q(paths[k]), n->ckpt_steps, err[0] ? "; refused: " : "", err);
  } else {
    n->ckpt_steps = 0;
    n->resumed = false;
    vlff_warn_limited(&n->warned.rollback, TAG, "the field diverged (%s): re-initialised, no checkpoint loads%s%s", why,
                      err[0] ? ": " : "", err);
  }
}

/* A step whose loss was not finite applied nothing; if the field itself is
 * what went non-finite, roll it back. The scan costs a pass over the
 * parameters and moments, as the trainer's periodic scan does. */
static void step_not_finite(struct vlff_node *n, const char *step_err) {
  STAT_ADD(n, steps_nonfinite, 1);
  char why[320];
  if (vlff_field_check(n->field, why, sizeof why) == 0) {
    /* Values within the bounds can still overflow together (weights of 1e6
     * through three layers): a field whose every step is non-finite learns
     * nothing and is rolled back as well. Keyframes are checked on entry,
     * so a run this long is the field's. */
    if (++n->nonfinite_run < NONFINITE_RUN_MAX) {
      vlff_warn_limited(&n->warned.nonfinite, TAG, "%s (the field itself is finite)", step_err);
      return;
    }
    snprintf(why, sizeof why, "%d steps in a row with a non-finite loss, the last: %s", NONFINITE_RUN_MAX, step_err);
  }
  n->nonfinite_run = 0;
  roll_back(n, why);
}

static int save_checkpoint(struct vlff_node *n) {
  char path[VLFF_CFG_PATH + 32], err[256];
  int slot = n->ckpt_slot;
  /* Only learning changes what a checkpoint holds, and every change is a
   * step: an idle node (no frames, stopped, a camera unplugged) writes
   * nothing, sparing the robot's flash. */
  long long steps = vlff_field_steps(n->field);
  if (steps == n->ckpt_steps) {
    VLFF_DEBUG(TAG, "checkpoint skipped: nothing learned since step %lld", steps);
    return 0;
  }
  /* A field gone non-finite where no step's loss showed it (a table entry
   * no ray reached since) is rolled back, never written over the last good
   * checkpoint. */
  if (vlff_field_check(n->field, err, sizeof err)) {
    roll_back(n, err);
    return -1;
  }
  /* The observation grid first: a field checkpoint is only ever newer than
   * (or as new as) the grid beside it. */
  obs_path(n, slot, path, sizeof path);
  int obs_rc = vlff_publisher_save(n->pub, path, err, sizeof err);
  ckpt_path(n, slot, path, sizeof path);
  if (obs_rc || vlff_field_save(n->field, path, err, sizeof err)) {
    VLFF_ERROR(TAG, "checkpoint failed: %s", err);
    pthread_mutex_lock(&n->slock);
    n->st.checkpoint_failures++;
    n->st.error_flags |= VLFF_NODE_ERR_CHECKPOINT;
    pthread_mutex_unlock(&n->slock);
    return -1;
  }
  /* Two alternating files: a crash while writing one leaves the other. */
  n->ckpt_slot ^= 1;
  n->rollback_tried = 0; /* a field that learned on since is worth going back to */
  pthread_mutex_lock(&n->slock);
  n->st.checkpoints++;
  n->st.error_flags &= ~(unsigned)VLFF_NODE_ERR_CHECKPOINT;
  pthread_mutex_unlock(&n->slock);
  n->ckpt_steps = steps;
  VLFF_INFO(TAG, "checkpoint %s at step %lld", VLFF_Q(path), steps);
  return 0;
}

static void restore_checkpoint(struct vlff_node *n) {
  /* A node killed while writing a checkpoint leaves its temporary behind,
   * as large as a checkpoint: nothing else would ever remove it. */
  static const char *const temps[] = {"field.", "map.", NULL};
  int stale = vlff_remove_dead_temps(n->cfg.node.state_dir, temps);
  if (stale) VLFF_INFO(TAG, "removed %d temporary file(s) of a dead writer in %s", stale, n->cfg.node.state_dir);
  char path[2][VLFF_CFG_PATH + 32];
  struct stat sb[2];
  bool have[2];
  for (int i = 0; i < 2; i++) {
    ckpt_path(n, i, path[i], sizeof path[i]);
    have[i] = stat(path[i], &sb[i]) == 0;
  }
  /* Newest first; fall back to the other when it is refused. */
  int order[2] = {0, 1};
  if (have[0] && have[1] &&
      (sb[1].st_mtim.tv_sec > sb[0].st_mtim.tv_sec ||
       (sb[1].st_mtim.tv_sec == sb[0].st_mtim.tv_sec && sb[1].st_mtim.tv_nsec > sb[0].st_mtim.tv_nsec)))
    order[0] = 1, order[1] = 0;
  for (int k = 0; k < 2; k++) {
    int i = order[k];
    if (!have[i]) continue;
    char err[256];
    if (vlff_field_load(n->field, path[i], err, sizeof err) == 0) {
      VLFF_INFO(TAG, "resumed from %s at step %lld", VLFF_Q(path[i]), vlff_field_steps(n->field));
      n->resumed = true;
      n->ckpt_steps = vlff_field_steps(n->field);
      n->ckpt_slot = i ^ 1;
      n->rollback_tried = 1u << i; /* diverging before the next save goes to the other slot */
      char op[VLFF_CFG_PATH + 32];
      obs_path(n, i, op, sizeof op);
      if (vlff_publisher_load(n->pub, op, err, sizeof err))
        VLFF_WARN(TAG, "observation grid not restored (the map refills as keyframes arrive): %s", err);
      return;
    }
    VLFF_ERROR(TAG, "checkpoint refused, skipped: %s", err);
    pthread_mutex_lock(&n->slock);
    n->st.checkpoint_failures++;
    pthread_mutex_unlock(&n->slock);
  }
}

/* Render depth at the candidate's pose at low resolution and compare it with
 * what the frame measured, on surfaces the map has already seen measured.
 * The bar adapts to how well the map currently explains good frames: a
 * young map disagrees with every frame by tens of centimetres, a wrong pose
 * disagrees by several times more than the frames admitted just before. */
static bool pose_check(struct vlff_node *n, const struct candidate *c) {
  const struct vlff_config *cfg = &n->cfg;
  if (vlff_kfstore_count(n->store) < cfg->keyframes.start_after ||
      vlff_field_steps(n->field) < cfg->keyframes.posecheck_min_steps)
    return true;
  enum { S = 4 };
  int w = c->view.width / S, h = c->view.height / S;
  if (w < 4 || h < 4) return true;
  size_t px = (size_t)w * h;
  float *rd = malloc(px * sizeof(float)), *md = malloc(px * sizeof(float));
  int *lab = malloc(px * sizeof(int));
  unsigned char *hit = malloc(px);
  bool ok = true;
  if (rd && md && lab && hit) {
    struct vlff_view cam = c->view;
    cam.width = w;
    cam.height = h;
    cam.fx /= S, cam.fy /= S, cam.cx /= S, cam.cy /= S;
    if (vlff_field_render(n->field, &cam, NULL, rd, NULL, lab, NULL) == 0) {
      for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
          size_t i = (size_t)y * w + x;
          md[i] = c->view.depth[(size_t)(y * S + S / 2) * c->view.width + x * S + S / 2];
          double d = rd[i], wp[3];
          vlff_unproject(cam.c2w, cam.fx, cam.fy, cam.cx, cam.cy, x + 0.5, y + 0.5, d, wp);
          hit[i] = lab[i] >= 0 && isfinite(d) && vlff_publisher_surface_known(n->pub, wp);
        }
      struct vlff_pose_evidence ev;
      double med_r = 0, med_i = 0;
      int k = n->n_accepted < KF_HISTORY ? n->n_accepted : KF_HISTORY;
      if (k >= 4) {
        float tr[KF_HISTORY], ti[KF_HISTORY];
        memcpy(tr, n->accepted_res, (size_t)k * sizeof tr[0]);
        memcpy(ti, n->accepted_inl, (size_t)k * sizeof ti[0]);
        med_r = vlff_medianf(tr, (size_t)k), med_i = vlff_medianf(ti, (size_t)k);
      }
      enum vlff_posecheck v = vlff_pose_evidence(rd, hit, md, px, 0.15, cfg->keyframes.bad_pose_threshold_m,
                                                 cfg->train.depth_noise_m, &ev);
      if (v != VLFF_POSE_UNKNOWN) v = vlff_pose_verdict(&ev, med_r, med_i);
      pthread_mutex_lock(&n->slock);
      n->st.last_pose_residual_m = ev.residual_m;
      pthread_mutex_unlock(&n->slock);
      if (v == VLFF_POSE_BAD) {
        vlff_warn_limited(&n->warned.kf_rejected, TAG,
                  "keyframe %lld rejected: depth residual %.3f m, %.2f of what a good frame shows at its ranges, "
                  "with %.0f %% inliers (recent good: %.2f, %.0f %%)",
                  c->id, ev.residual_m, ev.residual, 100 * ev.inlier_frac, med_r, 100 * med_i);
        ok = false;
      } else if (v == VLFF_POSE_OK) {
        VLFF_DEBUG(TAG, "keyframe %lld pose ok: depth residual %.3f m (%.2f scaled), %.0f %% inliers", c->id,
                   ev.residual_m, ev.residual, 100 * ev.inlier_frac);
        n->accepted_res[n->n_accepted % KF_HISTORY] = (float)ev.residual;
        n->accepted_inl[n->n_accepted % KF_HISTORY] = (float)ev.inlier_frac;
        n->n_accepted++;
      }
    }
  }
  VLFF_FREE_ALL(rd, md, lab, hit);
  return ok;
}

static void take_candidates(struct vlff_node *n, bool wait) {
  struct candidate *batch[QUEUE_CAP];
  int nb;
  pthread_mutex_lock(&n->qlock);
  if (wait && n->qlen == 0) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    ts.tv_nsec += 20 * 1000 * 1000;
    if (ts.tv_nsec >= 1000000000) ts.tv_sec++, ts.tv_nsec -= 1000000000;
    pthread_cond_timedwait(&n->qcond, &n->qlock, &ts);
  }
  nb = n->qlen;
  memcpy(batch, n->queue, (size_t)nb * sizeof batch[0]);
  n->qlen = 0;
  pthread_mutex_unlock(&n->qlock);
  for (int i = 0; i < nb; i++) {
    struct candidate *c = batch[i];
    char verr[256];
    if (n->mapping && vlff_publisher_check_view(n->pub, &c->view, verr, sizeof verr)) {
      /* Implausible intrinsics or pose would make every ray of this view
       * wrong (and, unbounded, endless): never train on or map it. */
      vlff_warn_limited(&n->warned.kf_refused, TAG, "keyframe %lld refused (intrinsics at train.image_scale): %s",
                        c->id, verr);
      /* Counted under its reason like the ingest's refusals, which hold
       * frames to the same bounds at full size. */
      const struct vlff_view *v = &c->view;
      int reason = vlff_intrinsics_plausible(v->width, v->height, v->fx, v->fy, v->cx, v->cy, NULL, 0)
                       ? VLFF_REFUSED_BAD_INTRINSICS
                       : VLFF_REFUSED_POSE_RANGE;
      pthread_mutex_lock(&n->slock);
      n->st.frames_invalid++;
      n->st.refused[reason]++;
      n->st.last_refusal = reason;
      pthread_mutex_unlock(&n->slock);
    } else if (n->mapping) {
      if (!pose_check(n, c)) {
        STAT_ADD(n, poses_rejected, 1);
      } else {
        struct vlff_keyframe_in kin = {.id = c->id, .t_ns = (long long)c->t_host_ns, .view = c->view,
                                       .feature_dim = n->cfg.field.feature_dim};
        if (vlff_kfstore_add(n->store, &kin) == 0) {
          /* The view passed the same check just above: these cannot refuse it. */
          if (vlff_publisher_observe(n->pub, &c->view, verr, sizeof verr) == 0)
            vlff_publisher_set_camera(n->pub, &c->view, c->t_host_ns, c->id, verr, sizeof verr);
          if (n->pending_lat < 64) n->pending_t_host[n->pending_lat++] = c->t_host_ns;
        } else {
          vlff_warn_limited(&n->warned.kf_store, TAG, "keyframe %lld does not fit the keyframe store: %s", c->id,
                            strerror(errno));
        }
      }
    }
    candidate_free(c);
  }
}

static void do_publish(struct vlff_node *n) {
  char err[256];
  struct vlff_publish_result r;
  const char *texts[VLFF_MAX_PROMPTS];
  for (int i = 0; i < n->prompt_k; i++) texts[i] = n->prompt_text[i];
  double t0 = vlff_seconds();
  if (vlff_publisher_publish(n->pub, n->field, texts, n->prompt_k, &r, err, sizeof err)) {
    vlff_warn_limited(&n->warned.publish, TAG, "publish failed: %s", err);
    return;
  }
  VLFF_DEBUG(TAG, "published map v%llu in %.0f ms: %zu labelled, %zu free, %zu unknown voxels",
             (unsigned long long)r.version, (vlff_seconds() - t0) * 1e3, r.labelled, r.free_voxels, r.unknown);
  uint64_t now = vlff_shm_now_ns();
  for (int i = 0; i < n->pending_lat; i++) {
    double ms = (double)(now - n->pending_t_host[i]) * 1e-6;
    n->lat_ms[n->lat_n++ % LAT_CAP] = ms;
  }
  n->pending_lat = 0;
  int cnt = n->lat_n < LAT_CAP ? n->lat_n : LAT_CAP;
  double p50 = -1, p99 = -1;
  if (cnt > 0) {
    double *tmp = malloc((size_t)cnt * sizeof(double));
    if (tmp) {
      memcpy(tmp, n->lat_ms, (size_t)cnt * sizeof(double));
      for (int i = 1; i < cnt; i++) /* insertion sort: cnt is small */
        for (int j = i; j > 0 && tmp[j - 1] > tmp[j]; j--) {
          double t = tmp[j];
          tmp[j] = tmp[j - 1];
          tmp[j - 1] = t;
        }
      p50 = tmp[cnt / 2];
      p99 = tmp[(int)floor(0.99 * (cnt - 1))];
      free(tmp);
    }
  }
  pthread_mutex_lock(&n->slock);
  n->st.map_version = r.version;
  n->st.miou2d = r.miou2d;
  n->st.miou2d_frame = r.miou2d_frame;
  n->st.miou3d = r.miou3d;
  n->st.frame_to_map_ms_p50 = p50;
  n->st.frame_to_map_ms_p99 = p99;
  pthread_mutex_unlock(&n->slock);
}

static void reset_mapping(struct vlff_node *n) {
  char err[256];
  struct vlff_field *f = vlff_field_create(&n->cfg.field, &n->cfg.train, n->cfg.node.threads, err, sizeof err);
  struct vlff_kfstore *s =
      vlff_kfstore_create((size_t)n->cfg.keyframes.memory_mb << 20, n->cfg.keyframes.max_keyframes, KF_PROTECT);
  if (!f || !s) {
    VLFF_ERROR(TAG, "reset failed: %s", f ? "out of memory" : err);
    vlff_field_destroy(f);
    vlff_kfstore_destroy(s);
    return;
  }
  vlff_field_destroy(n->field);
  vlff_kfstore_destroy(n->store);
  n->field = f;
  n->resumed = false;
  n->ckpt_steps = -1; /* the saved map is no longer the learned one */
  n->store = s;
  vlff_publisher_reset(n->pub);
  if (n->prompt_emb) vlff_field_set_prompts(n->field, n->prompt_emb, n->prompt_k, err, sizeof err);
  VLFF_INFO(TAG, "mapping reset");
}

static void run_commands(struct vlff_node *n, bool *publish_now) {
  int cmds[16][2], nc;
  pthread_mutex_lock(&n->clock);
  nc = n->ncmds;
  memcpy(cmds, n->cmds, sizeof cmds);
  n->ncmds = 0;
  pthread_mutex_unlock(&n->clock);
  for (int i = 0; i < nc; i++) {
    char err[256];
    switch (cmds[i][0]) {
    case VLFF_CMD_START: n->mapping = true; VLFF_INFO(TAG, "mapping started"); break;
    case VLFF_CMD_STOP: n->mapping = false; VLFF_INFO(TAG, "mapping stopped"); break;
    case VLFF_CMD_RESET: reset_mapping(n); break;
    case VLFF_CMD_SAVE: save_checkpoint(n); break;
    case VLFF_CMD_PUBLISH: *publish_now = true; break;
    case VLFF_CMD_PROMPT_SET:
      if (apply_prompt_set(n, cmds[i][1], err, sizeof err))
        VLFF_ERROR(TAG, "prompt set command: %s", err);
      else
        *publish_now = true;
      break;
    }
  }
}

/* Every request gets an answer in the mailbox, so that the poster learns whether its
 * prompts were taken; a malformed or half-written one is answered by the library and
 * only logged here. */
static void poll_mailbox(struct vlff_node *n, uint64_t *seq, bool *publish_now) {
  struct vlff_prompt_request req;
  if (!n->mailbox) return;
  int got = vlff_prompts_poll(n->mailbox, seq, &req);
  if (got < 0) {
    /* Once per repair by the library (a forged state word or request number),
     * but a group member can forge them at every iteration. */
    vlff_warn_limited(&n->warned.mailbox, TAG, "prompt mailbox: %s", vlff_shm_last_message());
    return;
  }
  if (got != 1) return;
  char err[256];
  int rc;
  if (req.set_index >= 0) {
    rc = apply_prompt_set(n, req.set_index, err, sizeof err);
  } else {
    char texts[VLFF_MAX_PROMPTS][VLFF_PROMPT_LEN];
    int k = req.count > VLFF_MAX_PROMPTS ? VLFF_MAX_PROMPTS : req.count;
    for (int i = 0; i < k; i++) snprintf(texts[i], VLFF_PROMPT_LEN, "%s", req.text[i]);
    rc = apply_prompts(n, (const char(*)[VLFF_PROMPT_LEN])texts, k, -1, err, sizeof err);
  }
  if (rc)
    vlff_warn_limited(&n->warned.mailbox_refused, TAG, "prompt mailbox request %llu from pid %d refused: %s",
                      (unsigned long long)req.seq, req.poster_pid, err);
  else
    *publish_now = true;
  if (vlff_prompts_answer(n->mailbox, req.seq, rc == 0, rc ? err : NULL))
    vlff_warn_limited(&n->warned.mailbox_answer, TAG, "prompt mailbox: cannot answer request %llu: %s",
                      (unsigned long long)req.seq, vlff_shm_last_message());
}

static void update_state(struct vlff_node *n) {
  double now = vlff_seconds();
  pthread_mutex_lock(&n->slock);
  unsigned f = n->st.error_flags & VLFF_NODE_ERR_CHECKPOINT;
  if (vlff_frame_watch_lost(&n->fwatch, now, n->cfg.shm.ring)) f |= VLFF_NODE_ERR_CAMERA_LOST, n->st.fps_in = 0;
  if (n->last_frame_s > 0 && now - n->last_pose_ok_s > 2.0) f |= VLFF_NODE_ERR_POSE_STALE;
  if (n->last_lapped_s > 0 && now - n->last_lapped_s < 2.0) f |= VLFF_NODE_ERR_SHM_LAPPED;
  n->st.error_flags = f;
  n->st.keyframes = vlff_kfstore_count(n->store);
  n->st.keyframes_evicted = vlff_kfstore_evicted(n->store);
  n->st.state = !n->mapping ? VLFF_NODE_STOPPED
                : n->st.keyframes >= n->cfg.keyframes.start_after ? VLFF_NODE_OPERATIONAL
                                                                  : VLFF_NODE_PREOP;
  n->st.map_age_s = vlff_publisher_age_s(n->pub);
  pthread_mutex_unlock(&n->slock);
}

static const char *state_name(int state) {
  switch (state) {
  case VLFF_NODE_BOOT: return "boot";
  case VLFF_NODE_PREOP: return "preoperational";
  case VLFF_NODE_OPERATIONAL: return "operational";
  case VLFF_NODE_STOPPED: return "stopped";
  case VLFF_NODE_ERROR: return "error";
  default: return "unknown";
  }
}

/* The status, as --status and CAN have it, into the map segment for any
 * controller (vlff-shm stat, vlff-view). Every reason is listed, counted or
 * not, with its name, so that readers learn the list from the segment. */
static void share_status(struct vlff_node *n) {
  _Static_assert(VLFF_REFUSED_COUNT - 1 <= VLFF_SHM_MAX_REASONS, "every refusal reason fits the map's status");
  struct vlff_node_status st;
  vlff_node_status(n, &st);
  struct vlff_map_status ms = {
      .state = st.state,
      .error_flags = st.error_flags,
      .frames_in = (uint64_t)st.frames_in,
      .frames_lost = (uint64_t)st.frames_lost,
      .frames_refused = (uint64_t)st.frames_invalid,
      .keyframes = (uint64_t)st.keyframes,
      .keyframes_evicted = (uint64_t)st.keyframes_evicted,
      .iterations = (uint64_t)st.iteration,
      .iterations_per_s = st.it_per_s,
      .fps_in = st.fps_in,
      .loss = st.loss,
      .loss_rgb = st.loss_rgb,
      .loss_depth = st.loss_depth,
      .loss_feat = st.loss_feat,
      .psnr = st.psnr,
  };
  snprintf(ms.state_name, sizeof ms.state_name, "%s", state_name(st.state));
  for (int r = 1; r < VLFF_REFUSED_COUNT; r++) {
    struct vlff_map_reason *e = &ms.reason[ms.reason_count++];
    snprintf(e->name, sizeof e->name, "%s", vlff_refusal_name(r));
    e->count = (uint64_t)st.refused[r];
  }
  char err[320];
  /* A map truncated under the node is replaced by the library; say so. */
  if (vlff_publisher_set_status(n->pub, &ms, err, sizeof err))
    vlff_warn_limited(&n->warned.map_status, TAG, "map status: %s", err);
}

/* The young-field schedules, both keyed on the field's step count. */
static void apply_warmup(struct vlff_node *n) {
  /* A young field learns faster from more, cheaper steps: a quarter
   * of the batch at first, growing geometrically to all of it. Not for
   * a field resumed from a checkpoint, however young: its keyframes are
   * gone, and many small steps on its first few new ones would pull the
   * shared MLPs toward those views and away from the rest of the map
   * (the end-to-end kill -9 test saw 3D mIoU fall from 23 to 4). */
  const struct vlff_config *cfg = &n->cfg;
  int warm = cfg->train.warmup_steps, full = cfg->train.rays_per_step;
  long long steps = vlff_field_steps(n->field);
  if (warm > 0 && !n->resumed) {
    double fr = fmin(1.0, (double)steps / warm);
    vlff_field_set_rays(n->field, (int)lround(full / 4.0 * pow(4.0, fr)));
  }
  /* Coarse to fine: the coarse levels, shared by many samples, fit a
   * new view's layout in fewer steps, and the finer ones, cheaper to
   * leave out, add detail once it is there. Keyed on the field's own
   * step, so a field resumed young goes on where it stopped rather than
   * switching its untrained fine levels on at once. */
  int l0 = cfg->train.warmup_levels, lw = cfg->train.warmup_level_steps, levels = cfg->field.hash_levels;
  if (l0 > 0 && l0 < levels && lw > 0 && steps <= lw)
    vlff_field_set_levels(n->field, l0 + (int)((levels - l0) * steps / lw));
}

static void *trainer_main(void *arg) {
  pthread_setname_np(pthread_self(), "vlff-trainer"); /* as ingest_main's */
  struct vlff_node *n = arg;
  const struct vlff_config *cfg = &n->cfg;
  double next_publish = vlff_seconds() + 1.0 / cfg->publish.rate_hz;
  double next_ckpt = cfg->node.checkpoint_period_s > 0 ? vlff_seconds() + cfg->node.checkpoint_period_s : INFINITY;
  uint64_t mailbox_seq = 0;
  struct rate_meter steps = {vlff_seconds(), 0};
  double status_s = -INFINITY;
  /* A resumed map is published before it trains on anything new, so
   * controllers have it back at once. */
  bool first = n->resumed;
  if (first) apply_warmup(n);
  /* The first step scans: a resumed field's values may be within the bounds
   * and still overflow together from its first update on. */
  n->scanned_step = -FIELD_SCAN_STEPS;
  while (!atomic_load(&n->stop)) {
    atomic_store(&n->trainer_beat_ns, vlff_shm_now_ns());
    bool publish_now = first;
    first = false;
    run_commands(n, &publish_now);
    poll_mailbox(n, &mailbox_seq, &publish_now);
    bool train = n->mapping && vlff_kfstore_count(n->store) >= cfg->keyframes.start_after;
    take_candidates(n, !train);
    if (train) {
      const struct vlff_view *views;
      const float *w;
      int nv = vlff_kfstore_views(n->store, cfg->keyframes.recent, &views, &w);
      apply_warmup(n);
      struct vlff_train_stats ts;
      char err[256];
      int rc = vlff_field_step(n->field, views, nv, w, &ts, err, sizeof err);
      if (rc == 0) {
        n->nonfinite_run = 0;
        /* Values can run out of bounds while every loss stays finite (a forged
         * checkpoint's weights of 1e6 drove Adam's m to 2e10 with a loss of
         * 1e29): the field is scanned every FIELD_SCAN_STEPS steps, a pass
         * over its parameters and moments, not only before a checkpoint. */
        if (ts.step - n->scanned_step >= FIELD_SCAN_STEPS) {
          char why[256];
          n->scanned_step = ts.step;
          if (vlff_field_check(n->field, why, sizeof why)) {
            roll_back(n, why);
            n->scanned_step = vlff_field_steps(n->field);
            continue;
          }
        }
        steps.count++;
        pthread_mutex_lock(&n->slock);
        n->st.iteration = ts.step;
        n->st.loss = ts.loss;
        n->st.loss_rgb = ts.loss_rgb;
        n->st.loss_depth = ts.loss_depth;
        n->st.loss_feat = ts.loss_feat;
        n->st.psnr = ts.psnr;
        pthread_mutex_unlock(&n->slock);
      } else if (rc == -2) {
        step_not_finite(n, err);
      } else {
        vlff_warn_limited(&n->warned.step_failed, TAG, "training step failed: %s", err);
      }
    }
    double now = vlff_seconds();
    rate_publish(&steps, now, n, &n->st.it_per_s);
    /* An untrained field has nothing to say: readers see version 0 until
     * the first step, and the heartbeat says the writer is alive. */
    bool published = false;
    if ((publish_now || now >= next_publish) && vlff_field_steps(n->field) > 0) {
      do_publish(n);
      published = true;
      /* publish.rate_hz is an upper bound: publishing never takes more than
       * a fifth of the trainer's time, or learning would stall behind it. */
      double spent = vlff_seconds() - now;
      next_publish = now + fmax(1.0 / cfg->publish.rate_hz, 5.0 * spent);
    } else {
      vlff_publisher_heartbeat(n->pub);
    }
    if (now >= next_ckpt) {
      save_checkpoint(n);
      next_ckpt = now + cfg->node.checkpoint_period_s;
    }
    update_state(n);
    /* Controllers see the status as often as the heartbeat says "alive". */
    if (published || now - status_s >= 0.1) {
      share_status(n);
      status_s = now;
    }
    if (cfg->node.run_seconds > 0 && now - n->t_start >= cfg->node.run_seconds) {
      atomic_store(&n->finished, true);
      break;
    }
  }
  share_status(n); /* the counts the node stopped with */
  return NULL;
}

/* ---- lifecycle ---------------------------------------------------------- */

struct vlff_node *vlff_node_create(const struct vlff_config *cfg, const struct vlff_source_hooks *hooks, char *err,
                                   size_t errlen) {
  static const struct vlff_source_hooks none;
  if (!hooks) hooks = &none;
  if (cfg->source.kind == VLFF_SOURCE_DATASET) {
    snprintf(err, errlen, "source.kind: dataset is for vlff-eval; vlff-node reads the frame ring (sim or ring)");
    return NULL;
  }
#ifndef VLFF_HAVE_VLM
  if (cfg->source.features == VLFF_FEAT_MODEL || cfg->vlm.text_model[0]) {
    snprintf(err, errlen, "%s: this vlff-node was built without OpenCV (VLFF_WITH_OPENCV=OFF)",
             cfg->source.features == VLFF_FEAT_MODEL ? "source.features: model" : "vlm.text_model");
    return NULL;
  }
#endif
  if (!cfg->prompts.embeddings[0] && !cfg->vlm.text_model[0] && !hooks->embed) {
    /* Checked before any segment is made: without a text encoder no prompt
     * can be embedded, and the node would stop at the first one. */
    snprintf(err, errlen, "no text encoder for the prompts: set prompts.embeddings (a precomputed file) or "
             "vlm.text_model (the CLIP text encoder, ONNX)");
    return NULL;
  }
  if (vlff_config_sim_features_misused(cfg)) {
    snprintf(err, errlen, "source.features: sim with source.kind: ring pairs the simulator's features with a "
             "camera's images; use ring or model, or set source.allow_sim_features: true to force it");
    return NULL;
  }
  if (cfg->source.features == VLFF_FEAT_SIM && !hooks->features) {
    snprintf(err, errlen, "source.features: sim, but the source gives no features (vlff-node makes the simulator's "
             "hooks; a program embedding the node passes them to vlff_node_create)");
    return NULL;
  }
  struct vlff_node *n = calloc(1, sizeof *n);
  if (!n) return snprintf(err, errlen, "out of memory"), NULL;
  n->cfg = *cfg;
  n->hooks = *hooks;
  n->mapping = true;
  n->t_start = vlff_seconds();
  vlff_frame_watch_init(&n->fwatch, n->t_start);
  n->st.prompt_set = cfg->prompts.active;
  n->st.map_age_s = -1;
  n->st.miou2d = n->st.miou3d = -1;
  n->st.miou2d_frame = -1;
  n->st.last_pose_residual_m = -1;
  n->st.frame_to_map_ms_p50 = n->st.frame_to_map_ms_p99 = -1;
  pthread_mutex_init(&n->qlock, NULL);
  pthread_cond_init(&n->qcond, NULL);
  pthread_mutex_init(&n->clock, NULL);
  pthread_mutex_init(&n->slock, NULL);

  if (mkdir(cfg->node.state_dir, 0750) != 0 && errno != EEXIST) {
    snprintf(err, errlen, "node.state_dir '%s': %s", VLFF_Q(cfg->node.state_dir), strerror(errno));
    goto fail;
  }
  n->field = vlff_field_create(&cfg->field, &cfg->train, cfg->node.threads, err, errlen);
  if (!n->field) goto fail;
  n->store = vlff_kfstore_create((size_t)cfg->keyframes.memory_mb << 20, cfg->keyframes.max_keyframes, KF_PROTECT);
  if (!n->store) {
    snprintf(err, errlen, "keyframe store: %s", strerror(errno));
    goto fail;
  }
  n->model_h = cfg->vlm.input_height;
  n->model_w = cfg->vlm.input_width;
  if (cfg->prompts.embeddings[0]) {
    n->emb_file = vlff_embeddings_load(cfg->prompts.embeddings, cfg->field.feature_dim, err, errlen);
    if (!n->emb_file) goto fail;
  }
#ifdef VLFF_HAVE_VLM
  if (!n->emb_file && cfg->vlm.text_model[0]) {
    n->text_enc = vlff_text_encoder_open(&cfg->vlm, cfg->prompts.templ, cfg->field.feature_dim, err, errlen);
    if (!n->text_enc) goto fail;
  }
  if (cfg->source.features == VLFF_FEAT_MODEL) {
    struct vlff_image_encoder *enc = vlff_image_encoder_open(&cfg->vlm, cfg->field.feature_dim, err, errlen);
    if (!enc) goto fail;
    int dd;
    vlff_image_encoder_shape(enc, &dd, &n->model_h, &n->model_w);
    n->image_worker = vlff_image_worker_start(enc, 2, err, errlen);
    if (!n->image_worker) goto fail;
  }
#endif
  n->pub = vlff_publisher_create(&cfg->publish, &cfg->shm, &cfg->field, &n->hooks, err, errlen);
  if (!n->pub) goto fail;
  /* Controllers of the segments' group post prompts: the mailbox alone is
   * group-writable whenever the group may read. */
  mode_t mode = cfg->shm.mode ? (mode_t)cfg->shm.mode : 0640;
  if (mode & S_IRGRP) mode |= S_IWGRP;
  struct vlff_shm_perm perm = {.mode = mode, .group = cfg->shm.group};
  n->mailbox = vlff_prompts_create(cfg->shm.prompts, &perm);
  if (!n->mailbox) {
    snprintf(err, errlen, "prompt mailbox %s: %s", cfg->shm.prompts, vlff_shm_last_message());
    goto fail;
  }
  restore_checkpoint(n);
  if (apply_prompt_set(n, cfg->prompts.active, err, errlen)) goto fail;
  atomic_store(&n->trainer_beat_ns, vlff_shm_now_ns());
  atomic_store(&n->ingest_beat_ns, vlff_shm_now_ns());
  if (pthread_create(&n->trainer_thread, NULL, trainer_main, n) != 0) {
    snprintf(err, errlen, "cannot start the trainer thread");
    goto fail;
  }
  n->trainer_started = true;
  if (pthread_create(&n->ingest_thread, NULL, ingest_main, n) != 0) {
    snprintf(err, errlen, "cannot start the ingest thread");
    goto fail;
  }
  n->ingest_started = true;
  return n;
fail:
  vlff_node_destroy(n, false);
  return NULL;
}

void vlff_node_stop(struct vlff_node *n) { atomic_store(&n->stop, true); }

/* After this only the calling thread touches the node. */
static void join_threads(struct vlff_node *n) {
  if (n->joined) return;
  atomic_store(&n->stop, true);
  if (n->ingest_started) pthread_join(n->ingest_thread, NULL);
  if (n->trainer_started) pthread_join(n->trainer_thread, NULL);
  n->joined = true;
}

bool vlff_node_finished(struct vlff_node *n) {
  return atomic_load(&n->finished) || atomic_load(&n->stop);
}

void vlff_node_destroy(struct vlff_node *n, bool save_on_exit) {
  if (!n) return;
  join_threads(n);
  if (save_on_exit && n->field && n->trainer_started && vlff_field_steps(n->field) > 0) save_checkpoint(n);
  for (int i = 0; i < n->qlen; i++) candidate_free(n->queue[i]);
  vlff_publisher_destroy(n->pub);
  vlff_prompts_close(n->mailbox);
  vlff_field_destroy(n->field);
  vlff_kfstore_destroy(n->store);
  vlff_embeddings_free(n->emb_file);
#ifdef VLFF_HAVE_VLM
  vlff_text_encoder_close(n->text_enc);
  vlff_image_worker_stop(n->image_worker);
#endif
  free(n->prompt_emb);
  pthread_mutex_destroy(&n->qlock);
  pthread_cond_destroy(&n->qcond);
  pthread_mutex_destroy(&n->clock);
  pthread_mutex_destroy(&n->slock);
  free(n);
}

int vlff_node_snapshot(struct vlff_node *n, struct vlff_snapshot *out, char *err, size_t errlen) {
  join_threads(n);
  memset(out, 0, sizeof *out);
  if (vlff_field_steps(n->field) == 0) return snprintf(err, errlen, "the field was never trained"), -1;
  const char *texts[VLFF_MAX_PROMPTS];
  for (int i = 0; i < n->prompt_k; i++) texts[i] = n->prompt_text[i];
  do_publish(n); /* the snapshot shows the final map */
  return vlff_publisher_snapshot(n->pub, n->field, texts, n->prompt_k, out, err, errlen);
}

void vlff_node_status(struct vlff_node *n, struct vlff_node_status *out) {
  pthread_mutex_lock(&n->slock);
  *out = n->st;
  pthread_mutex_unlock(&n->slock);
  out->trainer_beat_ns = atomic_load(&n->trainer_beat_ns);
  out->ingest_beat_ns = atomic_load(&n->ingest_beat_ns);
}

int vlff_node_command(struct vlff_node *n, int cmd, int arg) {
  if (cmd < VLFF_CMD_START || cmd > VLFF_CMD_PUBLISH) return -1;
  if (cmd == VLFF_CMD_PROMPT_SET && (arg < 0 || arg >= n->cfg.prompts.set_count)) return -1;
  pthread_mutex_lock(&n->clock);
  int rc = -1;
  if (n->ncmds < 16) {
    n->cmds[n->ncmds][0] = cmd;
    n->cmds[n->ncmds][1] = arg;
    n->ncmds++;
    rc = 0;
  }
  pthread_mutex_unlock(&n->clock);
  return rc;
}
