/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * view_fixture MAP FRAMES DIR [big]: a map writer and a camera for vlff-view's tests
 * that need a known map and depth without a learner (test_view_proto). It creates
 * the map segment and the frame ring, publishes version 1 of an 80x60x6 room (a
 * floor, a box, columns never seen) and a 64x48 RGB-D frame every 100 ms, writes
 * what it published to DIR/map-V.json (dims, origin, voxel size, prompts, labels,
 * confidences) and DIR/frame.json (the depth in millimetres, the intrinsics) and
 * prints "map V" once each is written. Each line "change" on stdin publishes the
 * next version (part of the box freed, a new box); end of input ends it.
 * With "big", version 1 is instead a 128x128x64 block with every voxel occupied
 * (1,048,576 voxels, labels 0..2 and confidences from the position), for the
 * whole-map sends of a 1 M-voxel map; "change" is then not taken.
 */
#include <vlff/shm.h>

#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

enum { FW = 64, FH = 48 };
static int NX = 80, NY = 60, NZ = 6;
static size_t N;
static uint16_t *labels;
static uint8_t *conf;
static const char *prompts[3] = {"floor", "box", "wall"};

static size_t at(int i, int j, int k) { return (size_t)i + NX * ((size_t)j + NY * (size_t)k); }

static uint16_t depth_mm(int x, int y) { return x == 0 ? 0 : (uint16_t)(500 + 37 * x + 101 * y); }

static int write_map(const char *dir, int v) {
  char p[4096];
  snprintf(p, sizeof p, "%s/map-%d.json", dir, v);
  FILE *f = fopen(p, "w");
  if (!f) return -1;
  fprintf(f, "{\"dims\":[%d,%d,%d],\"origin\":[-1,-2,0.5],\"voxel_size\":0.1,\"prompts\":[\"floor\",\"box\",\"wall\"],"
             "\"labels\":[", NX, NY, NZ);
  for (size_t i = 0; i < N; i++) fprintf(f, "%s%u", i ? "," : "", labels[i]);
  fprintf(f, "],\"confidence\":[");
  for (size_t i = 0; i < N; i++) fprintf(f, "%s%u", i ? "," : "", conf[i]);
  fprintf(f, "]}\n");
  return fclose(f);
}

static int write_frame(const char *dir) {
  char p[4096];
  snprintf(p, sizeof p, "%s/frame.json", dir);
  FILE *f = fopen(p, "w");
  if (!f) return -1;
  fprintf(f, "{\"width\":%d,\"height\":%d,\"fx\":80,\"fy\":80,\"cx\":32,\"cy\":24,\"depth_mm\":[", FW, FH);
  for (int y = 0; y < FH; y++)
    for (int x = 0; x < FW; x++) fprintf(f, "%s%u", x || y ? "," : "", depth_mm(x, y));
  fprintf(f, "]}\n");
  return fclose(f);
}

static int publish(struct vlff_map *m) {
  struct vlff_map_grid g = {{-1, -2, 0.5}, 0.1, {NX, NY, NZ}, labels, conf};
  struct vlff_map_update up = {.grid = &g, .prompts = prompts, .prompt_count = 3};
  return vlff_map_publish(m, &up);
}

static void frame(struct vlff_ring *r) {
  uint64_t seq;
  struct vlff_frame_hdr *h = vlff_ring_reserve(r, &seq);
  uint64_t len = vlff_frame_layout(h, vlff_ring_slot_size(r), FW, FH, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM);
  uint8_t *px = (uint8_t *)h + h->plane[0].offset;
  for (int i = 0; i < FW * FH * 3; i++) px[i] = (uint8_t)(i * 7);
  uint8_t *d = (uint8_t *)h + h->plane[1].offset;
  for (int y = 0; y < FH; y++)
    for (int x = 0; x < FW; x++) {
      uint16_t v = depth_mm(x, y);
      memcpy(d + (size_t)y * h->plane[1].stride + 2 * x, &v, 2);
    }
  h->frame_id = seq;
  h->t_host_ns = vlff_shm_now_ns();
  h->flags = VLFF_FRAME_POSE_VALID | VLFF_FRAME_INTRINSICS_VALID;
  h->fx = h->fy = 80, h->cx = FW / 2.0, h->cy = FH / 2.0;
  static const double P[16] = {1, 0, 0, 0.5, 0, 1, 0, 0.25, 0, 0, 1, 1, 0, 0, 0, 1};
  memcpy(h->pose, P, sizeof P);
  vlff_ring_commit(r, len);
}

int main(int argc, char **argv) {
  int big = argc == 5 && !strcmp(argv[4], "big");
  if (argc != 4 && !big) {
    fprintf(stderr, "usage: view_fixture MAP FRAMES DIR [big]\n");
    return 2;
  }
  if (big) NX = 128, NY = 128, NZ = 64;
  N = (size_t)NX * NY * NZ;
  labels = malloc(N * sizeof *labels);
  conf = malloc(N);
  if (!labels || !conf) return 1;
  for (int k = 0; k < NZ; k++)
    for (int j = 0; j < NY; j++)
      for (int i = 0; i < NX; i++) {
        uint16_t l = VLFF_LABEL_FREE;
        if (big) l = (uint16_t)((i + 2 * j + 3 * k) % 3);
        else if (i >= 76) l = VLFF_LABEL_UNKNOWN; /* never seen */
        else if (k == 0) l = 0;
        else if (i >= 10 && i < 20 && j >= 5 && j < 15 && k < 4) l = 1;
        labels[at(i, j, k)] = l;
        conf[at(i, j, k)] = (uint8_t)(i * 7 + j * 3 + k);
      }
  struct vlff_map_params mp = {N, 0, 0, {0, NULL}};
  struct vlff_map *m = vlff_map_create(argv[1], &mp);
  struct vlff_ring_params rp = {VLFF_RECORD_FRAME, 4, vlff_frame_slot_size(FW, FH, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM),
                                {0, NULL}};
  struct vlff_ring *r = vlff_ring_create(argv[2], &rp);
  if (!m || !r || write_frame(argv[3])) {
    fprintf(stderr, "view_fixture: %s\n", vlff_shm_last_message());
    return 1;
  }
  frame(r);
  int v = 1;
  if (publish(m) || write_map(argv[3], v)) return 1;
  printf("map %d\n", v);
  fflush(stdout);
  char line[64];
  for (;;) {
    struct pollfd pf = {0, POLLIN, 0};
    int n = poll(&pf, 1, 100);
    frame(r);
    if (n <= 0) continue;
    if (!fgets(line, sizeof line, stdin)) break;
    if (big || strncmp(line, "change", 6)) continue;
    v++;
    /* the box loses its western half; a box of another label appears */
    for (int k = 1; k < 4; k++)
      for (int j = 5; j < 15; j++)
        for (int i = 10; i < 15; i++) labels[at(i, j, k)] = VLFF_LABEL_FREE;
    for (int k = 1; k < 3 + v; k++)
      for (int j = 30; j < 34; j++)
        for (int i = 40 + v; i < 44 + v; i++) labels[at(i, j, k % NZ)] = 2, conf[at(i, j, k % NZ)] = (uint8_t)(100 + v);
    if (publish(m) || write_map(argv[3], v)) return 1;
    printf("map %d\n", v);
    fflush(stdout);
  }
  vlff_ring_close(r);
  vlff_map_detach(m);
  vlff_shm_unlink(argv[1]);
  vlff_shm_unlink(argv[2]);
  free(labels);
  free(conf);
  return 0;
}
