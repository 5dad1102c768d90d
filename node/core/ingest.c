/*
 * The ingest thread (vlff-ingest): its loop (ingest_main), the frame, pose
 * and feature rings it attaches and follows, the producer side of the
 * candidate queue, the keyframes waiting for their features (the pending
 * list) and the feature join. A frame's own stages are in admit.c.
 *
 * Thread: ingest only, except candidate_free, which whoever holds a
 * candidate calls (the trainer after taking it, destroy for what is left).
 * State: everything in struct ingest, local to ingest_main; of the node,
 * the image worker (submit and poll) and its counters in warned
 * (feature_ring, encoder); refusals through refuse() (admit.c).
 * Locks: qlock to push a candidate, slock for the status counts (short,
 * never across work, never two at once; node_internal.h).
 */
#include <errno.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "clock.h"
#include "feature_join.h"
#include "log.h"
#include "mem.h"
#include "node_internal.h"
#include "vlff/escape.h"
#include "vlff/shm.h"

void candidate_free(struct candidate *c) {
  if (!c) return;
  VLFF_FREE_ALL(c->rgb, c->depth, c->features, c);
}

void queue_push(struct vlff_node *n, struct candidate *c) {
  struct candidate *dropped = NULL;
  c->t_queued_ns = vlff_now_ns();
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

void pending_remove(struct candidate **pending, int *npend, int i) {
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
struct vlff_ring *attach_input(struct vlff_node *n, const char *name, uint32_t kind) {
  return vlff_ring_attach_owned(name, kind, geteuid(), shm_mode(n));
}

static struct vlff_ring *attach_retry(struct vlff_node *n, const char *name, uint32_t kind) {
  int refused = 0;
  while (!atomic_load(&n->stop)) {
    atomic_store(&n->ingest_beat_ns, vlff_now_ns());
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

/* Features that arrived (external extractor or in-node model) complete
 * their waiting keyframes; keyframes whose features never come expire. */
static void ingest_features(struct ingest *ig, struct vlff_ring **feats, uint16_t *fbuf, int model_h, int model_w) {
  struct vlff_node *n = ig->n;
  const struct vlff_config *cfg = ig->cfg;
  if (ig->join && !*feats) {
    *feats = attach_input(n, cfg->shm.feature_ring, VLFF_RECORD_FEATURE);
    /* From the oldest record the ring still holds, not the newest: the frame
     * ring may have been attached first, and a frame read before this attach
     * can have its features committed already (an extractor that started
     * with its camera, or one that replaced its ring). The join keeps maps
     * nobody waits for as orphans and evicts them oldest first; maps of
     * frames older than a keyframe may wait for them are passed over, since
     * an earlier camera session's frame ids may come again. */
    if (*feats) {
      vlff_ring_seek_oldest(*feats);
      uint64_t now = vlff_now_ns(), back = (uint64_t)(cfg->vlm.feature_timeout_s * 1e9);
      vlff_feature_join_not_before(ig->join, now > back ? now - back : 0);
    }
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
    /* A bad record is named (rate-limited) and counted, not left to show
     * up later as its keyframe's "features late". */
    struct vlff_feature_join_stats js;
    vlff_feature_join_stats(ig->join, &js);
    if (js.bad_records > ig->feats_bad) {
      vlff_warn_limited(&n->warned.feature_bad, TAG, "feature ring %s: %llu bad records refused so far; the latest: %s",
                        cfg->shm.feature_ring, (unsigned long long)js.bad_records,
                        vlff_feature_join_last_bad(ig->join));
      ig->feats_bad = js.bad_records;
    }
    uint64_t fid;
    int fh, fw, ev;
    while ((ev = vlff_feature_join_poll(ig->join, vlff_now_ns(), &fid, fbuf, &fh, &fw)) != VLFF_JOIN_NONE) {
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
      refuse(n, &ig->rl, VLFF_REFUSED_FEATURES_LATE, ig->pending[i]->id, "its features did not arrive within "
             "vlm.feature_timeout_s (%g s): the feature source lags or stopped", cfg->vlm.feature_timeout_s);
      candidate_free(ig->pending[i]);
      pending_remove(ig->pending, &ig->npend, i);
      i--;
    }
}

void *ingest_main(void *arg) {
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
    atomic_store(&n->ingest_beat_ns, vlff_now_ns());
    ingest_features(&ig, &feats, fbuf, model_h, model_w);
    ingest_held(&ig, vlff_seconds());
    refusal_summary(n, &ig.rl, vlff_seconds());
    struct vlff_ring_view info;
    /* A held frame, and a keyframe waiting for its features (their ring and
     * the image worker are polled at the top of this loop, not waited on),
     * are looked at again soon after each short wait: with the long one, a
     * keyframe's features that came just after it waited up to 50 ms more
     * before the keyframe went to the trainer, on every keyframe's
     * frame-to-map latency. */
    uint64_t wait_ns = ig.holding || ig.npend > 0 ? 5 * 1000 * 1000ull : 50 * 1000 * 1000ull;
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
