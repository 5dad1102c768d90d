/*
 * A recorded scene larger than the default scene box (+-2.5 m), replayed
 * into vlff-node as docs/replay.md tells a user: vlff-sim --write-dataset
 * writes a 10 x 8 m flat (its bbox.txt, points.ply, prompt vectors), the
 * node's config names the scene's bbox.txt in field.scene_box_file and no
 * scene_min/max, vlff-replay plays the scene at its stamps, looping. The node
 * must say the box it took and where from, publish a grid over the whole
 * box, and label the scene's points in its far corners, outside the
 * default box (issue 55: the node never saw the scene's box and clipped
 * the map to +-2.5 m, leaving those points unknown). The replay loops as a
 * robot's walk revisits places: on a loaded host the trainer's keyframe
 * queue drops candidates it cannot take in time (as with live cameras),
 * and a single pass could then lose every view of a corner (a CI run did:
 * one corner 35 % labelled after 60 s).
 *
 * Timings scale with VLFF_E2E_SCALE; the coverage thresholds do not.
 */
#define _XOPEN_SOURCE 700
#include <math.h>
#include <setjmp.h>
#include <signal.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "clock.h"
#include "config.h"
#include "dataset.h"
#include "testkit.h"
#include "vlff/shm.h"

static struct tk tk;

/* The scene: the flat over 10 x 8 x 3 m, small images and features so the
 * node keeps up on a loaded host. */
static const double box_lo[3] = {-5, -4, -1.5}, box_hi[3] = {5, 4, 1.5};
#define DEFAULT_HALF 2.5 /* configs/default.yaml's field.scene_min/max */

static int setup(void **state) {
  (void)state;
  tk_setup(&tk, "rbox");
  return 0;
}

static int teardown(void **state) {
  (void)state;
  return tk_teardown(&tk);
}

/* How much of the scene the map labels: the labelled points outside the
 * default box, and per far corner (|x|, |y| beyond it; index by the signs
 * of x and y) how many there are and how many the map labels (neither
 * UNKNOWN nor FREE). */
struct reach {
  int out_n, out_ok;
  int corner_n[4], corner_ok[4];
};

static struct reach reach_read(struct vlff_map *m, struct vlff_map_snapshot *snap, const struct vlff_points *pts) {
  struct reach r = {0};
  if (vlff_map_snapshot_take(m, snap)) return r;
  for (size_t i = 0; i < pts->n; i++) {
    if (pts->label[i] == 255) continue;
    const float *x = pts->xyz + 3 * i;
    bool out = false;
    for (int a = 0; a < 3; a++) out |= fabsf(x[a]) > DEFAULT_HALF;
    if (!out) continue;
    uint16_t lab = vlff_map_snapshot_label_at(snap, x[0], x[1], x[2], NULL);
    bool ok = lab != VLFF_LABEL_UNKNOWN && lab != VLFF_LABEL_FREE;
    r.out_n++, r.out_ok += ok;
    if (fabsf(x[0]) > DEFAULT_HALF && fabsf(x[1]) > DEFAULT_HALF) {
      int c = (x[0] > 0) + 2 * (x[1] > 0);
      r.corner_n[c]++, r.corner_ok[c] += ok;
    }
  }
  return r;
}

/* Most points beyond the default box labelled, and in every far corner
 * the walk saw. */
static bool reach_whole(const struct reach *r) {
  if (r->out_n < 1000 || r->out_ok < 0.8 * r->out_n) return false;
  int corners = 0;
  for (int c = 0; c < 4; c++) {
    if (r->corner_n[c] < 50) continue;
    corners++;
    if (r->corner_ok[c] < 0.6 * r->corner_n[c]) return false;
  }
  return corners >= 2;
}

static void test_map_covers_a_large_scene(void **state) {
  (void)state;
  char scene[300], sim_cfg[300], node_log[300], err[512];
  snprintf(scene, sizeof scene, "%s/scene", tk.dir);
  snprintf(sim_cfg, sizeof sim_cfg, "%s/sim.yaml", tk.dir);
  snprintf(node_log, sizeof node_log, "%s/node.log", tk.dir);
  FILE *f = fopen(sim_cfg, "w");
  assert_non_null(f);
  fprintf(f,
          "sim:\n  layout: flat\n  seed: 4\n  frames: 60\n  rate_hz: 10\n  width: 160\n  height: 120\n"
          "field:\n  feature_dim: 64\n  scene_min: [%g, %g, %g]\n  scene_max: [%g, %g, %g]\n",
          box_lo[0], box_lo[1], box_lo[2], box_hi[0], box_hi[1], box_hi[2]);
  assert_int_equal(fclose(f), 0);
  const char *sargs[] = {"--config", sim_cfg, "--quiet", "--write-dataset", scene, NULL};
  assert_int_equal(tk_wait_child(&tk, tk_spawn(&tk, "node/sim/vlff-sim", sargs, NULL)), 0);

  /* docs/replay.md's ring-source config: the scene's box and prompt vectors
   * by file, no field.scene_min/max (the defaults would clip the flat). */
  struct vlff_config cfg;
  const char *cfg_path =
      tk_config(&tk, &cfg,
                "node:\n  state_dir: %s/state\n"
                "source:\n  kind: ring\n  features: ring\n"
                "field:\n  scene_box_file: %s/bbox.txt\n  feature_dim: 64\n"
                "shm:\n%s  max_width: 320\n  max_height: 240\n"
                "keyframes:\n  start_after: 3\n"
                "publish:\n  rate_hz: 2\n  voxel_size_m: 0.1\n  label_width: 80\n  label_height: 60\n"
                "prompts:\n  embeddings: %s/prompt_embeddings.txt\n",
                tk.dir, scene, tk_shm_names(&tk), scene);
  for (int a = 0; a < 3; a++) {
    assert_true(cfg.field.scene_min[a] == box_lo[a]);
    assert_true(cfg.field.scene_max[a] == box_hi[a]);
  }
  struct vlff_points pts = {0};
  char ply[400];
  snprintf(ply, sizeof ply, "%s/points.ply", scene);
  if (vlff_ply_read(ply, &pts, err, sizeof err)) fail_msg("%s", err);

  const char *nargs[] = {"--config", cfg_path, "--fresh", NULL};
  pid_t node = tk_spawn(&tk, "node/vlff-node", nargs, node_log);
  const char *rargs[] = {"--config", cfg_path, "--wait-reader", "--loop", "--quiet", scene, NULL};
  pid_t replay = tk_spawn(&tk, "node/dataset/vlff-replay", rargs, NULL);

  /* The log names the box and its file. */
  char want[600];
  snprintf(want, sizeof want, "scene box [-5 -4 -1.5]..[5 4 1.5] m from field.scene_box_file %s/bbox.txt", scene);
  if (!tk_wait_for_text(node_log, want, 30 * tk.scale))
    fail_msg("no line '%s' in the node's log:\n%s", want, tk_slurp(node_log));

  struct vlff_map *m = NULL;
  double t0 = vlff_seconds(), deadline = 60 * tk.scale;
  while (!m && vlff_seconds() - t0 < deadline) {
    m = vlff_map_attach(cfg.shm.map);
    if (!m || vlff_map_version(m) == 0) {
      if (m) vlff_map_detach(m);
      m = NULL;
      tk_sleep_s(0.5);
    }
  }
  if (!m) fail_msg("no map published in %.0f s:\n%s", deadline, tk_slurp(node_log));
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(m);
  assert_non_null(snap);
  struct reach r = reach_read(m, snap, &pts);
  while (!reach_whole(&r) && vlff_seconds() - t0 < deadline) {
    tk_sleep_s(1);
    r = reach_read(m, snap, &pts);
  }
  /* The grid spans the scene's box, not the default one. */
  struct vlff_map_info info;
  assert_int_equal(vlff_map_snapshot_info(snap, &info), 0);
  const struct vlff_map_grid *g = &info.grid;
  printf("grid origin [%g %g %g], %u x %u x %u voxels of %g m; %d/%d points beyond +-%.1f m labelled; corners",
         g->origin[0], g->origin[1], g->origin[2], g->dims[0], g->dims[1], g->dims[2], g->voxel_size, r.out_ok,
         r.out_n, DEFAULT_HALF);
  for (int c = 0; c < 4; c++) printf(" %d/%d", r.corner_ok[c], r.corner_n[c]);
  printf(" after %.1f s\n", vlff_seconds() - t0);
  for (int a = 0; a < 3; a++) {
    assert_true(g->origin[a] <= box_lo[a] + 1e-6);
    assert_true(g->origin[a] + g->dims[a] * g->voxel_size >= box_hi[a] - 1e-6);
  }
  assert_true(reach_whole(&r));
  vlff_map_snapshot_free(snap);
  vlff_map_detach(m);

  kill(replay, SIGTERM);
  assert_int_equal(tk_wait_child(&tk, replay), 0);
  kill(node, SIGTERM);
  assert_int_equal(tk_wait_child(&tk, node), 0);
  vlff_points_free(&pts);
}

int main(void) {
  const struct CMUnitTest tests[] = {
      cmocka_unit_test_setup_teardown(test_map_covers_a_large_scene, setup, teardown),
  };
  return cmocka_run_group_tests(tests, NULL, NULL);
}
