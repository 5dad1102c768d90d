/*
 * What controllers ask of the node and what it tells them: prompt sets and
 * texts (embedded and handed to the field), the queued commands (start,
 * stop, reset, save, publish, prompt set), the prompt mailbox, and the
 * status (--status, CAN, the map segment).
 *
 * Thread: vlff_node_command and vlff_node_status are called from any
 * thread; everything else runs on the trainer's (apply_prompt_set also in
 * vlff_node_create, before the threads start).
 * State: the trainer-private prompts (prompt_emb, prompt_k, prompt_text) and
 * mapping, the mailbox, the command queue, the status.
 * Locks: cmd_lock for the command queue, slock for the status (short, never
 * across work, never two at once; node_internal.h).
 */
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "clock.h"
#include "embeddings.h"
#include "field.h"
#include "keyframes.h"
#include "log.h"
#include "node_internal.h"
#include "publish.h"
#include "vlff/escape.h"
#include "vlff/shm.h"
#ifdef VLFF_HAVE_VLM
#include "text_encoder.h"
#endif

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

/* An embeddings file given without prompts.sets defines the prompts: its
 * records, in its order, become set 0 (the map's label k is the file's
 * record k, as vlff-eval's ground truth numbers them). With prompts.sets the
 * sets apply and the file only supplies vectors. The log says which. */
int adopt_embeddings_prompts(struct vlff_node *n, char *err, size_t errlen) {
  struct vlff_cfg_prompts *pc = &n->cfg.prompts;
  if (!n->emb_file) return 0;
  if (pc->sets_named) {
    VLFF_INFO(TAG, "prompts: set '%s' of prompts.sets (prompts.active %d); vectors from %s", pc->sets[pc->active].name,
              pc->active, VLFF_Q(pc->embeddings));
    return 0;
  }
  int k = vlff_embeddings_count(n->emb_file);
  if (k < 1 || k > VLFF_MAX_PROMPTS) {
    snprintf(err, errlen, "prompts.embeddings %s holds %d prompts; without prompts.sets it defines the prompts, "
             "1 to %d of them: name the ones to use in prompts.sets", VLFF_Q(pc->embeddings), k, VLFF_MAX_PROMPTS);
    return -1;
  }
  struct vlff_prompt_set *s = &pc->sets[0];
  snprintf(s->name, sizeof s->name, "embeddings-file");
  for (int i = 0; i < k; i++) snprintf(s->text[i], VLFF_PROMPT_LEN, "%s", vlff_embeddings_prompt(n->emb_file, i));
  s->count = k;
  pc->set_count = 1;
  pc->active = 0;
  VLFF_INFO(TAG, "prompts: the %d of the embeddings file %s, in its order (no prompts.sets in the config)", k,
            VLFF_Q(pc->embeddings));
  return 0;
}

int apply_prompt_set(struct vlff_node *n, int idx, char *err, size_t errlen) {
  if (idx < 0 || idx >= n->cfg.prompts.set_count) {
    snprintf(err, errlen, "prompt set %d does not exist (have %d)", idx, n->cfg.prompts.set_count);
    return -1;
  }
  const struct vlff_prompt_set *s = &n->cfg.prompts.sets[idx];
  return apply_prompts(n, (const char(*)[VLFF_PROMPT_LEN])s->text, s->count, idx, err, errlen);
}

static void reset_mapping(struct vlff_node *n) {
  char err[256];
  struct vlff_field *f = vlff_field_create(&n->cfg.field, &n->cfg.train, n->cfg.node.threads, err, sizeof err);
  char serr[256] = "";
  struct vlff_kfstore *s = f ? node_kfstore_create(&n->cfg, serr, sizeof serr) : NULL;
  if (!f || !s) {
    VLFF_ERROR(TAG, "reset failed: %s", f ? serr : err);
    vlff_field_destroy(f);
    vlff_kfstore_destroy(s);
    return;
  }
  vlff_field_destroy(n->field);
  vlff_kfstore_destroy(n->store);
  n->field = f;
  n->resumed = false;
  n->ckpt_steps = -1; /* the saved map is no longer the learned one */
  n->ckpt_owed = false;
  n->store = s;
  n->kf_full_said = false;
  n->kf_dropped_said = 0;
  vlff_publisher_reset(n->pub);
  if (n->prompt_emb) vlff_field_set_prompts(n->field, n->prompt_emb, n->prompt_k, err, sizeof err);
  VLFF_INFO(TAG, "mapping reset");
}

void run_commands(struct vlff_node *n, bool *publish_now) {
  int cmds[16][2], nc;
  pthread_mutex_lock(&n->cmd_lock);
  nc = n->ncmds;
  memcpy(cmds, n->cmds, sizeof cmds);
  n->ncmds = 0;
  pthread_mutex_unlock(&n->cmd_lock);
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
void poll_mailbox(struct vlff_node *n, uint64_t *seq, bool *publish_now) {
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

/* The memory in use for the status, taken outside slock (trainer-private
 * reads: the keyframes, the evidence and its limit, the resident set, read
 * at most twice a second); the fixed figures are set at create. */
static void memory_state(struct vlff_node *n, double now, double mem[4]) {
  const double mib = 1.0 / (1 << 20);
  size_t ev_used, ev_limit;
  vlff_publisher_evidence_memory(n->pub, &ev_used, &ev_limit);
  mem[0] = (double)vlff_kfstore_bytes(n->store) * mib;
  mem[1] = (double)ev_used * mib;
  mem[2] = (double)ev_limit * mib;
  if (now - n->rss_read_s >= 0.5) {
    n->rss_read_s = now;
    FILE *f = fopen("/proc/self/statm", "r");
    unsigned long long size, resident;
    if (f && fscanf(f, "%llu %llu", &size, &resident) == 2)
      n->rss_mb = (double)resident * (double)sysconf(_SC_PAGESIZE) * mib;
    if (f) fclose(f);
  }
  mem[3] = n->rss_mb;
}

void update_state(struct vlff_node *n) {
  double now = vlff_seconds(), mem[4];
  memory_state(n, now, mem);
  size_t paged;
  long long paged_out, paged_in, dropped;
  vlff_publisher_evidence_paging(n->pub, &paged, &paged_out, &paged_in, &dropped);
  double box_lo[3], box_hi[3];
  long long grown;
  vlff_publisher_box(n->pub, box_lo, box_hi, &grown);
  long long slides, far_dropped;
  size_t far_blocks, far_bytes, far_limit;
  vlff_publisher_far(n->pub, &slides, &far_blocks, &far_bytes, &far_limit, &far_dropped);
  pthread_mutex_lock(&n->slock);
  unsigned f = n->st.error_flags & VLFF_NODE_ERR_CHECKPOINT;
  if (vlff_frame_watch_lost(&n->fwatch, now, n->cfg.shm.ring)) f |= VLFF_NODE_ERR_CAMERA_LOST, n->st.fps_in = 0;
  if (n->last_frame_s > 0 && now - n->last_pose_ok_s > 2.0) f |= VLFF_NODE_ERR_POSE_STALE;
  if (n->last_lapped_s > 0 && now - n->last_lapped_s < 2.0) f |= VLFF_NODE_ERR_SHM_LAPPED;
  n->st.error_flags = f;
  n->st.keyframes = vlff_kfstore_count(n->store);
  n->st.keyframes_evicted = vlff_kfstore_evicted(n->store);
  n->st.keyframes_retired = vlff_kfstore_retired(n->store);
  n->st.keyframes_paged = vlff_kfstore_paged(n->store);
  n->st.keyframes_paged_out = vlff_kfstore_paged_out(n->store);
  n->st.keyframes_paged_in = vlff_kfstore_paged_in(n->store);
  n->st.keyframes_dropped = vlff_kfstore_dropped(n->store);
  n->st.keyframes_page_mb = (double)vlff_kfstore_page_bytes(n->store) / (1 << 20);
  n->st.keyframes_page_limit_mb = (double)vlff_kfstore_page_limit(n->store) / (1 << 20);
  n->st.state = !n->mapping ? VLFF_NODE_STOPPED
                : n->st.keyframes >= n->cfg.keyframes.start_after ? VLFF_NODE_OPERATIONAL
                                                                  : VLFF_NODE_PREOP;
  n->st.map_age_s = vlff_publisher_age_s(n->pub);
  n->st.mem_keyframes_mb = mem[0];
  n->st.mem_evidence_mb = mem[1], n->st.mem_evidence_limit_mb = mem[2];
  n->st.mem_rss_mb = mem[3];
  n->st.evidence_paged = (long long)paged, n->st.evidence_paged_out = paged_out;
  n->st.evidence_paged_in = paged_in, n->st.evidence_dropped = dropped;
  n->st.box_growths = grown, n->st.box_refused = n->grow_refused;
  n->st.box_slides = slides, n->st.far_blocks = (long long)far_blocks, n->st.far_dropped = far_dropped;
  n->st.far_mb = (double)far_bytes / (1 << 20), n->st.far_limit_mb = (double)far_limit / (1 << 20);
  memcpy(n->st.box_lo, box_lo, sizeof box_lo), memcpy(n->st.box_hi, box_hi, sizeof box_hi);
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

/* Every reason is listed, counted or not, with its name, so that readers
 * learn the list from the segment. */
void vlff_node_map_status(const struct vlff_node_status *st, struct vlff_map_status *out) {
  _Static_assert(VLFF_REFUSED_COUNT - 1 <= VLFF_SHM_MAX_REASONS, "every refusal reason fits the map's status");
  struct vlff_map_status ms = {
      .state = st->state,
      .error_flags = st->error_flags,
      .frames_in = (uint64_t)st->frames_in,
      .frames_lost = (uint64_t)st->frames_lost,
      .frames_refused = (uint64_t)st->frames_invalid,
      .keyframes = (uint64_t)st->keyframes,
      .keyframes_evicted = (uint64_t)st->keyframes_evicted,
      .iterations = (uint64_t)st->iteration,
      .iterations_per_s = st->it_per_s,
      .fps_in = st->fps_in,
      .loss = st->loss,
      .loss_rgb = st->loss_rgb,
      .loss_depth = st->loss_depth,
      .loss_feat = st->loss_feat,
      .psnr = st->psnr,
      .cpu_budget = st->cpu_budget,
      .cpu_used = st->cpu_used,
      .frame_to_map_ms_p50 = st->frame_to_map_ms_p50,
      .frame_to_map_ms_p99 = st->frame_to_map_ms_p99,
      .publish_interval_s = st->publish_interval_s,
      .label_flips = (uint64_t)st->label_flips,
      .label_flips_refresh = (uint64_t)st->label_flips_refresh,
      .label_flips_total = (uint64_t)st->label_flips_total,
      .label_flip_frac = st->label_flip_frac,
      .mem_keyframes_mb = st->mem_keyframes_mb,
      .mem_keyframes_limit_mb = st->mem_keyframes_limit_mb,
      .mem_evidence_mb = st->mem_evidence_mb,
      .mem_evidence_limit_mb = st->mem_evidence_limit_mb,
      .mem_field_mb = st->mem_field_mb,
      .mem_rss_mb = st->mem_rss_mb,
      .keyframes_paged = (uint64_t)st->keyframes_paged,
      .keyframes_paged_out = (uint64_t)st->keyframes_paged_out,
      .keyframes_paged_in = (uint64_t)st->keyframes_paged_in,
      .keyframes_dropped = (uint64_t)st->keyframes_dropped,
      .keyframes_page_mb = st->keyframes_page_mb,
      .keyframes_page_limit_mb = st->keyframes_page_limit_mb,
      .evidence_paged = (uint64_t)st->evidence_paged,
      .evidence_paged_out = (uint64_t)st->evidence_paged_out,
      .evidence_paged_in = (uint64_t)st->evidence_paged_in,
      .evidence_dropped = (uint64_t)st->evidence_dropped,
      .box_lo = {st->box_lo[0], st->box_lo[1], st->box_lo[2]},
      .box_hi = {st->box_hi[0], st->box_hi[1], st->box_hi[2]},
      .box_growths = (uint64_t)st->box_growths,
      .box_refused = (uint64_t)st->box_refused,
  };
  snprintf(ms.state_name, sizeof ms.state_name, "%s", state_name(st->state));
  for (int r = 1; r < VLFF_REFUSED_COUNT; r++) {
    struct vlff_map_reason *e = &ms.reason[ms.reason_count++];
    snprintf(e->name, sizeof e->name, "%s", vlff_refusal_name(r));
    e->count = (uint64_t)st->refused[r];
  }
  *out = ms;
}

/* The status, as --status and CAN have it, into the map segment for any
 * controller (vlff-shm stat, vlff-view, vlff-dds). */
void share_status(struct vlff_node *n) {
  struct vlff_node_status st;
  vlff_node_status(n, &st);
  struct vlff_map_status ms;
  vlff_node_map_status(&st, &ms);
  char err[320];
  /* A map truncated under the node is replaced by the library; say so. */
  if (vlff_publisher_set_status(n->pub, &ms, err, sizeof err))
    vlff_warn_limited(&n->warned.map_status, TAG, "map status: %s", err);
}

void rate_publish(struct rate_meter *r, double now, struct vlff_node *n, double *out) {
  if (now - r->t0 < 1.0) return;
  pthread_mutex_lock(&n->slock);
  *out = r->count / (now - r->t0);
  pthread_mutex_unlock(&n->slock);
  r->t0 = now;
  r->count = 0;
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
  pthread_mutex_lock(&n->cmd_lock);
  int rc = -1;
  if (n->ncmds < 16) {
    n->cmds[n->ncmds][0] = cmd;
    n->cmds[n->ncmds][1] = arg;
    n->ncmds++;
    rc = 0;
  }
  pthread_mutex_unlock(&n->cmd_lock);
  return rc;
}
