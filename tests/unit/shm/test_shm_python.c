/* The Python ctypes example reads a known label through libvlff-shm.so. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <stdlib.h>

static void python_example_reads_label(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "py");
  struct vlff_map_params p = {.max_voxels = 64};
  struct vlff_map *w = vlff_map_create(name, &p);
  assert_non_null(w);
  uint16_t labels[64];
  uint8_t conf[64];
  for (int i = 0; i < 64; i++) {
    labels[i] = VLFF_LABEL_FREE;
    conf[i] = 10;
  }
  labels[1 + 4 * (2 + 4 * 3)] = 2; /* voxel (1,2,3) */
  conf[1 + 4 * (2 + 4 * 3)] = 201;
  const char *prompts[] = {"floor", "wall", "fire extinguisher"};
  struct vlff_map_grid g = {.origin = {0, 0, 0}, .voxel_size = 0.5, .dims = {4, 4, 4}, .labels = labels,
                            .confidence = conf};
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = 3};
  assert_int_equal(vlff_map_publish(w, &u), 0);

  const char *cases[][2] = {
    {"0.75 1.25 1.75", "label 2 confidence 201 prompt fire extinguisher\n"},
    {"0.1 0.1 0.1", "label 65534 confidence 10 prompt -\n"},
    {"-3 0 0", "label 65535 confidence 0 prompt -\n"},
  };
  for (size_t i = 0; i < sizeof cases / sizeof cases[0]; i++) {
    char cmd[1024], out[256] = {0};
    snprintf(cmd, sizeof cmd, "/usr/bin/python3 %s --lib %s %s %s", VLFF_PY_EXAMPLE, VLFF_SHM_SO, name, cases[i][0]);
    FILE *f = popen(cmd, "r");
    assert_non_null(f);
    size_t n = fread(out, 1, sizeof out - 1, f);
    out[n] = 0;
    assert_int_equal(pclose(f), 0);
    assert_string_equal(out, cases[i][1]);
  }
  /* A missing segment: non-zero exit, library message. */
  char cmd[1024];
  snprintf(cmd, sizeof cmd, "/usr/bin/python3 %s --lib %s /vlff-test-missing-%d 0 0 0 2>&1", VLFF_PY_EXAMPLE,
           VLFF_SHM_SO, (int)getpid());
  FILE *f = popen(cmd, "r");
  char out[256] = {0};
  size_t n = fread(out, 1, sizeof out - 1, f);
  out[n] = 0;
  assert_int_not_equal(pclose(f), 0);
  assert_non_null(strstr(out, "no such segment"));
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(python_example_reads_label))
