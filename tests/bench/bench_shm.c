/* bench_shm: what the frame ring costs a camera driver, and how fast a waiting
 * consumer hears about a new frame.
 *
 * Throughput: the producer reserves a slot, copies a frame into it and commits,
 * while a consumer thread takes every record it can in place (begin/validate, no
 * copy). The baseline is a plain memcpy of the same bytes into the same number of
 * rotating destination buffers, measured interleaved in the same run; the ratio is
 * ring frames/s over memcpy frames/s (1.0 = the ring is free).
 * Wake latency: commit -> consumer returns from its futex wait, against the same
 * hand-off through an eventfd, both paced so that the consumer is asleep each time. */
#include "bench_stats.h"
#include "vlff/shm.h"

#include <errno.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/eventfd.h>
#include <time.h>
#include <unistd.h>

#define SLOTS 4
#define REPS 5

static char name[64];
static _Atomic int stop;

static void *inplace_consumer(void *arg) {
  struct vlff_ring *r = arg;
  volatile uint8_t sink = 0;
  while (!atomic_load(&stop)) {
    struct vlff_ring_view v;
    if (vlff_ring_read_begin(r, &v, 1000000) < 0)
      continue;
    sink ^= ((const uint8_t *)v.data)[v.len - 1];
    vlff_ring_read_end(r, &v);
  }
  (void)sink;
  return NULL;
}

/* Returns frames/s for ring and memcpy of w x h RGB8 frames. */
static void throughput(uint32_t w, uint32_t h, int frames, double *ring_fps, double *copy_fps) {
  size_t bytes = (size_t)w * h * 3;
  uint64_t slot = vlff_frame_slot_size(w, h, VLFF_PIX_RGB8, VLFF_PIX_NONE);
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_FRAME, .slots = SLOTS, .slot_size = slot};
  struct vlff_ring *wr = vlff_ring_create(name, &p);
  struct vlff_ring *rd = vlff_ring_attach(name, VLFF_RECORD_FRAME);
  if (!wr || !rd) {
    fprintf(stderr, "bench_shm: %s\n", vlff_shm_last_message());
    exit(1);
  }
  uint8_t *src = malloc(bytes), *dst[SLOTS];
  for (int i = 0; i < SLOTS; i++) {
    dst[i] = malloc(bytes);
    memset(dst[i], 0, bytes);
  }
  for (size_t i = 0; i < bytes; i++)
    src[i] = (uint8_t)(i * 131);
  atomic_store(&stop, 0);
  pthread_t t;
  pthread_create(&t, NULL, inplace_consumer, rd);
  double rs[REPS], cs[REPS];
  for (int rep = 0; rep < REPS; rep++) {
    uint64_t t0 = vlff_shm_now_ns();
    for (int f = 0; f < frames; f++) {
      struct vlff_frame_hdr *hdr = vlff_ring_reserve(wr, NULL);
      uint64_t len = vlff_frame_layout(hdr, slot, w, h, VLFF_PIX_RGB8, VLFF_PIX_NONE);
      hdr->frame_id = (uint64_t)f;
      hdr->t_host_ns = t0;
      memcpy((uint8_t *)hdr + hdr->plane[0].offset, src, bytes);
      vlff_ring_commit(wr, len);
    }
    uint64_t t1 = vlff_shm_now_ns();
    for (int f = 0; f < frames; f++)
      memcpy(dst[f % SLOTS], src, bytes);
    uint64_t t2 = vlff_shm_now_ns();
    rs[rep] = frames / ((double)(t1 - t0) / 1e9);
    cs[rep] = frames / ((double)(t2 - t1) / 1e9);
  }
  atomic_store(&stop, 1);
  pthread_join(t, NULL);
  *ring_fps = bench_median(rs, REPS);
  *copy_fps = bench_median(cs, REPS);
  vlff_ring_close(rd);
  vlff_ring_close(wr);
  vlff_shm_unlink(name);
  free(src);
  for (int i = 0; i < SLOTS; i++)
    free(dst[i]);
}

#define WAKES 2000
static double lat_ring[WAKES], lat_efd[WAKES];
static _Atomic uint64_t efd_t;
static int efd;
static _Atomic int ready;

static void *ring_waiter(void *arg) {
  struct vlff_ring *r = arg;
  for (int i = 0; i < WAKES; i++) {
    struct vlff_ring_view v;
    atomic_store(&ready, 1);
    while (vlff_ring_read_begin(r, &v, UINT64_MAX) < 0)
      ;
    uint64_t now = vlff_shm_now_ns(), t;
    memcpy(&t, v.data, sizeof t);
    vlff_ring_read_end(r, &v);
    lat_ring[i] = (double)(now - t) / 1000.0;
  }
  return NULL;
}

static void *efd_waiter(void *arg) {
  (void)arg;
  for (int i = 0; i < WAKES; i++) {
    uint64_t n;
    atomic_store(&ready, 1);
    while (read(efd, &n, sizeof n) != sizeof n)
      ;
    uint64_t now = vlff_shm_now_ns();
    lat_efd[i] = (double)(now - atomic_load(&efd_t)) / 1000.0;
  }
  return NULL;
}

static void pace(void) {
  while (!atomic_load(&ready))
    sched_yield();
  atomic_store(&ready, 0);
  /* Long enough for the waiter to be asleep in the kernel. */
  nanosleep(&(struct timespec){0, 300000}, NULL);
}

static void wake_latency(double *rp50, double *rp99, double *ep50, double *ep99) {
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_RAW, .slots = 8, .slot_size = 64};
  struct vlff_ring *wr = vlff_ring_create(name, &p);
  struct vlff_ring *rd = vlff_ring_attach(name, VLFF_RECORD_RAW);
  pthread_t t;
  atomic_store(&ready, 0);
  pthread_create(&t, NULL, ring_waiter, rd);
  for (int i = 0; i < WAKES; i++) {
    pace();
    uint8_t *s = vlff_ring_reserve(wr, NULL);
    uint64_t now = vlff_shm_now_ns();
    memcpy(s, &now, sizeof now);
    vlff_ring_commit(wr, sizeof now);
  }
  pthread_join(t, NULL);
  efd = eventfd(0, 0);
  atomic_store(&ready, 0);
  pthread_create(&t, NULL, efd_waiter, NULL);
  for (int i = 0; i < WAKES; i++) {
    pace();
    atomic_store(&efd_t, vlff_shm_now_ns());
    uint64_t one = 1;
    if (write(efd, &one, sizeof one) != sizeof one)
      exit(1);
  }
  pthread_join(t, NULL);
  close(efd);
  qsort(lat_ring, WAKES, sizeof(double), bench_cmp_double);
  qsort(lat_efd, WAKES, sizeof(double), bench_cmp_double);
  *rp50 = lat_ring[WAKES / 2];
  *rp99 = lat_ring[WAKES * 99 / 100];
  *ep50 = lat_efd[WAKES / 2];
  *ep99 = lat_efd[WAKES * 99 / 100];
  vlff_ring_close(rd);
  vlff_ring_close(wr);
  vlff_shm_unlink(name);
}

int main(void) {
  snprintf(name, sizeof name, "/vlff-bench-%d", (int)getpid());
  struct {
    const char *label;
    uint32_t w, h;
    int frames;
  } sizes[] = {{"640x480", 640, 480, 400}, {"1080p", 1920, 1080, 60}};
  double ratio_1080 = 0;
  for (int i = 0; i < 2; i++) {
    double rf, cf, bytes = (double)sizes[i].w * sizes[i].h * 3;
    throughput(sizes[i].w, sizes[i].h, sizes[i].frames, &rf, &cf);
    printf("%-8s RGB8 ring %8.1f frames/s %6.2f GB/s | memcpy %8.1f frames/s %6.2f GB/s | ratio %.3f\n",
           sizes[i].label, rf, rf * bytes / 1e9, cf, cf * bytes / 1e9, rf / cf);
    if (i == 1)
      ratio_1080 = rf / cf;
  }
  double rp50, rp99, ep50, ep99;
  wake_latency(&rp50, &rp99, &ep50, &ep99);
  printf("wake latency (%d wakes): ring futex p50 %.1f us p99 %.1f us | eventfd p50 %.1f us p99 %.1f us\n", WAKES,
         rp50, rp99, ep50, ep99);
  printf("RESULT ring_vs_memcpy_1080p=%.3f wake_p50_us=%.1f wake_p99_us=%.1f wake_vs_eventfd_p99=%.3f\n", ratio_1080,
         rp50, rp99, rp99 / ep99);
  return 0;
}
