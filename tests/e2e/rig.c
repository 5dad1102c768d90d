#include "rig.h"
#include "testkit.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <ftw.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "embeddings.h"
#include "metrics.h"
#include "node.h"
#include "vlff/shm.h"

int rig_netns_enter(int argc, char **argv) {
  if (getenv("VLFF_RIG_NETNS")) return 1;
  if (system("unshare -rn sh -c 'ip link set lo up && ip addr add 127.0.0.2/8 dev lo' >/dev/null 2>&1") != 0) {
    fprintf(stderr, "rig: no private network namespace here (unshare -rn, ip): the camera rig cannot run\n");
    return 0;
  }
  setenv("VLFF_RIG_NETNS", "1", 1);
  char **av = calloc((size_t)argc + 8, sizeof *av);
  if (!av) return 0;
  int n = 0;
  av[n++] = "unshare";
  av[n++] = "-rn";
  av[n++] = "sh";
  av[n++] = "-c";
  av[n++] = "ip link set lo up && ip addr add 127.0.0.2/8 dev lo && exec \"$0\" \"$@\"";
  for (int i = 0; i < argc; i++) av[n++] = argv[i];
  av[n] = NULL;
  execvp("unshare", av);
  fprintf(stderr, "rig: unshare: %s\n", strerror(errno));
  free(av);
  return 0;
}

static int fail(char *err, size_t len, const char *what) {
  snprintf(err, len, "%s", what);
  return -1;
}

/* The tolerances the project ships (rig.h): what a user who starts from the
 * example configs runs. */
static int shipped_tolerances(struct rig *r, char *err, size_t errlen) {
  struct vlff_config *c = malloc(sizeof *c);
  if (!c) return fail(err, errlen, "out of memory");
  vlff_config_defaults(c);
  r->pose_tol_s = c->source.pose_tolerance_s;
  r->future_tol_s = c->pose.future_tolerance_s;
  const char *files[] = {"default.yaml", "aravis-gige.yaml", "aravis-rgbd.yaml"};
  for (int i = 0; i < 3; i++) {
    char path[512], e[512];
    snprintf(path, sizeof path, "%s/%s", VLFF_CONFIGS, files[i]);
    if (vlff_config_load(path, c, e, sizeof e)) {
      snprintf(err, errlen, "%s: %s", path, e);
      free(c);
      return -1;
    }
    r->pose_tol_s = fmin(r->pose_tol_s, c->source.pose_tolerance_s);
    /* 0 there means no check: the widest */
    if (c->pose.future_tolerance_s > 0 && (r->future_tol_s == 0 || c->pose.future_tolerance_s < r->future_tol_s))
      r->future_tol_s = c->pose.future_tolerance_s;
    r->pair_tol_s = c->depth_camera.pair_tolerance_s; /* the RGB-D example's, read last */
    r->pose_wait_s = c->source.pose_wait_s;           /* idem */
  }
  free(c);
  return 0;
}

int rig_init(struct rig *r, int cameras, char *err, size_t errlen) {
  memset(r, 0, sizeof *r);
  r->saved_stderr = -1;
  r->cameras = cameras;
  if (shipped_tolerances(r, err, errlen)) return -1;
  snprintf(r->tag, sizeof r->tag, "rig%d-%d", (int)getpid(), cameras);
  snprintf(r->dir, sizeof r->dir, "/tmp/vlff-%s", r->tag);
  mkdir(r->dir, 0755);
  snprintf(r->cfg_path, sizeof r->cfg_path, "%s/node.yaml", r->dir);
  snprintf(r->calib_path, sizeof r->calib_path, "%s/rig.yaml", r->dir);
  snprintf(r->camd_out, sizeof r->camd_out, "%s/camd.out", r->dir);
  snprintf(r->scenecam_out, sizeof r->scenecam_out, "%s/scenecam.out", r->dir);
  snprintf(r->pose_out, sizeof r->pose_out, "%s/pose.out", r->dir);
  snprintf(r->node_log, sizeof r->node_log, "%s/node.log", r->dir);
  /* The sim first (its intrinsics go into the calibration), from the same
   * room settings the config below gives every process. */
  struct vlff_config c0;
  vlff_config_defaults(&c0);
  c0.sim.seed = 3, c0.sim.rate_hz = 5, c0.sim.width = 160, c0.sim.height = 120, c0.sim.frames = RIG_FRAMES;
  struct vlff_sim *s = vlff_sim_create(&c0.sim, &c0.field, err, errlen);
  if (!s) return -1;
  double fx, fy, cx, cy;
  vlff_sim_intrinsics(s, &fx, &fy, &cx, &cy);
  int W, H, fw, fh, D;
  vlff_sim_size(s, &W, &H, &fw, &fh, &D);
  /* An identity rig: both cameras the sim's camera, no offset between them.
   * Calibration files count pixels as OpenCV does (centre of pixel 0 at 0),
   * the sim as the field does (at 0.5). */
  FILE *f = fopen(r->calib_path, "w");
  if (!f) return vlff_sim_destroy(s), fail(err, errlen, "cannot write the calibration");
  fprintf(f, "%%YAML:1.0\n---\n");
  for (int k = 1; k <= 2; k++)
    fprintf(f,
            "K%d: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ %.17g, 0., %.17g, 0., %.17g, %.17g, 0., 0., 1. ]\n"
            "D%d: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n",
            k, fx, cx - 0.5, fy, cy - 0.5, k);
  fprintf(f, "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]\n"
             "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ 0., 0., 0. ]\n");
  fclose(f);
  char emb_path[400];
  snprintf(emb_path, sizeof emb_path, "%s/prompt_embeddings.txt", r->dir);
  f = fopen(r->cfg_path, "w");
  if (!f) return vlff_sim_destroy(s), fail(err, errlen, "cannot write the config");
  fprintf(f,
          "node:\n  state_dir: %s/state\n  log_level: warn\n"
          "source:\n  kind: %s\n  features: %s\n  pose_tolerance_s: %.17g\n  pose_wait_s: %.17g\n"
          "pose:\n  future_tolerance_s: %.17g\n"
          "sim:\n  seed: 3\n  rate_hz: 5\n  width: %d\n  height: %d\n  frames: %d\n"
          "shm:\n  ring: /%s-f\n  map: /%s-m\n  prompts: /%s-p\n  pose_ring: /%s-q\n  feature_ring: /%s-x\n"
          "  max_width: 320\n  max_height: 240\n  ring_slots: 8\n"
          "train:\n  image_scale: 1.0\n"
          "keyframes:\n  start_after: 3\n  posecheck_min_steps: 30\n"
          "publish:\n  rate_hz: 1\n  voxel_size_m: 0.1\n  label_width: 80\n  label_height: 60\n"
          "prompts:\n%s%s%s  sets:\n"
          "    - name: scannet20\n      prompts: [wall, floor, cabinet, bed, chair, sofa, table, door, window,\n"
          "        bookshelf, picture, counter, desk, curtain, refrigerator, shower curtain, toilet, sink,\n"
          "        bathtub, other furniture]\n"
          "camera:\n  kind: aravis\n  device: 127.0.0.1\n  pixel_format: RGB8\n  width: %d\n  height: %d\n"
          "  frame_rate: 5\n  depth: stream\n  intrinsics: [0, 0, 0, 0]\n  reconnect_max_s: 0.5\n"
          "depth_camera:\n  kind: aravis\n  device: 127.0.0.2\n  pixel_format: Mono16\n  width: %d\n  height: %d\n"
          "  frame_rate: 5\n  scale_m: 0.001\n  calibration: %s\n  pair_tolerance_s: %.17g\n",
          r->dir, cameras ? "ring" : "sim", cameras ? "ring" : "sim", r->pose_tol_s, r->pose_wait_s, r->future_tol_s, W, H, RIG_FRAMES,
          r->tag, r->tag, r->tag, r->tag,
          r->tag, cameras ? "  embeddings: " : "", cameras ? emb_path : "", cameras ? "\n" : "", W, H, W, H,
          r->calib_path, r->pair_tol_s);
  fclose(f);
  if (vlff_config_load(r->cfg_path, &r->cfg, err, errlen)) return vlff_sim_destroy(s), -1;
  const struct vlff_prompt_set *set = &r->cfg.prompts.sets[r->cfg.prompts.active];
  float *emb = calloc((size_t)set->count * D, sizeof(float));
  const char *names[VLFF_MAX_PROMPTS];
  if (!emb) return vlff_sim_destroy(s), fail(err, errlen, "out of memory");
  for (int k = 0; k < set->count; k++) {
    names[k] = set->text[k];
    vlff_sim_text_embedding(s, set->text[k], emb + (size_t)k * D);
  }
  int rc = vlff_embeddings_save(emb_path, D, set->count, names, emb, err, errlen);
  free(emb);
  if (!rc) rc = vlff_sim_points(s, RIG_FRAMES, 5, 0.05, &r->gt, err, errlen);
  vlff_sim_destroy(s);
  return rc;
}

/* A child with stdout and stderr into out, killed when this process dies. */
static pid_t spawn(const char *out, char *const argv[]) {
  pid_t parent = getpid(), pid = fork();
  if (pid != 0) return pid;
  prctl(PR_SET_PDEATHSIG, SIGKILL);
  if (getppid() != parent) _exit(1);
  int fd = open(out, O_WRONLY | O_CREAT | O_TRUNC, 0644);
  if (fd >= 0) dup2(fd, 1), dup2(fd, 2);
  execv(argv[0], argv);
  _exit(127);
}

int rig_start(struct rig *r, char *err, size_t errlen) {
  if (!r->cameras) {
    /* The simulator source: vlff-sim writes the frame ring, poses in the
     * records; the node renders the features itself (test_node_e2e). */
    char *sim[] = {VLFF_SIM, "--config", r->cfg_path, "--quiet", NULL};
    r->scenecam = spawn(r->scenecam_out, sim);
    return r->scenecam < 0 ? fail(err, errlen, "fork failed") : 0;
  }
  char udp[64];
  snprintf(udp, sizeof udp, "127.0.0.1:%d", 20000 + (int)(getpid() % 20000));
  char *sc[] = {VLFF_SCENECAM, "--config", r->cfg_path, "--poses", udp, NULL};
  char *pose[] = {VLFF_POSE, "--config", r->cfg_path, "--udp", udp, "--clock", "realtime", NULL};
  char *camd[] = {VLFF_CAMD, "--config", r->cfg_path, NULL};
  r->pose = spawn(r->pose_out, pose);
  r->scenecam = spawn(r->scenecam_out, sc);
  r->camd = spawn(r->camd_out, camd);
  if (r->pose < 0 || r->scenecam < 0 || r->camd < 0) return fail(err, errlen, "fork failed");
  return 0;
}

static void end(pid_t *pid, double *cpu_s, double wait_s) {
  if (*pid <= 0) return;
  kill(*pid, SIGTERM);
  int st;
  struct rusage ru;
  for (int i = 0; i < wait_s * 20; i++) {
    if (wait4(*pid, &st, WNOHANG, &ru) == *pid) goto reaped;
    struct timespec ts = {0, 50 * 1000 * 1000};
    nanosleep(&ts, NULL);
  }
  kill(*pid, SIGKILL);
  wait4(*pid, &st, 0, &ru);
reaped:
  if (cpu_s)
    *cpu_s = (double)ru.ru_utime.tv_sec + ru.ru_utime.tv_usec * 1e-6 + (double)ru.ru_stime.tv_sec +
             ru.ru_stime.tv_usec * 1e-6;
  *pid = 0;
}

void rig_stop(struct rig *r) {
  /* vlff-camd ends its loop pass first: releasing or reopening a camera
   * that went away (rig_lose_range_camera) takes it many seconds */
  end(&r->camd, &r->camd_cpu_s, 40);
  end(&r->scenecam, NULL, 10);
  end(&r->pose, NULL, 10);
}

static int rm_one(const char *p, const struct stat *st, int flag, struct FTW *ftw) {
  (void)st, (void)flag, (void)ftw;
  return remove(p);
}

void rig_free(struct rig *r) {
  rig_release_stderr(r);
  rig_stop(r);
  vlff_sim_points_free(&r->gt);
  if (!getenv("VLFF_RIG_KEEP")) nftw(r->dir, rm_one, 16, FTW_DEPTH | FTW_PHYS);
  const char *suffix[] = {"f", "m", "p", "q", "x"};
  for (int i = 0; i < 5; i++) {
    char name[96];
    snprintf(name, sizeof name, "/%s-%s", r->tag, suffix[i]);
    vlff_shm_unlink(name);
  }
}

double rig_miou3d(const struct rig *r, uint64_t *version) {
  return tk_map_miou3d(r->cfg.shm.map, &r->gt, version, NULL);
}

long long rig_camd_stat(const struct rig *r, const char *key) {
  FILE *f = fopen(r->camd_out, "r");
  if (!f) return -1;
  char line[2048], pat[64];
  long long v = -1;
  snprintf(pat, sizeof pat, " %s=", key);
  while (fgets(line, sizeof line, f)) {
    const char *p = strncmp(line, "vlff-camd:", 10) ? NULL : strstr(line, pat);
    if (p) v = strtoll(p + strlen(pat), NULL, 10);
  }
  fclose(f);
  return v;
}

long long rig_scenecam_stat(const struct rig *r, const char *key) {
  const char *p = strstr(tk_slurp(r->scenecam_out), key);
  return p ? strtoll(p + strlen(key), NULL, 10) : -1;
}

int rig_capture_stderr(struct rig *r, char *err, size_t errlen) {
  fflush(stderr);
  int fd = open(r->node_log, O_WRONLY | O_CREAT | O_TRUNC | O_APPEND | O_CLOEXEC, 0644);
  if (fd < 0) return fail(err, errlen, "cannot create the node's log file");
  r->saved_stderr = dup(2);
  if (r->saved_stderr < 0 || dup2(fd, 2) < 0) {
    close(fd);
    return fail(err, errlen, "cannot redirect stderr");
  }
  close(fd);
  return 0;
}

void rig_release_stderr(struct rig *r) {
  if (r->saved_stderr < 0) return;
  fflush(stderr);
  dup2(r->saved_stderr, 2);
  close(r->saved_stderr);
  r->saved_stderr = -1;
  fputs(tk_slurp(r->node_log), stderr);
}

static double mono_s(void) { return (double)vlff_shm_now_ns() * 1e-9; }

double rig_lose_range_camera(struct rig *r, struct vlff_node *n, double timeout_s, char *err, size_t errlen) {
  static const char stopped[] = "range camera stopped, last fill at ";
  size_t log_from = strlen(tk_slurp(r->node_log)); /* what the node said before does not count */
  if (r->scenecam <= 0 || kill(r->scenecam, SIGUSR1)) return fail(err, errlen, "vlff-scenecam is not running"), -1;
  double t0 = mono_s(), last = -1, t_status = -1, t_log = -1;
  while (mono_s() - t0 < timeout_s && (last < 0 || t_status < 0 || t_log < 0)) {
    struct timespec ts = {0, 20 * 1000 * 1000};
    nanosleep(&ts, NULL);
    if (last < 0) {
      const char *p = strstr(tk_slurp(r->scenecam_out), stopped);
      if (p) last = strtod(p + strlen(stopped), NULL);
    }
    struct vlff_node_status st;
    vlff_node_status(n, &st);
    if (t_status < 0 && (st.error_flags & VLFF_NODE_ERR_CAMERA_LOST) && st.fps_in == 0) t_status = mono_s();
    const char *log = tk_slurp(r->node_log);
    if (t_log < 0 && strlen(log) >= log_from && strstr(log + log_from, "no frame from ring")) t_log = mono_s();
  }
  if (last < 0 || t_status < 0 || t_log < 0) {
    snprintf(err, errlen, "after %.0f s: %s%s%s", timeout_s, last < 0 ? "vlff-scenecam did not stop the range camera; " : "",
             t_status < 0 ? "the node's status does not show the camera lost (CAMERA_LOST, 0 frames/s); " : "",
             t_log < 0 ? "the node's log does not say 'no frame from ring'" : "");
    return -1;
  }
  return fmax(t_status, t_log) - last;
}
