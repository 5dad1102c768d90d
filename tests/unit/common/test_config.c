/* Config parser: good files, every error path, and default.yaml's promise. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include <dirent.h>
#include <fcntl.h>
#include <signal.h>
#include <sys/stat.h>
#include <sys/types.h>
#include <sys/wait.h>
#include <unistd.h>

#include "config.h"
#include "files.h"
#include "unit.h"
#include "vlff/shm.h"

static char err[512];

static int load(const char *yaml, struct vlff_config *cfg) {
  err[0] = 0;
  return vlff_config_load_mem(yaml, strlen(yaml), "t.yaml", cfg, err, sizeof err);
}

/* Expect rejection with a message that starts "t.yaml:LINE:COL: key 'KEY': "
 * and contains every fragment given. */
static void expect_error(const char *yaml, const char *prefix, const char *fragment) {
  struct vlff_config cfg;
  assert_int_equal(load(yaml, &cfg), -1);
  if (strncmp(err, prefix, strlen(prefix)) != 0 || !strstr(err, fragment)) {
    fail_msg("error message\n  %s\nlacks prefix '%s' or fragment '%s'", err, prefix, fragment);
  }
  /* A rejected file leaves the defaults in place. */
  struct vlff_config def;
  vlff_config_defaults(&def);
  assert_memory_equal(&cfg, &def, sizeof cfg);
}

/* Every rejected configuration: the file, the start of its message
 * ("t.yaml:LINE:COL: key 'KEY': ") and a fragment the message holds. */
static const struct {
  const char *yaml, *prefix, *fragment;
} bad[] = {
  /* A typo is answered with the key it is nearest (two edits at most). */
  {"node:\n  stat_dir: x\n", "t.yaml:2:3: key 'node.stat_dir': ", "unknown key (did you mean 'node.state_dir'?)"},
  {"nod:\n  name: x\n", "t.yaml:1:1: key 'nod': ", "unknown key (did you mean 'node'?)"},
  /* Keys that did nothing are gone: the node has no instance name, a scene
   * directory is vlff-replay's, and vlff-camd drives no simulated camera. */
  {"node:\n  name: x\n", "t.yaml:2:3: key 'node.name': ", "unknown key"},
  {"source:\n  dataset: /d\n", "t.yaml:2:3: key 'source.dataset': ", "unknown key"},
  {"source:\n  kind: dataset\n", "t.yaml:2:9: key 'source.kind': ", "expected one of sim|ring, got 'dataset'"},
  {"camera:\n  kind: sim\n", "t.yaml:2:9: key 'camera.kind': ", "expected one of aravis|libcamera, got 'sim'"},
  {"sim:\n  rate_hzz: 5\n", "t.yaml:2:3: key 'sim.rate_hzz': ", "unknown key (did you mean 'sim.rate_hz'?)"},
  /* One name for the feature dimension: the simulator's old key says where it went. */
  {"sim:\n  feature_dim: 16\n", "t.yaml:2:3: key 'sim.feature_dim': ", "field.feature_dim"},
  {"field:\n  feature_dim: abc\n", "t.yaml:2:16: key 'field.feature_dim': ", "expected integer in [8, 1024], got 'abc'"},
  {"field:\n  feature_dim: 2000\n", "t.yaml:2:16: key 'field.feature_dim': ", "got '2000'"},
  {"field:\n  feature_dim: 1.5\n", "t.yaml:2:16: key 'field.feature_dim': ", "expected integer"},
  {"train:\n  lr: fast\n", "t.yaml:2:7: key 'train.lr': ", "expected number in [0, 10], got 'fast'"},
  {"train:\n  lr: nan\n", "t.yaml:2:7: key 'train.lr': ", "expected number"},
  {"train:\n  lr: -1\n", "t.yaml:2:7: key 'train.lr': ", "got '-1'"},
  {"can:\n  enabled: maybe\n", "t.yaml:2:12: key 'can.enabled': ", "expected true or false, got 'maybe'"},
  {"train:\n  sampling: random\n", "t.yaml:2:13: key 'train.sampling': ", "expected one of depth|uniform, got 'random'"},
  {"sim:\n  layout: house\n", "t.yaml:2:11: key 'sim.layout': ", "expected one of room|flat|building, got 'house'"},
  {"sim:\n  object_bias: 2\n", "t.yaml:2:16: key 'sim.object_bias': ", "got '2'"},
  {"sim:\n  changes: 5\n", "t.yaml:2:12: key 'sim.changes': ", "expected a sequence of 0 to 16 changes {time_s, object, action, to}, got '5'"},
  /* the three structured lists share their walk: count, shape, unknown and repeated keys */
  {"sim:\n  changes: [{time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}, {time_s: 1, object: a, action: add}]\n",
   "t.yaml:2:12: key 'sim.changes': ", "changes {time_s, object, action, to}, got 17"},
  {"sim:\n  changes:\n    - [1, a, add]\n", "t.yaml:3:7: key 'sim.changes[0]': ", "expected mapping {time_s, object, action, to}, got a sequence"},
  {"sim:\n  changes:\n    - {time_s: 1, object: a, time_s: 2, action: add}\n", "t.yaml:3:30: key 'sim.changes[0].time_s': ",
   "duplicate key (first at line 3)"},
  {"sim:\n  changes:\n    - {time_s: 1, object: a, action: add, at: [1, 2]}\n", "t.yaml:3:43: key 'sim.changes[0].at': ",
   "unknown key (expected time_s, object, action or to)"},
  {"dds:\n  merge:\n    robots:\n      - {namespace: /r1, transform: [0, 0, 0, 0], transform: [1, 0, 0, 0]}\n",
   "t.yaml:4:51: key 'dds.merge.robots[0].transform': ", "duplicate key (first at line 4)"},
  {"sim:\n  changes:\n    - {time_s: -1, object: chair, action: remove}\n", "t.yaml:3:16: key 'sim.changes[0].time_s': ",
   "expected number in [0, 604800] (seconds of sim time), got '-1'"},
  {"sim:\n  changes:\n    - {time_s: 1, object: chair, action: jump}\n", "t.yaml:3:42: key 'sim.changes[0].action': ",
   "expected one of move|remove|add, got 'jump'"},
  {"sim:\n  changes:\n    - {time_s: 1, object: chair, action: move}\n", "t.yaml:3:7: key 'sim.changes[0]': ",
   "expected a 'to' for action move, got none"},
  {"sim:\n  changes:\n    - {time_s: 1, object: chair, action: move, to: [1, 1e9]}\n",
   "t.yaml:3:56: key 'sim.changes[0].to': ", "expected [x, y] with each in [-10000, 10000] m, got '1e9' at index 1"},
  {"sim:\n  changes:\n    - {time_s: 1, object: chair, action: remove, to: [1, 1]}\n", "t.yaml:3:7: key 'sim.changes[0]': ",
   "expected no 'to' for action remove"},
  {"publish:\n  label_hysteresis: 2.5\n", "t.yaml:2:21: key 'publish.label_hysteresis': ", "expected number in [0, 2], got '2.5'"},
  {"sim:\n  flats: 9\n", "t.yaml:2:10: key 'sim.flats': ", "expected integer in [2, 8], got '9'"},
  {"node:\n  state_dir: [a, b]\n", "t.yaml:2:14: key 'node.state_dir': ", "expected string, got a sequence"},
  {"can:\n  interface: aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa\n", "t.yaml:2:14: key 'can.interface': ", "at most 31 bytes"},
  {"field:\n  scene_min: [1, 2]\n", "t.yaml:2:14: key 'field.scene_min': ", "expected sequence of 3 numbers, got a sequence"},
  {"field:\n  scene_min: [1, x, 2]\n", "t.yaml:2:18: key 'field.scene_min': ", "at index 1, got 'x'"},
  {"field: 3\n", "t.yaml:1:8: key 'field': ", "expected a mapping, got '3'"},
  {"- a\n- b\n", "t.yaml:1:1: ", "expected a mapping at top level, got a sequence"},
  {"node:\n  state_dir: a\n  state_dir: b\n", "t.yaml:3:3: key 'node.state_dir': ", "duplicate key (first at line 2)"},
  {"node:\n  state_dir: [a\n", "t.yaml:", "YAML syntax error"},
  {"node:\n  state_dir: a\n---\nnode:\n  state_dir: b\n", "t.yaml:", "expected one YAML document"},
  {"prompts:\n  sets: x\n", "t.yaml:2:9: key 'prompts.sets': ", "expected a sequence of 1 to 8 prompt sets {name, prompts}, got 'x'"},
  {"prompts:\n  sets: []\n", "t.yaml:2:9: key 'prompts.sets': ", "expected a sequence of 1 to 8 prompt sets {name, prompts}, got 0"},
  {"prompts:\n  sets:\n    - name: a\n", "t.yaml:3:7: key 'prompts.sets[0]': ", "expected a 'prompts' list"},
  {"prompts:\n  sets:\n    - name: a\n      promts: [x]\n", "t.yaml:4:7: key 'prompts.sets[0].promts': ", "unknown key"},
  {"prompts:\n  sets:\n    - prompts: [x, \"\"]\n", "t.yaml:3:20: key 'prompts.sets[0].prompts': ", "at index 1, got ''"},
  {"prompts:\n  sets:\n    - prompts: []\n", "t.yaml:3:16: key 'prompts.sets[0].prompts': ", "expected sequence of 1 to 32 prompts"},
  {"prompts:\n  sets:\n    - 5\n", "t.yaml:3:7: key 'prompts.sets[0]': ", "expected mapping"},
  /* Cross-key checks name the key; they have no single source position. */
  {"field:\n  scene_min: [0, 0, 0]\n  scene_max: [1, 0, 1]\n", "t.yaml:3:14: key 'field.scene_max': ", "axis 1"},
  {"prompts:\n  active: 1\n", "t.yaml:2:11: key 'prompts.active': ", "below 1"},
  {"shm:\n  mode: 0666\n", "t.yaml:2:9: key 'shm.mode': ", "world-writable"},
  {"field:\n  base_resolution: 64\n  finest_resolution: 32\n", "t.yaml:3:22: key 'field.finest_resolution': ", ">= field.base_resolution"},
  {"field:\n  base_resolution: 4096\n", "t.yaml: key 'field.finest_resolution': ", "got 2048"},
  /* what start-up refused without a line, and a node that would never train */
  {"publish:\n  label_width: 8192\n", "t.yaml:2:16: key 'publish.label_width': ",
   "within the map segment's shm.label_max_width x label_max_height (640x480), got 8192x120"},
  {"shm:\n  label_max_height: 100\n", "t.yaml: key 'publish.label_height': ", "(640x100), got 160x120"},
  {"keyframes:\n  start_after: 400\n", "t.yaml:2:16: key 'keyframes.start_after': ",
   "at most keyframes.max_keyframes (325), the most the store holds: training would never start, got 400"},
  {"node:\n  cpu_budget: 0.05\n", "t.yaml:2:15: key 'node.cpu_budget': ", "expected 0 (no limit) or 0.1 to 256 cores, got 0.05"},
  {"node:\n  cpu_budget: 300\n", "t.yaml:2:15: key 'node.cpu_budget': ", "expected number in [0, 256], got '300'"},
  {"node:\n  cpu_budget: -1\n", "t.yaml:2:15: key 'node.cpu_budget': ", "got '-1'"},
  {"node:\n  cpu_budget: inf\n", "t.yaml:2:15: key 'node.cpu_budget': ", "expected number"},
  {"prompts:\n  template: a photo\n", "t.yaml:2:13: key 'prompts.template': ", "containing {}"},
  /* The simulator's features with a camera's frames: refused unless forced. */
  {"source:\n  kind: ring\n  features: sim\n", "t.yaml:3:13: key 'source.features': ", "source.allow_sim_features: true"},
  {"source:\n  features: sim\n", "t.yaml:2:13: key 'source.features': ", "never a camera's"},
  /* What the file says is quoted in messages without control bytes, and a
   * NUL inside a string is refused rather than cutting it short. */
  {"node:\n  state_dir: \"a\\0b\"\n", "t.yaml:2:14: key 'node.state_dir': ", "expected a string without NUL bytes, got 'a\\x00b'"},
  {"prompts:\n  sets:\n    - name: \"x\\0y\"\n      prompts: [a]\n", "t.yaml:3:13: key 'prompts.sets[0].name': ", "got 'x\\x00y'"},
  {"prompts:\n  sets:\n    - prompts: [\"a\\0b\"]\n", "t.yaml:3:17: key 'prompts.sets[0].prompts': ", "at index 0, got 'a\\x00b'"},
  /* Control characters in any string value (issue 29): a quoted scalar's
   * escapes make them. */
  {"node:\n  state_dir: \"/var/lib/a\\nb\"\n", "t.yaml:2:14: key 'node.state_dir': ", "without control characters, got '/var/lib/a\\x0ab'"},
  {"vlm:\n  text_model: \"m\\e]0;x\\a.onnx\"\n", "t.yaml:2:15: key 'vlm.text_model': ", "got 'm\\x1b]0;x\\x07.onnx'"},
  {"prompts:\n  template: \"a photo of a {}\\x7f\"\n", "t.yaml:2:13: key 'prompts.template': ", "without control characters"},
  {"prompts:\n  sets:\n    - name: \"a\\tb\"\n      prompts: [a]\n", "t.yaml:3:13: key 'prompts.sets[0].name': ", "without control characters, got 'a\\x09b'"},
  /* Prompt sets are checked as the mailbox and the embeddings format check
   * theirs (vlff_prompt_check), naming the prompt that breaks the rule. */
  {"prompts:\n  sets:\n    - prompts: [wall, \"door\\nlabel 0 prompt FAKE\"]\n", "t.yaml:3:23: key 'prompts.sets[0].prompts': ",
   "(prompts refused: prompt 2 is not UTF-8 text without control characters (tabs and newlines included)) at index 1, got 'door\\x0alabel 0 prompt FAKE'"},
  {"prompts:\n  sets:\n    - prompts: [\"a\\tb\"]\n", "t.yaml:3:17: key 'prompts.sets[0].prompts': ", "not UTF-8 text without control characters"},
  {"prompts:\n  sets:\n    - prompts: [\"c1 \\x85\"]\n", "t.yaml:3:17: key 'prompts.sets[0].prompts': ", "at index 0, got 'c1 \\xc2\\x85'"},
  {"prompts:\n  sets:\n    - prompts: [chair, table, chair]\n", "t.yaml:3:31: key 'prompts.sets[0].prompts': ",
   "(prompts refused: prompt 3 repeats prompt 1 ('chair')) at index 2, got 'chair'"},
  {"prompts:\n  sets:\n    - prompts: [a]\n    - prompts: [x, 0123456789012345678901234567890123456789012345678901234567890123]\n",
   "t.yaml:4:20: key 'prompts.sets[1].prompts': ", "prompt 2 is empty or longer than 63 bytes) at index 1"},
  {"node:\n  log_level: \"\\e[31mred\\e[0m\"\n", "t.yaml:2:14: key 'node.log_level': ", "got '\\x1b[31mred\\x1b[0m'"},
  {"node:\n  \"\\e[2J\": 1\n", "t.yaml:2:3: key 'node.\\x1b[2J': ", "unknown key"},
  /* valid UTF-8 is quoted as is (vlff/escape.h): names in other scripts are legitimate */
  {"node:\n  log_level: \"caf\\u00e9\"\n", "t.yaml:2:14: key 'node.log_level': ", "got 'caf\xc3\xa9'"},
  {"node:\n  log_level: \"it's \\\\x1b\"\n", "t.yaml:2:14: key 'node.log_level': ", "got 'it\\'s \\\\x1b'"},
  /* Segment names: valid POSIX names, distinct, refused with file:line. */
  {"shm:\n  ring: no-slash\n", "t.yaml:2:9: key 'shm.ring': ", "starting with '/'"},
  {"shm:\n  map: /a/b\n", "t.yaml:2:8: key 'shm.map': ", "no '/' after the leading one"},
  {"shm:\n  prompts: /\n", "t.yaml:2:12: key 'shm.prompts': ", "1 to 248 characters"},
  {"shm:\n  pose_ring: /..\n", "t.yaml:2:14: key 'shm.pose_ring': ", "other than '.' or '..'"},
  {"shm:\n  feature_ring: \"/a\\tb\"\n", "t.yaml:2:17: key 'shm.feature_ring': ", "without control characters, got '/a\\x09b'"},
  /* The same name twice: the mailbox would replace the map. */
  {"shm:\n  map: /x\n  prompts: /x\n", "t.yaml:3:12: key 'shm.prompts': ", "distinct from shm.map, got the same '/x'"},
  /* A name equal to another key's default is blamed where the file set it. */
  {"shm:\n  feature_ring: /vlff-frames\n", "t.yaml:2:17: key 'shm.feature_ring': ", "distinct from shm.ring"},
  {"shm:\n  ring: /vlff-map\n", "t.yaml: key 'shm.map': ", "distinct from shm.ring"},
};

static void test_defaults_valid(void **state) {
  (void)state;
  struct vlff_config cfg;
  assert_int_equal(load("", &cfg), 0);
  assert_int_equal(cfg.field.feature_dim, 512);
  assert_int_equal(cfg.field.hash_levels, 16);
  assert_int_equal(cfg.field.hash_log2_size, 19);
  assert_true(cfg.train.depth_weight == 0.1);
  assert_true(cfg.train.feature_weight == 0.5);
  assert_int_equal(cfg.prompts.set_count, 1);
  assert_int_equal(cfg.prompts.sets[0].count, 20);
  assert_string_equal(cfg.prompts.sets[0].text[15], "shower curtain");
  /* The default set passes the rule a configured one must pass. */
  const char *texts[VLFF_MAX_PROMPTS];
  for (int i = 0; i < cfg.prompts.sets[0].count; i++) texts[i] = cfg.prompts.sets[0].text[i];
  assert_int_equal(vlff_prompt_check(texts, cfg.prompts.sets[0].count), 0);
  assert_int_equal(cfg.shm.mode, 0640);
  assert_int_equal(cfg.sim.layout, VLFF_LAYOUT_ROOM);
  assert_true(cfg.sim.object_bias == 0);
  assert_true(cfg.node.cpu_budget == 0); /* no limit */
}

static void test_good_file(void **state) {
  (void)state;
  struct vlff_config cfg;
  const char *y = "node:\n  state_dir: /srv/robot1\n  log_level: debug\n  cpu_budget: 1.5\n"
                  "field:\n  feature_dim: 128\n  scene_min: [-1, -2, -3]\n  scene_max: [1, 2, 3.5]\n"
                  "can:\n  enabled: yes\n  node_id: 0x10\n"
                  "shm:\n  mode: 0660\n"
                  "sim:\n  layout: flat\n  object_bias: 0.3\n"
                  "prompts:\n  active: 1\n  sets:\n    - name: a\n      prompts: [x, y]\n"
                  "    - name: b\n      prompts: [chair, \"shower curtain\", z]\n";
  assert_int_equal(load(y, &cfg), 0);
  assert_string_equal(cfg.node.state_dir, "/srv/robot1");
  assert_int_equal(cfg.node.log_level, VLFF_LOG_DEBUG);
  assert_true(cfg.node.cpu_budget == 1.5);
  assert_int_equal(cfg.field.feature_dim, 128);
  assert_true(cfg.field.scene_min[2] == -3 && cfg.field.scene_max[2] == 3.5);
  assert_true(cfg.can.enabled);
  assert_int_equal(cfg.can.node_id, 16);
  assert_int_equal(cfg.shm.mode, 0660);
  assert_int_equal(cfg.sim.layout, VLFF_LAYOUT_FLAT);
  assert_true(cfg.sim.object_bias == 0.3);
  assert_int_equal(cfg.prompts.set_count, 2);
  assert_int_equal(cfg.prompts.active, 1);
  assert_int_equal(cfg.prompts.sets[1].count, 3);
  assert_string_equal(cfg.prompts.sets[1].text[1], "shower curtain");
  /* Untouched keys keep their defaults. */
  assert_int_equal(cfg.train.rays_per_step, 1024);
}

static void test_errors(void **state) {
  (void)state;
  for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) expect_error(bad[i].yaml, bad[i].prefix, bad[i].fragment);
}

static void test_sim_features(void **state) {
  (void)state;
  struct vlff_config cfg;
  assert_int_equal(load("source:\n  kind: ring\n  features: sim\n  allow_sim_features: true\n", &cfg), 0);
  assert_true(cfg.source.allow_sim_features);
  assert_false(vlff_config_sim_features_misused(&cfg));
  assert_int_equal(load("source:\n  kind: sim\n  features: sim\n", &cfg), 0);
  /* The defaults describe a rig: camera ring, pose ring, feature ring. */
  assert_int_equal(load("", &cfg), 0);
  assert_int_equal(cfg.source.kind, VLFF_SOURCE_RING);
  assert_int_equal(cfg.source.features, VLFF_FEAT_RING);
  cfg.source.features = VLFF_FEAT_SIM;
  assert_true(vlff_config_sim_features_misused(&cfg));
}

/* sim.changes reads into the sim section in the order written, and the
 * dump writes it back. */
static void test_sim_changes(void **state) {
  (void)state;
  struct vlff_config cfg;
  assert_int_equal(load("sim:\n  changes:\n    - {time_s: 30, object: chair#2, action: move, to: [1.5, -0.25]}\n"
                        "    - {time_s: 12.5, object: shower curtain, action: remove}\n"
                        "    - {time_s: 0, object: sofa, action: add}\n", &cfg), 0);
  assert_int_equal(cfg.sim.change_count, 3);
  assert_float_equal(cfg.sim.changes[0].time_s, 30, 0);
  assert_string_equal(cfg.sim.changes[0].object, "chair#2");
  assert_int_equal(cfg.sim.changes[0].action, VLFF_SIM_MOVE);
  assert_true(cfg.sim.changes[0].has_to);
  assert_float_equal(cfg.sim.changes[0].to[1], -0.25, 0);
  assert_string_equal(cfg.sim.changes[1].object, "shower curtain");
  assert_int_equal(cfg.sim.changes[1].action, VLFF_SIM_REMOVE);
  assert_int_equal(cfg.sim.changes[2].action, VLFF_SIM_ADD);
  assert_false(cfg.sim.changes[2].has_to);
  char *text = NULL;
  size_t len = 0;
  FILE *f = open_memstream(&text, &len);
  vlff_config_dump(&cfg, f);
  fclose(f);
  assert_non_null(strstr(text, "\nsim.changes[0]: {time_s: 30, object: \"chair#2\", action: move, to: [1.5, -0.25]}\n"));
  assert_non_null(strstr(text, "\nsim.changes[2]: {time_s: 0, object: \"sofa\", action: add}\n"));
  free(text);
  assert_int_equal(load("", &cfg), 0);
  assert_int_equal(cfg.sim.change_count, 0);
}

/* Deep brackets cost libyaml the square of their depth to load; the limit
 * refuses them at the first level too deep, naming where. Before the limit
 * this test ran for minutes (ctest's timeout failed it). */
static void test_deep_yaml(void **state) {
  (void)state;
  const int depth = 100000;
  char *y = malloc(6 + 2 * (size_t)depth + 1);
  assert_non_null(y);
  memcpy(y, "node: ", 6);
  memset(y + 6, '[', (size_t)depth);
  memset(y + 6 + depth, ']', (size_t)depth);
  y[6 + 2 * depth] = 0;
  struct vlff_config cfg;
  assert_int_equal(load(y, &cfg), -1);
  /* The mapping is level 1, so the 32nd bracket (column 38) is level 33. */
  assert_string_equal(err, "t.yaml:1:38: nesting deeper than 32 levels, not a vlff config");
  free(y);
  /* Block mappings count the same. */
  char deep[4096] = "";
  size_t n = 0;
  for (int i = 0; i < 40; i++) n += (size_t)snprintf(deep + n, sizeof deep - n, "%*sk%d:\n", 2 * i, "", i);
  snprintf(deep + n, sizeof deep - n, "%*sx: 1\n", 80, "");
  assert_int_equal(load(deep, &cfg), -1);
  assert_non_null(strstr(err, "nesting deeper than 32 levels"));
  assert_int_equal(strncmp(err, "t.yaml:33:", 10), 0);
  /* A flat list of more events than any config has. */
  const int items = 200000;
  char *flat = malloc(16 + 3 * (size_t)items);
  assert_non_null(flat);
  n = (size_t)sprintf(flat, "node: [");
  for (int i = 0; i < items; i++) n += (size_t)sprintf(flat + n, "1,");
  sprintf(flat + n, "1]\n");
  assert_int_equal(load(flat, &cfg), -1);
  assert_non_null(strstr(err, "more than 100000 YAML nodes"));
  assert_int_equal(strncmp(err, "t.yaml:1:", 9), 0);
  free(flat);
  /* The limit leaves room for real nesting: prompt sets are four deep. */
  assert_int_equal(load("prompts:\n  sets:\n    - name: a\n      prompts: [[x]]\n", &cfg), -1);
  assert_non_null(strstr(err, "at index 0, got a sequence"));
}

/* What the file says is quoted in messages without control bytes (more
 * cases in bad[]): not one byte of the message is a control byte. */
static void test_hostile_strings(void **state) {
  (void)state;
  struct vlff_config cfg;
  assert_int_equal(load("shm:\n  ring: \"/a\\e\"\n", &cfg), -1);
  assert_non_null(strstr(err, "got '/a\\x1b'"));
  for (const char *c = err; *c; c++) assert_true(*c >= 0x20 && *c < 0x7f);
  /* What the prompt rule takes (UTF-8 text, spaces, 63 bytes) is taken. */
  assert_int_equal(load("prompts:\n  sets:\n    - name: möbel\n      prompts: [\"café\", 椅子, \"a b\", "
                        "012345678901234567890123456789012345678901234567890123456789012]\n",
                        &cfg), 0);
  assert_int_equal(cfg.prompts.sets[0].count, 4);
  assert_string_equal(cfg.prompts.sets[0].text[1], "椅子");
  assert_string_equal(cfg.prompts.sets[0].name, "möbel");
}

/* Segment names that are valid and distinct are taken (those refused are
 * in bad[]). */
static void test_shm_names(void **state) {
  (void)state;
  struct vlff_config cfg;
  assert_int_equal(load("shm:\n  ring: /r\n  map: /m\n  prompts: /p\n  pose_ring: /q\n  feature_ring: /f\n", &cfg),
                   0);
  assert_string_equal(cfg.shm.prompts, "/p");
}

/* dds.namespace and dds.frame_id: ROS 2's name rules, so every topic the
 * bridge builds is one a ROS 2 tool accepts; the rest range-checked. */
static void test_dds_section(void **state) {
  (void)state;
  struct vlff_config cfg;
  assert_int_equal(load("dds:\n  domain_id: 7\n  namespace: /fleet/robot_1\n  frame_id: odom\n  map: false\n", &cfg), 0);
  assert_int_equal(cfg.dds.domain_id, 7);
  assert_string_equal(cfg.dds.ns, "/fleet/robot_1");
  assert_string_equal(cfg.dds.frame_id, "odom");
  assert_false(cfg.dds.on[VLFF_DDS_MAP]);
  assert_true(cfg.dds.on[VLFF_DDS_STATUS]);
  static const struct {
    const char *yaml, *fragment;
  } nsbad[] = {
      {"dds:\n  namespace: robot1\n", "a leading '/'"},
      {"dds:\n  namespace: /robot1/\n", "no empty token"},
      {"dds:\n  namespace: /a//b\n", "no empty token"},
      {"dds:\n  namespace: /1robot\n", "do not start with a digit"},
      {"dds:\n  namespace: /ro-bot\n", "only letters, digits"},
      {"dds:\n  frame_id: /map\n", "not starting with '/'"},
      {"dds:\n  frame_id: \"\"\n", "expected a frame id"},
      {"dds:\n  frame_id: \"a b\"\n", "expected a frame id"},
  };
  for (size_t i = 0; i < sizeof nsbad / sizeof nsbad[0]; i++) {
    assert_int_equal(load(nsbad[i].yaml, &cfg), -1);
    if (!strstr(err, nsbad[i].fragment)) fail_msg("%s: message '%s' lacks '%s'", nsbad[i].yaml, err, nsbad[i].fragment);
  }
  expect_error("dds:\n  domain_id: 233\n", "t.yaml:2:14: key 'dds.domain_id': ", "expected");
  expect_error("dds:\n  max_prompt_bytes: 20000\n", "t.yaml:2:21: key 'dds.max_prompt_bytes': ", "expected");
  /* map/updates: on, transient local, keep last 200; the whole map's period bounded */
  assert_int_equal(load("dds:\n  map_full_period_s: 30\n", &cfg), 0);
  assert_true(cfg.dds.on[VLFF_DDS_MAP_UPDATES]);
  assert_int_equal(cfg.dds.qos[VLFF_DDS_MAP_UPDATES].durability, VLFF_DDS_TRANSIENT_LOCAL);
  assert_int_equal(cfg.dds.qos[VLFF_DDS_MAP_UPDATES].depth, 200);
  assert_true(cfg.dds.map_full_period_s == 30);
  expect_error("dds:\n  map_full_period_s: 0.5\n", "t.yaml:2:22: key 'dds.map_full_period_s': ", "expected");
  expect_error("dds:\n  map_full_period_s: 4000\n", "t.yaml:2:22: key 'dds.map_full_period_s': ", "expected");

  /* Per-topic switches and QoS, nested or dotted. */
  assert_int_equal(load("dds:\n  tf: false\n  camera_frame_id: cam0\n  qos:\n    camera_image:\n      reliability: "
                        "best_effort\n      depth: 5\n  qos.map.durability: volatile\n",
                        &cfg),
                   0);
  assert_false(cfg.dds.on[VLFF_DDS_TF]);
  assert_true(cfg.dds.on[VLFF_DDS_CAMERA_IMAGE]);
  assert_false(cfg.dds.on[VLFF_DDS_CAMERA_IMAGE_COMPRESSED]);
  assert_string_equal(cfg.dds.camera_frame_id, "cam0");
  assert_int_equal(cfg.dds.qos[VLFF_DDS_CAMERA_IMAGE].reliability, VLFF_DDS_BEST_EFFORT);
  assert_int_equal(cfg.dds.qos[VLFF_DDS_CAMERA_IMAGE].depth, 5);
  assert_int_equal(cfg.dds.qos[VLFF_DDS_CAMERA_IMAGE].durability, VLFF_DDS_VOLATILE);
  assert_int_equal(cfg.dds.qos[VLFF_DDS_MAP].durability, VLFF_DDS_VOLATILE);
  assert_int_equal(cfg.dds.qos[VLFF_DDS_MAP].reliability, VLFF_DDS_RELIABLE);
  assert_int_equal(cfg.dds.qos[VLFF_DDS_PROMPTS].durability, VLFF_DDS_TRANSIENT_LOCAL);
  expect_error("dds:\n  qos:\n    map:\n      depth: 0\n", "t.yaml:4:14: key 'dds.qos.map.depth': ", "expected");
  expect_error("dds:\n  qos:\n    tf:\n      depth: 1001\n", "t.yaml:4:14: key 'dds.qos.tf.depth': ", "expected");
  expect_error("dds:\n  qos:\n    status:\n      reliability: sure\n",
               "t.yaml:4:20: key 'dds.qos.status.reliability': ", "best_effort");
  expect_error("dds:\n  qos:\n    map:\n      lifespan: 3\n", "t.yaml:4:7: key 'dds.qos.map.lifespan': ", "unknown key");
  expect_error("dds:\n  image_hz: 0\n", "t.yaml:2:13: key 'dds.image_hz': ", "expected");
  expect_error("dds:\n  jpeg_quality: 101\n", "t.yaml:2:17: key 'dds.jpeg_quality': ", "expected");
  /* Keep-last histories bounded in bytes: each switched-on topic's depth
   * times its largest message, together within dds.history_max_mb, the
   * depth that holds the most named (with its line when the file sets it). */
  expect_error("dds:\n  qos:\n    map:\n      depth: 1000\n", "t.yaml:4:14: key 'dds.qos.map.depth': ",
               "fits dds.history_max_mb (512 MiB), got keep last 1000 of up to 80.0 MiB");
  /* the grid's voxels and as many far points beside them (far_walk.h) */
  expect_error("shm:\n  map_max_voxels: 67108864\n", "t.yaml: key 'dds.qos.map.depth': ", "up to 2560.0 MiB");
  expect_error("shm:\n  map_max_voxels: 67108864\nfield:\n  grow: false\n", "t.yaml: key 'dds.qos.map.depth': ",
               "up to 1280.0 MiB"); /* a fixed box has no far map */
  expect_error("dds:\n  history_max_mb: 20\n", "t.yaml: key 'dds.qos.map.depth': ", "dds.history_max_mb (20 MiB)");
  expect_error("dds:\n  qos:\n    camera_image:\n      depth: 100\n", "t.yaml:4:14: key 'dds.qos.camera_image.depth': ",
               "keep last 100 of up to 5.9 MiB");
  /* map/updates take what the others leave: at least a point an update */
  expect_error("dds:\n  history_max_mb: 86.8\n  qos:\n    map_updates:\n      depth: 1000\n",
               "t.yaml:5:14: key 'dds.qos.map_updates.depth': ", "leaves no point per update");
  expect_error("dds:\n  history_max_mb: 86.8\n", "t.yaml: key 'dds.qos.map_updates.depth': ", "keep last 200");
  expect_error("dds:\n  history_max_mb: 0.001\n", "t.yaml:2:19: key 'dds.history_max_mb': ", "expected");
  assert_int_equal(load("dds:\n  history_max_mb: 86.8\n  map_updates: false\n", &cfg), 0);
  assert_int_equal(load("", &cfg), 0);
  assert_true(vlff_config_dds_message_max(&cfg, VLFF_DDS_MAP) == (4u << 20) * 20 + VLFF_DDS_MSG_OVERHEAD);
  uint64_t pts = vlff_config_dds_update_points(&cfg);
  assert_true(pts > 50000); /* a large region's change, within 512 MiB */
  assert_true(vlff_config_dds_message_max(&cfg, VLFF_DDS_MAP_UPDATES) == pts * 24 + VLFF_DDS_MSG_OVERHEAD);
  /* half a MiB more is 109 points more in each of 200 updates; the camera's
   * image switched off leaves its 1920x1080 RGB to them */
  assert_int_equal(load("dds:\n  history_max_mb: 512.5\n", &cfg), 0);
  uint64_t more = vlff_config_dds_update_points(&cfg) - pts;
  if (more < 109 || more > 110) fail_msg("%llu more points", (unsigned long long)more);
  assert_int_equal(load("dds:\n  camera_image: false\n", &cfg), 0);
  more = vlff_config_dds_update_points(&cfg) - pts;
  if (more < 1296 || more > 1297) fail_msg("%llu more points", (unsigned long long)more);
  static const struct {
    const char *yaml, *fragment;
  } cross[] = {
      {"dds:\n  qos:\n    prompts_in:\n      durability: transient_local\n", "expected volatile"},
      {"dds:\n  camera_frame_id: map\n", "distinct from dds.frame_id"},
      {"dds:\n  camera_frame_id: /cam\n", "dds.camera_frame_id"},
  };
  for (size_t i = 0; i < sizeof cross / sizeof cross[0]; i++) {
    assert_int_equal(load(cross[i].yaml, &cfg), -1);
    if (!strstr(err, cross[i].fragment)) fail_msg("%s: message '%s' lacks '%s'", cross[i].yaml, err, cross[i].fragment);
  }

  /* vlff-merge's fleet: robots with transforms, checked one by one. */
  assert_int_equal(load("dds:\n  merge:\n    robots:\n      - namespace: /r1\n      - {namespace: /r2, transform: [4, "
                        "0.5, 0, 90]}\n    bounds: [-5, -5, -1, 10, 10, 3]\n",
                        &cfg),
                   0);
  assert_int_equal(cfg.dds.merge.robot_count, 2);
  assert_string_equal(cfg.dds.merge.robots[1].ns, "/r2");
  assert_float_equal(cfg.dds.merge.robots[1].transform[1], 0.5, 0);
  assert_float_equal(cfg.dds.merge.robots[1].transform[3], 90, 0);
  assert_float_equal(cfg.dds.merge.robots[0].transform[0], 0, 0);
  assert_string_equal(cfg.dds.merge.map, "/vlff-fleet");
  /* a robot without a transform takes the one it publishes */
  assert_false(cfg.dds.merge.robots[0].has_transform);
  assert_true(cfg.dds.merge.robots[1].has_transform);
  assert_string_equal(cfg.dds.merge.frame_id, "world");
  assert_float_equal(cfg.dds.merge.half_life_s, 600, 0);
  /* a part of the simulator's walk */
  assert_int_equal(load("sim:\n  frames: 60\n  range_first: 20\n  range_count: 20\n", &cfg), 0);
  assert_int_equal(cfg.sim.range_first, 20);
  assert_int_equal(cfg.sim.range_count, 20);
  static const struct {
    const char *yaml, *fragment;
  } mbad[] = {
      {"dds:\n  merge:\n    robots: {namespace: /r1}\n", "expected a sequence of 0 to 8 robots {namespace, transform}, got a mapping"},
      {"dds:\n  merge:\n    robots:\n      - namespace: r1\n", "a leading '/'"},
      {"dds:\n  merge:\n    robots:\n      - namespace: /r1\n      - namespace: /r1\n", "not given before"},
      {"dds:\n  merge:\n    robots:\n      - {namespace: /r1, transform: [1, 2, 3]}\n", "expected [x, y, z, yaw_deg]"},
      {"dds:\n  merge:\n    robots:\n      - {namespace: /r1, transform: [1, 2, 3, 400]}\n", "degrees within"},
      {"dds:\n  merge:\n    robots:\n      - {transform: [1, 2, 3, 4]}\n", "expected a 'namespace'"},
      {"dds:\n  merge:\n    robots:\n      - {namespace: /r1, pose: 3}\n", "unknown key (expected namespace or transform)"},
      {"dds:\n  merge:\n    robots:\n      - namespace: /r1\n      - namespace: /fleet\n", "no robot has"},
      {"dds:\n  merge:\n    robots:\n      - namespace: /r1\n", "0 (no fleet) or 2 to 8 robots, got 1"},
      {"dds:\n  merge:\n    bounds: [0, 0, 0, 0, 1, 1]\n", "below x1 y1 z1"},
      {"dds:\n  merge:\n    bounds: [0, 0, 0, 1000, 1000, 100]\n    voxel_size_m: 0.01\n", "at most"},
      {"dds:\n  merge:\n    map: fleet\n", "dds.merge.map"},
      {"shm:\n  map: /m\ndds:\n  merge:\n    map: /m\n", "distinct from shm.map"},
      {"dds:\n  merge:\n    map: /vlff-frames\n", "distinct from shm.ring"},
      {"shm:\n  feature_ring: /f\ndds:\n  merge:\n    map: /f\n", "distinct from shm.feature_ring"},
      {"dds:\n  merge:\n    frame_id: /world\n", "dds.merge.frame_id"},
      {"dds:\n  merge:\n    half_life_s: 0\n", "dds.merge.half_life_s"},
      {"sim:\n  frames: 60\n  range_first: 50\n  range_count: 20\n", "within sim.frames (60), got 50 + 20"},
      {"sim:\n  range_first: 5\n", "1 or more frames with sim.range_first 5"},
      {"sim:\n  range_count: 5\n  changes:\n    - {time_s: 1, object: chair, action: remove}\n", "streamed whole"},
  };
  for (size_t i = 0; i < sizeof mbad / sizeof mbad[0]; i++) {
    assert_int_equal(load(mbad[i].yaml, &cfg), -1);
    if (!strstr(err, mbad[i].fragment)) fail_msg("%s: message '%s' lacks '%s'", mbad[i].yaml, err, mbad[i].fragment);
  }
}

static int load_fifo(void *path) {
  struct vlff_config cfg;
  char e[512];
  int rc = vlff_config_load(path, &cfg, e, sizeof e);
  return rc == -1 && strstr(e, "is a FIFO, expected a regular file") ? 0 : 1;
}

/* A FIFO where the config should be is refused at once, not waited on. The
 * load runs in a child so that a regression blocks the child, which its own
 * alarm then ends. */
static void test_fifo_config(void **state) {
  (void)state;
  char dir[] = "/tmp/vlff-cfgfifo-XXXXXX";
  assert_non_null(mkdtemp(dir));
  char path[256];
  snprintf(path, sizeof path, "%s/c.yaml", dir);
  assert_int_equal(mkfifo(path, 0600), 0);
  assert_int_equal(vlff_test_in_child(load_fifo, path, 20), 0);
  struct vlff_config cfg;
  assert_int_equal(vlff_config_load(dir, &cfg, err, sizeof err), -1);
  assert_non_null(strstr(err, "is a directory"));
  unlink(path);
  rmdir(dir);
}

/* Temporaries of a dead writer go; a live writer's, other names and
 * non-regular files stay. */
static void test_dead_temps(void **state) {
  (void)state;
  char dir[] = "/tmp/vlff-temps-XXXXXX";
  assert_non_null(mkdtemp(dir));
  pid_t dead = fork();
  if (dead == 0) _exit(0);
  waitpid(dead, NULL, 0);
  char p[512];
  const char *keep[] = {"field.0.ckpt", "field.0.ckpt.tmp.x1", "other.tmp.%d", "field.1.ckpt.tmp.%d"};
  const char *gone[] = {"field.0.ckpt.tmp.%d", "map.1.obs.tmp.%d"};
  for (int i = 0; i < 4; i++) {
    char name[64];
    snprintf(name, sizeof name, keep[i], i == 3 ? (int)getppid() : (int)dead);
    snprintf(p, sizeof p, "%s/%s", dir, name);
    int fd = open(p, O_CREAT | O_WRONLY, 0600);
    assert_true(fd >= 0);
    close(fd);
  }
  for (int i = 0; i < 2; i++) {
    char name[64];
    snprintf(name, sizeof name, gone[i], (int)dead);
    snprintf(p, sizeof p, "%s/%s", dir, name);
    int fd = open(p, O_CREAT | O_WRONLY, 0600);
    assert_true(fd >= 0);
    close(fd);
  }
  snprintf(p, sizeof p, "%s/map.0.obs.tmp.%d", dir, (int)dead);
  assert_int_equal(mkfifo(p, 0600), 0);
  const char *prefixes[] = {"field.", "map.", NULL};
  assert_int_equal(vlff_remove_dead_temps(dir, prefixes), 2);
  for (int i = 0; i < 2; i++) {
    char name[64];
    snprintf(name, sizeof name, gone[i], (int)dead);
    snprintf(p, sizeof p, "%s/%s", dir, name);
    assert_int_equal(access(p, F_OK), -1);
  }
  /* A writer's temporary: a FIFO or a link planted at its name is
   * replaced, never opened (the link's target stays untouched). */
  snprintf(p, sizeof p, "%s/w.tmp.%d", dir, (int)getpid());
  assert_int_equal(mkfifo(p, 0600), 0);
  int wfd = vlff_create_temp(p, 0600, err, sizeof err);
  assert_true(wfd >= 0);
  struct stat wst;
  assert_int_equal(fstat(wfd, &wst), 0);
  assert_true(S_ISREG(wst.st_mode));
  close(wfd);
  char target[600];
  snprintf(target, sizeof target, "%s/target", dir);
  int tfd = open(target, O_CREAT | O_WRONLY, 0600);
  assert_true(tfd >= 0);
  close(tfd);
  unlink(p);
  assert_int_equal(symlink(target, p), 0);
  wfd = vlff_create_temp(p, 0600, err, sizeof err);
  assert_true(wfd >= 0);
  assert_int_equal(write(wfd, "x", 1), 1);
  close(wfd);
  assert_int_equal(lstat(p, &wst), 0);
  assert_true(S_ISREG(wst.st_mode));
  assert_int_equal(stat(target, &wst), 0);
  assert_int_equal(wst.st_size, 0);
  long pid;
  assert_true(vlff_temp_name_pid("a.tmp.b.tmp.42", &pid) && pid == 42);
  assert_false(vlff_temp_name_pid("a.tmp.", &pid));
  assert_false(vlff_temp_name_pid("a.tmp.0", &pid));
  assert_false(vlff_temp_name_pid("a.tmp.12x", &pid));
  char cmd[300];
  snprintf(cmd, sizeof cmd, "rm -rf %s", dir);
  assert_int_equal(system(cmd), 0);
}

static void test_missing_file(void **state) {
  (void)state;
  struct vlff_config cfg;
  assert_int_equal(vlff_config_load("/nonexistent/x.yaml", &cfg, err, sizeof err), -1);
  assert_non_null(strstr(err, "/nonexistent/x.yaml: cannot open"));
}

/* A key near none is not given a guess. */
static void test_unknown_key_without_guess(void **state) {
  (void)state;
  expect_error("node:\n  xylophone: 1\n", "t.yaml:2:3: key 'node.xylophone': ", "unknown key");
  assert_null(strstr(err, "did you mean"));
  expect_error("x:\n  y: 1\n", "t.yaml:1:1: key 'x': ", "unknown key");
  assert_null(strstr(err, "did you mean"));
}

static char *dump_to_string(const struct vlff_config *cfg) {
  char *buf = NULL;
  size_t len = 0;
  FILE *f = open_memstream(&buf, &len);
  vlff_config_dump(cfg, f);
  fclose(f);
  return buf;
}

/* configs/default.yaml must list every key with exactly the built-in default,
 * and the shipped example configs must all be valid. */
static void test_shipped_configs(void **state) {
  (void)state;
  const char *src = getenv("VLFF_SOURCE_DIR");
  assert_non_null(src);
  char path[1024];
  struct vlff_config cfg, def;
  vlff_config_defaults(&def);
  snprintf(path, sizeof path, "%s/configs/default.yaml", src);
  assert_int_equal(vlff_config_load(path, &cfg, err, sizeof err), 0);
  char *a = dump_to_string(&cfg), *b = dump_to_string(&def);
  assert_string_equal(a, b);
  /* Whole numbers read as written (30, not 3e+01); fractions as short as
   * reads back (0.1). */
  assert_non_null(strstr(a, "\ncamera.exposure_us: 10000\n"));
  assert_non_null(strstr(a, "\nsim.rate_hz: 5\n"));
  assert_null(strstr(a, "e+"));
  free(a);
  free(b);
  FILE *f = fopen(path, "r");
  assert_non_null(f);
  char text[65536];
  size_t n = fread(text, 1, sizeof text - 1, f);
  text[n] = 0;
  fclose(f);
  for (size_t i = 0; i < vlff_config_key_count(); i++) {
    /* a.b at two spaces, a.b.c.d (dds.qos.map.depth) at six */
    const char *kp = vlff_config_key_path(i), *k = strrchr(kp, '.') + 1;
    int depth = 0;
    for (const char *c = kp; *c; c++) depth += *c == '.';
    char needle[80];
    snprintf(needle, sizeof needle, "\n%*s%s:", 2 * depth, "", k);
    if (!strstr(text, needle)) fail_msg("default.yaml lacks key %s", vlff_config_key_path(i));
  }
  /* Every vlff config shipped in configs/ (the install copies them to
   * /etc/vlff), found by listing the directory so that a new one is checked
   * too; OpenCV FileStorage calibrations ("%YAML:1.0") are not vlff configs. */
  snprintf(path, sizeof path, "%s/configs", src);
  DIR *d = opendir(path);
  assert_non_null(d);
  int checked = 0, installed = 0;
  for (struct dirent *e; (e = readdir(d));) {
    size_t l = strlen(e->d_name);
    if (l < 6 || strcmp(e->d_name + l - 5, ".yaml")) continue;
    snprintf(path, sizeof path, "%s/configs/%s", src, e->d_name);
    char head[16] = "";
    FILE *h = fopen(path, "r");
    assert_non_null(h);
    if (!fgets(head, sizeof head, h)) head[0] = 0;
    fclose(h);
    if (!strncmp(head, "%YAML:", 6)) continue;
    if (vlff_config_load(path, &cfg, err, sizeof err)) fail_msg("%s", err);
    checked++;
    installed += !strcmp(e->d_name, "vlff.yaml");
    /* A live camera's frames with a live tracker's poses: the newest pose is
     * up to a period older than the newest frame (docs/pose.md: the shipped
     * configs wait for it). default.yaml lists the built-in defaults. */
    if (cfg.source.kind == VLFF_SOURCE_RING && strcmp(e->d_name, "default.yaml") && !(cfg.source.pose_wait_s > 0))
      fail_msg("%s: source.pose_wait_s is %g, expected the shipped wait for a live tracker", e->d_name,
               cfg.source.pose_wait_s);
  }
  closedir(d);
  assert_int_equal(installed, 1);
  assert_true(checked >= 6); /* default, vlff, demo-sim and the three rigs' */
}

static void test_field_hash(void **state) {
  (void)state;
  struct vlff_config a, b;
  vlff_config_defaults(&a);
  b = a;
  b.train.lr = 0.5; /* training knobs do not change the model's shape */
  assert_true(vlff_config_field_hash(&a.field) == vlff_config_field_hash(&b.field));
  b.field.feature_dim = 128;
  assert_true(vlff_config_field_hash(&a.field) != vlff_config_field_hash(&b.field));
  /* The section alone, as the field keeps it, hashes as it does in the config. */
  struct vlff_cfg_field alone = b.field;
  assert_true(vlff_config_field_hash(&alone) == vlff_config_field_hash(&b.field));
  alone.scene_max[2] += 1;
  assert_true(vlff_config_field_hash(&alone) != vlff_config_field_hash(&b.field));
}

/* The search path: --config, then $VLFF_CONFIG, then the installed file;
 * nothing found is an error naming each place, never the defaults. */
static void test_config_find(void **state) {
  (void)state;
  char msg[512] = "";
  setenv("VLFF_CONFIG", "/from/env.yaml", 1);
  assert_string_equal(vlff_config_find("/given.yaml", msg, sizeof msg), "/given.yaml");
  assert_string_equal(vlff_config_find(NULL, msg, sizeof msg), "/from/env.yaml");
  setenv("VLFF_CONFIG", "", 1); /* empty is unset */
  const char *def = vlff_config_default_path();
  assert_non_null(strstr(def, "/vlff/vlff.yaml"));
  const char *got = vlff_config_find(NULL, msg, sizeof msg);
  FILE *f = fopen(def, "r");
  if (f) {
    fclose(f);
    assert_string_equal(got, def);
  } else {
    assert_null(got);
    assert_non_null(strstr(msg, "no config"));
    assert_non_null(strstr(msg, "VLFF_CONFIG"));
    assert_non_null(strstr(msg, def));
  }
  unsetenv("VLFF_CONFIG");
}

/* Issue 51's silent acceptances. Each row is checked and reported on its
 * own (the test fails once, after all rows), so every row is seen to fail
 * on a loader without the fix. */
struct refusal {
  const char *yaml, *prefix, *fragment;
};

static void expect_refusals(const struct refusal *rows, size_t n) {
  int wrong = 0;
  for (size_t i = 0; i < n; i++) {
    struct vlff_config cfg, def;
    vlff_config_defaults(&def);
    int rc = load(rows[i].yaml, &cfg);
    if (rc != -1 || strncmp(err, rows[i].prefix, strlen(rows[i].prefix)) != 0 || !strstr(err, rows[i].fragment) ||
        memcmp(&cfg, &def, sizeof cfg) != 0) {
      print_message("row %zu: rc %d, message '%s'; expected '%s...%s'\n", i, rc, err, rows[i].prefix, rows[i].fragment);
      wrong++;
    }
  }
  assert_int_equal(wrong, 0);
}

/* One key set twice, however spelt, in every mapping: whichever came last
 * used to win silently. */
static const struct refusal duplicates[] = {
  {"shm.ring: /b1\nshm: {ring: /a1}\n", "t.yaml:2:7: key 'shm.ring': ", "duplicate key (first at line 1, written 'shm.ring')"},
  {"shm: {ring: /a1}\nshm.ring: /b1\n", "t.yaml:2:1: key 'shm.ring': ", "duplicate key (first at line 1, written 'ring')"},
  {"sim:\n  seed: 3\nsim.seed: 4\n", "t.yaml:3:1: key 'sim.seed': ", "duplicate key (first at line 2, written 'seed')"},
  {"prompts.sets: [{prompts: [a]}]\nprompts:\n  sets: [{prompts: [b]}]\n", "t.yaml:3:3: key 'prompts.sets': ",
   "duplicate key (first at line 1, written 'prompts.sets')"},
  {"prompts:\n  sets:\n    - name: a\n      prompts: [x]\n      name: b\n", "t.yaml:5:7: key 'prompts.sets[0].name': ",
   "duplicate key (first at line 3)"},
  {"prompts:\n  sets:\n    - prompts: [x]\n    - prompts: [y]\n      prompts: [z]\n",
   "t.yaml:5:7: key 'prompts.sets[1].prompts': ", "duplicate key (first at line 4)"},
  /* Quoting does not make another key. */
  {"node:\n  state_dir: a\n  \"state_dir\": b\n", "t.yaml:3:3: key 'node.state_dir': ", "duplicate key (first at line 2)"},
};

static void test_duplicate_spellings(void **state) {
  (void)state;
  expect_refusals(duplicates, sizeof duplicates / sizeof *duplicates);
  /* Keys of one section spread over a dotted and a nested spelling are
   * still taken when no key repeats. */
  struct vlff_config cfg;
  assert_int_equal(load("shm.ring: /b1\nshm: {map: /m1}\n", &cfg), 0);
  assert_string_equal(cfg.shm.ring, "/b1");
  assert_string_equal(cfg.shm.map, "/m1");
}

/* A NUL in a key made it compare equal to the key before the NUL; in a
 * number, boolean or enum value it cut the value short. */
static const struct refusal nuls[] = {
  {"\"node.name\\0zzz\": x\n", "t.yaml:1:1: key 'node.name\\x00zzz': ", "expected a key without NUL bytes"},
  {"node:\n  \"name\\0zzz\": x\n", "t.yaml:2:3: key 'node.name\\x00zzz': ", "expected a key without NUL bytes"},
  {"\"shm\\0x\":\n  ring: /r\n", "t.yaml:1:1: key 'shm\\x00x': ", "expected a key without NUL bytes"},
  {"prompts:\n  sets:\n    - \"name\\0x\": a\n      prompts: [x]\n", "t.yaml:3:7: key 'prompts.sets[0].name\\x00x': ",
   "expected a key without NUL bytes"},
  {"node:\n  log_level: \"debug\\0x\"\n", "t.yaml:2:14: key 'node.log_level': ", "expected a value without NUL bytes, got 'debug\\x00x'"},
  {"can:\n  enabled: \"true\\0\"\n", "t.yaml:2:12: key 'can.enabled': ", "expected a value without NUL bytes, got 'true\\x00'"},
  {"shm:\n  ring_slots: \"16\\0 9\"\n", "t.yaml:2:15: key 'shm.ring_slots': ", "expected a value without NUL bytes, got '16\\x00 9'"},
  {"train:\n  lr: \"0.5\\0\"\n", "t.yaml:2:7: key 'train.lr': ", "expected a value without NUL bytes"},
  {"field:\n  scene_min: [-1, \"-2\\0\", -3]\n", "t.yaml:2:19: key 'field.scene_min': ", "at index 1, got '-2\\x00'"},
};

static void test_nul_keys_values(void **state) {
  (void)state;
  expect_refusals(nuls, sizeof nuls / sizeof *nuls);
}

/* A leading 0 read as octal (010 became 8, 0123 83); numbers are decimal,
 * integers may be hex, the mode is octal with its 0. */
static const struct refusal numbers[] = {
  {"shm:\n  ring_slots: 010\n", "t.yaml:2:15: key 'shm.ring_slots': ",
   "expected a number without a leading 0, got '010': YAML 1.1 reads it as octal (8), YAML 1.2 as 10; write the one you mean in decimal"},
  {"sim:\n  seed: 0123\n", "t.yaml:2:9: key 'sim.seed': ", "got '0123': YAML 1.1 reads it as octal (83), YAML 1.2 as 123"},
  {"sim.seed: 0123\n", "t.yaml:1:11: key 'sim.seed': ", "without a leading 0"},
  {"sim:\n  seed: 09\n", "t.yaml:2:9: key 'sim.seed': ", "expected a number without a leading 0, got '09': write it in decimal"},
  {"can:\n  node_id: -010\n", "t.yaml:2:12: key 'can.node_id': ", "octal (-8), YAML 1.2 as -10"},
  {"pose:\n  latency_s: 01.5\n", "t.yaml:2:14: key 'pose.latency_s': ", "got '01.5': write it in decimal"},
  {"field:\n  scene_min: [-1, -02, -3]\n", "t.yaml:2:19: key 'field.scene_min': ", "got '-02': write it in decimal"},
  /* strtoll skips leading blanks, which hid a leading 0 from the check. */
  {"shm:\n  ring_slots: \" 010\"\n", "t.yaml:2:15: key 'shm.ring_slots': ", "expected integer in [2, 1024], got ' 010'"},
  /* Hex is for integers; strtod's hex floats are not YAML. */
  {"train:\n  lr: 0x1\n", "t.yaml:2:7: key 'train.lr': ", "expected number in [0, 10], got '0x1'"},
  {"shm:\n  mode: 416\n", "t.yaml:2:9: key 'shm.mode': ", "expected a mode in octal with its leading 0 (like 0640), at most 0777, got '416'"},
  {"shm:\n  mode: 0x1a0\n", "t.yaml:2:9: key 'shm.mode': ", "got '0x1a0'"},
  {"shm:\n  mode: 0648\n", "t.yaml:2:9: key 'shm.mode': ", "in octal"},
};

static void test_leading_zero_numbers(void **state) {
  (void)state;
  expect_refusals(numbers, sizeof numbers / sizeof *numbers);
  struct vlff_config cfg;
  /* Hex integers are meant (CAN ids), as is a lone 0 and a decimal fraction. */
  assert_int_equal(load("can:\n  status_base_id: 0x180\n  command_id: 0X600\nsim:\n  seed: 0\n"
                        "pose:\n  latency_s: 0.25\nshm:\n  mode: 0600\n", &cfg), 0);
  assert_int_equal(cfg.can.status_base_id, 0x180);
  assert_int_equal(cfg.can.command_id, 0x600);
  assert_int_equal(cfg.sim.seed, 0);
  assert_true(cfg.pose.latency_s == 0.25);
  assert_int_equal(cfg.shm.mode, 0600);
  assert_int_equal(load("shm:\n  mode: 0\n", &cfg), 0);
  assert_int_equal(cfg.shm.mode, 0);
}

/* libyaml's loader costs the square of the anchor count: the pre-pass
 * refuses the 65th anchor, the 257th alias and the 17th directive. Every
 * file here would be refused by the loader with another message (an
 * unknown key), so the message proves the refusal came before the load. */
static void test_yaml_anchors(void **state) {
  (void)state;
  struct vlff_config cfg;
  /* The count: 99,990 anchors, 99,999 events, within the event
   * limit, so that only the anchor limit stands before the loader. */
  const int n = 99990;
  char *y = malloc(64 + 24 * (size_t)n);
  assert_non_null(y);
  size_t o = (size_t)sprintf(y, "x:\n");
  for (int i = 0; i < n; i++) o += (size_t)sprintf(y + o, "  - &a%d %d\n", i, i);
  assert_int_equal(load(y, &cfg), -1);
  /* Anchor 65 (&a64) is on line 1 + 65. */
  assert_string_equal(err, "t.yaml:66:5: more than 64 YAML anchors (&name), not a vlff config");
  /* Aliases of one anchor. */
  o = (size_t)sprintf(y, "node:\n  state_dir: &n x\nx:\n");
  for (int i = 0; i < 300; i++) o += (size_t)sprintf(y + o, "  - *n\n");
  assert_int_equal(load(y, &cfg), -1);
  assert_string_equal(err, "t.yaml:260:5: more than 256 YAML aliases (*name), not a vlff config");
  /* %TAG directives: libyaml's parser compares each with every earlier one. */
  o = 0;
  for (int i = 0; i < 40000; i++) o += (size_t)sprintf(y + o, "%%TAG !t%d! tag:x,%d:\n", i, i);
  sprintf(y + o, "---\nx: 1\n");
  assert_int_equal(load(y, &cfg), -1);
  assert_string_equal(err, "t.yaml:17:1: more than 16 YAML directives (%TAG, %YAML), not a vlff config");
  free(y);
  /* A config sharing values through a few anchors still loads. */
  const char *ok = "camera:\n  width: &w 640\n  height: &h 480\n"
                   "depth_camera:\n  width: *w\n  height: *h\n"
                   "prompts:\n  active: 1\n  sets:\n    - name: a\n      prompts: &p [chair, table]\n"
                   "    - name: b\n      prompts: *p\n";
  assert_int_equal(load(ok, &cfg), 0);
  assert_int_equal(cfg.depth_camera.width, 640);
  assert_int_equal(cfg.depth_camera.height, 480);
  assert_int_equal(cfg.prompts.set_count, 2);
  assert_string_equal(cfg.prompts.sets[1].text[1], "table");
  /* The limits themselves are taken. */
  char *at = malloc(64 * 16 + 300 * 8 + 64);
  assert_non_null(at);
  o = (size_t)sprintf(at, "prompts:\n  sets:\n    - prompts: [");
  for (int i = 0; i < VLFF_CONFIG_MAX_ANCHORS; i++) o += (size_t)sprintf(at + o, "%s&a%d p%d", i ? ", " : "", i, i);
  o += (size_t)sprintf(at + o, "]\n    - prompts: [");
  for (int i = 0; i < VLFF_CONFIG_MAX_ALIASES; i++) o += (size_t)sprintf(at + o, "%s*a%d", i ? ", " : "", i % 32);
  sprintf(at + o, "]\n");
  assert_int_equal(load(at, &cfg), -1);
  /* ...and refused only for what the prompt rules say (64 prompts in a set). */
  assert_non_null(strstr(err, "expected sequence of 1 to 32 prompts"));
  free(at);
}

/* The growth keys (field.grow, field.world_limit_m; sim.scene_min/max):
 * checked together, and in the field's hash only when growing, so that a
 * fixed box's checkpoints load as before they existed. */
static void test_grow_keys(void **state) {
  (void)state;
  struct vlff_config cfg;
  assert_int_equal(load("field:\n  grow: true\n  world_limit_m: 10\n  scene_max: [2.5, 2.5, 12]\n", &cfg), -1);
  assert_non_null(strstr(err, "within field.world_limit_m (10 m)"));
  assert_int_equal(load("sim:\n  scene_min: [1, -1, -1]\n  scene_max: [0, 1, 1]\n", &cfg), -1);
  assert_non_null(strstr(err, "sim.scene_max"));
  assert_int_equal(load("sim:\n  scene_min: [-5, -4, -1.5]\n  scene_max: [5, 4, 1.5]\n", &cfg), 0);
  double lo[3], hi[3];
  vlff_config_sim_box(&cfg.sim, &cfg.field, lo, hi);
  assert_true(lo[0] == -5 && hi[1] == 4);
  assert_int_equal(load("", &cfg), 0);
  vlff_config_sim_box(&cfg.sim, &cfg.field, lo, hi);
  assert_true(lo[0] == -2.5 && hi[1] == 2.5); /* unset: the field's box */
  /* growing by default; a fixed box's hash is the one it had before the
   * growth keys existed, whatever world_limit_m says */
  assert_true(cfg.field.grow);
  const uint64_t grow = vlff_config_field_hash(&cfg.field);
  assert_int_equal(load("field:\n  grow: false\n", &cfg), 0);
  const uint64_t fixed = vlff_config_field_hash(&cfg.field);
  assert_int_equal(load("field:\n  grow: false\n  world_limit_m: 20\n", &cfg), 0);
  assert_true(vlff_config_field_hash(&cfg.field) == fixed);
  assert_int_equal(load("field:\n  grow: true\n", &cfg), 0);
  assert_true(vlff_config_field_hash(&cfg.field) == grow);
  assert_true(grow != fixed);
  assert_int_equal(load("field:\n  grow: true\n  world_limit_m: 20\n", &cfg), 0);
  assert_true(vlff_config_field_hash(&cfg.field) != grow);
  /* a growing field's cells in metres: only when growing, and a real size */
  assert_int_equal(load("field:\n  grow: true\ntrain:\n  occupancy_cell_m: 0.2\n", &cfg), 0);
  assert_true(cfg.train.occupancy_cell_m == 0.2);
  assert_int_equal(load("field:\n  grow: false\ntrain:\n  occupancy_cell_m: 0.2\n", &cfg), -1);
  assert_non_null(strstr(err, "train.occupancy_cell_m"));
  assert_non_null(strstr(err, "unless field.grow is on"));
  assert_int_equal(load("field:\n  grow: true\ntrain:\n  occupancy_cell_m: 0.001\n", &cfg), -1);
  assert_non_null(strstr(err, "0.01-10 m"));
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_defaults_valid), cmocka_unit_test(test_good_file),
    cmocka_unit_test(test_errors), cmocka_unit_test(test_missing_file),
    cmocka_unit_test(test_shipped_configs), cmocka_unit_test(test_unknown_key_without_guess),
    cmocka_unit_test(test_field_hash), cmocka_unit_test(test_grow_keys),
    cmocka_unit_test(test_sim_features), cmocka_unit_test(test_sim_changes), cmocka_unit_test(test_deep_yaml),
    cmocka_unit_test(test_shm_names), cmocka_unit_test(test_fifo_config),
    cmocka_unit_test(test_dead_temps), cmocka_unit_test(test_config_find),
    cmocka_unit_test(test_hostile_strings), cmocka_unit_test(test_duplicate_spellings),
    cmocka_unit_test(test_nul_keys_values), cmocka_unit_test(test_leading_zero_numbers),
    cmocka_unit_test(test_yaml_anchors), cmocka_unit_test(test_dds_section))
