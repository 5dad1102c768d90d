/*
 * bench_node: time to a useful map on the synthetic 5 Hz stream.
 *
 * vlff-sim streams configs/demo-sim.yaml's room into the frame and feature
 * rings; the node (in this process, exactly the library vlff-node runs)
 * learns it. Every 0.5 s the node's own 2D mIoU (its published label image
 * against the synthetic ground truth) is sampled. Useful = the 2D mIoU,
 * smoothed over the last 5 s, first reaches 90 % of its value at 120 s
 * (VLFF_BENCH_SECONDS; VLFF_BENCH_CONFIG replaces the config). That value is
 * the mean over 120 +- 15 s: one view's mIoU swings by 20 points with what
 * it sees (a chair or a bare wall), and a 5-s window's by 10, which moved
 * the threshold, not the map. Baseline in the same run: the raw per-frame
 * features' 2D mIoU on the same scene (what the field must beat).
 *
 * Same view: the camera's walk repeats every sim.frames frames, so each
 * sample's view is seen again in the loop around `seconds` (the frames
 * within half a loop of the one published then; the run lasts until that
 * loop is whole). time_to_useful_same_view_s compares
 * like with like: the first time the 5-s window's mIoU reaches 90 % of what
 * the same views (the nearest loop positions, within a second of walk)
 * score in that final loop. A bare wall early and a cluttered corner late
 * no longer move it; a room entered for the first time still does. Views
 * the final loop published no label image near (keyframes refused there)
 * are left out. VLFF_BENCH_TRACE=FILE writes every sample: seconds, frame
 * id, 2D mIoU, the same views' final mIoU.
 */
#include <math.h>
#include <signal.h>
#include <stdbool.h>
#include <spawn.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "config.h"
#include "metrics.h"
#include "node.h"
#include "testkit.h"
#include "sim.h"

extern char **environ;

static double mono_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static long peak_rss_kb(void) {
  FILE *f = fopen("/proc/self/status", "r");
  char line[256];
  long kb = -1;
  while (f && fgets(line, sizeof line, f))
    if (!strncmp(line, "VmHWM:", 6)) kb = atol(line + 6);
  if (f) fclose(f);
  return kb;
}

/* Raw per-frame features: argmax over the prompt embeddings at feature
 * resolution, against the ground truth sampled at the same pixels. */
static double raw_miou2d(const struct vlff_config *cfg, int frames) {
  char err[256];
  struct vlff_sim *s = vlff_sim_create(&cfg->sim, &cfg->field, err, sizeof err);
  struct vlff_sim_frame *f = s ? vlff_sim_frame_new(s) : NULL;
  struct vlff_confusion c;
  if (!f || vlff_confusion_init(&c, VLFF_SIM_CLASSES, err, sizeof err)) return -1;
  const struct vlff_prompt_set *ps = &cfg->prompts.sets[cfg->prompts.active];
  int d = cfg->field.feature_dim, k = ps->count;
  float *emb = malloc((size_t)k * d * sizeof(float)), *unit = malloc((size_t)k * d * sizeof(float));
  int *cls = malloc((size_t)k * sizeof(int));
  for (int i = 0; i < k; i++) {
    vlff_sim_text_embedding(s, ps->text[i], emb + (size_t)i * d);
    cls[i] = vlff_sim_class_of(ps->text[i]);
  }
  vlff_normalize_rows(emb, unit, k, d);
  for (int i = 0; i < frames; i++) {
    vlff_sim_render(s, (long long)i * cfg->sim.frames / frames, VLFF_SIM_ALL, f, err, sizeof err);
    size_t n = (size_t)f->feat_width * f->feat_height;
    int *lab = malloc(n * sizeof(int));
    vlff_classify_f16(f->features, n, d, unit, k, lab, NULL);
    for (int y = 0; y < f->feat_height; y++)
      for (int x = 0; x < f->feat_width; x++) {
        int gy = (y * f->height + f->height / 2) / f->feat_height, gx = (x * f->width + f->width / 2) / f->feat_width;
        int l = lab[(size_t)y * f->feat_width + x];
        vlff_confusion_add_one(&c, f->label[(size_t)gy * f->width + gx], l >= 0 ? cls[l] : -1);
      }
    free(lab);
  }
  struct vlff_summary sum;
  vlff_confusion_summary(&c, &sum);
  vlff_confusion_free(&c);
  free(emb), free(unit), free(cls);
  vlff_sim_frame_free(f);
  vlff_sim_destroy(s);
  return sum.miou * 100;
}

int main(int argc, char **argv) {
  (void)argc;
  const char *src = getenv("VLFF_SOURCE_DIR") ? getenv("VLFF_SOURCE_DIR") : VLFF_SOURCE_DEFAULT;
  double seconds = getenv("VLFF_BENCH_SECONDS") ? atof(getenv("VLFF_BENCH_SECONDS")) : 120;
  char path[1024], err[512], tmp[256];
  static char yaml[16384];
  snprintf(tmp, sizeof tmp, "/tmp/vlff-bench-node-%d", (int)getpid());
  snprintf(path, sizeof path, "mkdir -p %s", tmp);
  if (system(path)) return 1;
  /* The demo's config with this run's own segments and an empty state. */
  snprintf(path, sizeof path, "%s/configs/demo-sim.yaml", src);
  if (getenv("VLFF_BENCH_CONFIG")) snprintf(path, sizeof path, "%s", getenv("VLFF_BENCH_CONFIG"));
  FILE *in = fopen(path, "r");
  if (!in) return fprintf(stderr, "bench_node: %s missing\n", path), 1;
  size_t len = fread(yaml, 1, sizeof yaml - 1, in);
  yaml[len] = 0;
  fclose(in);
  char cfg_path[300];
  snprintf(cfg_path, sizeof cfg_path, "%s/node.yaml", tmp);
  FILE *out = fopen(cfg_path, "w");
  for (char *line = strtok(yaml, "\n"); line; line = strtok(NULL, "\n")) {
    if (strstr(line, "state_dir:")) fprintf(out, "  state_dir: %s/state\n  checkpoint_period_s: 0\n", tmp);
    else if (strstr(line, "checkpoint_period_s:")) continue;
    else if (strstr(line, ": /vlff-demo-")) fprintf(out, "%.*s/bn%d-%s\n", (int)(strstr(line, "/vlff-demo-") - line), line, (int)getpid(), strstr(line, "/vlff-demo-") + 11);
    else fprintf(out, "%s\n", line);
  }
  fclose(out);
  struct vlff_config cfg;
  if (vlff_config_load(cfg_path, &cfg, err, sizeof err)) return fprintf(stderr, "%s\n", err), 1;

  double raw = raw_miou2d(&cfg, 30);
  printf("raw per-frame features: 2D mIoU %.1f (baseline)\n", raw);

  char simpath[1024];
  snprintf(simpath, sizeof simpath, "%.*s/../node/sim/vlff-sim", (int)(strrchr(argv[0], '/') - argv[0]), argv[0]);
  char *sargv[] = {simpath, "--config", cfg_path, "--quiet", NULL};
  pid_t sim;
  if (posix_spawn(&sim, simpath, NULL, NULL, sargv, environ)) return fprintf(stderr, "cannot start %s\n", simpath), 1;
  struct vlff_sim_source *sim_src;
  struct vlff_node *n = tk_node_create(&cfg, &sim_src, err, sizeof err);
  if (!n) {
    kill(sim, SIGKILL);
    return fprintf(stderr, "%s\n", err), 1;
  }
  enum { MAXS = 4096 };
  static double ts[MAXS], m2[MAXS];
  static long long fr[MAXS];
  int ns = 0;
  const int loop_n = cfg.sim.frames;
  const double loop_s = cfg.sim.frames / cfg.sim.rate_hz;
  double t0 = mono_s();
  struct vlff_node_status st;
  const double half = 15; /* the final value's window, each side of `seconds` */
  /* The final loop: the views whose frame ids lie within half a loop of the
   * one published at `seconds` (by ids, not by time: a simulator slower
   * than sim.rate_hz must still give every view). Run until it is whole,
   * or for one loop's time (twice, for a slow simulator) after `seconds`. */
  long long id_c = -1;
  for (;;) {
    double t = mono_s() - t0;
    bool final_done = id_c >= 0 && ns > 0 && fr[ns - 1] >= id_c + loop_n / 2;
    if (ns >= MAXS || (t >= seconds + half && final_done) || t >= seconds + 2 * loop_s) break;
    struct timespec nap = {0, 500 * 1000 * 1000};
    nanosleep(&nap, NULL);
    vlff_node_status(n, &st);
    ts[ns] = mono_s() - t0;
    fr[ns] = st.miou2d_frame;
    m2[ns++] = st.miou2d;
    if (id_c < 0 && ts[ns - 1] >= seconds && st.miou2d_frame >= 0) id_c = st.miou2d_frame;
    if (ns % 10 == 0)
      printf("t=%5.1f s  it %lld  kf %d  2D mIoU %.1f  3D mIoU %.1f\n", ts[ns - 1], st.iteration, st.keyframes,
             st.miou2d, st.miou3d);
  }
  vlff_node_status(n, &st);
  tk_node_destroy(n, sim_src);
  kill(sim, SIGTERM);
  waitpid(sim, NULL, 0);
  snprintf(path, sizeof path, "rm -rf %s /dev/shm/bn%d-*", tmp, (int)getpid());
  if (system(path)) fprintf(stderr, "bench_node: cleanup failed\n");

  /* Smooth over 5 s: each sample is one view's label image. */
  static double sm[MAXS];
  for (int i = 0; i < ns; i++) {
    double acc = 0;
    int c = 0;
    for (int j = i; j >= 0 && ts[i] - ts[j] < 5.0; j--)
      if (m2[j] >= 0) acc += m2[j], c++;
    sm[i] = c ? acc / c : -1;
  }
  double acc = 0;
  int cnt = 0;
  for (int i = 0; i < ns; i++)
    if (fabs(ts[i] - seconds) <= half && m2[i] >= 0) acc += m2[i], cnt++;
  double final = cnt ? acc / cnt : -1, useful = -1;
  for (int i = 0; i < ns; i++)
    if (final > 0 && sm[i] >= 0.9 * final) {
      useful = ts[i];
      break;
    }
  /* Same view: each loop position's mean in the loop around `seconds`. */
  double *qs = calloc((size_t)loop_n, sizeof *qs), useful_sv = -1;
  int *qc = calloc((size_t)loop_n, sizeof *qc);
  static double q[MAXS];
  if (!qs || !qc) return fprintf(stderr, "bench_node: out of memory\n"), 1;
  for (int i = 0; i < ns; i++)
    if (m2[i] >= 0 && id_c >= 0 && fr[i] >= id_c - loop_n / 2 && fr[i] < id_c + loop_n / 2)
      qs[fr[i] % loop_n] += m2[i], qc[fr[i] % loop_n]++;
  const int reach = (int)ceil(cfg.sim.rate_hz); /* a second of walk either side */
  for (int i = 0; i < ns; i++) {
    double a = 0;
    int c = 0;
    for (int d = -reach; fr[i] >= 0 && d <= reach; d++) {
      int p = (int)(((fr[i] + d) % loop_n + loop_n) % loop_n);
      a += qs[p], c += qc[p];
    }
    q[i] = c ? a / c : -1;
  }
  printf("same-view ratio (%%, 5-s windows):");
  for (int i = 0; i < ns && fr[i] < id_c - loop_n / 2; i++) {
    double a = 0, b = 0;
    int c = 0;
    for (int j = i; j >= 0 && ts[i] - ts[j] < 5.0; j--)
      if (m2[j] >= 0 && q[j] > 0) a += m2[j], b += q[j], c++;
    if (i % 2 && ts[i] < 30.5) printf(" %.0f", c ? 100 * a / b : -1);
    if (useful_sv < 0 && c >= 4 && a >= 0.9 * b) useful_sv = ts[i];
  }
  printf("\n");
  if (getenv("VLFF_BENCH_TRACE")) {
    FILE *tf = fopen(getenv("VLFF_BENCH_TRACE"), "w");
    for (int i = 0; tf && i < ns; i++) fprintf(tf, "%.2f %lld %.1f %.1f\n", ts[i], fr[i], m2[i], q[i]);
    if (tf) fclose(tf);
  }
  free(qs);
  free(qc);
  /* The first 30 s, where time to useful is decided. */
  printf("smoothed 2D mIoU (threshold %.1f):", 0.9 * final);
  for (int i = 1; i < ns && ts[i] < 30.5; i += 2) printf(" %.0f", sm[i]);
  printf("\n");
  printf("final: %lld iterations, %d keyframes, 3D mIoU %.1f, frame-to-map p50 %.0f ms, map refreshed every %.2f s "
         "(publish.rate_hz %.2f)\n",
         st.iteration, st.keyframes, st.miou3d, st.frame_to_map_ms_p50, st.publish_interval_s, cfg.publish.rate_hz);
  /* frame_to_map: a keyframe's capture stamp to the first map version whose
   * change log covers its voxels; publish_interval_s: the time between whole
   * refreshes of the map (target 1 / publish.rate_hz). */
  printf("RESULT time_to_useful_s=%.1f miou2d_at_%.0fs=%.1f frame_to_map_p99_ms=%.0f rss_mb=%.0f miou2d_raw=%.1f "
         "miou2d_vs_raw=%.2f miou3d=%.1f time_to_useful_same_view_s=%.1f publish_interval_s=%.2f\n",
         useful, seconds, final, st.frame_to_map_ms_p99, peak_rss_kb() / 1024.0, raw, raw > 0 ? final / raw : 0,
         st.miou3d, useful_sv, st.publish_interval_s);
  return 0;
}
