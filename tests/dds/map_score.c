/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * map_score: the 3D mIoU of map segments against the simulator's ground
 * truth, for test_dds_fleet.sh and scripts/bench dds: the scene of CONFIG
 * (its sim: section), its labelled points taken from every 5th frame of the
 * whole walk (sim.frames, whatever sim.range_* says) at 5 cm, scored as a
 * controller reads each map (testkit's tk_map_miou3d: a point takes the
 * class of the prompt text its voxel holds; free and unknown are wrong).
 *
 *   map_score CONFIG MAP...   prints "MAP miou3d M version V labels L" per
 *                             map (M -1 when it has no map); exit 0, or 1
 *                             when a map could not be scored
 */
#include <stdio.h>

#include "config.h"
#include "sim.h"
#include "testkit.h"

int main(int argc, char **argv) {
  if (argc < 3) {
    fprintf(stderr, "usage: map_score CONFIG MAP...\n");
    return 2;
  }
  static struct vlff_config cfg;
  char err[1024];
  vlff_config_defaults(&cfg);
  if (vlff_config_load(argv[1], &cfg, err, sizeof err) < 0) {
    fprintf(stderr, "map_score: %s\n", err);
    return 1;
  }
  cfg.sim.range_first = cfg.sim.range_count = 0; /* the whole scene is the truth */
  struct vlff_sim *s = vlff_sim_create(&cfg.sim, &cfg.field, err, sizeof err);
  struct vlff_sim_points gt = {0};
  if (!s || vlff_sim_points(s, cfg.sim.frames, 5, 0.05, &gt, err, sizeof err) < 0) {
    fprintf(stderr, "map_score: %s\n", err);
    return 1;
  }
  int rc = 0;
  for (int i = 2; i < argc; i++) {
    uint64_t version = 0;
    int labels = 0;
    double m = tk_map_miou3d(argv[i], &gt, &version, &labels);
    printf("%s miou3d %.2f version %llu labels %d\n", argv[i], m, (unsigned long long)version, labels);
    rc |= m < 0;
  }
  vlff_sim_points_free(&gt);
  vlff_sim_destroy(s);
  return rc;
}
