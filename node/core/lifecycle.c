/*
 * The node's life: vlff_node_create validates the config, builds the field,
 * the store, the encoders, the publisher and the mailbox, restores the
 * newest checkpoint and starts the trainer and ingest threads;
 * vlff_node_stop asks them to finish; vlff_node_destroy joins them, saves
 * when asked and frees; vlff_node_snapshot joins them and renders the final
 * map.
 *
 * Thread: the caller's. Before the threads start and after they are joined
 * it is the only thread touching the node; vlff_node_stop and
 * vlff_node_finished only use the atomics and may be called from any thread.
 * Locks: it initialises and destroys qlock, cmd_lock and slock; what it
 * calls after the join (the final checkpoint, do_publish) takes slock,
 * uncontended.
 * State: the threads, ingest_started, trainer_started, joined, and the
 * node's allocation as a whole (node_internal.h).
 */
#include <errno.h>
#include <malloc.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "budget.h"
#include "clock.h"
#include "embeddings.h"
#include "evidence.h"
#include "field.h"
#include "keyframes.h"
#include "log.h"
#include "node_internal.h"
#include "publish.h"
#include "vlff/escape.h"
#include "vlff/shm.h"
#ifdef VLFF_HAVE_VLM
#include "image_encoder.h"
#include "text_encoder.h"
#endif

/* Start-up adjustments, for the status (node.h "adjusted"). The publisher
 * plans its grid with vlff_map_grid_plan; the same plan here says whether it
 * had to coarsen the voxels to fit shm.map_max_voxels. */
static void note_adjustments(struct vlff_node *n) {
  const struct vlff_config *c = &n->cfg;
  uint32_t dims[3];
  double v = vlff_map_grid_plan(c->field.scene_min, c->field.scene_max, c->publish.voxel_size_m,
                                (size_t)c->shm.map_max_voxels, dims);
  if (v > c->publish.voxel_size_m)
    snprintf(n->st.adjusted, sizeof n->st.adjusted,
             "publish.voxel_size_m %.3f -> %.3f m (the box needs more than shm.map_max_voxels %d)",
             c->publish.voxel_size_m, v, c->shm.map_max_voxels);
}

/* The field's box, said once at start with where it came from: a box that
 * is not the scene's clips the map without any other sign. */
static void say_scene_box(const struct vlff_config *c) {
  const double *lo = c->field.scene_min, *hi = c->field.scene_max;
  char from[VLFF_CFG_PATH + 64];
  if (c->field.scene_box_file[0])
    snprintf(from, sizeof from, "field.scene_box_file %s", VLFF_Q(c->field.scene_box_file));
  else
    snprintf(from, sizeof from, "field.scene_min/max");
  VLFF_INFO("node", "scene box [%g %g %g]..[%g %g %g] m from %s", lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], from);
}

struct vlff_kfstore *node_kfstore_create(const struct vlff_config *cfg, char *err, size_t errlen) {
  struct vlff_kfstore *s =
      vlff_kfstore_create((size_t)cfg->keyframes.memory_mb << 20, cfg->keyframes.max_keyframes, KF_PROTECT);
  if (!s) {
    snprintf(err, errlen, "keyframe store: %s", strerror(errno));
    return NULL;
  }
  if (cfg->keyframes.page_mb > 0) {
    char path[VLFF_CFG_PATH + 32];
    snprintf(path, sizeof path, "%s/keyframes.pages", cfg->node.state_dir);
    char perr[256];
    if (vlff_kfstore_page_to(s, path, (size_t)cfg->keyframes.page_mb << 20, perr, sizeof perr))
      VLFF_WARN("node", "keyframes: %s: evicted keyframes will be dropped (counted), not paged", perr);
  }
  return s;
}

struct vlff_node *vlff_node_create(const struct vlff_config *cfg, const struct vlff_source_hooks *hooks, char *err,
                                   size_t errlen) {
  static const struct vlff_source_hooks none;
  if (!hooks) hooks = &none;
  if (vlff_node_check(cfg, hooks, false, err, errlen)) return NULL;
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
  n->st.frame_to_map_ms_p50 = n->st.frame_to_map_ms_p99 = n->st.publish_interval_s = n->st.label_flip_frac = -1;
  n->st.mem_rss_mb = n->rss_mb = -1;
  /* the memory figures that do not change while the node runs */
  n->st.mem_keyframes_limit_mb = cfg->keyframes.memory_mb;
  n->st.mem_field_mb = (double)vlff_field_plan_bytes(&cfg->field, &cfg->train) / (1 << 20);
  /* node.cpu_budget bounds the learner's threads (budget.h); the field made
   * again on a reset reads the same count from n->cfg. */
  n->cfg.node.threads = vlff_budget_threads(cfg->node.cpu_budget, cfg->node.threads);
  n->st.cpu_budget = cfg->node.cpu_budget;
  n->st.cpu_used = -1;
  n->st.threads = n->cfg.node.threads;
  pthread_mutex_init(&n->qlock, NULL);
  pthread_cond_init(&n->qcond, NULL);
  pthread_mutex_init(&n->cmd_lock, NULL);
  pthread_mutex_init(&n->slock, NULL);

  if (mkdir(cfg->node.state_dir, 0750) != 0 && errno != EEXIST) {
    snprintf(err, errlen, "node.state_dir '%s': %s", VLFF_Q(cfg->node.state_dir), strerror(errno));
    goto fail;
  }
  n->field = vlff_field_create(&cfg->field, &cfg->train, n->cfg.node.threads, err, errlen);
  if (!n->field) goto fail;
  n->store = node_kfstore_create(cfg, err, errlen);
  if (!n->store) goto fail;
  n->model_h = cfg->vlm.input_height;
  n->model_w = cfg->vlm.input_width;
  if (cfg->prompts.embeddings[0]) {
    n->emb_file = vlff_embeddings_load(cfg->prompts.embeddings, cfg->field.feature_dim, err, errlen);
    if (!n->emb_file || adopt_embeddings_prompts(n, err, errlen)) goto fail;
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
  char perr[VLFF_CFG_PATH + 400];
  if (vlff_publisher_page_evidence(n->pub, cfg->node.state_dir, perr, sizeof perr))
    VLFF_WARN(TAG, "%s: the evidence a full publish.evidence_max_mb gives up is dropped", perr);
  note_adjustments(n);
  say_scene_box(cfg);
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
  if (apply_prompt_set(n, n->cfg.prompts.active, err, errlen)) goto fail;
  atomic_store(&n->trainer_beat_ns, vlff_now_ns());
  atomic_store(&n->ingest_beat_ns, vlff_now_ns());
  /* Start-up's own CPU (building the field, restoring) is not charged to
   * the budget: it starts with the threads. */
  vlff_pacer_init(&n->pacer, cfg->node.cpu_budget);
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

void vlff_node_process_setup(void) { (void)mallopt(M_MMAP_THRESHOLD, 1 << 20); }

/* After this only the calling thread touches the node. */
static void join_threads(struct vlff_node *n) {
  if (n->joined) return;
  atomic_store(&n->stop, true);
  if (n->ingest_started) pthread_join(n->ingest_thread, NULL);
  if (n->trainer_started) pthread_join(n->trainer_thread, NULL);
  n->joined = true;
}

void vlff_node_join(struct vlff_node *n) { join_threads(n); }

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
  pthread_mutex_destroy(&n->cmd_lock);
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
