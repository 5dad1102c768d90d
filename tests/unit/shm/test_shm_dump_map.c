/* vlff-shm dump-map (binary and PLY) and the Python snapshot example
 * (shm/examples/read_map.py) read a known map back exactly (issue 55: the
 * map could not be dumped, and reading it whole needed the C API). */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static char name[64], dir[] = "/tmp/vlff-dump-map-XXXXXX";
static uint16_t labels[64];
static uint8_t conf[64];
static struct vlff_map *w;

#define AT(i, j, k) ((i) + 4 * ((j) + 4 * (k)))

static int setup(void **state) {
  (void)state;
  if (!mkdtemp(dir)) return -1;
  test_name(name, sizeof name, "dump");
  struct vlff_map_params p = {.max_voxels = 64};
  w = vlff_map_create(name, &p);
  if (!w) return -1;
  for (int i = 0; i < 64; i++) labels[i] = i < 32 ? VLFF_LABEL_FREE : VLFF_LABEL_UNKNOWN, conf[i] = 10;
  labels[AT(1, 2, 3)] = 2, conf[AT(1, 2, 3)] = 201;
  labels[AT(0, 0, 0)] = 0, conf[AT(0, 0, 0)] = 99;
  labels[AT(3, 1, 0)] = 1, conf[AT(3, 1, 0)] = 150;
  const char *prompts[] = {"floor", "wall", "fire extinguisher"};
  struct vlff_map_grid g = {.origin = {-1, 0, 2}, .voxel_size = 0.5, .dims = {4, 4, 4}, .labels = labels,
                            .confidence = conf};
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = 3};
  return vlff_map_publish(w, &u);
}

static int teardown(void **state) {
  (void)state;
  vlff_map_detach(w);
  vlff_shm_unlink(name);
  char cmd[128];
  snprintf(cmd, sizeof cmd, "rm -rf '%s'", dir);
  return system(cmd) ? -1 : 0;
}

static int run(const char *cmd, char *out, size_t len) {
  FILE *f = popen(cmd, "r");
  assert_non_null(f);
  size_t n = fread(out, 1, len - 1, f);
  out[n] = 0;
  return pclose(f);
}

static uint8_t *slurp(const char *path, size_t *n) {
  FILE *f = fopen(path, "rb");
  assert_non_null(f);
  static uint8_t buf[1 << 16];
  *n = fread(buf, 1, sizeof buf, f);
  fclose(f);
  return buf;
}

static void binary_dump_is_the_grid(void **state) {
  (void)state;
  char cmd[1024], out[512], path[128];
  snprintf(path, sizeof path, "%s/map.bin", dir);
  snprintf(cmd, sizeof cmd, "%s dump-map %s %s", VLFF_SHM_CLI, name, path);
  assert_int_equal(run(cmd, out, sizeof out), 0);
  char want[256];
  snprintf(want, sizeof want, "version 1 voxels 64 labelled 3 free 30 unknown 31 -> %s\n", path);
  assert_string_equal(out, want);
  size_t n;
  const uint8_t *b = slurp(path, &n);
  size_t head = 8 + 8 + 8 + 24 + 8 + 12 + 4 + 3 * 64;
  assert_int_equal(n, head + 64 * 2 + 64);
  assert_memory_equal(b, "VLFFMAP1", 8);
  uint64_t version;
  double origin[3], vs;
  uint32_t dims[3], k;
  memcpy(&version, b + 8, 8);
  memcpy(origin, b + 24, 24);
  memcpy(&vs, b + 48, 8);
  memcpy(dims, b + 56, 12);
  memcpy(&k, b + 68, 4);
  assert_int_equal(version, 1);
  assert_true(origin[0] == -1 && origin[1] == 0 && origin[2] == 2 && vs == 0.5);
  assert_true(dims[0] == 4 && dims[1] == 4 && dims[2] == 4 && k == 3);
  assert_string_equal((const char *)b + 72 + 2 * 64, "fire extinguisher");
  assert_memory_equal(b + head, labels, sizeof labels);
  assert_memory_equal(b + head + sizeof labels, conf, sizeof conf);
}

static void ply_dump_holds_the_labelled_voxels(void **state) {
  (void)state;
  char cmd[1024], out[512], path[128];
  snprintf(path, sizeof path, "%s/map.ply", dir);
  snprintf(cmd, sizeof cmd, "%s dump-map %s %s", VLFF_SHM_CLI, name, path);
  assert_int_equal(run(cmd, out, sizeof out), 0);
  size_t n;
  const uint8_t *b = slurp(path, &n);
  const char *end = strstr((const char *)b, "end_header\n");
  assert_non_null(end);
  assert_non_null(strstr((const char *)b, "comment prompt 2 fire extinguisher\n"));
  assert_non_null(strstr((const char *)b, "element vertex 3\n"));
  const uint8_t *v = (const uint8_t *)end + strlen("end_header\n");
  assert_int_equal(n - (size_t)(v - b), 3 * 18);
  /* voxels in index order: (0,0,0) floor, (3,1,0) wall, (1,2,3) fire extinguisher */
  const float want[3][3] = {{-0.75f, 0.25f, 2.25f}, {0.75f, 0.75f, 2.25f}, {-0.25f, 1.25f, 3.75f}};
  const uint16_t wl[3] = {0, 1, 2};
  const uint8_t wc[3] = {99, 150, 201};
  for (int i = 0; i < 3; i++, v += 18) {
    float xyz[3];
    uint16_t lab;
    memcpy(xyz, v, 12);
    memcpy(&lab, v + 15, 2);
    assert_memory_equal(xyz, want[i], 12);
    assert_int_equal(lab, wl[i]);
    assert_int_equal(v[17], wc[i]);
  }
}

static void python_snapshot_example(void **state) {
  (void)state;
  char cmd[1024], out[1024], pts[128];
  snprintf(pts, sizeof pts, "%s/points.txt", dir);
  FILE *f = fopen(pts, "w");
  assert_non_null(f);
  fputs("-0.25 1.25 3.75\n-0.9 0.1 2.1\n0 0 3.9\n5 5 5\n", f);
  fclose(f);
  snprintf(cmd, sizeof cmd, "/usr/bin/python3 %s --lib %s --points %s %s", VLFF_PY_MAP_EXAMPLE, VLFF_SHM_SO, pts, name);
  assert_int_equal(run(cmd, out, sizeof out), 0);
  assert_string_equal(out, "version 1 origin -1.000 0.000 2.000 voxel_size 0.500 dims 4 4 4\n"
                           "prompt 0 floor voxels 1\nprompt 1 wall voxels 1\nprompt 2 fire extinguisher voxels 1\n"
                           "free 30 unknown 31\n"
                           "-0.25 1.25 3.75 2 fire extinguisher\n-0.9 0.1 2.1 0 floor\n0 0 3.9 65535 unknown\n"
                           "5 5 5 65535 unknown\n");
}

/* The far map (docs/shm.md "The far map") is dumped too: its labelled
 * voxels join the PLY's, and the binary file ends with its section. */
static void far_map_dumped(void **state) {
  (void)state;
  /* one block, key (1, 0, 0) on the grid's lattice: x 7..15 m; its first
   * voxel wall (conf 77), the rest unknown */
  const struct vlff_map_far_block blk = {{1, 0, 0}, 0};
  const struct vlff_map_far_run runs[2] = {{.label = 1, .count = 1, .conf = 77},
                                           {.label = VLFF_LABEL_UNKNOWN, .count = 4095}};
  const struct vlff_map_far far = {.origin = {-1, 0, 2}, .voxel_size = 0.5, .nblocks = 1, .nruns = 2,
                                   .blocks = &blk, .runs = runs};
  assert_int_equal(vlff_map_reserve_far(w, 64, vlff_map_far_bytes(1, 2)), 0);
  assert_int_equal(vlff_map_set_far(w, &far), 0);
  struct vlff_map_grid g = {.origin = {-1, 0, 2}, .voxel_size = 0.5, .dims = {4, 4, 4}, .labels = labels,
                            .confidence = conf};
  struct vlff_map_range none = {0, 0};
  struct vlff_map_update u = {.grid = &g, .ranges = &none, .range_count = 1};
  assert_int_equal(vlff_map_publish(w, &u), 0);
  char cmd[1024], out[512], path[128];
  snprintf(path, sizeof path, "%s/far.ply", dir);
  snprintf(cmd, sizeof cmd, "%s dump-map %s %s", VLFF_SHM_CLI, name, path);
  assert_int_equal(run(cmd, out, sizeof out), 0);
  assert_non_null(strstr(out, "labelled 3 free 30 unknown 31 far_blocks 1 far_labelled 1 -> "));
  size_t n;
  const uint8_t *b = slurp(path, &n);
  assert_non_null(strstr((const char *)b, "element vertex 4\n"));
  const float want[3] = {7.25f, 0.25f, 2.25f};
  const uint8_t *v = b + n - 18;
  uint16_t lab;
  memcpy(&lab, v + 15, 2);
  assert_memory_equal(v, want, 12);
  assert_int_equal(lab, 1);
  assert_int_equal(v[17], 77);
  snprintf(path, sizeof path, "%s/far.bin", dir);
  snprintf(cmd, sizeof cmd, "%s dump-map %s %s", VLFF_SHM_CLI, name, path);
  assert_int_equal(run(cmd, out, sizeof out), 0);
  b = slurp(path, &n);
  const size_t grid_end = 72 + 64 * 3 + 64 * 3, far_n = 8 + 24 + 8 + 8 + 16 + 12;
  assert_int_equal(n, grid_end + far_n);
  assert_memory_equal(b + grid_end, "VLFFFAR1", 8);
  uint32_t counts[2];
  memcpy(counts, b + grid_end + 40, 8);
  assert_int_equal(counts[0], 1);
  assert_int_equal(counts[1], 2);
  assert_memory_equal(b + grid_end + 48, &blk, 16);
  assert_memory_equal(b + grid_end + 64, runs, 12);
  /* a point in it, through the library's reader */
  snprintf(cmd, sizeof cmd, "%s label %s 7.3 0.3 2.3", VLFF_SHM_CLI, name);
  assert_int_equal(run(cmd, out, sizeof out), 0);
  assert_non_null(strstr(out, "label 1 confidence 77 prompt wall"));
}

static void missing_map_fails(void **state) {
  (void)state;
  char cmd[1024], out[512];
  snprintf(cmd, sizeof cmd, "%s dump-map /vlff-test-missing-%d %s/x.bin 2>&1", VLFF_SHM_CLI, (int)getpid(), dir);
  assert_int_not_equal(run(cmd, out, sizeof out), 0);
  assert_non_null(strstr(out, "no such segment"));
  snprintf(cmd, sizeof cmd, "%s/x.bin", dir);
  assert_int_not_equal(access(cmd, F_OK), 0);
}

VLFF_UNIT_MAIN(setup, teardown,
    cmocka_unit_test(binary_dump_is_the_grid), cmocka_unit_test(ply_dump_holds_the_labelled_voxels),
    cmocka_unit_test(python_snapshot_example), cmocka_unit_test(far_map_dumped),
    cmocka_unit_test(missing_map_fails))
