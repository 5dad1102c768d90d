/* The far map (far.h): what the map's window leaves when it slides is kept
 * as run-length blocks on the lattice, comes back voxel for voxel when the
 * window returns, exports as the segment's contract wants it (vlff/shm.h:
 * vlff_map_set_far takes it), and stays within its byte budget by dropping
 * the blocks farthest from the robot, counted. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>
#include <unistd.h>
#include <cmocka.h>
#include <stdbool.h>

#include "far.h"
#include "unit.h"
#include "vlff/shm.h"

enum { N = 20, NV = N * N * N };
static uint16_t lab[NV], got_lab[NV];
static uint8_t conf[NV], got_conf[NV];

/* A room in the window: the floor (z = 2) labelled by x % 3, FREE above it
 * up to z = 6, the rest never seen. */
static void room(void) {
  for (int i = 0; i < NV; i++) {
    const int x = i % N, z = i / (N * N);
    lab[i] = z == 2 ? (uint16_t)(x % 3) : z > 2 && z < 7 ? VLFF_LABEL_FREE : VLFF_LABEL_UNKNOWN;
    conf[i] = z == 2 ? (uint8_t)(100 + x) : 255;
  }
}

static void collect(void *ctx, size_t i, uint16_t label, uint8_t c) {
  (void)ctx;
  assert_true(i < NV);
  assert_int_not_equal(label, VLFF_LABEL_UNKNOWN);
  got_lab[i] = label, got_conf[i] = c;
}

static void test_store_restore(void **state) {
  (void)state;
  room();
  const double origin[3] = {-1, 2, 0};
  struct vlff_far *f = vlff_far_create(origin, 0.1, 1 << 20);
  assert_non_null(f);
  /* the window at lattice voxel (-5, 3, 0) moves 20 voxels along +x: all of it leaves */
  const uint32_t dims[3] = {N, N, N};
  const long k0[3] = {-5, 3, 0};
  const int32_t away[3] = {-N, 0, 0};
  assert_int_equal(vlff_far_store(f, dims, k0, away, dims, lab, conf), 0);
  /* x -5..14 and y 3..22 cross two blocks each; z 2..6 (what holds something) one */
  assert_int_equal(vlff_far_blocks(f), 4);
  struct vlff_map_far out;
  assert_int_equal(vlff_far_export(f, &out), 0);
  assert_int_equal(out.nblocks, 4);
  assert_true(out.voxel_size == 0.1 && out.origin[0] == -1 && out.origin[1] == 2);
  assert_int_equal(vlff_map_far_bytes(out.nblocks, out.nruns), vlff_far_bytes(f));
  /* sorted z, y, x: keys (-1,0,0) (0,0,0) (-1,1,0) (0,1,0) */
  const int32_t keys[4][3] = {{-1, 0, 0}, {0, 0, 0}, {-1, 1, 0}, {0, 1, 0}};
  for (int b = 0; b < 4; b++) assert_memory_equal(out.blocks[b].key, keys[b], sizeof keys[b]);
  /* every block's runs cover its 4096 voxels */
  for (uint32_t b = 0; b < out.nblocks; b++) {
    const uint32_t end = b + 1 < out.nblocks ? out.blocks[b + 1].first_run : out.nruns;
    unsigned sum = 0;
    for (uint32_t r = out.blocks[b].first_run; r < end; r++) sum += out.runs[r].count;
    assert_int_equal(sum, 4096);
  }
  /* the window comes back (the old one 20 voxels further along +x in it):
   * every voxel that held something returns as it was, none else */
  for (int i = 0; i < NV; i++) got_lab[i] = VLFF_LABEL_UNKNOWN, got_conf[i] = 0;
  const int32_t back[3] = {N, 0, 0};
  vlff_far_restore(f, dims, back, dims, k0, collect, NULL);
  assert_memory_equal(got_lab, lab, sizeof lab);
  for (int i = 0; i < NV; i++)
    if (lab[i] != VLFF_LABEL_UNKNOWN) assert_int_equal(got_conf[i], conf[i]);
  /* a window that overlaps the old one gets only what the old did not hold */
  for (int i = 0; i < NV; i++) got_lab[i] = VLFF_LABEL_UNKNOWN;
  const int32_t half[3] = {N / 2, 0, 0};
  vlff_far_restore(f, dims, half, dims, k0, collect, NULL);
  for (int i = 0; i < NV; i++)
    assert_int_equal(got_lab[i], i % N < N / 2 ? lab[i] : VLFF_LABEL_UNKNOWN);
  /* a second departure rewrites what it leaves in the blocks it touches:
   * the floor relabelled, the window leaving along -y this time */
  for (int i = 0; i < NV; i++)
    if (lab[i] <= VLFF_LABEL_MAX) lab[i] = 7;
  const int32_t down[3] = {0, N, 0};
  assert_int_equal(vlff_far_store(f, dims, k0, down, dims, lab, conf), 0);
  for (int i = 0; i < NV; i++) got_lab[i] = VLFF_LABEL_UNKNOWN;
  const int32_t up[3] = {0, -N, 0};
  vlff_far_restore(f, dims, up, dims, k0, collect, NULL);
  assert_memory_equal(got_lab, lab, sizeof lab);
  /* the labels are texts: the first prompt list says which; a new list
   * renames each to its text's index there, UNKNOWN where it is gone */
  const char *abc[3] = {"floor", "wall", "door"}, *cba[2] = {"door", "floor"};
  uint64_t gen = vlff_far_generation(f);
  assert_int_equal(vlff_far_prompts(f, abc, 3), 0);
  assert_true(vlff_far_generation(f) != gen); /* the texts a checkpoint holds: written again */
  gen = vlff_far_generation(f);
  assert_int_equal(vlff_far_prompts(f, abc, 3), 0);
  assert_int_equal(vlff_far_generation(f), gen); /* the same list: no rewrite owed */
  assert_int_equal(vlff_far_prompts(f, cba, 2), 1);
  assert_true(vlff_far_generation(f) != gen);
  for (int i = 0; i < NV; i++) got_lab[i] = VLFF_LABEL_UNKNOWN;
  vlff_far_restore(f, dims, up, dims, k0, collect, NULL);
  for (int i = 0; i < NV; i++)
    if (lab[i] == 7) assert_int_equal(got_lab[i], VLFF_LABEL_UNKNOWN); /* label 7: no text in the first list */
  /* the floor again, labelled by the first list's indices */
  for (int i = 0; i < NV; i++)
    if (lab[i] <= VLFF_LABEL_MAX) lab[i] = (uint16_t)(i % N % 3);
  assert_int_equal(vlff_far_prompts(f, abc, 3), 0); /* nothing labelled to rename: the list only */
  assert_int_equal(vlff_far_store(f, dims, k0, down, dims, lab, conf), 0);
  assert_int_equal(vlff_far_prompts(f, cba, 2), 1);
  for (int i = 0; i < NV; i++) got_lab[i] = VLFF_LABEL_UNKNOWN;
  vlff_far_restore(f, dims, up, dims, k0, collect, NULL);
  const uint16_t renamed[3] = {1, VLFF_LABEL_UNKNOWN, 0}; /* floor -> 1, wall gone, door -> 0 */
  for (int i = 0; i < NV; i++)
    if (lab[i] <= VLFF_LABEL_MAX) assert_int_equal(got_lab[i], renamed[lab[i]]);
  /* a checkpoint: saved, read back into a far map of the same lattice */
  char path[64];
  snprintf(path, sizeof path, "/tmp/vlff-test-far-%d.far", (int)getpid());
  char err[512];
  gen = vlff_far_generation(f);
  assert_int_equal(vlff_far_save(f, path, err, sizeof err), 0);
  assert_int_equal(vlff_far_generation(f), gen);
  struct vlff_far *g = vlff_far_create(origin, 0.1, 1 << 20);
  gen = vlff_far_generation(g);
  assert_int_equal(vlff_far_load(g, path, err, sizeof err), 0);
  assert_true(vlff_far_generation(g) != gen);
  struct vlff_map_far a, b;
  assert_int_equal(vlff_far_export(f, &a), 0);
  assert_int_equal(vlff_far_export(g, &b), 0);
  assert_int_equal(a.nblocks, b.nblocks);
  assert_int_equal(a.nruns, b.nruns);
  assert_memory_equal(a.blocks, b.blocks, a.nblocks * sizeof *a.blocks);
  assert_memory_equal(a.runs, b.runs, a.nruns * sizeof *a.runs);
  vlff_far_destroy(g);
  /* another lattice's, a flipped byte, a cut file: refused, the far map untouched */
  const double moved[3] = {-1, 2, 0.05};
  g = vlff_far_create(moved, 0.1, 1 << 20);
  assert_int_equal(vlff_far_load(g, path, err, sizeof err), -1);
  assert_non_null(strstr(err, "another map's lattice"));
  vlff_far_destroy(g);
  g = vlff_far_create(origin, 0.1, 1 << 20);
  FILE *fp = fopen(path, "r+b");
  assert_non_null(fp);
  fseek(fp, 60, SEEK_SET);
  int c = fgetc(fp);
  fseek(fp, 60, SEEK_SET);
  fputc(c ^ 1, fp);
  fclose(fp);
  assert_int_equal(vlff_far_load(g, path, err, sizeof err), -1);
  assert_non_null(strstr(err, "checksum"));
  assert_int_equal(truncate(path, 100), 0);
  assert_int_equal(vlff_far_load(g, path, err, sizeof err), -1);
  assert_non_null(strstr(err, "truncated"));
  assert_int_equal(vlff_far_blocks(g), 0);
  /* none: no file, and saving none removes it */
  vlff_far_reset(f);
  assert_int_equal(vlff_far_save(f, path, err, sizeof err), 0);
  assert_int_equal(access(path, F_OK), -1);
  assert_int_equal(vlff_far_load(g, path, err, sizeof err), 1);
  vlff_far_destroy(g);
  assert_int_equal(vlff_far_blocks(f), 0);
  assert_int_equal(vlff_far_bytes(f), 0);
  vlff_far_destroy(f);
}

/* The budget: the blocks farthest from the new window go first, counted;
 * what stays restores as it was. */
static void test_budget(void **state) {
  (void)state;
  room();
  const double origin[3] = {0, 0, 0};
  const uint32_t dims[3] = {N, N, N};
  const long k0[3] = {0, 0, 0};
  const int32_t away[3] = {-100, 0, 0}; /* the window moves 100 voxels along +x */
  /* each block's bytes, from a far map without a budget */
  struct vlff_far *all = vlff_far_create(origin, 0.1, SIZE_MAX);
  assert_int_equal(vlff_far_store(all, dims, k0, away, dims, lab, conf), 0);
  struct vlff_map_far out;
  assert_int_equal(vlff_far_export(all, &out), 0);
  assert_int_equal(out.nblocks, 4);
  size_t near = 0; /* the blocks of x 16..31: nearer the window at x = 100 */
  for (uint32_t b = 0; b < out.nblocks; b++) {
    const uint32_t end = b + 1 < out.nblocks ? out.blocks[b + 1].first_run : out.nruns;
    if (out.blocks[b].key[0] == 1) near += vlff_map_far_bytes(1, end - out.blocks[b].first_run);
  }
  vlff_far_destroy(all);
  struct vlff_far *f = vlff_far_create(origin, 0.1, near);
  assert_int_equal(vlff_far_store(f, dims, k0, away, dims, lab, conf), 0);
  assert_int_equal(vlff_far_dropped(f), 0); /* stored whole: only a trim drops */
  const long at[3] = {100, 0, 0};        /* the new window */
  vlff_far_trim(f, at, dims);
  assert_int_equal(vlff_far_bytes(f), near);
  assert_int_equal(vlff_far_dropped(f), 2);
  assert_int_equal(vlff_far_export(f, &out), 0);
  assert_int_equal(out.nblocks, 2);
  for (uint32_t b = 0; b < out.nblocks; b++) assert_int_equal(out.blocks[b].key[0], 1);
  for (int i = 0; i < NV; i++) got_lab[i] = VLFF_LABEL_UNKNOWN;
  const int32_t back[3] = {100, 0, 0};
  vlff_far_restore(f, dims, back, dims, k0, collect, NULL);
  for (int i = 0; i < NV; i++)
    assert_int_equal(got_lab[i], i % N >= 16 ? lab[i] : VLFF_LABEL_UNKNOWN); /* dropped: unknown */
  vlff_far_destroy(f);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_store_restore), cmocka_unit_test(test_budget))
