/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * bench_dds: the load and the remote subscriber for scripts/bench dds
 * (tests/bench/dds.sh).
 *
 *   bench_dds publish MAP FRAMES SECONDS   a 64x64x32 map published at 1 Hz,
 *       each version relabelling 12 small regions (4x4x3 voxels) published
 *       as partial updates (their runs, as the node publishes), with a
 *       160x120 label image; 640x480 RGB frames with a pose and intrinsics
 *       at 2 Hz. Prints "versions N changed_voxels M" (voxels whose label,
 *       or a labelled voxel's confidence, changed: what a map subscriber
 *       sees change; summed over the versions after the first).
 *   bench_dds subscribe DOMAIN NAMESPACE SECONDS   Cyclone readers of the
 *       bridge's map, map updates, images, camera info and tf (the IDL
 *       only): per map change (an update, or a whole map), the latency from
 *       its publish into the segment (the header stamp) to its receipt;
 *       payload bytes per topic, apart those of the writers' histories sent
 *       when the reader joined and the first whole map. Prints "key value" lines.
 */
#include <vlff/shm.h>

#include <dds/dds.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "sensor_msgs.h"
#include "tf2_msgs.h"

enum { NX = 64, NY = 64, NZ = 32, N = NX * NY * NZ, PROMPTS = 20, LW = 160, LH = 120, FW = 640, FH = 480 };

static void sleep_until(uint64_t t_ns) {
  uint64_t now = vlff_shm_now_ns();
  if (t_ns <= now) return;
  struct timespec ts = {(time_t)((t_ns - now) / 1000000000u), (long)((t_ns - now) % 1000000000u)};
  nanosleep(&ts, NULL);
}

/* A room: floor, walls and boxes labelled; the rest free or unknown. */
static uint16_t room_label(int i, int j, int k) {
  if (k == 0) return 1;
  if (i == 0 || j == 0 || i == NX - 1 || j == NY - 1) return k < 26 ? 0 : VLFF_LABEL_UNKNOWN;
  int box = ((i / 10) * 7 + (j / 9) * 3) % PROMPTS;
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
  uint8_t *conf = malloc(N);
  if (!map || !ring || !labels || !conf || !limg) {
    fprintf(stderr, "bench_dds: %s\n", vlff_shm_last_message());
    return 1;
  }
  for (int k = 0; k < NZ; k++)
    for (int j = 0; j < NY; j++)
      for (int i = 0; i < NX; i++) {
        labels[i + NX * (j + NY * k)] = room_label(i, j, k);
        conf[i + NX * (j + NY * k)] = 200;
      }
  struct vlff_map_grid g = {{-0.2, -0.2, -0.2}, 0.1, {NX, NY, NZ}, labels, conf};
  struct vlff_map_label_image li = {LW, LH, limg, NULL, 150, 150, 80, 60, {1, 0, 0, 3, 0, 1, 0, 2.5, 0, 0, 1, 1.2, 0, 0, 0, 1}, 0};
  struct vlff_map_update up = {.grid = &g, .prompts = prompts, .prompt_count = PROMPTS, .label_image = &li};
  uint64_t t0 = vlff_shm_now_ns(), next_map = t0, next_frame = t0, end = t0 + (uint64_t)(secs * 1e9);
  unsigned rng = 12345, versions = 0;
  unsigned long long changed = 0;
  while (vlff_shm_now_ns() < end) {
    if (next_frame <= next_map) {
      sleep_until(next_frame);
      uint64_t seq;
      struct vlff_frame_hdr *h = vlff_ring_reserve(ring, &seq);
      uint64_t len = vlff_frame_layout(h, vlff_ring_slot_size(ring), FW, FH, VLFF_PIX_RGB8, VLFF_PIX_NONE);
      uint8_t *px = (uint8_t *)h + h->plane[0].offset;
      for (int y = 0; y < FH; y++)
        for (int x = 0; x < FW; x++)
          for (int c = 0; c < 3; c++)
            px[(y * FW + x) * 3 + c] = (uint8_t)((((x / 16 + y / 16) & 1) ? 60 : 150) + ((x + y + (int)seq * 7) & 255) / 4 + c * 10);
      h->frame_id = seq;
      h->t_host_ns = vlff_shm_now_ns();
      h->flags = VLFF_FRAME_POSE_VALID | VLFF_FRAME_INTRINSICS_VALID;
      h->fx = h->fy = 500, h->cx = FW / 2.0, h->cy = FH / 2.0;
      memcpy(h->pose, li.pose, sizeof h->pose);
      vlff_ring_commit(ring, len);
      next_frame += 500000000u;
      continue;
    }
    sleep_until(next_map);
    /* a learner refining a few regions per version, publishing their runs */
    static struct vlff_map_range runs[12 * 12];
    static uint16_t prev_l[N];
    static uint8_t prev_c[N];
    size_t nruns = 0;
    memcpy(prev_l, labels, sizeof prev_l);
    memcpy(prev_c, conf, sizeof prev_c);
    for (int r = 0; versions && r < 12; r++) {
      rng = rng * 1103515245u + 12345u;
      int ci = (int)(rng >> 8) % NX, cj = (int)(rng >> 14) % NY, ck = (int)(rng >> 20) % 8;
      uint16_t nl = (uint16_t)((rng >> 4) % PROMPTS);
      uint8_t nc = (uint8_t)(100 + (rng >> 24) % 155);
      for (int k = ck; k < ck + 3 && k < NZ; k++)
        for (int j = cj; j < cj + 4 && j < NY; j++) {
          int i1 = ci + 4 < NX ? ci + 4 : NX;
          runs[nruns++] = (struct vlff_map_range){(uint32_t)(ci + NX * (j + NY * k)), (uint32_t)(i1 - ci)};
          for (int i = ci; i < i1; i++) {
            size_t idx = i + NX * (j + NY * (size_t)k);
            uint16_t l = labels[idx];
            if (l <= VLFF_LABEL_MAX) l = (r & 3) ? nl : VLFF_LABEL_FREE;
            else if ((r & 3) == 1) l = nl;
            labels[idx] = l;
            conf[idx] = nc;
          }
        }
    }
    /* what a subscriber sees change: a label, or a labelled voxel's confidence */
    for (size_t i = 0; versions && i < N; i++)
      changed += labels[i] != prev_l[i] || (labels[i] <= VLFF_LABEL_MAX && conf[i] != prev_c[i]);
    up.ranges = versions ? runs : NULL;
    up.range_count = versions ? nruns : 0;
    for (int p = 0; p < LW * LH; p++) limg[p] = (uint16_t)((p / LW / 20 + versions) % PROMPTS);
    li.t_ns = vlff_shm_now_ns();
    if (vlff_map_publish(map, &up) != 0) fprintf(stderr, "bench_dds: publish: %s\n", vlff_shm_last_message());
    versions++;
    next_map += 1000000000u;
  }
  printf("versions %u\nchanged_voxels %llu\n", versions, changed);
  vlff_map_detach(map);
  vlff_ring_close(ring);
  vlff_shm_unlink(mapname);
  vlff_shm_unlink(frames);
  free(labels);
  free(conf);
  free(limg);
  return 0;
}

static dds_entity_t reader(dds_entity_t pp, const dds_topic_descriptor_t *d, const char *name, bool transient) {
  dds_entity_t t = dds_create_topic(pp, d, name, NULL, NULL);
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 4);
  if (transient) dds_qset_durability(q, DDS_DURABILITY_TRANSIENT_LOCAL);
  dds_entity_t r = dds_create_reader(pp, t, q, NULL);
  dds_delete_qos(q);
  return r;
}

static int cmp_double(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return x < y ? -1 : x > y;
}

static int subscribe(int domain, const char *ns, double secs) {
  dds_entity_t pp = dds_create_participant((dds_domainid_t)domain, NULL, NULL);
  if (pp < 0) {
    fprintf(stderr, "bench_dds: participant: %s\n", dds_strretcode(pp));
    return 1;
  }
  char name[6][256];
  snprintf(name[0], sizeof name[0], "rt%s/vlff/map", ns);
  snprintf(name[5], sizeof name[5], "rt%s/vlff/map/updates", ns);
  snprintf(name[1], sizeof name[1], "rt%s/vlff/label_image", ns);
  snprintf(name[2], sizeof name[2], "rt%s/vlff/camera/image_raw", ns);
  snprintf(name[3], sizeof name[3], "rt%s/vlff/camera/camera_info", ns);
  snprintf(name[4], sizeof name[4], "rt%s/tf", ns);
  dds_entity_t r[6] = {reader(pp, &sensor_msgs_msg_dds__PointCloud2__desc, name[0], true),
                       reader(pp, &sensor_msgs_msg_dds__Image__desc, name[1], false),
                       reader(pp, &sensor_msgs_msg_dds__Image__desc, name[2], false),
                       reader(pp, &sensor_msgs_msg_dds__CameraInfo__desc, name[3], false),
                       reader(pp, &tf2_msgs_msg_dds__TFMessage__desc, name[4], false),
                       reader(pp, &sensor_msgs_msg_dds__PointCloud2__desc, name[5], true)};
  dds_entity_t ws = dds_create_waitset(pp);
  for (int i = 0; i < 6; i++) dds_waitset_attach(ws, dds_create_readcondition(r[i], DDS_ANY_STATE), i);
  static double lat[100000];
  size_t nlat = 0;
  unsigned long long bytes[6] = {0}, count[6] = {0}, joined_bytes = 0, last_full = 0;
  struct timespec t0;
  clock_gettime(CLOCK_MONOTONIC, &t0);
  /* samples written before this reader existed come from the histories */
  dds_time_t joined = dds_time();
  for (;;) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    if ((double)(t.tv_sec - t0.tv_sec) + 1e-9 * (double)(t.tv_nsec - t0.tv_nsec) >= secs) break;
    dds_waitset_wait(ws, NULL, 0, DDS_MSECS(100));
    for (int i = 0; i < 6; i++) {
      void *s[8] = {NULL};
      dds_sample_info_t info[8];
      dds_return_t n = dds_take(r[i], s, info, 8, 8);
      if (n <= 0) continue;
      struct timespec rt;
      clock_gettime(CLOCK_REALTIME, &rt);
      for (int k = 0; k < n; k++) {
        if (!info[k].valid_data) continue;
        count[i]++;
        if (i == 0 || i == 5) {
          const sensor_msgs_msg_dds__PointCloud2_ *m = s[k];
          /* the first whole map (the history's, or the bridge's first) is
           * what joining costs, not the steady rate */
          bool first_full = i == 0 && !last_full;
          if (i == 0) last_full = m->data._length;
          if (info[k].source_timestamp < joined || first_full) {
            joined_bytes += m->data._length;
            count[i]--;
            continue;
          }
          bytes[i] += m->data._length;
          double ms = ((double)rt.tv_sec - m->header.stamp.sec) * 1e3 + ((double)rt.tv_nsec - m->header.stamp.nanosec) / 1e6;
          if (nlat < sizeof lat / sizeof lat[0]) lat[nlat++] = ms;
        } else if (i < 3) {
          bytes[i] += ((const sensor_msgs_msg_dds__Image_ *)s[k])->data._length;
        }
      }
      dds_return_loan(r[i], s, n);
    }
  }
  qsort(lat, nlat, sizeof lat[0], cmp_double);
  printf("maps %llu\nupdates %llu\nlatency_n %zu\n", count[0], count[5], nlat);
  if (nlat) {
    printf("latency_p50_ms %.2f\n", lat[nlat / 2]);
    printf("latency_p99_ms %.2f\n", lat[(size_t)ceil(0.99 * (double)nlat) - 1]);
    printf("latency_max_ms %.2f\n", lat[nlat - 1]);
  }
  printf("map_bytes %llu\nupdate_bytes %llu\njoined_bytes %llu\nlast_full_bytes %llu\n", bytes[0], bytes[5], joined_bytes,
         last_full);
  printf("label_image_bytes %llu\ncamera_image_bytes %llu\n", bytes[1], bytes[2]);
  printf("label_images %llu\ncamera_images %llu\ncamera_infos %llu\ntfs %llu\n", count[1], count[2], count[3], count[4]);
  dds_delete(pp);
  return 0;
}

int main(int argc, char **argv) {
  if (argc == 5 && !strcmp(argv[1], "publish")) return publish(argv[2], argv[3], atof(argv[4]));
  if (argc == 5 && !strcmp(argv[1], "subscribe")) return subscribe(atoi(argv[2]), argv[3], atof(argv[4]));
  fprintf(stderr, "usage: bench_dds publish MAP FRAMES SECONDS | subscribe DOMAIN NAMESPACE SECONDS\n");
  return 2;
}
