/* The map's change log (issue 49): partial publishes and a reader that follows
 * versions by copying only what the log says changed. A follower must end every
 * follow bit for bit equal to a fresh whole copy; it must fall back to a whole copy
 * when the log wrapped past its version, the geometry or the writer's generation
 * changed, or it holds nothing yet; and it must never see a mix of two versions
 * while the writer publishes as fast as it can (a thread here, so ThreadSanitizer
 * checks the protocol). */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <errno.h>
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <stdlib.h>

#define DX 24
#define DY 16
#define DZ 12
#define NV (DX * DY * DZ)
#define LW 8
#define LH 6

static char name[64];

static int remove_seg(void **state) {
  (void)state;
  vlff_shm_unlink(name);
  return 0;
}

static struct vlff_map *make_writer(void) {
  test_name(name, sizeof name, "follow");
  struct vlff_map_params mp = {.max_voxels = NV, .label_max_width = LW, .label_max_height = LH};
  struct vlff_map *w = vlff_map_create(name, &mp);
  assert_non_null(w);
  return w;
}

static uint16_t val(uint64_t k, uint64_t i) { return (uint16_t)(mix64(k * 7919u + i) % 40); }
static uint8_t cval(uint64_t k, uint64_t i) { return (uint8_t)mix64(k * 31u + i * 3u + 1u); }

static struct vlff_map_grid grid_of(uint16_t *labels, uint8_t *conf, const uint32_t dims[3]) {
  struct vlff_map_grid g = {.origin = {-1, -2, 0}, .voxel_size = 0.1, .labels = labels, .confidence = conf};
  memcpy(g.dims, dims, sizeof g.dims);
  return g;
}

/* The runs version k changes (a pure function of k, so a reader can replay
 * them): 1..8 runs of 1..64 elements anywhere in the grid of n elements. */
static size_t runs_of(uint64_t k, uint64_t n, struct vlff_map_range *r) {
  size_t c = 1 + mix64(k) % 8;
  for (size_t i = 0; i < c; i++) {
    uint64_t x = mix64(k * 131u + i);
    uint32_t len = 1 + (uint32_t)(x % 64);
    uint32_t first = (uint32_t)((x >> 20) % (n - len + 1));
    r[i] = (struct vlff_map_range){first, len};
  }
  return c;
}

/* Applies version k's runs to the mirror of the map. */
static void apply(uint64_t k, uint64_t n, uint16_t *labels, uint8_t *conf) {
  struct vlff_map_range r[8];
  size_t c = runs_of(k, n, r);
  for (size_t j = 0; j < c; j++)
    for (uint32_t i = r[j].first; i < r[j].first + r[j].count; i++)
      labels[i] = val(k, i), conf[i] = cval(k, i);
}

static int publish_full(struct vlff_map *w, uint64_t k, uint16_t *labels, uint8_t *conf, const uint32_t dims[3]) {
  uint64_t n = (uint64_t)dims[0] * dims[1] * dims[2];
  for (uint64_t i = 0; i < n; i++)
    labels[i] = val(k, i), conf[i] = cval(k, i);
  struct vlff_map_grid g = grid_of(labels, conf, dims);
  const char *prompts[2] = {"wall", "floor"};
  static uint16_t img[LW * LH];
  for (int i = 0; i < LW * LH; i++)
    img[i] = (uint16_t)(k + i);
  struct vlff_map_label_image li = {.width = LW, .height = LH, .labels = img, .t_ns = k};
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = 2, .label_image = &li};
  return vlff_map_publish(w, &u);
}

static int publish_runs(struct vlff_map *w, uint64_t k, uint16_t *labels, uint8_t *conf, const uint32_t dims[3]) {
  uint64_t n = (uint64_t)dims[0] * dims[1] * dims[2];
  apply(k, n, labels, conf);
  struct vlff_map_range r[8];
  size_t c = runs_of(k, n, r);
  struct vlff_map_grid g = grid_of(labels, conf, dims);
  struct vlff_map_update u = {.grid = &g, .ranges = r, .range_count = c};
  return vlff_map_publish(w, &u);
}

/* snap holds exactly what a fresh whole copy holds, grid and image. */
static void assert_same(struct vlff_map *m, struct vlff_map_snapshot *s) {
  struct vlff_map_snapshot *t = vlff_map_snapshot_new(m);
  assert_int_equal(vlff_map_snapshot_take(m, t), 0);
  struct vlff_map_info a, b;
  vlff_map_snapshot_info(s, &a);
  vlff_map_snapshot_info(t, &b);
  assert_int_equal(a.version, b.version);
  assert_memory_equal(a.grid.dims, b.grid.dims, sizeof a.grid.dims);
  size_t n = (size_t)a.grid.dims[0] * a.grid.dims[1] * a.grid.dims[2];
  assert_memory_equal(a.grid.labels, b.grid.labels, 2 * n);
  assert_memory_equal(a.grid.confidence, b.grid.confidence, n);
  assert_int_equal(a.has_label_image, b.has_label_image);
  if (a.has_label_image)
    assert_memory_equal(a.label_image.labels, b.label_image.labels, 2 * (size_t)a.label_image.width * a.label_image.height);
  assert_int_equal(a.prompt_count, b.prompt_count);
  vlff_map_snapshot_free(t);
}

/* Every element where before and after differ lies in one of the snapshot's
 * reported changes. */
static void assert_changes_cover(const struct vlff_map_snapshot *s, const uint16_t *before, const uint8_t *cbefore) {
  struct vlff_map_info in;
  vlff_map_snapshot_info(s, &in);
  const struct vlff_map_range *r;
  int all;
  size_t nr = vlff_map_snapshot_changes(s, &r, &all);
  size_t j = 0;
  for (size_t i = 0; i < NV; i++) {
    while (j < nr && r[j].first + r[j].count <= i)
      j++;
    bool inside = j < nr && r[j].first <= i;
    if (!inside && (in.grid.labels[i] != before[i] || in.grid.confidence[i] != cbefore[i]))
      fail_msg("element %zu changed outside the reported ranges", i);
  }
  for (size_t i = 1; i < nr; i++)
    assert_true(r[i].first > r[i - 1].first + r[i - 1].count); /* sorted, disjoint, not touching */
}

/* Hundreds of partial publishes, followed one at a time and several at once: each
 * follow copies only runs and leaves the snapshot equal to a whole copy. */
static void test_follow_equals_take(void **state) {
  (void)state;
  static uint16_t labels[NV], before[NV];
  static uint8_t conf[NV], cbefore[NV];
  const uint32_t dims[3] = {DX, DY, DZ};
  struct vlff_map *w = make_writer();
  struct vlff_map *m = vlff_map_attach(name);
  assert_non_null(m);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  assert_non_null(s);
  /* Nothing published: an empty whole copy. */
  assert_int_equal(vlff_map_snapshot_follow(m, s), 1);
  assert_int_equal(publish_full(w, 1, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 1);
  assert_same(m, s);
  int all;
  const struct vlff_map_range *r;
  assert_int_equal(vlff_map_snapshot_changes(s, &r, &all), 1);
  assert_int_equal(all, 1);
  assert_int_equal(r[0].first, 0);
  assert_int_equal(r[0].count, NV);
  uint64_t k = 1;
  for (int round = 0; round < 300; round++) {
    int burst = 1 + round % 5; /* 1..5 publishes between two follows */
    for (int b = 0; b < burst; b++)
      assert_int_equal(publish_runs(w, ++k, labels, conf, dims), 0);
    struct vlff_map_info in;
    vlff_map_snapshot_info(s, &in);
    memcpy(before, in.grid.labels, sizeof before);
    memcpy(cbefore, in.grid.confidence, sizeof cbefore);
    assert_int_equal(vlff_map_snapshot_follow(m, s), 0);
    assert_same(m, s);
    vlff_map_snapshot_info(s, &in);
    assert_int_equal(in.version, k);
    assert_memory_equal(in.grid.labels, labels, sizeof labels);
    assert_memory_equal(in.grid.confidence, conf, sizeof conf);
    assert_changes_cover(s, before, cbefore);
    size_t nr = vlff_map_snapshot_changes(s, &r, &all);
    assert_int_equal(all, 0);
    assert_true(nr >= 1 && nr <= 8 * (size_t)burst);
  }
  /* Already current: nothing copied, nothing reported. */
  assert_int_equal(vlff_map_snapshot_follow(m, s), 0);
  assert_int_equal(vlff_map_snapshot_changes(s, &r, &all), 0);
  /* The label image follows too when a publish replaces it. */
  assert_int_equal(publish_full(w, ++k, labels, conf, dims), 0);
  assert_int_equal(publish_runs(w, ++k, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 0);
  assert_same(m, s);
  vlff_map_snapshot_free(s);
  vlff_map_detach(m);
  vlff_map_detach(w);
}

/* A follower left behind by more publishes than the log holds copies everything,
 * and is right. */
static void test_follow_wrapped(void **state) {
  (void)state;
  static uint16_t labels[NV];
  static uint8_t conf[NV];
  const uint32_t dims[3] = {DX, DY, DZ};
  struct vlff_map *w = make_writer();
  struct vlff_map *m = vlff_map_attach(name);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  assert_int_equal(publish_full(w, 1, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 1);
  /* The log of a map this small holds 512 runs; each publish logs up to 8. */
  uint64_t k = 1;
  for (int i = 0; i < 200; i++)
    assert_int_equal(publish_runs(w, ++k, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 1);
  assert_same(m, s);
  int all;
  vlff_map_snapshot_changes(s, NULL, &all);
  assert_int_equal(all, 1);
  /* And from there on it follows runs again. */
  assert_int_equal(publish_runs(w, ++k, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 0);
  assert_same(m, s);
  vlff_map_snapshot_free(s);
  vlff_map_detach(m);
  vlff_map_detach(w);
}

/* A publish with more runs than a quarter of the log is coarsened: the follower
 * still ends equal, the log keeps room for other versions. */
static void test_follow_coarsened(void **state) {
  (void)state;
  static uint16_t labels[NV];
  static uint8_t conf[NV];
  const uint32_t dims[3] = {DX, DY, DZ};
  struct vlff_map *w = make_writer();
  struct vlff_map *m = vlff_map_attach(name);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  assert_int_equal(publish_full(w, 1, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 1);
  static struct vlff_map_range r[1000];
  for (uint32_t i = 0; i < 1000; i++) {
    uint32_t at = (uint32_t)(mix64(i) % NV);
    r[i] = (struct vlff_map_range){at, 1};
    labels[at] = (uint16_t)(100 + i % 7);
    conf[at] = (uint8_t)i;
  }
  struct vlff_map_grid g = grid_of(labels, conf, dims);
  struct vlff_map_update u = {.grid = &g, .ranges = r, .range_count = 1000};
  assert_int_equal(vlff_map_publish(w, &u), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 0);
  assert_same(m, s);
  struct vlff_map_info in;
  vlff_map_snapshot_info(s, &in);
  assert_memory_equal(in.grid.labels, labels, sizeof labels);
  const struct vlff_map_range *c;
  size_t nc = vlff_map_snapshot_changes(s, &c, NULL);
  assert_true(nc >= 1 && nc <= 512 / 4); /* this map's log holds 512 runs */
  /* The next one-run publish is still followed from the log. */
  assert_int_equal(publish_runs(w, 3, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 0);
  assert_same(m, s);
  vlff_map_snapshot_free(s);
  vlff_map_detach(m);
  vlff_map_detach(w);
}

/* A new geometry is a whole copy; runs for another geometry than the published
 * one, or before any grid, or past the grid, are refused and change nothing. */
static void test_follow_geometry(void **state) {
  (void)state;
  static uint16_t labels[NV];
  static uint8_t conf[NV];
  const uint32_t dims[3] = {DX, DY, DZ}, small[3] = {DX, DY, DZ / 2};
  struct vlff_map *w = make_writer();
  struct vlff_map *m = vlff_map_attach(name);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  struct vlff_map_range one = {0, 4};
  struct vlff_map_grid g = grid_of(labels, conf, dims);
  struct vlff_map_update u = {.grid = &g, .ranges = &one, .range_count = 1};
  errno = 0;
  assert_int_equal(vlff_map_publish(w, &u), -1); /* nothing published yet */
  assert_int_equal(errno, EINVAL);
  assert_int_equal(publish_full(w, 1, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 1);
  assert_int_equal(publish_full(w, 2, labels, conf, small), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 1);
  assert_same(m, s);
  g = grid_of(labels, conf, dims);
  errno = 0;
  assert_int_equal(vlff_map_publish(w, &u), -1); /* the published grid is the small one */
  assert_int_equal(errno, EINVAL);
  g = grid_of(labels, conf, small);
  struct vlff_map_range past = {NV / 2 - 2, 4};
  u.ranges = &past;
  errno = 0;
  assert_int_equal(vlff_map_publish(w, &u), -1);
  assert_int_equal(errno, EINVAL);
  assert_int_equal(vlff_map_version(m), 2);
  assert_int_equal(publish_runs(w, 3, labels, conf, small), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 0);
  assert_same(m, s);
  vlff_map_snapshot_free(s);
  vlff_map_detach(m);
  vlff_map_detach(w);
}

/* A writer that restarts on the segment (a new generation) may not have logged
 * what it changed: followers copy everything once. */
static void test_follow_generation(void **state) {
  (void)state;
  static uint16_t labels[NV];
  static uint8_t conf[NV];
  const uint32_t dims[3] = {DX, DY, DZ};
  struct vlff_map *w = make_writer();
  struct vlff_map *m = vlff_map_attach(name);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  assert_int_equal(publish_full(w, 1, labels, conf, dims), 0);
  assert_int_equal(publish_runs(w, 2, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 1);
  uint32_t gen = vlff_map_generation(m);
  vlff_map_detach(w);
  /* The creator's own process may take its segment over again. */
  struct vlff_map_params mp = {.max_voxels = NV, .label_max_width = LW, .label_max_height = LH};
  w = vlff_map_create(name, &mp);
  assert_non_null(w);
  assert_int_equal(vlff_map_generation(m), gen + 1);
  assert_int_equal(publish_runs(w, 3, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 1);
  assert_same(m, s);
  assert_int_equal(publish_runs(w, 4, labels, conf, dims), 0);
  assert_int_equal(vlff_map_snapshot_follow(m, s), 0);
  assert_same(m, s);
  vlff_map_snapshot_free(s);
  vlff_map_detach(m);
  vlff_map_detach(w);
}

/* ------------------------------------------- concurrent writer and follower */

#define LAST 3000

static _Atomic int done;
static _Atomic uint64_t published, seen;

/* Publishes versions 1..LAST as fast as it can, but lets the follower come within
 * 48 versions every 16, so that it follows from the log while racing the writer
 * rather than always falling behind it. */
static void *writer_main(void *arg) {
  struct vlff_map *w = arg;
  static uint16_t labels[NV];
  static uint8_t conf[NV];
  const uint32_t dims[3] = {DX, DY, DZ};
  void *ok = arg;
  if (publish_full(w, 1, labels, conf, dims) != 0)
    ok = NULL;
  else
    atomic_store(&published, 1);
  for (uint64_t k = 2; ok && k <= LAST; k++) {
    if (publish_runs(w, k, labels, conf, dims) != 0) {
      ok = NULL;
      break;
    }
    atomic_store(&published, k);
    if (k % 16 == 0)
      while (atomic_load(&seen) + 32 < k)
        sched_yield();
  }
  atomic_store(&done, 1);
  return ok;
}

/* The follower replays the writer's runs into its own mirror up to the version it
 * got and compares: a snapshot mixing two versions, or missing a run, cannot
 * match. */
static void test_follow_concurrent(void **state) {
  (void)state;
  struct vlff_map *w = make_writer();
  struct vlff_map *m = vlff_map_attach(name);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  static uint16_t mirror[NV];
  static uint8_t cmirror[NV];
  atomic_store(&done, 0);
  atomic_store(&published, 0);
  atomic_store(&seen, 0);
  pthread_t t;
  assert_int_equal(pthread_create(&t, NULL, writer_main, w), 0);
  uint64_t at = 0, follows = 0, partial = 0, whole = 0;
  while (!atomic_load(&done) || at < atomic_load(&published)) {
    int rc = vlff_map_snapshot_follow(m, s);
    if (rc < 0) {
      assert_int_equal(errno, EAGAIN); /* lapped for too long: allowed, never torn */
      continue;
    }
    struct vlff_map_info in;
    vlff_map_snapshot_info(s, &in);
    if (!in.version)
      continue;
    follows++;
    rc ? whole++ : partial++;
    assert_true(in.version >= at);
    if (at == 0) {
      for (uint64_t i = 0; i < NV; i++)
        mirror[i] = val(1, i), cmirror[i] = cval(1, i);
      at = 1;
    }
    for (uint64_t k = at + 1; k <= in.version; k++)
      apply(k, NV, mirror, cmirror);
    at = in.version;
    if (memcmp(in.grid.labels, mirror, sizeof mirror) || memcmp(in.grid.confidence, cmirror, sizeof cmirror))
      fail_msg("follow %llu (version %llu, %s copy) differs from the version it names",
               (unsigned long long)follows, (unsigned long long)at, rc ? "whole" : "partial");
    atomic_store(&seen, at);
  }
  void *ok;
  pthread_join(t, &ok);
  assert_non_null(ok);
  assert_int_equal(at, LAST);
  print_message("%llu follows: %llu by runs, %llu whole\n", (unsigned long long)follows,
                (unsigned long long)partial, (unsigned long long)whole);
  assert_true(partial > whole);
  vlff_map_snapshot_free(s);
  vlff_map_detach(m);
  vlff_map_detach(w);
}

int main(void) {
  const struct CMUnitTest tests[] = {
      cmocka_unit_test_teardown(test_follow_equals_take, remove_seg),
      cmocka_unit_test_teardown(test_follow_wrapped, remove_seg),
      cmocka_unit_test_teardown(test_follow_coarsened, remove_seg),
      cmocka_unit_test_teardown(test_follow_geometry, remove_seg),
      cmocka_unit_test_teardown(test_follow_generation, remove_seg),
      cmocka_unit_test_teardown(test_follow_concurrent, remove_seg),
  };
  return cmocka_run_group_tests(tests, NULL, NULL);
}
