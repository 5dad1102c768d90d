/* vlff-eval --online (online.h). */
#include "online.h"

#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <signal.h>
#include <spawn.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "clock.h"
#include "metrics.h"
#include "vlff/escape.h"
#include "vlff/shm.h"

extern char **environ;

#define SEGS 5

struct run {
  const struct vlff_online_opts *o;
  char dir[200], cfg_path[220];
  char seg[SEGS][64];
  pid_t node, replay;
  struct vlff_map *map;
  struct vlff_map_snapshot *snap;
  FILE *curve;
};

static void sleep_s(double s) {
  struct timespec ts = {(time_t)s, (long)((s - (double)(time_t)s) * 1e9)};
  while (nanosleep(&ts, &ts) < 0 && errno == EINTR) {
  }
}

/* name beside this program, else at the build tree's place (rel), else NULL. */
static int find_bin(const char *given, const char *name, const char *rel, char *out, size_t len) {
  if (given) return snprintf(out, len, "%s", given), 0;
  char self[PATH_MAX];
  ssize_t n = readlink("/proc/self/exe", self, sizeof self - 1);
  if (n <= 0) return -1;
  self[n] = 0;
  char *slash = strrchr(self, '/');
  if (!slash) return -1;
  *slash = 0;
  /* A name that does not fit is no program found. */
  if (snprintf(out, len, "%s/%s", self, name) < (int)len && access(out, X_OK) == 0) return 0;
  return snprintf(out, len, "%s/%s", self, rel) < (int)len && access(out, X_OK) == 0 ? 0 : -1;
}

/* The config as YAML the loader reads back: vlff_config_dump's "a.b: v"
 * lines grouped under their sections; prompts.sets left out so that the
 * embeddings file defines the prompts. */
static int write_config(const struct vlff_config *c, const char *path, char *err, size_t errlen) {
  char *flat = NULL;
  size_t flen = 0;
  FILE *m = open_memstream(&flat, &flen);
  if (!m) return snprintf(err, errlen, "out of memory"), -1;
  vlff_config_dump(c, m);
  fclose(m);
  FILE *f = fopen(path, "w");
  if (!f) {
    free(flat);
    return snprintf(err, errlen, "%s: %s", VLFF_Q(path), strerror(errno)), -1;
  }
  fprintf(f, "# written by vlff-eval --online: the evaluation's config, for the node it runs\n");
  /* sections in their first order; each line goes under its own */
  char done[64][32];
  int nd = 0;
  for (char *l = flat; l && *l;) {
    char *e = strchr(l, '\n');
    size_t ll = e ? (size_t)(e - l) : strlen(l);
    char *dot = memchr(l, '.', ll);
    if (dot && !strncmp(l, "prompts.sets[", 13)) dot = NULL;
    if (dot && (size_t)(dot - l) < sizeof done[0]) {
      char sec[32];
      snprintf(sec, sizeof sec, "%.*s", (int)(dot - l), l);
      int seen = 0;
      for (int i = 0; i < nd; i++) seen |= !strcmp(done[i], sec);
      if (!seen && nd < 64) {
        snprintf(done[nd++], sizeof done[0], "%s", sec);
        fprintf(f, "%s:\n", sec);
        for (char *q = l; q && *q;) {
          char *qe = strchr(q, '\n');
          size_t ql = qe ? (size_t)(qe - q) : strlen(q);
          size_t sl = strlen(sec);
          if (ql > sl + 1 && !strncmp(q, sec, sl) && q[sl] == '.' && strncmp(q, "prompts.sets[", 13))
            fprintf(f, "  %.*s\n", (int)(ql - sl - 1), q + sl + 1);
          q = qe ? qe + 1 : NULL;
        }
      }
    }
    l = e ? e + 1 : NULL;
  }
  free(flat);
  if (fclose(f) != 0) return snprintf(err, errlen, "%s: %s", VLFF_Q(path), strerror(errno)), -1;
  struct vlff_config back;
  if (vlff_config_load(path, &back, err, errlen) < 0) return -1;
  return 0;
}

static pid_t spawn(char *const argv[], const char *log, char *err, size_t errlen) {
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  posix_spawn_file_actions_addopen(&fa, 1, log, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  posix_spawn_file_actions_adddup2(&fa, 1, 2);
  pid_t pid;
  int rc = posix_spawn(&pid, argv[0], &fa, NULL, argv, environ);
  posix_spawn_file_actions_destroy(&fa);
  if (rc) return snprintf(err, errlen, "cannot start %s: %s", VLFF_Q(argv[0]), strerror(rc)), -1;
  return pid;
}

/* Stops a child: SIGTERM, then SIGKILL after grace_s. */
static void stop(pid_t *pid, double grace_s) {
  if (*pid <= 0) return;
  kill(*pid, SIGTERM);
  double t0 = vlff_seconds();
  int st;
  while (waitpid(*pid, &st, WNOHANG) == 0) {
    if (vlff_seconds() - t0 > grace_s) {
      kill(*pid, SIGKILL);
      waitpid(*pid, &st, 0);
      break;
    }
    sleep_s(0.05);
  }
  *pid = 0;
}

static void cleanup(struct run *r) {
  stop(&r->replay, 5);
  stop(&r->node, 60);
  vlff_map_snapshot_free(r->snap);
  vlff_map_detach(r->map);
  for (int i = 0; i < SEGS; i++) vlff_shm_unlink(r->seg[i]);
  if (r->curve) fclose(r->curve);
}

/* One sample of the map: scores at the labelled points. */
struct sample {
  double t, miou, macc, coverage, refresh_s;
  uint64_t version, publish_ns, frames, keyframes;
};

static int take(struct run *r, const struct vlff_points *pts, const uint8_t *seen, int k,
                const char (*names)[VLFF_PROMPT_LEN], struct vlff_confusion *c, struct sample *s, char *err,
                size_t errlen) {
  if (vlff_map_snapshot_take(r->map, r->snap) < 0)
    return snprintf(err, errlen, "map %s: %s", r->seg[2], vlff_shm_last_message()), -1;
  struct vlff_map_info mi;
  if (vlff_map_snapshot_info(r->snap, &mi) < 0)
    return snprintf(err, errlen, "map %s: %s", r->seg[2], vlff_shm_last_message()), -1;
  int cls[VLFF_SHM_MAX_PROMPTS];
  for (int p = 0; p < mi.prompt_count && p < VLFF_SHM_MAX_PROMPTS; p++) {
    const char *t = vlff_map_snapshot_prompt(r->snap, (uint16_t)p);
    cls[p] = -1;
    for (int q = 0; t && q < k; q++)
      if (!strcmp(t, names[q])) cls[p] = q;
  }
  vlff_confusion_reset(c);
  size_t want = 0, got = 0;
  for (size_t i = 0; i < pts->n; i++) {
    int gt = pts->label[i];
    if (gt >= k) continue;
    const float *x = pts->xyz + 3 * i;
    uint16_t lab = mi.version ? vlff_map_snapshot_label_at(r->snap, x[0], x[1], x[2], NULL) : VLFF_LABEL_UNKNOWN;
    int pred = lab < mi.prompt_count && lab < VLFF_SHM_MAX_PROMPTS ? cls[lab] : -1;
    vlff_confusion_add_one(c, gt, pred);
    if (!seen || seen[i]) want++, got += lab <= VLFF_LABEL_MAX;
  }
  struct vlff_summary sum;
  vlff_confusion_summary(c, &sum);
  struct vlff_map_status st;
  if (vlff_map_get_status(r->map, &st) < 0) memset(&st, 0, sizeof st);
  s->miou = sum.miou, s->macc = sum.macc, s->coverage = want ? (double)got / want : 0;
  s->version = mi.version, s->publish_ns = mi.publish_ns, s->frames = st.frames_in, s->keyframes = st.keyframes;
  s->refresh_s = st.t_ns ? st.publish_interval_s : -1;
  return 0;
}

static void print_row(struct run *r, const struct sample *s, const char *note) {
  char line[256];
  snprintf(line, sizeof line, "%8.1f %8llu %7llu %9llu %8.1f %8.1f %9.1f%s", s->t, (unsigned long long)s->version,
           (unsigned long long)s->frames, (unsigned long long)s->keyframes, 100 * s->miou, 100 * s->macc,
           100 * s->coverage, note);
  printf("%s\n", line);
  fflush(stdout);
  if (r->curve)
    fprintf(r->curve, "%.1f\t%llu\t%llu\t%llu\t%.2f\t%.2f\t%.2f\n", s->t, (unsigned long long)s->version,
            (unsigned long long)s->frames, (unsigned long long)s->keyframes, 100 * s->miou, 100 * s->macc,
            100 * s->coverage);
}

int vlff_eval_online(const struct vlff_online_opts *o, const struct vlff_config *cfg, const struct vlff_points *pts,
                     const uint8_t *seen, int k, const char (*names)[VLFF_PROMPT_LEN], struct vlff_online_result *res,
                     char *err, size_t errlen) {
  struct run r = {.o = o};
  struct vlff_confusion c = {0};
  int rc = -1;
  res->miou3d = res->macc3d = res->coverage = res->publish_interval_s = -1;
  res->version = 0, res->samples = 0;
  char node_bin[PATH_MAX], replay_bin[PATH_MAX];
  if (find_bin(o->node_bin, "vlff-node", "../vlff-node", node_bin, sizeof node_bin) < 0 ||
      find_bin(o->replay_bin, "vlff-replay", "../dataset/vlff-replay", replay_bin, sizeof replay_bin) < 0)
    return snprintf(err, errlen, "vlff-node or vlff-replay not found beside vlff-eval (--node, --replay name them)"),
           -1;
  /* The state directory and the paths in the node's config must fit it. */
  if (strlen(o->out) > sizeof r.dir - 8)
    return snprintf(err, errlen, "--out %s: longer than %zu bytes", VLFF_Q(o->out), sizeof r.dir - 8), -1;
  snprintf(r.dir, sizeof r.dir, "%s/online", o->out);
  if (mkdir(r.dir, 0755) < 0 && errno != EEXIST)
    return snprintf(err, errlen, "%s: %s", VLFF_Q(r.dir), strerror(errno)), -1;
  static const char *const what[SEGS] = {"frames", "poses", "map", "prompts", "features"};
  for (int i = 0; i < SEGS; i++) snprintf(r.seg[i], sizeof r.seg[i], "/vlff-eval-%d-%s", (int)getpid(), what[i]);

  struct vlff_config nc = *cfg;
  snprintf(nc.node.state_dir, sizeof nc.node.state_dir, "%s/state", r.dir);
  nc.node.resume = false, nc.node.run_seconds = 0;
  nc.source.kind = VLFF_SOURCE_RING, nc.source.features = VLFF_FEAT_RING;
  snprintf(nc.shm.ring, sizeof nc.shm.ring, "%s", r.seg[0]);
  snprintf(nc.shm.pose_ring, sizeof nc.shm.pose_ring, "%s", r.seg[1]);
  snprintf(nc.shm.map, sizeof nc.shm.map, "%s", r.seg[2]);
  snprintf(nc.shm.prompts, sizeof nc.shm.prompts, "%s", r.seg[3]);
  snprintf(nc.shm.feature_ring, sizeof nc.shm.feature_ring, "%s", r.seg[4]);
  if (nc.shm.max_width < o->width) nc.shm.max_width = o->width;
  if (nc.shm.max_height < o->height) nc.shm.max_height = o->height;
  nc.field.scene_box_file[0] = 0; /* the box is in scene_min/max already */
  if (strlen(o->embeddings) >= sizeof nc.prompts.embeddings)
    return snprintf(err, errlen, "%s: path longer than prompts.embeddings takes", VLFF_Q(o->embeddings)), -1;
  snprintf(nc.prompts.embeddings, sizeof nc.prompts.embeddings, "%s", o->embeddings);
  nc.prompts.active = 0;
  snprintf(r.cfg_path, sizeof r.cfg_path, "%s/node.yaml", r.dir);
  if (write_config(&nc, r.cfg_path, err, errlen) < 0) return -1;
  if (vlff_confusion_init(&c, k, err, errlen) < 0) return -1;

  char log[PATH_MAX + 32];
  snprintf(log, sizeof log, "%s/node.log", r.dir);
  char *nargv[] = {node_bin, "--config", r.cfg_path, "--fresh", NULL};
  if ((r.node = spawn(nargv, log, err, errlen)) < 0) {
    r.node = 0;
    goto out;
  }
  double t_start = vlff_seconds();
  int st;
  while (!(r.map = vlff_map_attach(r.seg[2]))) {
    if (waitpid(r.node, &st, WNOHANG) == r.node) {
      r.node = 0;
      snprintf(err, errlen, "vlff-node stopped before publishing its map (see %s)", log);
      goto out;
    }
    if (vlff_seconds() - t_start > 60) {
      snprintf(err, errlen, "vlff-node created no map segment in 60 s (see %s)", log);
      goto out;
    }
    sleep_s(0.1);
  }
  if (!(r.snap = vlff_map_snapshot_new(r.map))) {
    snprintf(err, errlen, "map %s: %s", r.seg[2], vlff_shm_last_message());
    goto out;
  }
  snprintf(log, sizeof log, "%s/replay.log", r.dir);
  char scene[PATH_MAX];
  snprintf(scene, sizeof scene, "%s", o->scene);
  char *rargv[] = {replay_bin, "--config", r.cfg_path, "--wait-reader", "--quiet", scene, NULL};
  if ((r.replay = spawn(rargv, log, err, errlen)) < 0) {
    r.replay = 0;
    goto out;
  }
  char tsv[PATH_MAX + 32];
  snprintf(tsv, sizeof tsv, "%s/curve.tsv", r.dir);
  r.curve = fopen(tsv, "w");
  if (r.curve) fprintf(r.curve, "t_s\tversion\tframes\tkeyframes\tmiou3d\tmacc3d\tcoverage\n");
  printf("online: %s played by vlff-replay into vlff-node (config %s)\n", o->scene, r.cfg_path);
  printf("%8s %8s %7s %9s %8s %8s %9s\n", "t_s", "version", "frames", "keyframes", "mIoU3D", "mAcc3D", "coverage");
  const double t0 = vlff_seconds();
  double next = t0 + o->interval_s, end = -1, limit = o->replay_limit_s;
  struct sample first = {0}, s = {0};
  for (;;) {
    double now = vlff_seconds();
    if (r.replay && waitpid(r.replay, &st, WNOHANG) == r.replay) {
      r.replay = 0;
      if (!WIFEXITED(st) || WEXITSTATUS(st) != 0) {
        snprintf(err, errlen, "vlff-replay failed (see %s)", log);
        goto out;
      }
      end = now;
      printf("online: replay ended at %.1f s\n", end - t0);
    }
    if (r.replay && now - t0 > limit) {
      snprintf(err, errlen, "vlff-replay still running after %.0f s (see %s)", limit, log);
      goto out;
    }
    if (waitpid(r.node, &st, WNOHANG) == r.node) {
      r.node = 0;
      snprintf(err, errlen, "vlff-node stopped during the run (see %s/node.log)", r.dir);
      goto out;
    }
    double due = end >= 0 && end + o->after_s < next ? end + o->after_s : next;
    if (now >= due) {
      if (take(&r, pts, seen, k, names, &c, &s, err, errlen) < 0) goto out;
      s.t = now - t0;
      res->samples++;
      if (!first.version && s.version) first = s;
      int last = end >= 0 && due == end + o->after_s;
      print_row(&r, &s, last ? "   <- end of replay + after" : "");
      if (last) break;
      if (due == next) next += o->interval_s;
    }
    sleep_s(0.02);
  }
  res->miou3d = s.miou, res->macc3d = s.macc, res->coverage = s.coverage, res->version = s.version;
  /* The node publishes what keyframes change as they come and refreshes the
   * rest in slices: its publish interval is the time between whole
   * refreshes, from its status; a writer without one, the time per version. */
  if (s.refresh_s > 0)
    res->publish_interval_s = s.refresh_s;
  else if (first.version && s.version > first.version)
    res->publish_interval_s = (double)(s.publish_ns - first.publish_ns) * 1e-9 / (double)(s.version - first.version);
  rc = 0;
out:
  cleanup(&r);
  vlff_confusion_free(&c);
  return rc;
}
