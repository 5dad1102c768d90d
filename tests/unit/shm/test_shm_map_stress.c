/* Map readers hammering snapshots and point lookups while the writer publishes as
 * fast as it can. Version k's voxels, confidences, prompts and label image are all a
 * function of k, so a snapshot mixing two versions cannot verify. Threads in one
 * process (so ThreadSanitizer checks the protocol) plus one reader process. Then
 * the same while the grid grows past the segment's capacity again and again
 * (vlff_map_reserve moves the map to a larger segment under the readers). */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <pthread.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <sys/wait.h>

#define DX 24
#define DY 16
#define DZ 12
#define NV (DX * DY * DZ)
#define LW 32
#define LH 24
#define READERS 3
#define GROW_MAX 40 /* growing: the grid's x side goes from DX to DX + GROW_MAX */

static char name[64];
static _Atomic int stop, growing;

/* Version k's x side. */
static uint32_t dx(uint64_t k) {
  return DX + (atomic_load(&growing) ? (uint32_t)(k / 4 < GROW_MAX ? k / 4 : GROW_MAX) : 0);
}

static uint16_t lab(uint64_t k, uint64_t i) { return (uint16_t)(mix64(k * 1000003u + i) % 40); }
static uint8_t cnf(uint64_t k, uint64_t i) { return (uint8_t)(k + i); }

static void *writer(void *arg) {
  struct vlff_map *w = arg;
  static uint16_t labels[(DX + GROW_MAX) * DY * DZ], li[LW * LH];
  static uint8_t conf[(DX + GROW_MAX) * DY * DZ];
  char texts[4][64];
  const char *prompts[4] = {texts[0], texts[1], texts[2], texts[3]};
  uint64_t *published = calloc(1, sizeof *published);
  /* growing, to the end whatever the host's speed */
  for (uint64_t k = 1; !atomic_load(&stop) || (atomic_load(&growing) && k <= 4 * GROW_MAX + 1); k++) {
    const uint64_t nv = (uint64_t)dx(k) * DY * DZ;
    /* a new segment each time the grid outgrows it: GROW_MAX moves */
    if (nv > vlff_map_capacity(w) && vlff_map_reserve(w, nv) != 0)
      return NULL;
    for (uint64_t i = 0; i < nv; i++) {
      labels[i] = lab(k, i);
      conf[i] = cnf(k, i);
    }
    for (uint64_t i = 0; i < LW * LH; i++)
      li[i] = lab(k, i + 7);
    for (int i = 0; i < 4; i++)
      snprintf(texts[i], sizeof texts[i], "v%llu-p%d", (unsigned long long)k, i);
    struct vlff_map_grid g = {.origin = {(double)k, 0, 0}, .voxel_size = 0.1, .dims = {dx(k), DY, DZ},
                              .labels = labels, .confidence = conf};
    struct vlff_map_label_image img = {.width = LW, .height = LH, .labels = li, .t_ns = k, .fx = (double)k};
    struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = (int)(k % 4) + 1,
                                .label_image = &img};
    if (vlff_map_publish(w, &u) != 0)
      return NULL;
    *published = k;
  }
  return published;
}

struct reader_res {
  uint64_t snapshots, bad, backwards, lookups;
};

static void verify_loop(struct reader_res *res, uint64_t min_snapshots) {
  struct vlff_map *m = vlff_map_attach(name);
  if (!m) {
    res->bad++;
    return;
  }
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  uint64_t last = 0, n = 0;
  while (!atomic_load(&stop) || res->snapshots < min_snapshots) {
    /* every other one followed (the changed runs, or whole), the rest taken whole */
    if ((n++ % 2 ? vlff_map_snapshot_follow(m, s) : vlff_map_snapshot_take(m, s)) < 0)
      continue; /* EAGAIN under heavy publishing is allowed: never a torn result */
    struct vlff_map_info in;
    vlff_map_snapshot_info(s, &in);
    uint64_t k = in.version;
    if (k == 0)
      continue;
    res->snapshots++;
    if (k < last)
      res->backwards++;
    last = k;
    int ok = in.grid.origin[0] == (double)k && in.grid.dims[0] == dx(k) && in.prompt_count == (int)(k % 4) + 1 &&
             in.has_label_image && in.label_image.t_ns == k && in.label_image.fx == (double)k;
    for (uint64_t i = 0; ok && i < (uint64_t)dx(k) * DY * DZ; i++)
      ok = in.grid.labels[i] == lab(k, i) && in.grid.confidence[i] == cnf(k, i);
    for (uint64_t i = 0; ok && i < LW * LH; i++)
      ok = in.label_image.labels[i] == lab(k, i + 7);
    for (int i = 0; ok && i < in.prompt_count; i++) {
      char want[64];
      snprintf(want, sizeof want, "v%llu-p%d", (unsigned long long)k, i);
      ok = strcmp(vlff_map_snapshot_prompt(s, (uint16_t)i), want) == 0;
    }
    if (!ok)
      res->bad++;
    /* A point lookup is consistent with itself: the voxel it reports belongs to
     * the version whose origin placed the point in it. */
    uint16_t l;
    uint8_t c;
    if (vlff_map_label_at(m, (double)k + 0.05, 0.05, 0.05, &l, &c) == 0) {
      res->lookups++;
      if (l != VLFF_LABEL_UNKNOWN && l >= 40)
        res->bad++;
    }
  }
  vlff_map_snapshot_free(s);
  vlff_map_detach(m);
}

static void *reader(void *arg) {
  verify_loop(arg, 20);
  return NULL;
}

static void run_stress(void) {
  atomic_store(&stop, 0);
  test_name(name, sizeof name, "mapstress");
  struct vlff_map_params p = {.max_voxels = NV, .label_max_width = LW, .label_max_height = LH};
  struct vlff_map *w = vlff_map_create(name, &p);
  assert_non_null(w);
  /* The reader process is forked before any thread exists. */
  int fd[2];
  assert_int_equal(pipe(fd), 0);
  pid_t child = fork();
  if (child == 0) {
    struct reader_res r = {0};
    uint64_t t_end = vlff_shm_now_ns() + 1500000000ull;
    /* Own stop condition: a deadline, since the parent's flag is not shared. */
    while (vlff_shm_now_ns() < t_end) {
      struct reader_res part = {0};
      atomic_store(&stop, 1);
      verify_loop(&part, 5);
      r.snapshots += part.snapshots;
      r.bad += part.bad;
      r.backwards += part.backwards;
    }
    (void)!write(fd[1], &r, sizeof r);
    _exit(0);
  }
  pthread_t wt, rt[READERS];
  struct reader_res res[READERS] = {{0}};
  assert_int_equal(pthread_create(&wt, NULL, writer, w), 0);
  for (int i = 0; i < READERS; i++)
    assert_int_equal(pthread_create(&rt[i], NULL, reader, &res[i]), 0);
  nanosleep(&(struct timespec){1, 500000000}, NULL);
  atomic_store(&stop, 1);
  void *published;
  for (int i = 0; i < READERS; i++)
    pthread_join(rt[i], NULL);
  pthread_join(wt, &published);
  assert_non_null(published);
  struct reader_res cr;
  assert_int_equal(read(fd[0], &cr, sizeof cr), (ssize_t)sizeof cr);
  int st;
  waitpid(child, &st, 0);
  print_message("writer published %llu versions\n", (unsigned long long)*(uint64_t *)published);
  for (int i = 0; i < READERS; i++) {
    print_message("reader thread %d: %llu snapshots verified, %llu lookups\n", i,
                  (unsigned long long)res[i].snapshots, (unsigned long long)res[i].lookups);
    assert_int_equal(res[i].bad, 0);
    assert_int_equal(res[i].backwards, 0);
    assert_true(res[i].snapshots >= 20);
  }
  print_message("reader process: %llu snapshots verified\n", (unsigned long long)cr.snapshots);
  assert_int_equal(cr.bad, 0);
  assert_true(cr.snapshots > 0);
  assert_true(*(uint64_t *)published > 20);
  if (atomic_load(&growing)) {
    /* it grew to the end and outgrew its first segment on the way */
    assert_true(*(uint64_t *)published > 4 * GROW_MAX);
    assert_true(vlff_map_capacity(w) >= (uint64_t)(DX + GROW_MAX) * DY * DZ);
  }
  free(published);
  close(fd[0]);
  close(fd[1]);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

static void snapshots_always_consistent(void **state) {
  (void)state;
  atomic_store(&growing, 0);
  run_stress();
}

static void snapshots_consistent_while_the_segment_grows(void **state) {
  (void)state;
  atomic_store(&growing, 1);
  run_stress();
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(snapshots_always_consistent), cmocka_unit_test(snapshots_consistent_while_the_segment_grows))
