/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * bench_view: the load for scripts/bench view (tests/bench/view.sh).
 *
 *   bench_view publish MAP FRAMES SECONDS   a 64x54x32 map published at 2 Hz, each
 *       version moving a few surfaces (a share of the voxels changes label,
 *       confidence or occupancy) as a partial publish of the regions it touched,
 *       with a label image; 640x480 RGB frames at 5 Hz. Also prints
 *       "changed_bytes_per_version B": the bytes (label and confidence) of the
 *       voxels whose value changed, per version.
 *   bench_view read MAP SECONDS             the baseline: a bare controller following
 *       every version (vlff_map_snapshot_follow), the least any reader of the map does.
 * Both print their own CPU time at the end: "cpu_s X wall_s Y versions N".
 */
#include <vlff/shm.h>

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <time.h>

enum { NX = 64, NY = 54, NZ = 32, N = NX * NY * NZ, PROMPTS = 20, LW = 160, LH = 120, FW = 640, FH = 480 };

static double cpu_s(void) {
  struct rusage ru;
  getrusage(RUSAGE_SELF, &ru);
  return ru.ru_utime.tv_sec + ru.ru_stime.tv_sec + (ru.ru_utime.tv_usec + ru.ru_stime.tv_usec) / 1e6;
}

static void sleep_until(uint64_t t_ns) {
  uint64_t now = vlff_shm_now_ns();
  if (t_ns <= now) return;
  struct timespec ts = {(time_t)((t_ns - now) / 1000000000u), (long)((t_ns - now) % 1000000000u)};
  nanosleep(&ts, NULL);
}

/* A room: walls, floor and a few boxes occupied; the rest free or unknown. */
static uint16_t room_label(int i, int j, int k, unsigned seed) {
  if (k == 0) return 1;
  if (i == 0 || j == 0 || i == NX - 1 || j == NY - 1) return k < 26 ? 0 : VLFF_LABEL_UNKNOWN;
  int box = ((i / 10) * 7 + (j / 9) * 3 + (int)seed) % PROMPTS;
  if (k < 3 + (box % 6) && (i % 10) > 2 && (j % 9) > 3 && box > 1) return (uint16_t)box;
  return k < 28 ? VLFF_LABEL_FREE : VLFF_LABEL_UNKNOWN;
}

static int publish(const char *mapname, const char *frames, double secs) {
  static const char *prompts[PROMPTS] = {"wall", "floor", "cabinet", "bed", "chair", "sofa", "table",
                                         "door", "window", "bookshelf", "picture", "counter", "desk",
                                         "curtain", "refrigerator", "shower curtain", "toilet", "sink",
                                         "bathtub", "other furniture"};
  struct vlff_map_params mp = {N, LW, LH, {0, NULL}};
  struct vlff_map *map = vlff_map_create(mapname, &mp);
  struct vlff_ring_params rp = {VLFF_RECORD_FRAME, 4, vlff_frame_slot_size(FW, FH, VLFF_PIX_RGB8, VLFF_PIX_NONE), {0, NULL}};
  struct vlff_ring *ring = vlff_ring_create(frames, &rp);
  uint16_t *labels = malloc(N * 2), *limg = malloc(LW * LH * 2);
  uint8_t *conf = malloc(N), *lconf = malloc(LW * LH);
  if (!map || !ring || !labels || !conf || !limg || !lconf) {
    fprintf(stderr, "bench_view: %s\n", vlff_shm_last_message());
    return 1;
  }
  for (int k = 0; k < NZ; k++)
    for (int j = 0; j < NY; j++)
      for (int i = 0; i < NX; i++) {
        labels[i + NX * (j + NY * k)] = room_label(i, j, k, 0);
        conf[i + NX * (j + NY * k)] = 200;
      }
  struct vlff_map_grid g = {{-0.2, -0.2, -0.2}, 0.1, {NX, NY, NZ}, labels, conf};
  struct vlff_map_label_image li = {LW, LH, limg, lconf, 150, 150, 80, 60, {1, 0, 0, 3, 0, 1, 0, 2.5, 0, 0, 1, 1.2, 0, 0, 0, 1}, 0};
  struct vlff_map_update up = {.grid = &g, .prompts = prompts, .prompt_count = PROMPTS, .label_image = &li};
  uint64_t t0 = vlff_shm_now_ns(), next_map = t0, next_frame = t0, end = t0 + (uint64_t)(secs * 1e9);
  unsigned rng = 12345, versions = 0;
  static struct vlff_map_range runs[12 * 3 * 4];
  uint64_t changed_voxels = 0;
  int first = 1;
  double c0 = cpu_s();
  while (vlff_shm_now_ns() < end) {
    if (next_frame <= next_map) {
      sleep_until(next_frame);
      uint64_t seq;
      struct vlff_frame_hdr *h = vlff_ring_reserve(ring, &seq);
      uint64_t len = vlff_frame_layout(h, vlff_ring_slot_size(ring), FW, FH, VLFF_PIX_RGB8, VLFF_PIX_NONE);
      uint8_t *px = (uint8_t *)h + h->plane[0].offset;
      /* a camera-like picture: 16-pixel tiles of two shades over a moving ramp */
      for (int y = 0; y < FH; y++)
        for (int x = 0; x < FW; x++)
          for (int c = 0; c < 3; c++)
            px[(y * FW + x) * 3 + c] =
                (uint8_t)((((x / 16 + y / 16) & 1) ? 60 : 150) + ((x + y + (int)seq * 7) & 255) / 4 + c * 10);
      h->frame_id = seq;
      h->t_host_ns = vlff_shm_now_ns();
      h->flags = VLFF_FRAME_POSE_VALID | VLFF_FRAME_INTRINSICS_VALID;
      h->fx = h->fy = 500, h->cx = FW / 2.0, h->cy = FH / 2.0;
      memcpy(h->pose, li.pose, sizeof h->pose);
      vlff_ring_commit(ring, len);
      next_frame += 200000000u;
      continue;
    }
    sleep_until(next_map);
    /* a learner refines a few regions per version: relabel some boxes' voxels,
     * grow or shrink surfaces, nudge confidences */
    size_t nruns = 0;
    for (int r = 0; r < 12; r++) {
      rng = rng * 1103515245u + 12345u;
      int ci = (int)(rng >> 8) % NX, cj = (int)(rng >> 14) % NY, ck = (int)(rng >> 20) % 8;
      uint16_t nl = (uint16_t)((rng >> 4) % PROMPTS);
      for (int k = ck; k < ck + 3 && k < NZ; k++)
        for (int j = cj; j < cj + 4 && j < NY; j++) {
          int i1 = ci + 4 < NX ? ci + 4 : NX;
          runs[nruns++] = (struct vlff_map_range){(uint32_t)(ci + NX * (j + NY * k)), (uint32_t)(i1 - ci)};
          for (int i = ci; i < i1; i++) {
            size_t idx = i + NX * (j + NY * (size_t)k);
            uint16_t ol = labels[idx];
            uint8_t oc = conf[idx];
            if (labels[idx] <= VLFF_LABEL_MAX) labels[idx] = (r & 3) ? nl : VLFF_LABEL_FREE;
            else if ((r & 3) == 1) labels[idx] = nl;
            conf[idx] = (uint8_t)(100 + (rng >> 24) % 155);
            /* a voxel two regions touched counts once per change */
            changed_voxels += labels[idx] != ol || conf[idx] != oc;
          }
        }
    }
    /* the first version whole, then only the regions touched */
    up.ranges = first ? NULL : runs;
    up.range_count = first ? 0 : nruns;
    first = 0;
    for (int p = 0; p < LW * LH; p++) limg[p] = (uint16_t)((p / LW / 20 + versions) % PROMPTS);
    memset(lconf, 255, LW * LH);
    li.t_ns = vlff_shm_now_ns();
    if (vlff_map_publish(map, &up) != 0) fprintf(stderr, "bench_view: publish: %s\n", vlff_shm_last_message());
    versions++;
    next_map += 500000000u;
  }
  printf("cpu_s %.3f wall_s %.3f versions %u changed_bytes_per_version %.1f\n", cpu_s() - c0,
         (vlff_shm_now_ns() - t0) / 1e9, versions, versions ? 3.0 * (double)changed_voxels / versions : 0.0);
  vlff_map_detach(map);
  vlff_ring_close(ring);
  vlff_shm_unlink(mapname);
  vlff_shm_unlink(frames);
  free(labels);
  free(conf);
  free(limg);
  free(lconf);
  return 0;
}

static int read_map(const char *mapname, double secs) {
  struct vlff_map *map = NULL;
  uint64_t t0 = vlff_shm_now_ns(), end = t0 + (uint64_t)(secs * 1e9), last = 0;
  while (!map && vlff_shm_now_ns() < end) {
    map = vlff_map_attach(mapname);
    if (!map) sleep_until(vlff_shm_now_ns() + 100000000u);
  }
  struct vlff_map_snapshot *s = map ? vlff_map_snapshot_new(map) : NULL;
  if (!s) {
    fprintf(stderr, "bench_view: %s\n", vlff_shm_last_message());
    return 1;
  }
  double c0 = cpu_s();
  unsigned versions = 0;
  t0 = vlff_shm_now_ns();
  while (vlff_shm_now_ns() < end) {
    uint64_t v = vlff_map_version(map);
    if (v != last && vlff_map_snapshot_follow(map, s) >= 0) {
      last = v;
      versions++;
    }
    sleep_until(vlff_shm_now_ns() + 20000000u); /* the viewer's default poll period */
  }
  printf("cpu_s %.3f wall_s %.3f versions %u\n", cpu_s() - c0, (vlff_shm_now_ns() - t0) / 1e9, versions);
  vlff_map_snapshot_free(s);
  vlff_map_detach(map);
  return 0;
}

int main(int argc, char **argv) {
  if (argc == 5 && !strcmp(argv[1], "publish")) return publish(argv[2], argv[3], atof(argv[4]));
  if (argc == 4 && !strcmp(argv[1], "read")) return read_map(argv[2], atof(argv[3]));
  fprintf(stderr, "usage: bench_view publish MAP FRAMES SECONDS | bench_view read MAP SECONDS\n");
  return 2;
}
