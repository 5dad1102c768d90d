/* field.scene_box_file: a scene's bbox.txt sets the field's box (issue 55:
 * a node fed by vlff-replay never saw the scene's box and clipped the map
 * to the default +-2.5 m). */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include <unistd.h>

#include "config.h"
#include "scene_box.h"
#include "unit.h"

static char dir[] = "/tmp/vlff-scene-box-XXXXXX";
static char err[512];

static void put(const char *name, const char *text, char *path, size_t len) {
  snprintf(path, len, "%s/%s", dir, name);
  FILE *f = fopen(path, "w");
  assert_non_null(f);
  fputs(text, f);
  fclose(f);
}

static int load_with(const char *box_path, struct vlff_config *cfg) {
  char yaml[1024];
  snprintf(yaml, sizeof yaml, "field:\n  scene_box_file: %s\n", box_path);
  err[0] = 0;
  return vlff_config_load_mem(yaml, strlen(yaml), "t.yaml", cfg, err, sizeof err);
}

/* The scene's box replaces the default, and the field's hash follows the
 * box (a checkpoint of another box is not resumed), not the file's name. */
static void test_box_from_file(void **state) {
  (void)state;
  char p[512], q[512];
  put("bbox.txt", "-0.5 -1.25 -0.1\n8.4 11.5 3.2\n", p, sizeof p);
  /* commas separate as white space does, as vlff-eval's scene reader takes bbox.txt */
  put("same.txt", "-0.5, -1.25, -0.1,\n8.4,11.5,3.2\n", q, sizeof q);
  struct vlff_config cfg, other, def;
  vlff_config_defaults(&def);
  assert_int_equal(load_with(p, &cfg), 0);
  assert_true(cfg.field.scene_min[0] == -0.5 && cfg.field.scene_min[1] == -1.25 && cfg.field.scene_min[2] == -0.1);
  assert_true(cfg.field.scene_max[0] == 8.4 && cfg.field.scene_max[1] == 11.5 && cfg.field.scene_max[2] == 3.2);
  assert_int_equal(load_with(q, &other), 0);
  assert_true(vlff_config_field_hash(&cfg.field) == vlff_config_field_hash(&other.field));
  assert_true(vlff_config_field_hash(&cfg.field) != vlff_config_field_hash(&def.field));
  assert_true(other.field.scene_min[1] == -1.25 && other.field.scene_max[2] == 3.2);
}

/* The file's box replaces field.scene_min/max set in the same config,
 * before or after the file's key. */
static void test_file_wins_over_keys(void **state) {
  (void)state;
  char p[512], yaml[1200];
  put("bbox.txt", "-5 -4 -1.5 5 4 1.5\n", p, sizeof p);
  const char *fmt[] = {"field:\n  scene_min: [-1, -1, -1]\n  scene_max: [1, 1, 1]\n  scene_box_file: %s\n",
                       "field:\n  scene_box_file: %s\n  scene_min: [-1, -1, -1]\n  scene_max: [1, 1, 1]\n"};
  for (int i = 0; i < 2; i++) {
    struct vlff_config cfg;
    snprintf(yaml, sizeof yaml, fmt[i], p);
    assert_int_equal(vlff_config_load_mem(yaml, strlen(yaml), "t.yaml", &cfg, err, sizeof err), 0);
    assert_true(cfg.field.scene_min[0] == -5 && cfg.field.scene_min[1] == -4 && cfg.field.scene_min[2] == -1.5);
    assert_true(cfg.field.scene_max[0] == 5 && cfg.field.scene_max[1] == 4 && cfg.field.scene_max[2] == 1.5);
  }
}

/* A bad box file is refused at load, naming the key and the file. */
static void test_bad_box_files(void **state) {
  (void)state;
  static const struct {
    const char *text, *fragment;
  } bad[] = {
      {"0 0 0 1 1", "expected 6 numbers"},
      {"0 0 0 1 1 1 7", "nothing after them"},
      {"0 0 0 1 nan 1", "not a finite coordinate"},
      {"0 0 0 1 1e9 1", "not a finite coordinate"},
      {"0 2 0 1 1 1", "axis 1 has min 2 >= max 1"},
      {"zero 0 0 1 1 1", "expected 6 numbers"},
  };
  char p[512];
  struct vlff_config cfg;
  for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) {
    put("bad.txt", bad[i].text, p, sizeof p);
    assert_int_equal(load_with(p, &cfg), -1);
    if (!strstr(err, "key 'field.scene_box_file'") || !strstr(err, p) || !strstr(err, bad[i].fragment))
      fail_msg("'%s': message '%s' lacks the key, the file or '%s'", bad[i].text, err, bad[i].fragment);
  }
  snprintf(p, sizeof p, "%s/missing.txt", dir);
  assert_int_equal(load_with(p, &cfg), -1);
  assert_non_null(strstr(err, "missing.txt"));
  /* a directory is not a box file */
  assert_int_equal(load_with(dir, &cfg), -1);
}

int main(void) {
  if (!mkdtemp(dir)) return 1;
  const struct CMUnitTest tests[] = {cmocka_unit_test(test_box_from_file), cmocka_unit_test(test_file_wins_over_keys),
                                     cmocka_unit_test(test_bad_box_files)};
  int rc = cmocka_run_group_tests(tests, NULL, NULL);
  char cmd[600];
  snprintf(cmd, sizeof cmd, "rm -rf '%s'", dir);
  if (system(cmd)) rc = rc ? rc : 1;
  return rc;
}
