/*
 * The trainer thread (vlff-trainer): its loop (trainer_main) takes the
 * candidates the ingest thread queued, checks their poses against the map,
 * stores keyframes, runs the field's steps with their young-field
 * schedules, publishes the map and times checkpoints, commands and status
 * (checkpoint.c, commands.c).
 *
 * Thread: trainer only, except do_publish, which vlff_node_snapshot also
 * calls once the threads are joined.
 * State: the field, the keyframe store, the publisher and the
 * trainer-private fields of struct vlff_node (node_internal.h).
 * Locks: qlock to take candidates (the only wait, a short timed one when
 * there is nothing to train), slock for the status (short, never across
 * work, never two at once).
 */
#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "bounds.h"
#include "clock.h"
#include "field.h"
#include "keyframes.h"
#include "log.h"
#include "mem.h"
#include "node_internal.h"
#include "publish.h"
#include "refresh.h"
#include "select.h"
#include "stats.h"
#include "vlff/shm.h"

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

/* A keyframe's measured points and its camera: their box, false when the
 * view has no depth. Every fourth pixel of every fourth row: the box of a
 * surface, not of each pixel. */
static bool view_extent(const struct vlff_view *v, double lo[3], double hi[3]) {
  const double *T = v->c2w;
  for (int a = 0; a < 3; a++) lo[a] = hi[a] = T[4 * a + 3];
  if (!v->depth) return false;
  bool any = false;
  for (int y = 0; y < v->height; y += 4)
    for (int x = 0; x < v->width; x += 4) {
      float d = v->depth[(size_t)y * v->width + x];
      if (!(d > 0) || !isfinite(d)) continue;
      double c[3] = {(x + 0.5 - v->cx) / v->fx * d, (y + 0.5 - v->cy) / v->fy * d, d};
      for (int a = 0; a < 3; a++) {
        double w = T[4 * a] * c[0] + T[4 * a + 1] * c[1] + T[4 * a + 2] * c[2] + T[4 * a + 3];
        lo[a] = fmin(lo[a], w), hi[a] = fmax(hi[a], w);
      }
      any = true;
    }
  return any;
}

/* field.grow: a keyframe whose camera or measured points (with a margin for
 * the samples around a surface) leave the field's or the map's box grows
 * both, ahead of what it needs by a quarter of the box's side on that axis
 * (at least GROW_AHEAD_M): each growth copies every grid, so a robot walking
 * on grows them a few times per building rather than every few keyframes.
 * When a cap refuses that, the growth is tried again with the margin alone,
 * and where a cap refuses both, each grid slides with the camera instead
 * (docs/field.md "Beyond the caps").
 * What cannot grow even then (the world's limit, a memory cap) is said,
 * rate-limited, and counted; the keyframe is trained and mapped within the
 * box as it is. */
#define GROW_NEAR_M 0.25
#define GROW_AHEAD_M 1.0
static void grow_to_view(struct vlff_node *n, const struct vlff_view *v) {
  double lo[3], hi[3], flo[3], fhi[3], plo[3], phi[3];
  if (!n->cfg.field.grow || !view_extent(v, lo, hi)) return;
  vlff_field_box(n->field, flo, fhi);
  vlff_publisher_box(n->pub, plo, phi, NULL);
  bool held = true;
  double alo[3], ahi[3];
  for (int a = 0; a < 3; a++) {
    lo[a] -= GROW_NEAR_M, hi[a] += GROW_NEAR_M;
    held = held && lo[a] >= fmax(flo[a], plo[a]) && hi[a] <= fmin(fhi[a], phi[a]);
    double ahead = fmax(GROW_AHEAD_M, 0.25 * (phi[a] - plo[a]));
    alo[a] = lo[a] < plo[a] || lo[a] < flo[a] ? lo[a] - ahead : lo[a];
    ahi[a] = hi[a] > phi[a] || hi[a] > fhi[a] ? hi[a] + ahead : hi[a];
  }
  if (held) return;
  char e[320];
  /* Growing (the wanted box, else the needed one) before sliding: a growth
   * keeps every cell. */
  int rf = vlff_field_grow(n->field, alo, ahi, e, sizeof e);
  if (rf < 0) rf = vlff_field_grow(n->field, lo, hi, e, sizeof e);
  if (rf < 0) rf = vlff_field_slide(n->field, alo, ahi, e, sizeof e);
  if (rf < 0) rf = vlff_field_slide(n->field, lo, hi, e, sizeof e);
  if (rf < 0) vlff_warn_limited(&n->warned.grow, TAG, "the box does not grow: %s", e);
  int rp = vlff_publisher_grow(n->pub, alo, ahi, lo, hi, e, sizeof e);
  if (rp < 0) vlff_warn_limited(&n->warned.grow, TAG, "the box does not grow: %s", e);
  if (rf < 0 || rp < 0) n->grow_refused++;
  if (rf > 0 || rp > 0) {
    vlff_field_box(n->field, flo, fhi);
    vlff_publisher_box(n->pub, plo, phi, NULL);
    VLFF_INFO(TAG, "box grown for keyframe at (%.1f, %.1f, %.1f): field [%.1f, %.1f] x [%.1f, %.1f] x [%.1f, %.1f] m, "
                   "map [%.1f, %.1f] x [%.1f, %.1f] x [%.1f, %.1f] m%s",
              v->c2w[3], v->c2w[7], v->c2w[11], flo[0], fhi[0], flo[1], fhi[1], flo[2], fhi[2], plo[0], phi[0],
              plo[1], phi[1], plo[2], phi[2],
              rp == 2   ? " (refitted at shm.map_max_voxels: the voxels that held nothing beyond it dropped)"
              : rp == 3 ? " (slid at shm.map_max_voxels: what it left is in the far map)"
                        : "");
  }
}

static bool contradicted(void *pub, const struct vlff_view *v) { return vlff_publisher_contradicted(pub, v); }

/* Newer depth saw through surfaces the map had measured (a thing moved or
 * went): the keyframes that show them are no longer trained on, or the
 * field would keep them where they were. */
static void retire_contradicted(struct vlff_node *n) {
  long long c = vlff_publisher_cleared(n->pub);
  if (c == n->cleared_seen) return;
  n->cleared_seen = c;
  int k = vlff_kfstore_retire(n->store, contradicted, n->pub);
  if (k) VLFF_DEBUG(TAG, "%d keyframes retired: newer depth sees through what they show", k);
}

static void take_candidates(struct vlff_node *n, bool wait) {
  struct candidate *batch[QUEUE_CAP];
  int nb;
  pthread_mutex_lock(&n->qlock);
  if (wait && n->qlen == 0) {
    /* pthread_cond_timedwait's deadline is on the wall clock */
    uint64_t until = vlff_wall_ns() + 20 * 1000 * 1000;
    struct timespec ts = {.tv_sec = (time_t)(until / 1000000000u), .tv_nsec = (long)(until % 1000000000u)};
    pthread_cond_timedwait(&n->qcond, &n->qlock, &ts);
  }
  nb = n->qlen;
  memcpy(batch, n->queue, (size_t)nb * sizeof batch[0]);
  n->qlen = 0;
  pthread_mutex_unlock(&n->qlock);
  for (int i = 0; i < nb; i++) {
    struct candidate *c = batch[i];
    char verr[256];
    uint64_t now = vlff_now_ns();
    VLFF_DEBUG(TAG, "keyframe %lld taken: captured %.0f ms ago, queued %.0f ms ago", c->id,
               (double)(now - c->t_host_ns) * 1e-6, (double)(now - c->t_queued_ns) * 1e-6);
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
          if (!n->kf_full_said && vlff_kfstore_evicted(n->store) > 0) {
            n->kf_full_said = true;
            VLFF_INFO(TAG, "keyframes: the store is full at %d keyframes (keyframes.memory_mb %d MiB, "
                           "max_keyframes %d); from now on each new one replaces the most redundant (the view "
                           "nearest another), counted as evicted, %s",
                      vlff_kfstore_count(n->store), n->cfg.keyframes.memory_mb, n->cfg.keyframes.max_keyframes,
                      n->cfg.keyframes.page_mb > 0 ? "which goes to keyframes.pages (keyframes.page_mb) and comes "
                                                     "back when the camera returns near it"
                                                   : "and dropped (keyframes.page_mb 0)");
          }
          /* The camera back where it has been: a view of it paged out comes
           * back, at most one a keyframe. */
          if (vlff_kfstore_page_in(n->store, c->view.c2w, KF_PAGE_IN_RADIUS) > 0) {
            VLFF_DEBUG(TAG, "keyframes: one paged keyframe back near keyframe %lld", c->id);
            /* Newer depth may have seen through what it shows while it was
             * on disk (retire_contradicted below judges it now). */
            n->cleared_seen = -1;
          }
          /* With keyframes.page_mb 0 dropping is what was asked for, and
           * the store's first fill said so. */
          long long dropped = vlff_kfstore_dropped(n->store);
          if (n->cfg.keyframes.page_mb > 0 && dropped > n->kf_dropped_said) {
            n->kf_dropped_said = dropped;
            vlff_warn_limited(&n->warned.kf_store, TAG, "keyframes: %lld evicted keyframes dropped, not paged: %s",
                              dropped, vlff_kfstore_page_error(n->store));
          }
          grow_to_view(n, &c->view);
          /* The view passed the same check just above: these cannot refuse it. */
          if (vlff_publisher_observe(n->pub, &c->view, verr, sizeof verr) == 0)
            vlff_publisher_set_camera(n->pub, &c->view, c->t_host_ns, c->id, verr, sizeof verr);
          retire_contradicted(n);
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

static bool candidates_waiting(struct vlff_node *n) {
  pthread_mutex_lock(&n->qlock);
  bool any = n->qlen > 0;
  pthread_mutex_unlock(&n->qlock);
  return any;
}

/* What a publish did to the node's figures: the map version; with covers,
 * the frame-to-map latency of every keyframe admitted before it (their
 * voxels are in this version's change log); the scores when the map was
 * wholly refreshed. */
static void note_publish(struct vlff_node *n, const struct vlff_publish_result *r, bool covers) {
  double p50 = -1, p99 = -1;
  if (covers) {
    uint64_t now = vlff_now_ns();
    for (int i = 0; i < n->pending_lat; i++) {
      double ms = (double)(now - n->pending_t_host[i]) * 1e-6;
      n->lat_ms[n->lat_n++ % LAT_CAP] = ms;
    }
    n->pending_lat = 0;
    int cnt = n->lat_n < LAT_CAP ? n->lat_n : LAT_CAP;
    if (cnt > 0) {
      double *tmp = malloc((size_t)cnt * sizeof(double));
      if (tmp) {
        memcpy(tmp, n->lat_ms, (size_t)cnt * sizeof(double));
        p99 = vlff_percentile(tmp, (size_t)cnt, 0.99);
        p50 = tmp[cnt / 2]; /* tmp is sorted now: the upper middle value, as vlff_medianf */
        free(tmp);
      }
    }
  }
  pthread_mutex_lock(&n->slock);
  n->st.map_version = r->version;
  if (r->scored) {
    n->st.miou2d = r->miou2d;
    n->st.miou2d_frame = r->miou2d_frame;
    n->st.miou3d = r->miou3d;
  }
  if (p50 >= 0) {
    n->st.frame_to_map_ms_p50 = p50;
    n->st.frame_to_map_ms_p99 = p99;
  }
  n->st.label_flips = (long long)r->flips;
  n->st.label_flips_total += (long long)r->flips;
  n->st.label_flips_elsewhere += (long long)r->flips_elsewhere;
  n->st.label_mapped_elsewhere += (long long)r->mapped_elsewhere;
  n->round_flips += (long long)r->flips;
  n->round_flips_elsewhere += (long long)r->flips_elsewhere;
  n->round_mapped_elsewhere += (long long)r->mapped_elsewhere;
  if (r->cycle_done) {
    /* Over a whole refresh every labelled voxel was relabelled once: the
     * share of those no keyframe saw again that flipped is the churn a
     * reader sees between two of its copies of the map. */
    n->st.label_flips_refresh = n->round_flips;
    n->st.label_flip_frac =
        n->round_mapped_elsewhere > 0 ? (double)n->round_flips_elsewhere / (double)n->round_mapped_elsewhere : -1;
    n->round_flips = n->round_flips_elsewhere = n->round_mapped_elsewhere = 0;
  }
  pthread_mutex_unlock(&n->slock);
}

static void prompt_texts(const struct vlff_node *n, const char **texts) {
  for (int i = 0; i < n->prompt_k; i++) texts[i] = n->prompt_text[i];
}

void do_publish(struct vlff_node *n) {
  char err[256];
  struct vlff_publish_result r;
  const char *texts[VLFF_MAX_PROMPTS];
  prompt_texts(n, texts);
  double t0 = vlff_seconds();
  if (vlff_publisher_publish(n->pub, n->field, texts, n->prompt_k, &r, err, sizeof err)) {
    vlff_warn_limited(&n->warned.publish, TAG, "publish failed: %s", err);
    return;
  }
  VLFF_DEBUG(TAG, "published map v%llu in %.0f ms: %zu labelled, %zu free, %zu unknown voxels",
             (unsigned long long)r.version, (vlff_seconds() - t0) * 1e3, r.labelled, r.free_voxels, r.unknown);
  note_publish(n, &r, true);
}

/* What the keyframes admitted since the last publish changed, at once:
 * true when it had to be a whole publish (new prompts, a reset). */
static bool publish_changed(struct vlff_node *n) {
  char err[256];
  struct vlff_publish_result r;
  const char *texts[VLFF_MAX_PROMPTS];
  prompt_texts(n, texts);
  double t0 = vlff_seconds();
  if (vlff_publisher_publish_changed(n->pub, n->field, texts, n->prompt_k, &r, err, sizeof err)) {
    vlff_warn_limited(&n->warned.publish, TAG, "publish failed: %s", err);
    return false;
  }
  VLFF_DEBUG(TAG, "published map v%llu (%s) in %.0f ms: %zu voxels", (unsigned long long)r.version,
             r.whole ? "whole" : "keyframes", (vlff_seconds() - t0) * 1e3, r.changed);
  note_publish(n, &r, true);
  return r.whole;
}

/* The map's round-robin refresh up to fraction `to` of the grid: true when
 * it ended a round (the whole map refreshed); *whole when that took a
 * whole publish (owed after a reset or new prompts). */
static bool publish_slice(struct vlff_node *n, double to, bool *whole) {
  char err[256];
  struct vlff_publish_result r;
  const char *texts[VLFF_MAX_PROMPTS];
  prompt_texts(n, texts);
  double t0 = vlff_seconds();
  *whole = false;
  if (vlff_publisher_publish_slice(n->pub, n->field, texts, n->prompt_k, to, &r, err, sizeof err)) {
    vlff_warn_limited(&n->warned.publish, TAG, "publish failed: %s", err);
    return false;
  }
  *whole = r.whole;
  VLFF_DEBUG(TAG, "published map v%llu (%s) in %.0f ms: %zu voxels changed", (unsigned long long)r.version,
             r.whole ? "whole" : r.cycle_done ? "last slice" : "slice", (vlff_seconds() - t0) * 1e3, r.changed);
  /* A whole publish (owed after a reset or new prompts) covers every keyframe. */
  note_publish(n, &r, r.whole);
  return r.cycle_done;
}

/* The next piece of what a round of slices owes (publish.h). */
static void publish_image(struct vlff_node *n) {
  char err[256];
  struct vlff_publish_result r;
  const char *texts[VLFF_MAX_PROMPTS];
  prompt_texts(n, texts);
  double t0 = vlff_seconds();
  if (vlff_publisher_publish_image(n->pub, n->field, texts, n->prompt_k, &r, err, sizeof err)) {
    vlff_warn_limited(&n->warned.publish, TAG, "publish failed: %s", err);
    return;
  }
  VLFF_DEBUG(TAG, "label image piece in %.0f ms (map v%llu)%s", (vlff_seconds() - t0) * 1e3,
             (unsigned long long)r.version, r.scored ? ", scored" : "");
  note_publish(n, &r, false);
}

/* A refresh round ended (refresh.h): the mean time between rounds into
 * the status once there is one. */
static void refresh_round_end(struct vlff_node *n, struct vlff_refresh *rf, double end, bool counted, bool whole) {
  double prev = rf->last_end, cost = rf->cost;
  double mean = vlff_refresh_round_end(rf, end, counted, whole);
  VLFF_DEBUG(TAG, "refresh round ended (%s): %.2f s after the last, its slices %.0f ms, a pass %.0f ms",
             whole ? "whole" : "slices", prev >= 0 ? end - prev : -1.0, cost * 1e3, rf->pass * 1e3);
  if (mean < 0) return;
  pthread_mutex_lock(&n->slock);
  n->st.publish_interval_s = mean;
  pthread_mutex_unlock(&n->slock);
}

/* Under node.cpu_budget below one core, the publishing work's shares of
 * the trainer's time (keyframes, the refresh) shrink with the budget: they
 * run outside the pacer, which delays only training, and at their
 * one-core shares they alone would pass a small budget. */
static double work_scale(const struct vlff_node *n) {
  double b = n->cfg.node.cpu_budget;
  return b > 0 && b < 1 ? b : 1.0;
}

/* Keyframes go first: what admitted keyframes saw is published at once
 * (the frame-to-map latency is the time to here). A publish that cost c
 * waits c (3 / s - 1) before the next, s = work_scale (what is admitted
 * meanwhile goes out with it), so keyframes never take more than s / 3 of
 * the trainer's time: on a slow machine (a sanitizer build's, a small
 * core's) they would take all of it, and the field would not train, nor
 * the mailbox be answered. */
static bool publish_keyframes(struct vlff_node *n, struct vlff_refresh *rf, double *next_kf_publish) {
  if ((vlff_publisher_pending(n->pub) == 0 && n->pending_lat == 0) || vlff_field_steps(n->field) == 0 ||
      vlff_seconds() < *next_kf_publish)
    return false;
  double t = vlff_seconds();
  bool whole = publish_changed(n);
  double end = vlff_seconds(), c = end - t;
  /* a whole publish is owed once (new prompts, a reset): not a rate; it
   * refreshed the whole map, so the refresh's round starts over */
  *next_kf_publish = whole ? 0 : t + c * (3.0 / work_scale(n) - 1.0);
  if (whole) refresh_round_end(n, rf, end, false, true);
  return whole;
}

/* The keyframes waiting now, taken and published before other work (a
 * slice, a checkpoint): true when that was a whole publish. */
static bool serve_keyframes(struct vlff_node *n, struct vlff_refresh *rf, double *next_kf_publish) {
  take_candidates(n, false);
  return publish_keyframes(n, rf, next_kf_publish);
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

/* node.cpu_budget (budget.h): whether to step now. Sleeps while the process
 * is over its budget, at most 0.1 s per pass so the loop still beats,
 * publishes and takes commands; only training waits. Always measures the
 * use, for the status. */
static bool pace_training(struct vlff_node *n, bool train) {
  double used;
  bool go = vlff_pacer_pace(&n->pacer, train, 0.1, &used);
  if (used >= 0) {
    pthread_mutex_lock(&n->slock);
    n->st.cpu_used = used;
    pthread_mutex_unlock(&n->slock);
    double b = n->cfg.node.cpu_budget;
    if (b > 0 && used > 1.2 * b)
      vlff_warn_limited(&n->warned.cpu_budget, TAG,
                        "node.cpu_budget %.2f cores: the process used %.2f over the last 3 s; its work besides "
                        "training (ingest, publishing, encoders) takes more than the budget",
                        b, used);
  }
  return train && go;
}

void *trainer_main(void *arg) {
  pthread_setname_np(pthread_self(), "vlff-trainer"); /* as ingest_main's */
  struct vlff_node *n = arg;
  const struct vlff_config *cfg = &n->cfg;
  /* The map is refreshed whole every 1 / publish.rate_hz, in slices
   * between steps (refresh.h), so no single publish stalls training for
   * long; what keyframes change is published as soon as they are
   * admitted. */
  struct vlff_refresh rf;
  vlff_refresh_init(&rf, 1.0 / cfg->publish.rate_hz);
  if (work_scale(n) < 1) rf.share = VLFF_REFRESH_SHARE_BUDGETED * work_scale(n);
  double next_kf_publish = 0; /* when keyframes may be published again */
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
    atomic_store(&n->trainer_beat_ns, vlff_now_ns());
    vlff_refresh_pass(&rf, vlff_seconds());
    bool publish_now = first;
    first = false;
    run_commands(n, &publish_now);
    poll_mailbox(n, &mailbox_seq, &publish_now);
    bool train = n->mapping && vlff_kfstore_count(n->store) >= cfg->keyframes.start_after;
    take_candidates(n, !train);
    if (!publish_now) publish_keyframes(n, &rf, &next_kf_publish);
    train = pace_training(n, train);
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
    bool published = false, tail = false;
    double to = -1;
    if (vlff_field_steps(n->field) > 0) {
      to = publish_now ? 1 : vlff_refresh_due(&rf, now, vlff_publisher_refresh_done(n->pub));
      /* What a round owes after its last slice (its label image, in
       * pieces, then its scores) goes first, a piece a pass instead of a
       * slice: a keyframe waits for one piece at most. */
      tail = !publish_now && vlff_publisher_image_owed(n->pub);
      if ((to >= 0 || tail) && !publish_now && rf.start >= 0) {
        /* Keyframes still go first: those admitted during the step are
         * published before the slice, not a pass later. One that had to be
         * a whole publish refreshed the map and restarted the round. */
        serve_keyframes(n, &rf, &next_kf_publish);
        to = vlff_refresh_due(&rf, vlff_seconds(), vlff_publisher_refresh_done(n->pub));
      }
    }
    if (tail) {
      double t = vlff_seconds();
      publish_image(n);
      vlff_refresh_sliced(&rf, vlff_seconds() - t);
      published = true;
    } else if (to >= 0 && vlff_field_steps(n->field) > 0) {
      double t = vlff_seconds();
      bool round, whole = true;
      if (publish_now) {
        do_publish(n);
        round = true;
        vlff_refresh_sliced(&rf, vlff_seconds() - t);
      } else {
        /* A slice stops after about 40 ms of queries (publish.h): the
         * keyframes admitted meanwhile go out before it goes on to `to`.
         * One that had to be a whole publish restarted the round. Once a
         * pass: candidates that come after that end the slicing after its
         * piece and are taken at the pass's top, or on a host too slow for
         * the keyframes' rate (a sanitizer build's) the trainer would only
         * ever take keyframes, and never step. */
        bool served = false;
        for (;;) {
          round = publish_slice(n, to, &whole);
          vlff_refresh_sliced(&rf, vlff_seconds() - t);
          if (round || whole || atomic_load(&n->stop) || !(vlff_publisher_refresh_done(n->pub) < to)) break;
          if (served) {
            if (candidates_waiting(n)) break;
          } else {
            served = true;
            if (serve_keyframes(n, &rf, &next_kf_publish)) break;
          }
          t = vlff_seconds();
        }
      }
      double end = vlff_seconds();
      published = true;
      /* A whole publish out of turn (new prompts, a reset, the first map)
       * restarts the grid; a round of slices ends on its deadline. */
      if (round) refresh_round_end(n, &rf, end, !whole, whole);
    } else {
      vlff_publisher_heartbeat(n->pub);
    }
    if (n->ckpt_owed) {
      /* The field's part, a pass after the grid's: the keyframes that came
       * while the grid was written went out at this pass's top. */
      save_checkpoint_end(n);
    } else if (now >= next_ckpt) {
      /* A checkpoint holds the trainer for a while (the field's moments are
       * written whole): the keyframes already waiting go out before it. */
      serve_keyframes(n, &rf, &next_kf_publish);
      save_checkpoint_begin(n);
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
  update_state(n); /* the counts the node stopped with: the pass that saw the stop may have added to them */
  share_status(n);
  return NULL;
}
