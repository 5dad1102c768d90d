/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * map_writer: robots' map segments with known content for test_dds_merge.sh,
 * and the check of a fleet map merged from them.
 *
 *   map_writer write NAME SEED SECONDS   a 20x20x10 grid of 0.1 m voxels at
 *       the origin: a floor, a wall and a box labelled, confidences that
 *       differ by SEED (odd for 1, even for 2), a prompt list of SEED's;
 *       seed 1's map also has a far map (what a robot's window left
 *       behind, vlff/shm.h "The far map"): a layer of floor beside the
 *       grid (x -1.6 to 0 m), and a block of wall the grid covers up to
 *       1 m (the grid answers there) reaching 0.6 m above it;
 *       published once; after 2 s a partial publish (its runs) that clears
 *       part of the wall and labels a new box, then prints "changed"; alive
 *       (heartbeats) for SECONDS.
 *   map_writer churn NAME VERSIONS HZ SECONDS   for test_dds_updates.sh:
 *       seed 1's map, then after 3 s VERSIONS partial publishes at HZ
 *       (vlff_map_update.ranges, as the node's), each relabelling a 3x3x2
 *       box to a prompt's label, free or unknown with a new confidence; the
 *       prompt list grows by one text halfway; the last version labels a
 *       box with that text, a change every subscriber sees. Prints
 *       "final V" (the last version) and stays alive SECONDS.
 *   map_writer check FLEET SEG@X,Y,Z,YAW ...   every labelled voxel of each
 *       robot segment, at its centre moved by its transform, against the
 *       fleet segment: each fleet voxel holds the text with the most
 *       evidence (confidences summed per text) among the robot voxels
 *       falling in it, its confidence that evidence over their count, and
 *       no other voxel is labelled. A robot's far voxels beyond its grid
 *       count as its voxels (decoded here, not with vlff's code). The robots' maps differ in age by
 *       seconds, a fraction of a percent of weight at vlff-merge's default
 *       half-life: a text within 1 % of the best is accepted, and a
 *       confidence within 2. Exit 0 when all agree; the first mismatches
 *       printed.
 *   map_writer check-any FLEET SEG@X,Y,Z,YAW ...   the same voxels labelled,
 *       each with a text some robot voxel falling there holds (for robots
 *       whose votes vlff-merge also weighs by their camera paths).
 */
#include <math.h>
#include <stdbool.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "vlff/shm.h"

enum { NX = 20, NY = 20, NZ = 10, N = NX * NY * NZ };

static volatile sig_atomic_t stop;
static void on_signal(int s) { (void)s, stop = 1; }

static int write_map(const char *name, int seed, double secs) {
  static const char *const lists[2][3] = {{"wall", "floor", "chair"}, {"floor", "table", "wall"}};
  const char *const *texts = lists[seed == 2];
  struct vlff_map_params mp = {N, 0, 0, {0, NULL}};
  /* seed 1's far map: block (-1, 0, 0), its first z layer floor (256
   * voxels), and block (0, 0, 0), all wall, whose voxels the grid covers
   * (up to 1 m) are the grid's, and whose 6 layers above it (1536 voxels)
   * are far voxels */
  static const struct vlff_map_far_block blocks[2] = {{{-1, 0, 0}, 0}, {{0, 0, 0}, 2}};
  enum { E3 = VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE, LAYER = E3 / VLFF_MAP_FAR_EDGE };
  const struct vlff_map_far_run far_runs[3] = {
      {1, LAYER, 150, 0}, {VLFF_LABEL_FREE, E3 - LAYER, 0, 0}, {0, E3, 90, 0}}; /* floor, free; wall */
  const struct vlff_map_far far = {{0, 0, 0}, 0.1, 2, 3, blocks, far_runs};
  struct vlff_map *m =
      seed == 1 ? vlff_map_create_far(name, &mp, vlff_map_far_bytes(2, 3)) : vlff_map_create(name, &mp);
  static uint16_t labels[N];
  static uint8_t conf[N];
  if (!m || (seed == 1 && vlff_map_set_far(m, &far) < 0)) {
    fprintf(stderr, "map_writer: %s\n", vlff_shm_last_message());
    return 1;
  }
  /* label texts: floor at k = 0, wall at i = 0, a box (chair or table) */
  int floor_l = seed == 2 ? 0 : 1, wall_l = seed == 2 ? 2 : 0, box_l = seed == 2 ? 1 : 2;
  for (int k = 0; k < NZ; k++)
    for (int j = 0; j < NY; j++)
      for (int i = 0; i < NX; i++) {
        size_t v = i + NX * (j + NY * (size_t)k);
        uint16_t l = VLFF_LABEL_FREE;
        if (k == 0) l = (uint16_t)floor_l;
        else if (i == 0 && k < 6) l = (uint16_t)wall_l;
        else if (i >= 8 && i < 12 && j >= 5 + 3 * seed && j < 9 + 3 * seed && k < 4) l = (uint16_t)box_l;
        labels[v] = l;
        conf[v] = (uint8_t)(2 * ((i * 7 + j * 3 + k * 5 + seed * 11) % 100) + 20 + (seed == 1));
      }
  struct vlff_map_grid g = {{0, 0, 0}, 0.1, {NX, NY, NZ}, labels, conf};
  struct vlff_map_update up = {.grid = &g, .prompts = texts, .prompt_count = 3};
  if (vlff_map_publish(m, &up) < 0) {
    fprintf(stderr, "map_writer: publish: %s\n", vlff_shm_last_message());
    return 1;
  }
  signal(SIGTERM, on_signal);
  signal(SIGINT, on_signal);
  struct timespec t0, t;
  clock_gettime(CLOCK_MONOTONIC, &t0);
  int changed = 0;
  do {
    struct timespec half = {0, 200000000};
    nanosleep(&half, NULL);
    vlff_map_heartbeat(m);
    clock_gettime(CLOCK_MONOTONIC, &t);
    if (!changed && t.tv_sec - t0.tv_sec >= 2) {
      /* the map changes: a subscriber following it (vlff-merge) must too */
      struct vlff_map_range runs[2 * 3 + 3 * 3];
      size_t nr = 0;
      for (int k = 1; k < 3; k++)
        for (int j = 0; j < 3; j++) {
          size_t first = NX * ((size_t)j + NY * (size_t)k);
          runs[nr++] = (struct vlff_map_range){(uint32_t)first, 1};
          labels[first] = VLFF_LABEL_FREE;
        }
      for (int k = 1; k < 4; k++)
        for (int j = 15; j < 18; j++) {
          size_t first = 14 + NX * ((size_t)j + NY * (size_t)k);
          runs[nr++] = (struct vlff_map_range){(uint32_t)first, 3};
          for (size_t v = first; v < first + 3; v++) labels[v] = (uint16_t)box_l, conf[v] = (uint8_t)(240 + seed);
        }
      struct vlff_map_update pu = {.grid = &g, .ranges = runs, .range_count = nr};
      if (vlff_map_publish(m, &pu) < 0) {
        fprintf(stderr, "map_writer: publish: %s\n", vlff_shm_last_message());
        return 1;
      }
      printf("changed\n");
      fflush(stdout);
      changed = 1;
    }
  } while (!stop && (double)(t.tv_sec - t0.tv_sec) < secs);
  vlff_map_detach(m);
  return 0;
}

static void sleep_s(double s) {
  struct timespec t = {(time_t)s, (long)((s - (double)(time_t)s) * 1e9)};
  nanosleep(&t, NULL);
}

static int churn(const char *name, int versions, double hz, double secs) {
  static const char *const texts[4] = {"wall", "floor", "chair", "door"};
  struct vlff_map_params mp = {N, 0, 0, {0, NULL}};
  struct vlff_map *m = vlff_map_create(name, &mp);
  static uint16_t labels[N];
  static uint8_t conf[N];
  if (!m) {
    fprintf(stderr, "map_writer: %s\n", vlff_shm_last_message());
    return 1;
  }
  for (size_t v = 0; v < N; v++) {
    size_t k = v / (NX * NY), i = v % NX;
    labels[v] = k == 0 ? 1 : i == 0 && k < 6 ? 0 : VLFF_LABEL_FREE;
    conf[v] = (uint8_t)(20 + v % 200);
  }
  struct vlff_map_grid g = {{0, 0, 0}, 0.1, {NX, NY, NZ}, labels, conf};
  struct vlff_map_update up = {.grid = &g, .prompts = texts, .prompt_count = 3};
  if (vlff_map_publish(m, &up) < 0) {
    fprintf(stderr, "map_writer: publish: %s\n", vlff_shm_last_message());
    return 1;
  }
  signal(SIGTERM, on_signal);
  signal(SIGINT, on_signal);
  for (int t = 0; t < 15 && !stop; t++) { /* subscribers join */
    sleep_s(0.2);
    vlff_map_heartbeat(m);
  }
  unsigned rng = 7;
  for (int n = 1; n <= versions && !stop; n++) {
    rng = rng * 1103515245u + 12345u;
    int ci = (int)(rng >> 8) % (NX - 3), cj = (int)(rng >> 14) % (NY - 3), ck = (int)(rng >> 20) % (NZ - 2);
    int nprompts = n > versions / 2 ? 4 : 3;
    uint16_t l = (uint16_t)((rng >> 4) % (unsigned)(nprompts + 2));
    if (l >= nprompts) l = l == nprompts ? VLFF_LABEL_FREE : VLFF_LABEL_UNKNOWN;
    if (n == versions) l = 3;
    uint8_t c = (uint8_t)(1 + (rng >> 24) % 255);
    struct vlff_map_range ranges[6];
    size_t nr = 0;
    for (int k = ck; k < ck + 2; k++)
      for (int j = cj; j < cj + 3; j++) {
        size_t first = (size_t)ci + NX * ((size_t)j + NY * (size_t)k);
        ranges[nr++] = (struct vlff_map_range){(uint32_t)first, 3};
        for (size_t v = first; v < first + 3; v++) labels[v] = l, conf[v] = c;
      }
    struct vlff_map_update pu = {.grid = &g, .prompts = texts, .prompt_count = nprompts, .ranges = ranges,
                                 .range_count = nr};
    if (vlff_map_publish(m, &pu) < 0) {
      fprintf(stderr, "map_writer: publish: %s\n", vlff_shm_last_message());
      return 1;
    }
    sleep_s(1 / hz);
  }
  printf("final %llu\n", (unsigned long long)vlff_map_version(m));
  fflush(stdout);
  for (double t = 0; t < secs && !stop; t += 0.2) {
    sleep_s(0.2);
    vlff_map_heartbeat(m);
  }
  vlff_map_detach(m);
  return 0;
}

/* A fleet voxel's expected evidence: per text, the summed confidence. */
struct want {
  int n;             /* robot voxels falling here */
  int ntexts;
  char text[4][VLFF_SHM_PROMPT_LEN];
  double sum[4];
};

/* A robot's voxel at p (its frame) with label and confidence, moved by its
 * transform (tf, c/sn its yaw's cosine and sine) into the fleet's grid fg:
 * a vote for its text in the fleet voxel it falls in (1; 0 outside it). */
static int vote(struct want *want, const struct vlff_map_grid *fg, const struct vlff_map_snapshot *s,
                 const double tf[4], double c, double sn, const double p[3], uint16_t label, uint8_t conf) {
  double w[3] = {c * p[0] - sn * p[1] + tf[0], sn * p[0] + c * p[1] + tf[1], p[2] + tf[2]};
  size_t ix[3];
  for (int a = 0; a < 3; a++) {
    double f = floor((w[a] - fg->origin[a]) / fg->voxel_size);
    if (!(f >= 0 && f < fg->dims[a])) return 0;
    ix[a] = (size_t)f;
  }
  struct want *wv = &want[ix[0] + fg->dims[0] * (ix[1] + (size_t)fg->dims[1] * ix[2])];
  const char *t = vlff_map_snapshot_prompt(s, label);
  int x = 0;
  while (x < wv->ntexts && strcmp(wv->text[x], t)) x++;
  if (x == 4) return 0; /* the robots here hold 2 texts at most */
  if (x == wv->ntexts) snprintf(wv->text[wv->ntexts++], sizeof wv->text[0], "%s", t);
  wv->sum[x] += conf / 255.0;
  wv->n++;
  return 1;
}

static int check(const char *fleet, int nrobots, char **robots, bool anyof) {
  struct vlff_map *fm = vlff_map_attach(fleet);
  struct vlff_map_snapshot *fs = fm ? vlff_map_snapshot_new(fm) : NULL;
  struct vlff_map_info fi;
  if (!fs || vlff_map_snapshot_take(fm, fs) < 0 || vlff_map_snapshot_info(fs, &fi) < 0) {
    printf("check: %s: %s\n", fleet, vlff_shm_last_message());
    return 1;
  }
  const struct vlff_map_grid *fg = &fi.grid;
  size_t total = (size_t)fg->dims[0] * fg->dims[1] * fg->dims[2];
  struct want *want = calloc(total, sizeof *want);
  size_t nfar = 0; /* votes from the robots' far maps */
  for (int r = 0; r < nrobots; r++) {
    char name[256];
    double tf[4];
    if (sscanf(robots[r], "%255[^@]@%lf,%lf,%lf,%lf", name, &tf[0], &tf[1], &tf[2], &tf[3]) != 5) {
      printf("check: '%s' is not SEG@X,Y,Z,YAW\n", robots[r]);
      return 2;
    }
    struct vlff_map *m = vlff_map_attach(name);
    struct vlff_map_snapshot *s = m ? vlff_map_snapshot_new(m) : NULL;
    struct vlff_map_info in;
    if (!s || vlff_map_snapshot_take(m, s) < 0 || vlff_map_snapshot_info(s, &in) < 0) {
      printf("check: %s: %s\n", name, vlff_shm_last_message());
      return 1;
    }
    double c = cos(tf[3] * 3.14159265358979323846 / 180), sn = sin(tf[3] * 3.14159265358979323846 / 180);
    const struct vlff_map_grid *g = &in.grid;
    for (uint32_t k = 0; k < g->dims[2]; k++)
      for (uint32_t j = 0; j < g->dims[1]; j++)
        for (uint32_t i = 0; i < g->dims[0]; i++) {
          size_t v = i + g->dims[0] * (j + (size_t)g->dims[1] * k);
          if (g->labels[v] > VLFF_LABEL_MAX) continue;
          double p[3] = {g->origin[0] + (i + 0.5) * g->voxel_size, g->origin[1] + (j + 0.5) * g->voxel_size,
                         g->origin[2] + (k + 0.5) * g->voxel_size};
          vote(want, fg, s, tf, c, sn, p, g->labels[v], g->confidence ? g->confidence[v] : 255);
        }
    /* its far voxels beyond its grid, decoded from the runs */
    struct vlff_map_far far;
    if (vlff_map_snapshot_far(s, &far) < 0) far.nblocks = 0;
    const uint32_t E = VLFF_MAP_FAR_EDGE;
    for (uint32_t b = 0; b < far.nblocks; b++) {
      const uint32_t end = b + 1 < far.nblocks ? far.blocks[b + 1].first_run : far.nruns;
      uint32_t at = 0;
      for (uint32_t u = far.blocks[b].first_run; u < end; at += far.runs[u++].count)
        for (uint32_t q = at; far.runs[u].label <= VLFF_LABEL_MAX && q < at + far.runs[u].count; q++) {
          const uint32_t l[3] = {q % E, q / E % E, q / (E * E)};
          double p[3];
          int in_grid = 1;
          for (int a = 0; a < 3; a++) {
            p[a] = far.origin[a] + ((double)far.blocks[b].key[a] * E + l[a] + 0.5) * far.voxel_size;
            const double f = floor((p[a] - g->origin[a]) / g->voxel_size);
            in_grid = in_grid && f >= 0 && f < g->dims[a];
          }
          if (!in_grid) nfar += vote(want, fg, s, tf, c, sn, p, far.runs[u].label, far.runs[u].conf);
        }
    }
    vlff_map_snapshot_free(s);
    vlff_map_detach(m);
  }
  size_t bad = 0, labelled = 0, overlap = 0;
  for (size_t v = 0; v < total; v++) {
    const struct want *w = &want[v];
    uint16_t l = fg->labels[v];
    const char *text = l <= VLFF_LABEL_MAX ? vlff_map_snapshot_prompt(fs, l) : NULL;
    int cf = l <= VLFF_LABEL_MAX ? (fg->confidence ? fg->confidence[v] : 255) : -1;
    double best = 0, got = -1;
    int bk = 0;
    for (int k = 0; k < w->ntexts; k++) {
      if (w->sum[k] > best) best = w->sum[k], bk = k;
      if (text && !strcmp(text, w->text[k])) got = w->sum[k];
    }
    labelled += w->n > 0;
    overlap += w->ntexts > 1;
    /* anyof: the votes' weights are not all in the segments (vlff-merge
     * weighs by the robots' camera paths): a text some robot gave there */
    bool ok = !w->n ? !text : anyof ? text && got >= 0 : text && got >= 0.99 * best && abs(cf - (int)lrint(255 * got / w->n)) <= 2;
    if (!ok && bad++ < 5)
      printf("check: fleet voxel %zu: '%s' confidence %d, expected '%s' %ld (of %d robot voxels, %d texts)\n", v,
             text ? text : "-", cf, w->n ? w->text[bk] : "-", w->n ? lrint(255 * best / w->n) : -1L, w->n, w->ntexts);
  }
  printf("check: %zu labelled voxels expected (%zu where robots disagree, %zu robot voxels from far maps), %zu "
         "mismatches, fleet map version %llu, %d labels\n",
         labelled, overlap, nfar, bad, (unsigned long long)fi.version, fi.prompt_count);
  free(want);
  vlff_map_snapshot_free(fs);
  vlff_map_detach(fm);
  return bad || !labelled;
}

int main(int argc, char **argv) {
  if (argc == 5 && !strcmp(argv[1], "write")) return write_map(argv[2], atoi(argv[3]), atof(argv[4]));
  if (argc == 6 && !strcmp(argv[1], "churn")) return churn(argv[2], atoi(argv[3]), atof(argv[4]), atof(argv[5]));
  if (argc >= 4 && !strcmp(argv[1], "check")) return check(argv[2], argc - 3, argv + 3, false);
  if (argc >= 4 && !strcmp(argv[1], "check-any")) return check(argv[2], argc - 3, argv + 3, true);
  fprintf(stderr, "usage: map_writer write NAME SEED SECONDS | churn NAME VERSIONS HZ SECONDS | check|check-any FLEET SEG@X,Y,Z,YAW ...\n");
  return 2;
}
