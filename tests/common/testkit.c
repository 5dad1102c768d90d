#include "testkit.h"

#include <fcntl.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>
#include <ftw.h>
#include <glob.h>
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
#include "vlff/shm.h"

extern char **environ;

void tk_setup(struct tk *t, const char *prefix) {
  memset(t, 0, sizeof *t);
  snprintf(t->tag, sizeof t->tag, "%s%d", prefix, (int)getpid());
  snprintf(t->dir, sizeof t->dir, "/tmp/vlff-%s", t->tag);
  mkdir(t->dir, 0755);
  t->scale = tk_time_scale();
}

double tk_time_scale(void) {
  const char *sc = getenv("VLFF_E2E_SCALE");
  return sc && atof(sc) > 0 ? atof(sc) : 1;
}

static int rm_one(const char *p, const struct stat *st, int flag, struct FTW *ftw) {
  (void)st, (void)flag, (void)ftw;
  return remove(p) == 0 ? 0 : -1;
}

/* Nodes tk_node_create made and tk_node_destroy has not destroyed: a test
 * that fails an assertion leaves its node running, and the next test, using
 * the same segment names, would otherwise share its rings with it. */
enum { TK_MAX_NODES = 8 };
static struct {
  struct vlff_node *n;
  struct vlff_sim_source *src;
} tk_nodes[TK_MAX_NODES];

int tk_teardown(struct tk *t) {
  for (int i = 0; i < TK_MAX_NODES; i++)
    if (tk_nodes[i].n) tk_node_destroy(tk_nodes[i].n, tk_nodes[i].src);
  for (int i = 0; i < t->nchildren; i++)
    if (t->children[i] > 0) tk_stop_child(t, t->children[i], SIGKILL);
  t->nchildren = 0;
  int rc = nftw(t->dir, rm_one, 16, FTW_DEPTH | FTW_PHYS) == 0 ? 0 : -1;
  char pat[128];
  snprintf(pat, sizeof pat, "/dev/shm/%s-*", t->tag);
  glob_t g;
  if (glob(pat, 0, NULL, &g) == 0) {
    for (size_t i = 0; i < g.gl_pathc; i++)
      if (unlink(g.gl_pathv[i]) != 0) rc = -1;
    globfree(&g);
  }
  return rc;
}

const char *tk_shm_names(struct tk *t) {
  snprintf(t->shm_names, sizeof t->shm_names,
           "  ring: /%s-f\n  map: /%s-m\n  prompts: /%s-p\n  pose_ring: /%s-q\n  feature_ring: /%s-x\n", t->tag,
           t->tag, t->tag, t->tag, t->tag);
  return t->shm_names;
}

const char *tk_config(struct tk *t, struct vlff_config *cfg, const char *fmt, ...) {
  snprintf(t->cfg_path, sizeof t->cfg_path, "%s/node.yaml", t->dir);
  FILE *f = fopen(t->cfg_path, "w");
  assert_non_null(f);
  va_list ap;
  va_start(ap, fmt);
  vfprintf(f, fmt, ap);
  va_end(ap);
  assert_int_equal(fclose(f), 0);
  char err[512];
  if (vlff_config_load(t->cfg_path, cfg, err, sizeof err)) fail_msg("%s", err);
  return t->cfg_path;
}

pid_t tk_spawn(struct tk *t, const char *prog, const char *const *args, const char *out) {
  char path[512];
  const char *bin = getenv("VLFF_BINARY_DIR");
  snprintf(path, sizeof path, "%s/%s", bin ? bin : ".", prog);
  char *argv[32];
  int n = 0;
  argv[n++] = path;
  for (; args[n - 1] && n < 31; n++) argv[n] = (char *)args[n - 1];
  argv[n] = NULL;
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  if (out) {
    posix_spawn_file_actions_addopen(&fa, 1, out, O_WRONLY | O_CREAT | O_TRUNC, 0644);
    posix_spawn_file_actions_adddup2(&fa, 1, 2);
  }
  pid_t pid = -1;
  if (posix_spawn(&pid, path, &fa, NULL, argv, environ) != 0) pid = -1;
  posix_spawn_file_actions_destroy(&fa);
  if (pid > 0 && t->nchildren < TK_CHILDREN) t->children[t->nchildren++] = pid;
  return pid;
}

static void forget(struct tk *t, pid_t pid) {
  for (int i = 0; i < t->nchildren; i++)
    if (t->children[i] == pid) t->children[i] = 0;
}

int tk_wait_child(struct tk *t, pid_t pid) {
  int st;
  if (waitpid(pid, &st, 0) != pid) return -1;
  forget(t, pid);
  return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
}

void tk_stop_child(struct tk *t, pid_t pid, int sig) {
  if (pid <= 0) return;
  kill(pid, sig);
  waitpid(pid, NULL, 0);
  forget(t, pid);
}

void tk_sleep_s(double s) {
  struct timespec ts = {(time_t)s, (long)((s - (time_t)s) * 1e9)};
  nanosleep(&ts, NULL);
}

const char *tk_slurp(const char *path) {
  static char buf[1 << 20];
  FILE *f = fopen(path, "r");
  if (!f) return strcpy(buf, "");
  size_t n = fread(buf, 1, sizeof buf - 1, f);
  buf[n] = 0;
  fclose(f);
  return buf;
}

bool tk_wait_for_text(const char *path, const char *text, double timeout_s) {
  double t0 = vlff_seconds();
  while (vlff_seconds() - t0 < timeout_s) {
    if (strstr(tk_slurp(path), text)) return true;
    tk_sleep_s(0.1);
  }
  return false;
}

double tk_map_miou3d(const char *map, const struct vlff_sim_points *gt, uint64_t *version, int *prompt_count) {
  char err[256];
  struct vlff_map *m = vlff_map_attach(map);
  if (!m) return -1;
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(m);
  double miou = -1;
  struct vlff_map_info info;
  struct vlff_confusion c;
  if (snap && vlff_map_snapshot_take(m, snap) == 0 && vlff_map_snapshot_info(snap, &info) == 0 && info.version > 0 &&
      vlff_confusion_init(&c, VLFF_SIM_CLASSES, err, sizeof err) == 0) {
    if (version) *version = info.version;
    if (prompt_count) *prompt_count = info.prompt_count;
    for (size_t i = 0; i < gt->n; i++) {
      const float *x = gt->xyz + i * 3;
      uint16_t lab = vlff_map_snapshot_label_at(snap, x[0], x[1], x[2], NULL);
      const char *text = vlff_map_snapshot_prompt(snap, lab);
      vlff_confusion_add_one(&c, gt->label[i], text ? vlff_sim_class_of(text) : -1);
    }
    struct vlff_summary sum;
    vlff_confusion_summary(&c, &sum);
    miou = sum.miou * 100;
    vlff_confusion_free(&c);
  }
  vlff_map_snapshot_free(snap);
  vlff_map_detach(m);
  return miou;
}

struct vlff_node *tk_node_create(const struct vlff_config *cfg, struct vlff_sim_source **src, char *err,
                                 size_t errlen) {
  struct vlff_source_hooks hooks;
  *src = vlff_sim_source_create(cfg, &hooks, err, errlen);
  struct vlff_node *n = *src ? vlff_node_create(cfg, &hooks, err, errlen) : NULL;
  if (!n) {
    vlff_sim_source_destroy(*src);
    *src = NULL;
    return NULL;
  }
  for (int i = 0; i < TK_MAX_NODES; i++)
    if (!tk_nodes[i].n) {
      tk_nodes[i].n = n, tk_nodes[i].src = *src;
      break;
    }
  return n;
}

void tk_node_destroy(struct vlff_node *n, struct vlff_sim_source *src) {
  for (int i = 0; i < TK_MAX_NODES; i++)
    if (tk_nodes[i].n == n) tk_nodes[i].n = NULL, tk_nodes[i].src = NULL;
  vlff_node_destroy(n, false);
  vlff_sim_source_destroy(src);
}

double tk_wait_miou3d(const char *map, const struct vlff_sim_points *gt, double want, double timeout_s,
                      uint64_t *version) {
  double best = -1, t0 = vlff_seconds();
  while (vlff_seconds() - t0 < timeout_s) {
    tk_sleep_s(2);
    double m = tk_map_miou3d(map, gt, version, NULL);
    if (m > best) best = m;
    if (best >= want) break;
  }
  return best;
}

void tk_report(struct vlff_node *n, double t, double best, uint64_t version, struct vlff_node_status *st) {
  vlff_node_status(n, st);
  printf("after %.0f s: 3D mIoU %.1f, %lld iterations, %lld frames in, %lld invalid, %lld lost, %d keyframes, "
         "%lld feature timeouts, map v%llu\n",
         t, best, st->iteration, st->frames_in, st->frames_invalid, st->frames_lost, st->keyframes,
         st->features_timeout, (unsigned long long)version);
}

void tk_scene_open(struct tk_scene *sc, const struct vlff_config *cfg, int slots, int w, int h) {
  char err[512];
  sc->sim = vlff_sim_create(&cfg->sim, &cfg->field, err, sizeof err);
  if (!sc->sim) fail_msg("%s", err);
  sc->frame = vlff_sim_frame_new(sc->sim);
  assert_non_null(sc->frame);
  struct vlff_ring_params rp = {VLFF_RECORD_FRAME, (uint32_t)slots,
                                vlff_frame_slot_size((uint32_t)w, (uint32_t)h, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM),
                                {0640, NULL}};
  sc->ring = vlff_ring_create(cfg->shm.ring, &rp);
  assert_non_null(sc->ring);
}

struct vlff_node *tk_scene_node(struct tk_scene *sc, const struct vlff_config *cfg, int slots, int w, int h,
                                struct vlff_sim_source **src) {
  tk_scene_open(sc, cfg, slots, w, h);
  char err[512];
  struct vlff_node *n = tk_node_create(cfg, src, err, sizeof err);
  if (!n) fail_msg("%s", err);
  tk_sleep_s(0.5);
  return n;
}

struct vlff_frame_hdr *tk_frame_reserve(struct vlff_ring *ring, const struct vlff_sim_frame *f, long long id,
                                        uint64_t t_ns, int w, int h, int depth_format, uint64_t *len) {
  struct vlff_frame_hdr *hd = vlff_ring_reserve(ring, NULL);
  assert_non_null(hd);
  *len = vlff_frame_layout(hd, vlff_ring_slot_size(ring), (uint32_t)w, (uint32_t)h, VLFF_PIX_RGB8,
                           (uint32_t)depth_format);
  assert_true(*len > 0);
  hd->frame_id = (uint64_t)id;
  hd->t_host_ns = t_ns;
  hd->flags = VLFF_FRAME_POSE_VALID | VLFF_FRAME_INTRINSICS_VALID;
  hd->fx = f->fx, hd->fy = f->fy, hd->cx = f->cx, hd->cy = f->cy;
  memcpy(hd->pose, f->c2w, sizeof hd->pose);
  return hd;
}

void tk_scene_close(struct tk_scene *sc) {
  vlff_ring_close(sc->ring);
  vlff_sim_frame_free(sc->frame);
  vlff_sim_destroy(sc->sim);
  memset(sc, 0, sizeof *sc);
}
