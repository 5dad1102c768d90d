/*
 * The same room through (a) the node's built-in simulator source and (b)
 * the camera rig (rig.h: two Aravis fake GigE cameras, vlff-camd pairing
 * and registering, vlff-pose, the feature ring): the time from the node's
 * start until its published map reaches the test threshold of 3D mIoU, and
 * their ratio; the rig's share of range frames that made no record (found
 * no colour frame, or the pair was dropped) after the start-up
 * (pairs_dropped_frac: counted on the range camera's side, as the colour
 * camera streams on alone once the range camera is gone below; frames
 * before the first pair are start-up frames, the colour camera's counted
 * apart as pairs_startup_frames, the mean per rig run; range frames of a
 * tick the scene server's colour camera skipped, its fill more than a
 * period late on a busy host, have no colour frame to pair with: counted
 * apart as scene_skipped_frac of the range frames after the start-up);
 * vlff-camd's CPU time per pair; after each rig run the range camera goes
 * away, and camera_lost_visible_s is the time from its last frame until
 * the node's status (CAMERA_LOST, no frame rate: what --status shows) and
 * its log both say so (rig_lose_range_camera). tests/bench/e2e.sh adds
 * the depth registration figure of bench_register. Medians of REPS runs of
 * each, interleaved.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "bench_stats.h"
#include "node.h"
#include "testkit.h"
#include "rig.h"
#include "vlff/shm.h"

#define USEFUL_MIOU 35
#define LIMIT_S 300
#define REPS 3
/* The rig keeps streaming this long after the start, useful or not, so
 * that the pairing figures are not those of the first frames alone. */
#define RIG_MIN_S 20

static double mono_s(void) { return (double)vlff_shm_now_ns() * 1e-9; }

/* Seconds from the first frame in the node's ring to a useful map (-1:
 * never), and in *first the seconds from the node's start to that frame:
 * the cameras' start-up (discovery, stream set-up) is a one-off cost at
 * boot, reported apart so that the ratio compares the two data paths. */
static double time_to_useful(struct rig *r, long long *frames_in, double *first, double *lost_visible) {
  char err[1024];
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_node_create(&r->cfg, &src, err, sizeof err);
  if (!n) {
    fprintf(stderr, "bench_e2e: %s\n", err);
    return -1;
  }
  double t0 = mono_s(), t = -1, best = -1;
  struct vlff_node_status st;
  *first = -1;
  if (rig_start(r, err, sizeof err)) fprintf(stderr, "bench_e2e: %s\n", err);
  while (mono_s() - t0 < LIMIT_S) {
    struct timespec ts = {0, 50 * 1000 * 1000};
    nanosleep(&ts, NULL);
    if (*first < 0) {
      vlff_node_status(n, &st);
      if (st.frames_in > 0) *first = mono_s() - t0;
      continue;
    }
    best = fmax(best, rig_miou3d(r, NULL));
    if (best >= USEFUL_MIOU && t < 0) t = mono_s() - t0 - *first;
    if (t >= 0 && (!r->cameras || mono_s() - t0 >= RIG_MIN_S)) break;
  }
  vlff_node_status(n, &st);
  *frames_in = st.frames_in;
  if (r->cameras) {
    *lost_visible = -1;
    if (rig_capture_stderr(r, err, sizeof err) == 0) {
      *lost_visible = rig_lose_range_camera(r, n, 30, err, sizeof err);
      rig_release_stderr(r);
    }
    if (*lost_visible < 0) fprintf(stderr, "bench_e2e: camera lost: %s\n", err);
    else printf("camera rig: the range camera's loss visible in the node after %.2f s\n", *lost_visible);
  }
  printf("%s: first frame after %.1f s, %s %.1f s after it (ran %.0f s), 3D mIoU %.1f, %lld frames in, %lld refused, "
         "%d keyframes\n",
         r->cameras ? "camera rig" : "sim source", *first, t >= 0 ? "useful" : "not useful within",
         t >= 0 ? t : mono_s() - t0, mono_s() - t0, best, st.frames_in, st.frames_invalid, st.keyframes);
  tk_node_destroy(n, src);
  rig_stop(r);
  return t;
}

int main(int argc, char **argv) {
  if (!rig_netns_enter(argc, argv)) return 1;
  char err[1024];
  double t_sim[REPS], t_cam[REPS], f_sim[REPS], f_cam[REPS], lost_vis[REPS], cpu = 0, unused;
  long long range = 0, pairs = 0, unpaired = 0, startup = 0, orphans = 0, fin;
  /* Interleaved, so that the host's load falls on both alike. */
  for (int k = 0; k < REPS; k++) {
    struct rig sim, cam;
    if (rig_init(&sim, 0, err, sizeof err)) {
      fprintf(stderr, "bench_e2e: %s\n", err);
      return 1;
    }
    t_sim[k] = time_to_useful(&sim, &fin, &f_sim[k], &unused);
    rig_free(&sim);
    if (rig_init(&cam, 1, err, sizeof err)) {
      fprintf(stderr, "bench_e2e: %s\n", err);
      return 1;
    }
    t_cam[k] = time_to_useful(&cam, &fin, &f_cam[k], &lost_vis[k]);
    long long c = rig_camd_stat(&cam, "color_frames"), p = rig_camd_stat(&cam, "committed"),
              u = rig_camd_stat(&cam, "unmatched_color"), d = rig_camd_stat(&cam, "dropped"),
              s0 = rig_camd_stat(&cam, "startup_color"), r = rig_camd_stat(&cam, "depth_frames"),
              r0 = rig_camd_stat(&cam, "startup_depth"),
              o = rig_scenecam_stat(&cam, "range frames of a skipped colour tick: ");
    printf("vlff-camd: %lld pairs of %lld colour frames, %lld before the range camera's first, %lld colour unmatched, "
           "%lld dropped, %.2f s CPU; vlff-scenecam: %lld range frames of a tick its colour camera skipped\n",
           p, c, s0, u, d, cam.camd_cpu_s, o);
    /* A lost pair is the bench's finding, its reason vlff-camd's log. */
    if (r - r0 - p - o > 0) {
      fputs(tk_slurp(cam.camd_out), stdout);
    }
    rig_free(&cam);
    if (t_sim[k] < 0 || t_cam[k] < 0 || c <= 0 || p <= 0 || s0 < 0 || s0 >= c || r0 < 0 || r0 >= r || o < 0 ||
        lost_vis[k] < 0) {
      fprintf(stderr, "bench_e2e: a run did not reach a useful map or the rig delivered nothing\n");
      return 1;
    }
    range += r - r0, startup += s0, pairs += p, unpaired += r - r0 - p - o, orphans += o, cpu += cam.camd_cpu_s;
  }
  qsort(t_sim, REPS, sizeof *t_sim, bench_cmp_double);
  qsort(t_cam, REPS, sizeof *t_cam, bench_cmp_double);
  qsort(f_sim, REPS, sizeof *f_sim, bench_cmp_double);
  qsort(f_cam, REPS, sizeof *f_cam, bench_cmp_double);
  qsort(lost_vis, REPS, sizeof *lost_vis, bench_cmp_double);
  /* camd opens the cameras one after the other, and scenecam creates them
   * as camd starts: the colour camera may stream a few frames before the
   * range camera's first. Those are start-up frames, not lost pairs. */
  printf("RESULT e2e_time_to_useful_s=%.1f sim_time_to_useful_s=%.1f e2e_vs_sim_time=%.2f e2e_first_frame_s=%.1f "
         "sim_first_frame_s=%.1f pairs_dropped_frac=%.3f pairs_startup_frames=%.1f scene_skipped_frac=%.3f "
         "camd_cpu_ms_per_pair=%.2f",
         t_cam[REPS / 2], t_sim[REPS / 2], t_cam[REPS / 2] / t_sim[REPS / 2], f_cam[REPS / 2], f_sim[REPS / 2],
         (double)unpaired / (double)(range - orphans), (double)startup / REPS, (double)orphans / (double)range,
         cpu * 1e3 / (double)pairs);
  printf(" camera_lost_visible_s=%.2f\n", lost_vis[REPS / 2]);
  return 0;
}
