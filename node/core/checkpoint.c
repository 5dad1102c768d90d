/*
 * The field's saved state: two alternating checkpoint slots (field and
 * observation grid) in node.state_dir, the restore at start, and the
 * rollback of a field gone non-finite or out of bounds.
 *
 * Thread: the trainer's (periodic and commanded saves, rollbacks); the
 * caller's in vlff_node_create (restore, before the threads start) and
 * vlff_node_destroy (the final save, after the join).
 * State: the trainer-private ckpt_slot, ckpt_owed, ckpt_steps, rollback_tried,
 * nonfinite_run and resumed, the field and the publisher's grid.
 * Locks: slock for the status counts only (node_internal.h).
 */
#include <errno.h>
#include <pthread.h>
#include <stdio.h>
#include <string.h>
#include <unistd.h>
#include <sys/stat.h>

#include "clock.h"
#include "field.h"
#include "files.h"
#include "log.h"
#include "node_internal.h"
#include "publish.h"
#include "vlff/escape.h"

static void ckpt_path(const struct vlff_node *n, int slot, char *out, size_t len) {
  snprintf(out, len, "%s/field.%d.ckpt", n->cfg.node.state_dir, slot);
}

static void obs_path(const struct vlff_node *n, int slot, char *out, size_t len) {
  snprintf(out, len, "%s/map.%d.obs", n->cfg.node.state_dir, slot);
}

/* The field's own state went non-finite or out of the bounds of field.h (why
 * names where): back to the newest checkpoint that loads, or to a new field
 * when none does. The keyframes stay, so it learns again from what it has. */
void roll_back(struct vlff_node *n, const char *why) {
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
  n->ckpt_owed = false; /* a grid written for the field rolled back from is not written beside another */
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
void step_not_finite(struct vlff_node *n, const char *step_err) {
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

static void ckpt_failed(struct vlff_node *n, const char *err) {
  VLFF_ERROR(TAG, "checkpoint failed: %s", err);
  pthread_mutex_lock(&n->slock);
  n->st.checkpoint_failures++;
  n->st.error_flags |= VLFF_NODE_ERR_CHECKPOINT;
  pthread_mutex_unlock(&n->slock);
}

int save_checkpoint_begin(struct vlff_node *n) {
  char path[VLFF_CFG_PATH + 32], err[256];
  n->ckpt_owed = false;
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
  double t = vlff_seconds();
  obs_path(n, n->ckpt_slot, path, sizeof path);
  if (vlff_publisher_save(n->pub, path, err, sizeof err)) {
    ckpt_failed(n, err);
    return -1;
  }
  VLFF_DEBUG(TAG, "checkpoint: observation grid %s written in %.0f ms", VLFF_Q(path), (vlff_seconds() - t) * 1e3);
  n->ckpt_owed = true;
  /* The map the grid holds is at least this version: said with the
   * checkpoint, so that a resumed map is compared with what was saved
   * rather than with a map published while the field was written. */
  pthread_mutex_lock(&n->slock);
  n->ckpt_map_version = n->st.map_version;
  pthread_mutex_unlock(&n->slock);
  return 1;
}

int save_checkpoint_end(struct vlff_node *n) {
  char path[VLFF_CFG_PATH + 32], err[256];
  /* A rollback or a mapping reset since the grid was written: the grid is
   * not this field's, and the slot is written whole next time. */
  if (!n->ckpt_owed) return 0;
  n->ckpt_owed = false;
  double t = vlff_seconds();
  long long steps = vlff_field_steps(n->field);
  ckpt_path(n, n->ckpt_slot, path, sizeof path);
  if (vlff_field_save(n->field, path, err, sizeof err)) {
    ckpt_failed(n, err);
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
  VLFF_DEBUG(TAG, "checkpoint: field written in %.0f ms", (vlff_seconds() - t) * 1e3);
  VLFF_INFO(TAG, "checkpoint %s at step %lld, map v%llu", VLFF_Q(path), steps, (unsigned long long)n->ckpt_map_version);
  return 0;
}

int save_checkpoint(struct vlff_node *n) {
  int rc = save_checkpoint_begin(n);
  return rc == 1 ? save_checkpoint_end(n) : rc;
}

void restore_checkpoint(struct vlff_node *n) {
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
  if (!n->cfg.node.resume) {
    /* A fresh start removes the old run's checkpoints rather than leaving
     * them beside this run's: a later resume must never fall back to them. */
    int removed = 0;
    for (int i = 0; i < 2; i++) {
      char op[VLFF_CFG_PATH + 32], fp[VLFF_CFG_PATH + 40];
      obs_path(n, i, op, sizeof op);
      removed += have[i] && unlink(path[i]) == 0;
      for (int j = 0; j < 3; j++) { /* the grid, the far map and its evidence beside it (publish.h) */
        snprintf(fp, sizeof fp, "%s%s", op, vlff_publisher_files[j]);
        if (unlink(fp) != 0 && errno != ENOENT)
          VLFF_WARN(TAG, "fresh start: cannot remove %s: %s", VLFF_Q(fp), strerror(errno));
      }
      if (have[i] && access(path[i], F_OK) == 0)
        VLFF_WARN(TAG, "fresh start: cannot remove %s: %s", VLFF_Q(path[i]), strerror(errno));
    }
    VLFF_INFO(TAG, "fresh start (node.resume false): %d checkpoint(s) in %s removed, not resumed", removed,
              VLFF_Q(n->cfg.node.state_dir));
    return;
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
      /* A refused grid (corrupt, forged, another map's) is counted with
       * the refused checkpoints; the field is kept. */
      if (vlff_publisher_load(n->pub, op, err, sizeof err)) {
        VLFF_WARN(TAG, "observation grid not restored (the map refills as keyframes arrive): %s", err);
        if (access(op, F_OK) == 0) {
          pthread_mutex_lock(&n->slock);
          n->st.checkpoint_failures++;
          pthread_mutex_unlock(&n->slock);
        }
      }
      return;
    }
    VLFF_ERROR(TAG, "checkpoint refused, skipped: %s", err);
    pthread_mutex_lock(&n->slock);
    n->st.checkpoint_failures++;
    pthread_mutex_unlock(&n->slock);
  }
}
