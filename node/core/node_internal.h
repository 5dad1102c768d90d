/*
 * The node's private state, shared by the files that make up vlff_node
 * (node.h is the public contract; this header is not installed or used
 * outside node/core).
 *
 * Two threads do the work. The ingest thread never touches the field: it
 * turns ring records into candidate keyframes (validated, posed, downscaled,
 * with features) and hands them over through a small queue that drops the
 * oldest candidate rather than ever blocking the ring. The trainer thread
 * owns the field, the keyframe store and the map writer; it interleaves pose
 * checks, optimisation steps, publishes and checkpoints, so none of them
 * needs a lock around the model.
 *
 * Where each thread's work lives
 *  - ingest.c:     the ingest thread's loop, its rings, the candidate queue
 *                  (producer side), the pending list and the feature join.
 *  - admit.c:      a frame's stages on the ingest thread (checks, pose,
 *                  admission) and the refusal log.
 *  - trainer.c:    the trainer thread's loop: candidates in, pose check,
 *                  steps, publishing.
 *  - checkpoint.c: saving, restoring and rolling back the field (trainer
 *                  thread; restore at create, a final save at destroy).
 *  - commands.c:   prompts, queued commands and the prompt mailbox (trainer
 *                  thread), the status (any thread reads it).
 *  - lifecycle.c:  create, stop, destroy and snapshot (the caller's thread).
 *  - check.c:      what create refuses before it makes anything, also run
 *                  by --check-config (vlff_node_check, node.h).
 *
 * Contract of struct vlff_node
 *  - cfg, hooks, model_h/model_w and t_start are set by vlff_node_create
 *    before the threads start and only read afterwards.
 *  - The field, the keyframe store, the publisher, the mailbox, the text
 *    encoders and everything under "trainer-private" belong to the trainer
 *    thread; the caller's thread touches them only before the threads start
 *    (create) or after they are joined (destroy, snapshot).
 *  - ingest_* threads' state is local to ingest_main (struct ingest); of the
 *    node it uses cfg, hooks and the image worker (submit and poll).
 *  - qlock guards queue and qlen (ingest pushes, trainer takes; qcond wakes
 *    the trainer). cmd_lock guards cmds and ncmds (any thread posts, the
 *    trainer takes). slock guards st and last_frame_s, last_pose_ok_s,
 *    last_lapped_s, fwatch. Each is held for a short copy or update, never across
 *    work, and no two are ever held together.
 *  - stop, finished and the two beats are atomics, read and written by any
 *    thread without a lock.
 *  - Each counter in warned is used by one thread only (vlff_warn_limited).
 */
#ifndef VLFF_NODE_INTERNAL_H
#define VLFF_NODE_INTERNAL_H

#include <pthread.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>
#include <sys/types.h>

#include "budget.h"
#include "embeddings.h"
#include "feature_join.h"
#include "field.h"
#include "keyframes.h"
#include "node.h"
#include "publish.h"
#include "select.h"
#include "source.h"
#include "watch.h"
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
/* Keyframe candidates waiting for the trainer, which takes them between
 * its steps: a publish of a large map or a checkpoint holds it for seconds
 * on a loaded 2-core host (5 Hz keyframes: 16 are 3.2 s), and a candidate
 * dropped when the queue is full is a view the map never observes. */
#define QUEUE_CAP 16
#define PENDING_CAP 16
#define LAT_CAP 4096
#define KF_PROTECT 8  /* newest keyframes never evicted */
/* A paged keyframe comes back when the camera is this near it
 * (vlff_pose_distance: metres + 0.5 m per radian): in the same room, looking
 * the same way. */
#define KF_PAGE_IN_RADIUS 1.5
#define KF_HISTORY 32 /* admitted keyframes the pose check compares against */

struct candidate {
  long long id;
  uint64_t t_host_ns;
  uint64_t t_queued_ns; /* when the ingest queued it (debug log of its latency's parts) */
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
    uint64_t mailbox, mailbox_refused, mailbox_answer, map_status, publish, feature_ring, feature_bad, encoder,
        kf_rejected, kf_refused, kf_store, step_failed, nonfinite, rollback, cpu_budget, grow;
  } warned;
  long long grow_refused; /* trainer: keyframes whose box the field or the map could not grow to (field.grow) */

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
  pthread_mutex_t cmd_lock;
  int cmds[16][2];
  int ncmds;

  /* status (short critical sections, never held across work) */
  pthread_mutex_t slock;
  struct vlff_node_status st;
  double last_frame_s, last_pose_ok_s, last_lapped_s;
  double rss_read_s, rss_mb; /* the resident set, MiB, and when update_state last read it (trainer) */
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
  uint64_t ckpt_map_version;   /* trainer: the newest map published when the grid was written */
  bool ckpt_owed;             /* trainer: the grid of ckpt_slot is written, its field not yet (save_checkpoint_begin) */
  struct vlff_pacer pacer;    /* trainer: node.cpu_budget's pacing and the measured use (budget.h) */
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
  long long cleared_seen; /* vlff_publisher_cleared when keyframes were last checked against it */
  bool kf_full_said;      /* the keyframe store's first eviction was logged */
  long long kf_dropped_said; /* keyframes dropped (not paged) when last logged */
  /* trainer: the label flips of the publishes since the last whole refresh
   * ended (all, without new evidence, and the voxels that could) */
  long long round_flips, round_flips_elsewhere, round_mapped_elsewhere;
};

#define STAT_ADD(n, field, v)          \
  do {                                 \
    pthread_mutex_lock(&(n)->slock);   \
    (n)->st.field += (v);              \
    pthread_mutex_unlock(&(n)->slock); \
  } while (0)

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
  uint64_t feats_bad;  /* bad feature records already said */
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
  /* The keyframe candidate before (whatever became of it): its pose and
   * farthest depth, for the box-free units check (vlff_pose_step_plausible). */
  double prev_c2w[16];
  double prev_depth_max_m;
  bool have_prev;
};

/* Events per second over windows of at least a second (frames in, training
 * steps): once a window is over, its rate goes into *out under the status
 * lock and a new window starts (rate_publish). */
struct rate_meter {
  double t0;
  long long count;
};

/* ingest.c (ingest thread; candidate_free on any thread that owns the candidate) */
void candidate_free(struct candidate *c);

/* lifecycle.c: the keyframe store by the config, paging to the state
 * directory's keyframes.pages (a new file) when keyframes.page_mb > 0 (a
 * file that cannot be made is warned about, and the store drops what it
 * evicts); NULL with err when there is no memory. */
struct vlff_kfstore *node_kfstore_create(const struct vlff_config *cfg, char *err, size_t errlen);
void queue_push(struct vlff_node *n, struct candidate *c);
void pending_remove(struct candidate **pending, int *npend, int i);
struct vlff_ring *attach_input(struct vlff_node *n, const char *name, uint32_t kind);
void *ingest_main(void *arg);

/* admit.c (ingest thread) */
void refuse(struct vlff_node *n, struct refusal_log *rl, int reason, long long id, const char *fmt, ...)
    __attribute__((format(printf, 5, 6)));
void refusal_summary(struct vlff_node *n, struct refusal_log *rl, double now);
void ingest_held(struct ingest *ig, double now);
void ingest_frame(struct ingest *ig, const void *buf, ssize_t len, double now);

/* trainer.c (trainer thread; do_publish also from vlff_node_snapshot after the join) */
void do_publish(struct vlff_node *n);
void *trainer_main(void *arg);

/* checkpoint.c (trainer thread; restore at create, a final save at destroy) */
void roll_back(struct vlff_node *n, const char *why);
void step_not_finite(struct vlff_node *n, const char *step_err);
int save_checkpoint(struct vlff_node *n);
/* save_checkpoint in two parts, for the trainer's periodic checkpoint: the
 * grid (begin: 1 when the field's part is owed, 0 nothing to save, -1
 * failed), then in a later pass the field (end), so keyframes that arrive
 * meanwhile are published between the two writes rather than after both.
 * A rollback or a mapping reset in between cancels the field's part. */
int save_checkpoint_begin(struct vlff_node *n);
int save_checkpoint_end(struct vlff_node *n);
void restore_checkpoint(struct vlff_node *n);

/* commands.c (trainer thread; apply_prompt_set also at create, rate_publish
 * on either thread for its own meter) */
int apply_prompt_set(struct vlff_node *n, int idx, char *err, size_t errlen);
int adopt_embeddings_prompts(struct vlff_node *n, char *err, size_t errlen);
void run_commands(struct vlff_node *n, bool *publish_now);
void poll_mailbox(struct vlff_node *n, uint64_t *seq, bool *publish_now);
void update_state(struct vlff_node *n);
void share_status(struct vlff_node *n);
void rate_publish(struct rate_meter *r, double now, struct vlff_node *n, double *out);

#endif
