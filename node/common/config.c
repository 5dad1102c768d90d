/*
 * YAML config -> struct vlff_config.
 *
 * The schema is one table: each row names a dotted key, its type, where it
 * lives in the struct, its range and its default. Defaults, validation,
 * unknown-key detection and the dump all read the same table, so a key can
 * never be documented, parsed and defaulted three different ways.
 * Parsing uses libyaml's document API because we want the source mark
 * (line:column) of every key and value for error messages.
 */
#include "config.h"
#include "hash.h"

#include <ctype.h>
#include <errno.h>
#include <limits.h>
#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <unistd.h>
#include <yaml.h>

#include "bounds.h" /* VLFF_DEPTH_MAX_M */
#include "files.h"
#include "scene_box.h"
#include "vlff/shm.h" /* vlff_prompt_check: the mailbox's and the embeddings format's rule */
#include "vlff/escape.h" /* vlff_escape: outside data quoted in messages */

_Static_assert(VLFF_PROMPT_LEN == VLFF_SHM_PROMPT_LEN && VLFF_MAX_PROMPTS == VLFF_SHM_MAX_PROMPTS,
               "a configured prompt set fits the map's prompt table and the mailbox");

enum ktype { T_INT, T_MODE, T_DOUBLE, T_BOOL, T_STRING, T_ENUM, T_DVEC };

struct key {
  const char *path;
  enum ktype type;
  size_t off;
  size_t size; /* bytes for strings, element count for vectors */
  double lo, hi;
  double def;
  const char *sdef; /* strings and enum names */
  const char *const *names;
  const double *vdef;
};

#define F(field) offsetof(struct vlff_config, field)
#define SZ(field) sizeof(((struct vlff_config *)0)->field)
#define INT(p, f, lo, hi, d) {p, T_INT, F(f), 0, lo, hi, d, NULL, NULL, NULL}
#define DBL(p, f, lo, hi, d) {p, T_DOUBLE, F(f), 0, lo, hi, d, NULL, NULL, NULL}
/* A file mode: octal, written with its leading 0 as chmod takes it. */
#define MODE(p, f, lo, hi, d) {p, T_MODE, F(f), 0, lo, hi, d, NULL, NULL, NULL}
#define BOOL(p, f, d) {p, T_BOOL, F(f), 0, 0, 1, d, NULL, NULL, NULL}
#define STR(p, f, d) {p, T_STRING, F(f), SZ(f), 0, 0, 0, d, NULL, NULL}
/* A file the install puts under its datadir: the default follows the
 * install the program runs from (installed_vocab), and "" in a config file
 * means that default, so a config copied from default.yaml names no prefix
 * (lo = 1 marks it; vlm.bpe_vocab is the only one). */
#define STR_INSTALLED(p, f, d) {p, T_STRING, F(f), SZ(f), 1, 0, 0, d, NULL, NULL}
#define ENUM(p, f, names, d) {p, T_ENUM, F(f), 0, 0, 0, 0, d, names, NULL}
#define DVEC(p, f, lo, hi, d) \
  {p, T_DVEC, F(f), SZ(f) / sizeof(double), lo, hi, 0, NULL, NULL, d}

static const char *const log_levels[] = {"error", "warn", "info", "debug", NULL};
static const char *const source_kinds[] = {"sim", "ring", NULL};
static const char *const feature_sources[] = {"sim", "model", "ring", NULL};
static const char *const feat_losses[] = {"l2", "l1", "cos", NULL};
static const char *const samplings[] = {"depth", "uniform", NULL};
static const char *const label_images[] = {"surface", "render", NULL};
static const char *const trajectories[] = {"walk", "orbit", NULL};
static const char *const sim_layouts[] = {"room", "flat", "building", NULL};
static const char *const camera_kinds[] = {"aravis", "libcamera", NULL};
static const char *const trigger_modes[] = {"freerun", "software", "hardware", NULL};
static const char *const gpio_modes[] = {"off", "output", "input", NULL};
static const char *const depth_kinds[] = {"none", "stream", "stereo", NULL};
static const char *const depth_units[] = {"mm", "m", NULL};
static const char *const depth_camera_kinds[] = {"none", "aravis", NULL};

static const char *const dds_reliabilities[] = {"best_effort", "reliable", NULL};
static const char *const dds_durabilities[] = {"volatile", "transient_local", NULL};
/* A DDS topic's switch and QoS: dds.<name>, dds.qos.<name>.{reliability,
 * durability,depth}. A history deeper than 1000 samples holds more of a
 * map or image stream than a robot's memory wants. */
#define DDS_TOPIC(name, i, def_on, rel, dur, hist)                                                                         \
  BOOL("dds." name, dds.on[i], def_on), ENUM("dds.qos." name ".reliability", dds.qos[i].reliability, dds_reliabilities, rel), \
      ENUM("dds.qos." name ".durability", dds.qos[i].durability, dds_durabilities, dur),                                  \
      INT("dds.qos." name ".depth", dds.qos[i].depth, 1, 1000, hist)

static const double merge_bounds_def[6] = {-10, -10, -2, 10, 10, 4};
static const double scene_min_def[3] = {-2.5, -2.5, -2.5};
static const double zero3[3] = {0, 0, 0};
static const double scene_max_def[3] = {2.5, 2.5, 2.5};
static const double zero4[4] = {0, 0, 0, 0};
static const double zero5[5] = {0, 0, 0, 0, 0};
static const double identity7[7] = {0, 0, 0, 0, 0, 0, 1};
static const char *const pose_clocks[] = {"monotonic", "realtime", NULL};
static const char *const pose_stamps[] = {"source", "host", NULL};
/* CLIP's image normalisation, which LSeg inherits. */
static const double clip_mean[3] = {0.48145466, 0.4578275, 0.40821073};
static const double clip_std[3] = {0.26862954, 0.26130258, 0.27577711};

#if !defined VLFF_DATADIR || !defined VLFF_SYSCONFDIR || !defined VLFF_BINDIR_REL || !defined VLFF_DATADIR_REL || \
    !defined VLFF_SYSCONFDIR_REL
#error "VLFF_{DATA,SYSCONF}DIR and the install's relative dirs must come from the install's layout (CMake)"
#endif
#define BPE_VOCAB_FILE "/vlff/bpe_simple_vocab_16e6.txt.gz"
#define BPE_VOCAB_DEFAULT VLFF_DATADIR BPE_VOCAB_FILE
_Static_assert(sizeof BPE_VOCAB_DEFAULT <= VLFF_CFG_PATH, "the install's datadir is too long for vlm.bpe_vocab");

/* ---- the install's files, where the running program's install put them --
 *
 * The paths configured at build time hold for an install to that prefix; an
 * install with `cmake --install --prefix P`, or a prefix moved afterwards,
 * puts them under P. A program in an install's bindir finds them from its own
 * location (as vlff-shm.pc does from its own), with the install's rules for
 * the sysconfdir (cmake/VlffInstallPaths.cmake.in: prefix /usr keeps its
 * configs in /etc, /opt/X in /etc/opt/X). A file not found there (a program
 * run from the build tree) is looked for where the build configured it. */
_Static_assert(sizeof VLFF_SYSCONFDIR "/vlff/vlff.yaml" <= PATH_MAX, "the install's sysconfdir is too long");
static struct {
  pthread_once_t once;
  char config[PATH_MAX], vocab[VLFF_CFG_PATH];
} installed = {PTHREAD_ONCE_INIT, "", ""};

/* The prefix of the install the running program lies in, or -1. */
static int exe_prefix(char *out, size_t len) {
  char exe[PATH_MAX];
  if (vlff_exe_dir(exe, sizeof exe) != 0) return -1;
  size_t el = strlen(exe), bl = strlen(VLFF_BINDIR_REL);
  if (el < bl + 1) return -1;
  char *bin = exe + el - bl;
  if (bin[-1] != '/' || strcmp(bin, VLFF_BINDIR_REL) != 0) return -1;
  bin[-1] = 0;
  return snprintf(out, len, "%s", exe[0] ? exe : "/") < (int)len ? 0 : -1;
}

/* The install's sysconfdir for prefix p (an absolute sysconfdir stays). */
static int sysconfdir_of(const char *p, char *out, size_t len) {
  int k;
  if (VLFF_SYSCONFDIR_REL[0] == '/') k = snprintf(out, len, "%s", VLFF_SYSCONFDIR_REL);
  else if (!strcmp(VLFF_SYSCONFDIR_REL, "etc") && !strcmp(p, "/usr")) k = snprintf(out, len, "/etc");
  else if (!strcmp(VLFF_SYSCONFDIR_REL, "etc") && !strncmp(p, "/opt/", 5) && p[5]) k = snprintf(out, len, "/etc%s", p);
  else k = snprintf(out, len, "%s/%s", strcmp(p, "/") ? p : "", VLFF_SYSCONFDIR_REL);
  return k > 0 && k < (int)len ? 0 : -1;
}

/* path, when it exists and fits out. */
static void take_if_present(const char *path, int n, char *out, size_t len) {
  if (n > 0 && (size_t)n < len && access(path, F_OK) == 0) memcpy(out, path, (size_t)n + 1);
}

static void find_installed(void) {
  memcpy(installed.config, VLFF_SYSCONFDIR "/vlff/vlff.yaml", sizeof VLFF_SYSCONFDIR "/vlff/vlff.yaml");
  memcpy(installed.vocab, BPE_VOCAB_DEFAULT, sizeof BPE_VOCAB_DEFAULT);
  char prefix[PATH_MAX], dir[PATH_MAX], path[PATH_MAX];
  if (exe_prefix(prefix, sizeof prefix)) return;
  const char *root = strcmp(prefix, "/") ? prefix : "";
  int n = VLFF_DATADIR_REL[0] == '/' ? snprintf(path, sizeof path, "%s" BPE_VOCAB_FILE, VLFF_DATADIR_REL)
                                     : snprintf(path, sizeof path, "%s/%s" BPE_VOCAB_FILE, root, VLFF_DATADIR_REL);
  take_if_present(path, n, installed.vocab, sizeof installed.vocab);
  if (sysconfdir_of(prefix, dir, sizeof dir)) return;
  n = snprintf(path, sizeof path, "%s/vlff/vlff.yaml", dir);
  take_if_present(path, n, installed.config, sizeof installed.config);
}

static const char *installed_vocab(void) {
  pthread_once(&installed.once, find_installed);
  return installed.vocab;
}

static const struct key schema[] = {
    ENUM("node.log_level", node.log_level, log_levels, "info"),
    STR("node.state_dir", node.state_dir, "/var/lib/vlff"),
    DBL("node.checkpoint_period_s", node.checkpoint_period_s, 0, 86400, 60),
    BOOL("node.resume", node.resume, 1),
    DBL("node.run_seconds", node.run_seconds, 0, 1e7, 0),
    INT("node.threads", node.threads, 0, 256, 0),
    /* As node.threads, at most the cores a machine the pool could use has. */
    DBL("node.cpu_budget", node.cpu_budget, 0, 256, 0),

    STR("shm.ring", shm.ring, "/vlff-frames"),
    INT("shm.ring_slots", shm.ring_slots, 2, 1024, 8),
    INT("shm.max_width", shm.max_width, 16, 8192, 1920),
    INT("shm.max_height", shm.max_height, 16, 8192, 1080),
    STR("shm.pose_ring", shm.pose_ring, "/vlff-poses"),
    INT("shm.pose_slots", shm.pose_slots, 2, 65536, 256),
    STR("shm.map", shm.map, "/vlff-map"),
    INT("shm.map_max_voxels", shm.map_max_voxels, 1, 1 << 26, 1 << 21),
    INT("shm.map_far_max_mb", shm.map_far_max_mb, 0, 4096, 64),
    INT("shm.label_max_width", shm.label_max_width, 16, 8192, 640),
    INT("shm.label_max_height", shm.label_max_height, 16, 8192, 480),
    STR("shm.prompts", shm.prompts, "/vlff-prompts"),
    STR("shm.feature_ring", shm.feature_ring, "/vlff-features"),
    STR("shm.group", shm.group, ""),
    MODE("shm.mode", shm.mode, 0, 0777, 0640),

    ENUM("source.kind", source.kind, source_kinds, "ring"),
    ENUM("source.features", source.features, feature_sources, "ring"),
    DBL("source.pose_tolerance_s", source.pose_tolerance_s, 0, 10, 0.04),
    DBL("source.pose_wait_s", source.pose_wait_s, 0, 10, 0),
    BOOL("source.allow_sim_features", source.allow_sim_features, 0),

    INT("sim.seed", sim.seed, 0, 2147483647, 1),
    DBL("sim.rate_hz", sim.rate_hz, 0.1, 1000, 5),
    INT("sim.width", sim.width, 16, 4096, 320),
    INT("sim.height", sim.height, 16, 4096, 240),
    DBL("sim.difficulty", sim.difficulty, 0, 1, 0.5),
    ENUM("sim.trajectory", sim.trajectory, trajectories, "walk"),
    ENUM("sim.layout", sim.layout, sim_layouts, "room"),
    INT("sim.flats", sim.flats, 2, 8, 3),
    DBL("sim.object_bias", sim.object_bias, 0, 1, 0),
    DBL("sim.speed_mps", sim.speed_mps, 0.01, 10, 0.4),
    DBL("sim.depth_noise_m", sim.depth_noise_m, 0, 1, 0.01),
    DBL("sim.depth_hole_frac", sim.depth_hole_frac, 0, 1, 0.02),
    DBL("sim.depth_max_m", sim.depth_max_m, 0.1, VLFF_DEPTH_MAX_M, 6), /* the node takes no depth beyond it */
    INT("sim.frames", sim.frames, 1, 1000000, 300),
    /* A part of the walk, for a robot of a fleet that covers one region. */
    INT("sim.range_first", sim.range_first, 0, 999999, 0),
    INT("sim.range_count", sim.range_count, 0, 1000000, 0),
    DBL("sim.bad_pose_frac", sim.bad_pose_frac, 0, 1, 0),
    DVEC("sim.scene_min", sim.scene_min, -1e4, 1e4, zero3),
    DVEC("sim.scene_max", sim.scene_max, -1e4, 1e4, zero3),

    INT("field.feature_dim", field.feature_dim, 8, 1024, 512),
    INT("field.hash_levels", field.hash_levels, 1, 32, 16),
    INT("field.hash_features", field.hash_features, 1, 8, 2),
    INT("field.hash_log2_size", field.hash_log2_size, 10, 24, 19),
    INT("field.base_resolution", field.base_resolution, 2, 4096, 16),
    INT("field.finest_resolution", field.finest_resolution, 2, 1 << 20, 2048),
    INT("field.freq_bands", field.freq_bands, 0, 16, 2),
    INT("field.geo_dim", field.geo_dim, 1, 256, 15),
    INT("field.density_width", field.density_width, 8, 1024, 64),
    INT("field.density_layers", field.density_layers, 1, 8, 1),
    INT("field.color_width", field.color_width, 8, 1024, 64),
    INT("field.color_layers", field.color_layers, 1, 8, 1),
    INT("field.feature_width", field.feature_width, 8, 1024, 128),
    INT("field.feature_layers", field.feature_layers, 1, 8, 1),
    INT("field.sh_degree", field.sh_degree, 1, 4, 4),
    DVEC("field.scene_min", field.scene_min, -1e4, 1e4, scene_min_def),
    DVEC("field.scene_max", field.scene_max, -1e4, 1e4, scene_max_def),
    STR("field.scene_box_file", field.scene_box_file, ""),
    BOOL("field.grow", field.grow, 1),
    DBL("field.world_limit_m", field.world_limit_m, 10, 1e4, 1000),

    DBL("train.lr", train.lr, 0, 10, 1e-2),
    DBL("train.beta1", train.beta1, 0, 0.999999, 0.9),
    DBL("train.beta2", train.beta2, 0, 0.9999999, 0.99),
    DBL("train.eps", train.eps, 0, 1, 1e-15),
    DBL("train.weight_decay", train.weight_decay, 0, 1, 1e-6),
    DBL("train.weight_average", train.weight_average, 0, 0.9999, 0.99),
    DBL("train.lr_decay", train.lr_decay, 0, 1, 1),
    INT("train.lr_decay_steps", train.lr_decay_steps, 1, 1 << 30, 10000),
    INT("train.rays_per_step", train.rays_per_step, 1, 1 << 20, 1024),
    INT("train.warmup_steps", train.warmup_steps, 0, 1 << 30, 800),
    INT("train.warmup_levels", train.warmup_levels, 0, 32, 4),
    INT("train.warmup_level_steps", train.warmup_level_steps, 0, 1 << 30, 600),
    INT("train.samples_per_ray", train.samples_per_ray, 1, 4096, 24),
    ENUM("train.sampling", train.sampling, samplings, "depth"),
    DBL("train.depth_weight", train.depth_weight, 0, 100, 0.1),
    DBL("train.feature_weight", train.feature_weight, 0, 100, 0.5),
    ENUM("train.feature_loss", train.feature_loss, feat_losses, "l1"),
    DBL("train.class_balance", train.class_balance, 0, 1, 0),
    DBL("train.error_sampling", train.error_sampling, 0, 4, 0.5),
    DBL("train.near_m", train.near_m, 0, 100, 0.05),
    DBL("train.depth_noise_m", train.depth_noise_m, 0, 1, 0.01),
    INT("train.occupancy_resolution", train.occupancy_resolution, 8, 512, 64),
    DBL("train.occupancy_cell_m", train.occupancy_cell_m, 0, 10, 0),
    DBL("train.occupancy_max_mb", train.occupancy_max_mb, 1, 1 << 20, 256),
    INT("train.occupancy_update_steps", train.occupancy_update_steps, 1, 1 << 20, 16),
    DBL("train.image_scale", train.image_scale, 0.05, 1, 0.5),

    DBL("keyframes.rate_hz", keyframes.rate_hz, 0.01, 1000, 5),
    DBL("keyframes.min_translation_m", keyframes.min_translation_m, 0, 100, 0.0),
    DBL("keyframes.min_rotation_deg", keyframes.min_rotation_deg, 0, 180, 0.0),
    INT("keyframes.memory_mb", keyframes.memory_mb, 1, 1 << 20, 1024),
    INT("keyframes.page_mb", keyframes.page_mb, 0, 1 << 20, 2048),
    INT("keyframes.max_keyframes", keyframes.max_keyframes, 1, 1 << 20, 325),
    INT("keyframes.start_after", keyframes.start_after, 1, 1 << 20, 5),
    INT("keyframes.recent", keyframes.recent, 1, 1 << 20, 8),
    DBL("keyframes.bad_pose_threshold_m", keyframes.bad_pose_threshold_m, 0.01, 100, 0.1),
    INT("keyframes.posecheck_min_steps", keyframes.posecheck_min_steps, 0, 1 << 30, 200),

    DBL("publish.rate_hz", publish.rate_hz, 0.01, 1000, 1),
    DBL("publish.voxel_size_m", publish.voxel_size_m, 0.001, 100, 0.1),
    INT("publish.label_width", publish.label_width, 8, 8192, 160),
    INT("publish.label_height", publish.label_height, 8, 8192, 120),
    ENUM("publish.label_image", publish.label_image, label_images, "surface"),
    DBL("publish.free_density", publish.free_density, 0, 1e6, 1.0),
    DBL("publish.evidence_weight", publish.evidence_weight, 0, 100, 1.0),
    INT("publish.field_trust_rays", publish.field_trust_rays, 0, 65535, 50),
    DBL("publish.lost_class_ratio", publish.lost_class_ratio, 0, 1, 0.25),
    DBL("publish.evidence_voxel_m", publish.evidence_voxel_m, 0.01, 10, 0.1),
    INT("publish.evidence_max_mb", publish.evidence_max_mb, 1, 1 << 16, 64),
    INT("publish.evidence_page_mb", publish.evidence_page_mb, 0, 1 << 20, 512),
    DBL("publish.label_hysteresis", publish.label_hysteresis, 0, 2, 0.05),
    DBL("publish.region_weight", publish.region_weight, 0, 100, 1.0),

    INT("prompts.active", prompts.active, 0, VLFF_MAX_PROMPT_SETS - 1, 0),
    STR("prompts.template", prompts.templ, "{}"),
    STR("prompts.embeddings", prompts.embeddings, ""),

    BOOL("can.enabled", can.enabled, 0),
    STR("can.interface", can.interface, "can0"),
    INT("can.node_id", can.node_id, 1, 127, 0x2a),
    INT("can.heartbeat_ms", can.heartbeat_ms, 1, 65535, 100),
    INT("can.status_ms", can.status_ms, 1, 65535, 200),
    INT("can.status_base_id", can.status_base_id, 0, 0x7ff, 0x180),
    INT("can.command_id", can.command_id, 0, 0x7ff, 0x600),
    INT("can.ack_id", can.ack_id, 0, 0x7ff, 0x580),
    BOOL("can.fd", can.fd, 0),
    INT("can.rt_priority", can.rt_priority, 0, 99, 10),
    INT("can.heartbeat_spin_max_us", can.heartbeat_spin_max_us, 0, 20000, 4000),

    ENUM("camera.kind", camera.kind, camera_kinds, "aravis"),
    STR("camera.device", camera.device, ""),
    STR("camera.pixel_format", camera.pixel_format, "RGB8"),
    INT("camera.width", camera.width, 0, 16384, 0),
    INT("camera.height", camera.height, 0, 16384, 0),
    INT("camera.offset_x", camera.offset_x, 0, 16384, 0),
    INT("camera.offset_y", camera.offset_y, 0, 16384, 0),
    DBL("camera.exposure_us", camera.exposure_us, 1, 1e7, 10000),
    DBL("camera.gain_db", camera.gain_db, 0, 100, 0),
    DBL("camera.frame_rate", camera.frame_rate, 0.1, 1000, 30),
    INT("camera.packet_size", camera.packet_size, 0, 16384, 0),
    ENUM("camera.trigger", camera.trigger, trigger_modes, "freerun"),
    STR("camera.trigger_line", camera.trigger_line, "Line1"),
    INT("camera.sensor_id", camera.sensor_id, 0, 255, 0),
    DVEC("camera.intrinsics", camera.intrinsics, 0, 1e6, zero4),
    DVEC("camera.distortion", camera.distortion, -1e3, 1e3, zero5),
    STR("camera.calibration", camera.calibration, ""),
    ENUM("camera.depth", camera.depth, depth_kinds, "none"),
    ENUM("camera.depth_unit", camera.depth_unit, depth_units, "mm"),
    DBL("camera.stereo_baseline_m", camera.stereo_baseline_m, 0, 10, 0),
    INT("camera.stereo_disparities", camera.stereo_disparities, 16, 1024, 64),
    DBL("camera.reconnect_max_s", camera.reconnect_max_s, 0.1, 3600, 5),

    ENUM("depth_camera.kind", depth_camera.kind, depth_camera_kinds, "none"),
    STR("depth_camera.device", depth_camera.device, ""),
    STR("depth_camera.pixel_format", depth_camera.pixel_format, "Mono16"),
    INT("depth_camera.width", depth_camera.width, 0, 16384, 0),
    INT("depth_camera.height", depth_camera.height, 0, 16384, 0),
    DBL("depth_camera.exposure_us", depth_camera.exposure_us, 1, 1e7, 10000),
    DBL("depth_camera.frame_rate", depth_camera.frame_rate, 0.1, 1000, 30),
    INT("depth_camera.packet_size", depth_camera.packet_size, 0, 16384, 0),
    ENUM("depth_camera.trigger", depth_camera.trigger, trigger_modes, "freerun"),
    STR("depth_camera.trigger_line", depth_camera.trigger_line, "Line1"),
    DBL("depth_camera.scale_m", depth_camera.scale_m, 1e-6, 1, 0.001),
    STR("depth_camera.calibration", depth_camera.calibration, ""),
    DBL("depth_camera.pair_tolerance_s", depth_camera.pair_tolerance_s, 1e-6, 1, 0.005),
    INT("depth_camera.register_width", depth_camera.register_width, 0, 16384, 0),
    INT("depth_camera.register_height", depth_camera.register_height, 0, 16384, 0),

    ENUM("gpio.mode", gpio.mode, gpio_modes, "off"),
    STR("gpio.chip", gpio.chip, "gpiochip0"),
    STR("gpio.line", gpio.line, "0"),
    DBL("gpio.rate_hz", gpio.rate_hz, 0.01, 10000, 10),
    DBL("gpio.pulse_us", gpio.pulse_us, 1, 1e6, 1000),
    BOOL("gpio.active_low", gpio.active_low, 0),
    DBL("gpio.debounce_us", gpio.debounce_us, 0, 1e6, 0),

    STR("pose.udp", pose.udp, ""),
    ENUM("pose.clock", pose.clock, pose_clocks, "monotonic"),
    DBL("pose.clock_offset_s", pose.clock_offset_s, -1e10, 1e10, 0),
    ENUM("pose.stamp", pose.stamp, pose_stamps, "source"),
    DBL("pose.latency_s", pose.latency_s, 0, 60, 0),
    DVEC("pose.extrinsic", pose.extrinsic, -1e4, 1e4, identity7),
    DBL("pose.quat_tolerance", pose.quat_tolerance, 0, 0.5, 0.01),
    BOOL("pose.extra_fields", pose.extra_fields, 0),
    INT("pose.source_id", pose.source_id, 0, 2147483647, 0),
    STR("pose.udp_peer", pose.udp_peer, ""),
    /* A pose is computed after its image, so a stamp ahead of the clock is
     * the hosts' clock disagreement: milliseconds under NTP on a LAN,
     * microseconds under PTP. 50 ms passes that with margin and stays under
     * two periods of a 30 Hz tracker; a wrong clock or offset is beyond it. */
    DBL("pose.future_tolerance_s", pose.future_tolerance_s, 0, 1e10, 0.05),
    INT("pose.out_of_order_reset", pose.out_of_order_reset, 0, 1000000, 10),

    STR("vlm.image_model", vlm.image_model, ""),
    STR("vlm.text_model", vlm.text_model, ""),
    STR_INSTALLED("vlm.bpe_vocab", vlm.bpe_vocab, BPE_VOCAB_DEFAULT),
    INT("vlm.input_width", vlm.input_width, 16, 4096, 320),
    INT("vlm.input_height", vlm.input_height, 16, 4096, 240),
    DVEC("vlm.mean", vlm.mean, -10, 10, clip_mean),
    DVEC("vlm.std", vlm.std, 1e-6, 10, clip_std),
    BOOL("vlm.bgr", vlm.bgr, 0),
    BOOL("vlm.normalize", vlm.normalize, 1),
    BOOL("vlm.cuda", vlm.cuda, 0),
    DBL("vlm.feature_timeout_s", vlm.feature_timeout_s, 0.001, 600, 2),

    /* 232 is the highest domain whose ports fit under 65536 with the RTPS
     * port mapping DDS uses by default. */
    INT("dds.domain_id", dds.domain_id, 0, 232, 0),
    STR("dds.namespace", dds.ns, ""),
    STR("dds.frame_id", dds.frame_id, "map"),
    STR("dds.camera_frame_id", dds.camera_frame_id, "camera"),
    DDS_TOPIC("map", VLFF_DDS_MAP, 1, "reliable", "transient_local", 1),
    DDS_TOPIC("status", VLFF_DDS_STATUS, 1, "reliable", "volatile", 10),
    DDS_TOPIC("prompts_in", VLFF_DDS_PROMPTS_IN, 1, "reliable", "volatile", 10),
    DDS_TOPIC("prompts", VLFF_DDS_PROMPTS, 1, "reliable", "transient_local", 1),
    DDS_TOPIC("label_image", VLFF_DDS_LABEL_IMAGE, 1, "reliable", "volatile", 1),
    DDS_TOPIC("label_image_compressed", VLFF_DDS_LABEL_IMAGE_COMPRESSED, 0, "reliable", "volatile", 1),
    DDS_TOPIC("camera_image", VLFF_DDS_CAMERA_IMAGE, 1, "reliable", "volatile", 1),
    DDS_TOPIC("camera_image_compressed", VLFF_DDS_CAMERA_IMAGE_COMPRESSED, 0, "reliable", "volatile", 1),
    DDS_TOPIC("camera_info", VLFF_DDS_CAMERA_INFO, 1, "reliable", "volatile", 1),
    DDS_TOPIC("tf", VLFF_DDS_TF, 1, "reliable", "volatile", 10),
    /* A late joiner needs every update since the whole map it gets: the
     * bridge resends the whole map before more than depth updates follow it. */
    DDS_TOPIC("map_updates", VLFF_DDS_MAP_UPDATES, 1, "reliable", "transient_local", 200),
    DBL("dds.status_hz", dds.status_hz, 0.01, 100, 1),
    DBL("dds.poll_hz", dds.poll_hz, 1, 1000, 20),
    /* A safety net for subscribers that lost updates (late joiners get the
     * updates' history): every resend costs the whole map, dozens of
     * versions' changes for a map refined a region at a time. */
    DBL("dds.map_full_period_s", dds.map_full_period_s, 1, 3600, 120),
    DBL("dds.image_hz", dds.image_hz, 0.01, 60, 2),
    DBL("dds.prompt_rate_hz", dds.prompt_rate_hz, 0.01, 100, 2),
    /* A JSON list of 32 prompts of 63 bytes, each \u-escaped at worst
     * (6 bytes per byte), fits 16 KiB; the default takes plainly written ones. */
    INT("dds.max_prompt_bytes", dds.max_prompt_bytes, 64, 16384, 4096),
    INT("dds.jpeg_quality", dds.jpeg_quality, 1, 100, 80),
    /* Every topic's history (depth x its largest message) within it: a map
     * segment of shm.map_max_voxels is 40 MiB a whole map at the default. */
    DBL("dds.history_max_mb", dds.history_max_mb, 0.01, 65536, 512),
    STR("dds.merge.map", dds.merge.map, "/vlff-fleet"),
    STR("dds.merge.namespace", dds.merge.ns, "/fleet"),
    DVEC("dds.merge.bounds", dds.merge.bounds, -1e5, 1e5, merge_bounds_def),
    DBL("dds.merge.voxel_size_m", dds.merge.voxel_size_m, 0.01, 10, 0.1),
    STR("dds.merge.frame_id", dds.merge.frame_id, "world"),
    /* A robot's evidence counts half when it is this much older than the
     * newest: long against a walk through a flat, short against a day. */
    DBL("dds.merge.half_life_s", dds.merge.half_life_s, 1, 1e7, 600),
};

#define NKEYS (sizeof schema / sizeof schema[0])

/* prompts.sets is the one structured key: a sequence of {name, prompts}. */
static const char PROMPT_SETS[] = "prompts.sets";
static const char MERGE_ROBOTS[] = "dds.merge.robots";

static const char *const default_prompts[] = {
    "wall",   "floor",   "cabinet", "bed",      "chair",        "sofa",           "table",
    "door",   "window",  "bookshelf", "picture", "counter",     "desk",           "curtain",
    "refrigerator", "shower curtain", "toilet", "sink", "bathtub", "other furniture", NULL};

size_t vlff_config_key_count(void) { return NKEYS; }

const char *vlff_config_key_path(size_t i) { return i < NKEYS ? schema[i].path : NULL; }

static void *at(struct vlff_config *cfg, const struct key *k) { return (char *)cfg + k->off; }
static const void *cat(const struct vlff_config *cfg, const struct key *k) {
  return (const char *)cfg + k->off;
}

void vlff_config_defaults(struct vlff_config *cfg) {
  memset(cfg, 0, sizeof *cfg);
  for (size_t i = 0; i < NKEYS; i++) {
    const struct key *k = &schema[i];
    switch (k->type) {
    case T_INT:
    case T_MODE: *(int *)at(cfg, k) = (int)k->def; break;
    case T_DOUBLE: *(double *)at(cfg, k) = k->def; break;
    case T_BOOL: *(bool *)at(cfg, k) = k->def != 0; break;
    case T_STRING: snprintf(at(cfg, k), k->size, "%s", k->lo ? installed_vocab() : k->sdef); break;
    case T_ENUM:
      for (int j = 0; k->names[j]; j++)
        if (!strcmp(k->names[j], k->sdef)) *(int *)at(cfg, k) = j;
      break;
    case T_DVEC: memcpy(at(cfg, k), k->vdef, k->size * sizeof(double)); break;
    }
  }
  struct vlff_prompt_set *s = &cfg->prompts.sets[0];
  snprintf(s->name, sizeof s->name, "scannet20");
  for (s->count = 0; default_prompts[s->count]; s->count++)
    snprintf(s->text[s->count], VLFF_PROMPT_LEN, "%s", default_prompts[s->count]);
  cfg->prompts.set_count = 1;
}

/* ---- parsing ------------------------------------------------------------ */

struct parse {
  yaml_document_t doc;
  const yaml_node_t *where[sizeof schema / sizeof schema[0]]; /* value node per key, if set */
  const yaml_node_t *key_at[sizeof schema / sizeof schema[0]]; /* its key node, as written */
  const yaml_node_t *sets_key;                                 /* prompts.sets' key, once set */
  const yaml_node_t *robots_key;                               /* dds.merge.robots' key, once set */
  const yaml_node_t *changes_key;                              /* sim.changes' key, once set */
  const char *name;
  char *err;
  size_t errlen;
};

static int fail(struct parse *p, const yaml_node_t *n, const char *key, const char *fmt, ...) {
  char what[512], ekey[512];
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(what, sizeof what, fmt, ap);
  va_end(ap);
  if (key) {
    vlff_escape(ekey, sizeof ekey, key, strlen(key), 120);
    key = ekey;
  }
  unsigned line = n ? (unsigned)n->start_mark.line + 1 : 0;
  unsigned col = n ? (unsigned)n->start_mark.column + 1 : 0;
  if (key)
    snprintf(p->err, p->errlen, "%s:%u:%u: key '%s': %s", p->name, line, col, key, what);
  else
    snprintf(p->err, p->errlen, "%s:%u:%u: %s", p->name, line, col, what);
  return -1;
}

static const char *node_kind(const yaml_node_t *n) {
  switch (n->type) {
  case YAML_SCALAR_NODE: return "a scalar";
  case YAML_SEQUENCE_NODE: return "a sequence";
  case YAML_MAPPING_NODE: return "a mapping";
  default: return "nothing";
  }
}

static const char *scalar(const yaml_node_t *n) { return (const char *)n->data.scalar.value; }

/* "got" text for messages: the scalar quoted, or the node kind. */
static void got(const yaml_node_t *n, char *buf, size_t len) {
  if (n->type == YAML_SCALAR_NODE) {
    char e[256];
    vlff_escape(e, sizeof e, scalar(n), n->data.scalar.length, 60);
    /* the caller's buffer bounds the quote; an escaped value may be cut */
    snprintf(buf, len, "'%.*s'", (int)(len > 3 ? len - 3 : 0), e);
  } else {
    snprintf(buf, len, "%s", node_kind(n));
  }
}

/* A scalar holding a NUL ("a\0b") would be cut short silently by every C
 * string use after it. */
static bool has_nul(const yaml_node_t *n) {
  return n->type == YAML_SCALAR_NODE && strlen(scalar(n)) != n->data.scalar.length;
}

/* A control character (C0, tabs and newlines included, or DEL) in a string
 * value: no name, path or text of a config has one, and one written out again
 * (--print-config, a log line, a terminal) could pass for an escape sequence
 * or another line. libyaml keeps them out of plain scalars, but a quoted
 * scalar's escapes ("\t", "\e", "\x1b") make them. */
static bool has_control(const yaml_node_t *n) {
  const unsigned char *c = (const unsigned char *)scalar(n);
  for (size_t i = 0; i < n->data.scalar.length; i++)
    if (c[i] < 0x20 || c[i] == 0x7f) return true;
  return false;
}

/* A number written with a leading 0 before another digit ("010", "-07",
 * "01.5"): YAML 1.1 reads 010 as octal 8, YAML 1.2 and a person as 10, and
 * strtoll's base 0 took the octal. Refused, so that no reading is chosen
 * silently; the message says what each would be. */
static bool leading_zero(const char *s) {
  if (*s == '-' || *s == '+') s++;
  return s[0] == '0' && s[1] >= '0' && s[1] <= '9';
}

static int fail_leading_zero(struct parse *p, const yaml_node_t *n, const char *key, const char *g) {
  const char *s = scalar(n), *d = s + (*s == '-' || *s == '+');
  const char *sign = *s == '-' ? "-" : "";
  size_t l = strlen(d);
  /* Where the readings differ (010, not 07), say what each would be. */
  if (l < 19 && strspn(d, "01234567") == l && strtoll(d, NULL, 8) != strtoll(d, NULL, 10))
    return fail(p, n, key, "expected a number without a leading 0, got %s: YAML 1.1 reads it as octal (%s%lld), "
                "YAML 1.2 as %s%lld; write the one you mean in decimal", g, sign, strtoll(d, NULL, 8), sign,
                strtoll(d, NULL, 10));
  return fail(p, n, key, "expected a number without a leading 0, got %s: write it in decimal", g);
}

/* Integers are decimal or hexadecimal ("0x2a": CAN ids are written so);
 * other numbers decimal only (strtod's hex floats are not YAML). Leading
 * whitespace (a quoted " 5") is refused as strtoll would skip it. */
static int parse_number(const yaml_node_t *n, bool integer, double *out) {
  if (n->type != YAML_SCALAR_NODE || !*scalar(n) || has_nul(n)) return -1;
  const char *s = scalar(n);
  if (leading_zero(s) || !(*s == '-' || *s == '+' || *s == '.' || (*s >= '0' && *s <= '9'))) return -1;
  char *end;
  errno = 0;
  if (integer) {
    long long v = strtoll(s, &end, 0);
    if (errno || *end) return -1;
    *out = (double)v;
  } else {
    if (strpbrk(s, "xX")) return -1;
    double v = strtod(s, &end);
    if (errno == ERANGE || *end || !isfinite(v)) return -1;
    *out = v;
  }
  return 0;
}

static int set_key(struct parse *p, const struct key *k, yaml_node_t *n, struct vlff_config *cfg) {
  char g[96];
  got(n, g, sizeof g);
  /* A NUL ends the value for every C string function after it: "info\0x"
   * would read as info, "5\0x" as 5. */
  if (n->type == YAML_SCALAR_NODE && has_nul(n))
    return fail(p, n, k->path, "expected a %s without NUL bytes, got %s", k->type == T_STRING ? "string" : "value", g);
  if ((k->type == T_INT || k->type == T_DOUBLE) && n->type == YAML_SCALAR_NODE && leading_zero(scalar(n)))
    return fail_leading_zero(p, n, k->path, g);
  double v;
  switch (k->type) {
  case T_MODE: {
    const char *s = n->type == YAML_SCALAR_NODE ? scalar(n) : "";
    size_t l = strlen(s);
    if (s[0] != '0' || l > 4 || strspn(s, "01234567") != l || (v = (double)strtol(s, NULL, 8)) < k->lo || v > k->hi)
      return fail(p, n, k->path, "expected a mode in octal with its leading 0 (like 0640), at most %04o, got %s",
                  (unsigned)k->hi, g);
    *(int *)at(cfg, k) = (int)v;
    return 0;
  }
  case T_INT:
    if (parse_number(n, true, &v) || v < k->lo || v > k->hi)
      return fail(p, n, k->path, "expected integer in [%.0f, %.0f], got %s", k->lo, k->hi, g);
    *(int *)at(cfg, k) = (int)v;
    return 0;
  case T_DOUBLE:
    if (parse_number(n, false, &v) || v < k->lo || v > k->hi)
      return fail(p, n, k->path, "expected number in [%g, %g], got %s", k->lo, k->hi, g);
    *(double *)at(cfg, k) = v;
    return 0;
  case T_BOOL: {
    static const char *const yes[] = {"true", "yes", "on", NULL};
    static const char *const no[] = {"false", "no", "off", NULL};
    if (n->type == YAML_SCALAR_NODE) {
      for (int i = 0; yes[i]; i++)
        if (!strcasecmp(scalar(n), yes[i])) return *(bool *)at(cfg, k) = true, 0;
      for (int i = 0; no[i]; i++)
        if (!strcasecmp(scalar(n), no[i])) return *(bool *)at(cfg, k) = false, 0;
    }
    return fail(p, n, k->path, "expected true or false, got %s", g);
  }
  case T_STRING:
    if (n->type != YAML_SCALAR_NODE)
      return fail(p, n, k->path, "expected string, got %s", g);
    if (has_control(n)) return fail(p, n, k->path, "expected a string without control characters, got %s", g);
    if (strlen(scalar(n)) >= k->size)
      return fail(p, n, k->path, "expected string of at most %zu bytes, got %zu bytes", k->size - 1,
                  strlen(scalar(n)));
    snprintf(at(cfg, k), k->size, "%s", k->lo && !*scalar(n) ? installed_vocab() : scalar(n));
    return 0;
  case T_ENUM: {
    char opts[160] = "";
    for (int i = 0; k->names[i]; i++) {
      if (n->type == YAML_SCALAR_NODE && !strcmp(scalar(n), k->names[i]))
        return *(int *)at(cfg, k) = i, 0;
      size_t l = strlen(opts);
      snprintf(opts + l, sizeof opts - l, "%s%s", i ? "|" : "", k->names[i]);
    }
    return fail(p, n, k->path, "expected one of %s, got %s", opts, g);
  }
  case T_DVEC: {
    double tmp[8];
    if (n->type != YAML_SEQUENCE_NODE ||
        n->data.sequence.items.top - n->data.sequence.items.start != (long)k->size)
      return fail(p, n, k->path, "expected sequence of %zu numbers, got %s", k->size, g);
    for (size_t i = 0; i < k->size; i++) {
      yaml_node_t *e = yaml_document_get_node(&p->doc, n->data.sequence.items.start[i]);
      char ge[96];
      got(e, ge, sizeof ge);
      if (e->type == YAML_SCALAR_NODE && leading_zero(scalar(e)) && !has_nul(e))
        return fail_leading_zero(p, e, k->path, ge);
      if (parse_number(e, false, &tmp[i]) || tmp[i] < k->lo || tmp[i] > k->hi)
        return fail(p, e, k->path, "expected number in [%g, %g] at index %zu, got %s", k->lo, k->hi,
                    i, ge);
    }
    memcpy(at(cfg, k), tmp, k->size * sizeof(double));
    return 0;
  }
  }
  return -1;
}

/* A key with a NUL ("node.name\0zzz", a quoted scalar's escape) would
 * compare equal to the key before the NUL: refused, quoted whole. */
static int fail_nul_key(struct parse *p, const yaml_node_t *kn, const char *prefix) {
  char e[512], path[640];
  vlff_escape(e, sizeof e, scalar(kn), kn->data.scalar.length, 120);
  snprintf(path, sizeof path, "%s%s%s", prefix, prefix[0] ? "." : "", e);
  /* Written here, not through fail(): it would escape the escapes again. */
  snprintf(p->err, p->errlen, "%s:%u:%u: key '%s': expected a key without NUL bytes", p->name,
           (unsigned)kn->start_mark.line + 1, (unsigned)kn->start_mark.column + 1, path);
  return -1;
}

/* ---- the structured keys: prompts.sets, dds.merge.robots, sim.changes ----
 *
 * Each is a sequence of lo..hi mappings whose keys come from a fixed list,
 * none twice; parse_list walks it and names every fault by the entry's path
 * (prompts.sets[1].prompts) and line, and the list's own callbacks read the
 * values. */
#define LIST_MAX_KEYS 4
struct list_spec {
  const char *key;                       /* the list's config key */
  const char *noun;                      /* "prompt sets" */
  const char *const names[LIST_MAX_KEYS + 1]; /* an entry's keys, NULL-ended */
  long lo, hi;                           /* entries */
  int required;                          /* the key every entry must have (-1: none) */
  const char *required_what;             /* it, for the message: "a 'namespace'" */
  /* entry i before its keys (its defaults) */
  void (*begin)(struct vlff_config *cfg, long i);
  /* key names[k] of entry i with value vn; sub its path for messages */
  int (*value)(struct parse *p, struct vlff_config *cfg, long i, int k, yaml_node_t *vn, const char *sub);
  /* entry i after its keys, NULL if none: what it lacks otherwise */
  int (*end)(struct parse *p, struct vlff_config *cfg, long i, yaml_node_t *entry, const char *path);
};

/* "{a, b, c}" and "a, b or c" of the spec's keys. */
static void list_keys(const struct list_spec *ls, char *shape, size_t slen, char *alts, size_t alen) {
  int n = 0;
  while (ls->names[n]) n++;
  size_t s = (size_t)snprintf(shape, slen, "{"), a = 0;
  alts[0] = 0;
  for (int k = 0; k < n; k++) {
    s += (size_t)snprintf(shape + s, s < slen ? slen - s : 0, "%s%s", k ? ", " : "", ls->names[k]);
    a += (size_t)snprintf(alts + a, a < alen ? alen - a : 0, "%s%s", k == 0 ? "" : k == n - 1 ? " or " : ", ",
                          ls->names[k]);
  }
  snprintf(shape + s, s < slen ? slen - s : 0, "}");
}

static int parse_list(struct parse *p, yaml_node_t *n, const struct list_spec *ls, struct vlff_config *cfg) {
  char g[96], shape[96], alts[96];
  list_keys(ls, shape, sizeof shape, alts, sizeof alts);
  got(n, g, sizeof g);
  long count = n->type == YAML_SEQUENCE_NODE ? n->data.sequence.items.top - n->data.sequence.items.start : -1;
  if (count < 0)
    return fail(p, n, ls->key, "expected a sequence of %ld to %ld %s %s, got %s", ls->lo, ls->hi, ls->noun, shape, g);
  if (count < ls->lo || count > ls->hi)
    return fail(p, n, ls->key, "expected a sequence of %ld to %ld %s %s, got %ld", ls->lo, ls->hi, ls->noun, shape,
                count);
  for (long i = 0; i < count; i++) {
    yaml_node_t *s = yaml_document_get_node(&p->doc, n->data.sequence.items.start[i]);
    char path[64];
    snprintf(path, sizeof path, "%s[%ld]", ls->key, i);
    got(s, g, sizeof g);
    if (s->type != YAML_MAPPING_NODE) return fail(p, s, path, "expected mapping %s, got %s", shape, g);
    ls->begin(cfg, i);
    const yaml_node_t *seen[LIST_MAX_KEYS] = {NULL};
    for (yaml_node_pair_t *pr = s->data.mapping.pairs.start; pr < s->data.mapping.pairs.top; pr++) {
      yaml_node_t *kn = yaml_document_get_node(&p->doc, pr->key);
      yaml_node_t *vn = yaml_document_get_node(&p->doc, pr->value);
      if (has_nul(kn)) return fail_nul_key(p, kn, path);
      const char *kname = kn->type == YAML_SCALAR_NODE ? scalar(kn) : "";
      char sub[96];
      snprintf(sub, sizeof sub, "%s.%s", path, kname);
      int k = 0;
      while (ls->names[k] && strcmp(kname, ls->names[k])) k++;
      if (!ls->names[k]) return fail(p, kn, sub, "unknown key (expected %s)", alts);
      /* A second value would replace the first. */
      if (seen[k]) return fail(p, kn, sub, "duplicate key (first at line %u)", (unsigned)seen[k]->start_mark.line + 1);
      seen[k] = kn;
      if (ls->value(p, cfg, i, k, vn, sub)) return -1;
    }
    if (ls->required >= 0 && !seen[ls->required]) return fail(p, s, path, "expected %s, got none", ls->required_what);
    if (ls->end && ls->end(p, cfg, i, s, path)) return -1;
  }
  return 0;
}

/* prompts.sets: {name, prompts}. */
static void prompt_set_begin(struct vlff_config *cfg, long i) {
  memset(&cfg->prompts.sets[i], 0, sizeof cfg->prompts.sets[i]);
}

static int prompt_set_value(struct parse *p, struct vlff_config *cfg, long i, int k, yaml_node_t *vn, const char *sub) {
  struct vlff_prompt_set *set = &cfg->prompts.sets[i];
  char g[96];
  got(vn, g, sizeof g);
  if (k == 0) { /* name */
    if (vn->type != YAML_SCALAR_NODE || has_nul(vn) || has_control(vn) || strlen(scalar(vn)) >= VLFF_PROMPT_LEN)
      return fail(p, vn, sub, "expected string of at most %d bytes without control characters, got %s",
                  VLFF_PROMPT_LEN - 1, g);
    snprintf(set->name, sizeof set->name, "%s", scalar(vn));
    return 0;
  }
  long m = vn->type == YAML_SEQUENCE_NODE ? vn->data.sequence.items.top - vn->data.sequence.items.start : -1;
  if (m < 1 || m > VLFF_MAX_PROMPTS)
    return fail(p, vn, sub, "expected sequence of 1 to %d prompts, got %s", VLFF_MAX_PROMPTS, g);
  const char *texts[VLFF_MAX_PROMPTS];
  for (long j = 0; j < m; j++) {
    yaml_node_t *e = yaml_document_get_node(&p->doc, vn->data.sequence.items.start[j]);
    got(e, g, sizeof g);
    if (e->type != YAML_SCALAR_NODE || has_nul(e))
      return fail(p, e, sub, "expected a prompt (a string without NUL bytes) at index %ld, got %s", j, g);
    /* The set is checked as the prompt mailbox and the embeddings format
     * check theirs (UTF-8 text without control characters, 1..63 bytes,
     * none repeated), one prompt more each time: the first prompt that
     * breaks the rule is the one named. */
    texts[j] = scalar(e);
    if (vlff_prompt_check(texts, (int)j + 1) < 0)
      return fail(p, e, sub, "expected a prompt as the mailbox and embeddings files take it (%s) at index %ld, got %s",
                  vlff_shm_last_message(), j, g);
    snprintf(set->text[j], VLFF_PROMPT_LEN, "%s", scalar(e));
  }
  set->count = (int)m;
  return 0;
}

static const struct list_spec prompt_sets_spec = {
    PROMPT_SETS, "prompt sets", {"name", "prompts", NULL}, 1, VLFF_MAX_PROMPT_SETS, 1, "a 'prompts' list",
    prompt_set_begin, prompt_set_value, NULL};

static const char *dds_ns_problem(const char *s);

/* dds.merge.robots: {namespace, transform: [x, y, z, yaw]}. */
static void robot_begin(struct vlff_config *cfg, long i) {
  memset(&cfg->dds.merge.robots[i], 0, sizeof cfg->dds.merge.robots[i]);
}

static int robot_value(struct parse *p, struct vlff_config *cfg, long i, int k, yaml_node_t *vn, const char *sub) {
  struct vlff_cfg_dds_merge *m = &cfg->dds.merge;
  struct vlff_cfg_merge_robot *r = &m->robots[i];
  char g[96];
  got(vn, g, sizeof g);
  if (k == 0) { /* namespace */
    const char *why = vn->type != YAML_SCALAR_NODE || has_nul(vn) || has_control(vn) || !*scalar(vn) ||
                              strlen(scalar(vn)) >= VLFF_CFG_STR
                          ? "a string"
                          : dds_ns_problem(scalar(vn));
    if (why) return fail(p, vn, sub, "expected a ROS namespace like /robot1 (%s), got %s", why, g);
    for (long j = 0; j < i; j++)
      if (!strcmp(m->robots[j].ns, scalar(vn)))
        return fail(p, vn, sub, "expected a namespace not given before, got %s", g);
    snprintf(r->ns, sizeof r->ns, "%s", scalar(vn));
    return 0;
  }
  long n = vn->type == YAML_SEQUENCE_NODE ? vn->data.sequence.items.top - vn->data.sequence.items.start : -1;
  if (n != 4) return fail(p, vn, sub, "expected [x, y, z, yaw_deg], got %s", g);
  for (long j = 0; j < 4; j++) {
    yaml_node_t *e = yaml_document_get_node(&p->doc, vn->data.sequence.items.start[j]);
    double v, lim = j < 3 ? 1e5 : 360;
    got(e, g, sizeof g);
    if (e->type != YAML_SCALAR_NODE || parse_number(e, false, &v) || !(fabs(v) <= lim))
      return fail(p, e, sub, "expected %s within +-%g at index %ld, got %s", j < 3 ? "metres" : "degrees", lim, j, g);
    r->transform[j] = v;
  }
  r->has_transform = true;
  return 0;
}

static const struct list_spec merge_robots_spec = {
    MERGE_ROBOTS, "robots", {"namespace", "transform", NULL}, 0, VLFF_MAX_MERGE_ROBOTS, 0, "a 'namespace'",
    robot_begin, robot_value, NULL};

/* sim.changes: {time_s, object, action, to}. Which objects a scene has is
 * the simulator's to say (vlff_sim_create); here each value's form and
 * physical bounds. */
static const char SIM_CHANGES[] = "sim.changes";
static const char *const sim_actions[] = {"move", "remove", "add", NULL};

static void change_begin(struct vlff_config *cfg, long i) {
  struct vlff_sim_change *ch = &cfg->sim.changes[i];
  memset(ch, 0, sizeof *ch);
  ch->action = -1;
  ch->time_s = -1;
}

static int change_value(struct parse *p, struct vlff_config *cfg, long i, int k, yaml_node_t *vn, const char *sub) {
  struct vlff_sim_change *ch = &cfg->sim.changes[i];
  char g[96];
  got(vn, g, sizeof g);
  double v;
  switch (k) {
  case 0: /* time_s: a week of simulated time, far beyond any run */
    if (parse_number(vn, false, &v) || v < 0 || v > 604800)
      return fail(p, vn, sub, "expected number in [0, 604800] (seconds of sim time), got %s", g);
    ch->time_s = v;
    return 0;
  case 1: /* object */
    if (vn->type != YAML_SCALAR_NODE || has_nul(vn) || has_control(vn) || !*scalar(vn) ||
        strlen(scalar(vn)) >= VLFF_SIM_OBJECT_LEN)
      return fail(p, vn, sub, "expected an object name (a class, or class#n) of 1 to %d bytes, got %s",
                  VLFF_SIM_OBJECT_LEN - 1, g);
    snprintf(ch->object, sizeof ch->object, "%s", scalar(vn));
    return 0;
  case 2: /* action */
    for (int a = 0; sim_actions[a] && vn->type == YAML_SCALAR_NODE; a++)
      if (!strcmp(scalar(vn), sim_actions[a])) ch->action = a;
    if (ch->action < 0) return fail(p, vn, sub, "expected one of move|remove|add, got %s", g);
    return 0;
  default: { /* to */
    long m = vn->type == YAML_SEQUENCE_NODE ? vn->data.sequence.items.top - vn->data.sequence.items.start : -1;
    if (m != 2) return fail(p, vn, sub, "expected [x, y] in metres, got %s", g);
    for (int j = 0; j < 2; j++) {
      yaml_node_t *e = yaml_document_get_node(&p->doc, vn->data.sequence.items.start[j]);
      got(e, g, sizeof g);
      /* the field's box is bounded the same way (field.scene_min/max) */
      if (parse_number(e, false, &v) || fabs(v) > 1e4)
        return fail(p, e, sub, "expected [x, y] with each in [-10000, 10000] m, got %s at index %d", g, j);
      ch->to[j] = v;
    }
    ch->has_to = true;
    return 0;
  }
  }
}

static int change_end(struct parse *p, struct vlff_config *cfg, long i, yaml_node_t *c, const char *path) {
  const struct vlff_sim_change *ch = &cfg->sim.changes[i];
  if (ch->time_s < 0) return fail(p, c, path, "expected a 'time_s', got none");
  if (!ch->object[0]) return fail(p, c, path, "expected an 'object', got none");
  if (ch->action < 0) return fail(p, c, path, "expected an 'action' (move, remove or add), got none");
  if (ch->action == VLFF_SIM_MOVE && !ch->has_to) return fail(p, c, path, "expected a 'to' for action move, got none");
  if (ch->action == VLFF_SIM_REMOVE && ch->has_to)
    return fail(p, c, path, "expected no 'to' for action remove (it takes the object away)");
  return 0;
}

static const struct list_spec sim_changes_spec = {
    SIM_CHANGES, "changes", {"time_s", "object", "action", "to", NULL}, 0, VLFF_SIM_MAX_CHANGES, -1, NULL,
    change_begin, change_value, change_end};

static int parse_prompt_sets(struct parse *p, yaml_node_t *n, struct vlff_config *cfg) {
  if (parse_list(p, n, &prompt_sets_spec, cfg)) return -1;
  cfg->prompts.set_count = (int)(n->data.sequence.items.top - n->data.sequence.items.start);
  cfg->prompts.sets_named = true;
  return 0;
}

static int parse_merge_robots(struct parse *p, yaml_node_t *n, struct vlff_config *cfg) {
  if (parse_list(p, n, &merge_robots_spec, cfg)) return -1;
  long count = n->data.sequence.items.top - n->data.sequence.items.start;
  /* vlff-merge refuses a fleet of one at start, without the line */
  if (count == 1)
    return fail(p, n, MERGE_ROBOTS, "expected 0 (no fleet) or 2 to %d robots, got 1", VLFF_MAX_MERGE_ROBOTS);
  cfg->dds.merge.robot_count = (int)count;
  return 0;
}

static int parse_sim_changes(struct parse *p, yaml_node_t *n, struct vlff_config *cfg) {
  if (parse_list(p, n, &sim_changes_spec, cfg)) return -1;
  cfg->sim.change_count = (int)(n->data.sequence.items.top - n->data.sequence.items.start);
  return 0;
}

static bool has_prefix(const char *prefix) {
  size_t l = strlen(prefix);
  for (size_t i = 0; i < NKEYS; i++)
    if (!strncmp(schema[i].path, prefix, l) && schema[i].path[l] == '.') return true;
  return !strcmp(prefix, "prompts");
}

/* Edit distance (insertions, deletions, substitutions) of a and b[0..nb). */
static size_t edit_distance(const char *a, const char *b, size_t nb) {
  size_t row[64], na = strlen(a);
  if (na >= 64 || nb >= 64) return SIZE_MAX;
  for (size_t j = 0; j <= nb; j++) row[j] = j;
  for (size_t i = 1; i <= na; i++) {
    size_t diag = row[0];
    row[0] = i;
    for (size_t j = 1; j <= nb; j++) {
      size_t up = row[j], best = diag + (a[i - 1] != b[j - 1]);
      if (up + 1 < best) best = up + 1;
      if (row[j - 1] + 1 < best) best = row[j - 1] + 1;
      diag = up, row[j] = best;
    }
  }
  return row[nb];
}

/* The key or section of the schema nearest an unknown path (a typo: at most
 * two edits, and fewer than half its length), into out; false if none. */
static bool nearest_key(const char *path, char *out, size_t cap) {
  size_t best = 3, depth = 0;
  for (const char *c = path; *c; c++) depth += *c == '.';
  for (size_t i = 0; i < NKEYS; i++) {
    /* The schema path cut to as many components as the unknown one has. */
    const char *s = schema[i].path, *e = s;
    for (size_t d = 0; *e && (*e != '.' || d++ < depth); e++) {}
    size_t n = (size_t)(e - s), dist = edit_distance(path, s, n);
    if (dist < best && 2 * dist < strlen(path)) best = dist, snprintf(out, cap, "%.*s", (int)n, s);
  }
  return best < 3;
}

static int walk(struct parse *p, yaml_node_t *map, const char *prefix, struct vlff_config *cfg) {
  for (yaml_node_pair_t *pr = map->data.mapping.pairs.start; pr < map->data.mapping.pairs.top; pr++) {
    yaml_node_t *kn = yaml_document_get_node(&p->doc, pr->key);
    yaml_node_t *vn = yaml_document_get_node(&p->doc, pr->value);
    if (kn->type != YAML_SCALAR_NODE) return fail(p, kn, prefix[0] ? prefix : NULL, "expected a plain key");
    if (has_nul(kn)) return fail_nul_key(p, kn, prefix);
    char path[160];
    snprintf(path, sizeof path, "%s%s%s", prefix, prefix[0] ? "." : "", scalar(kn));
    /* Duplicate keys are almost always an edit mistake: refuse them. */
    for (yaml_node_pair_t *q = map->data.mapping.pairs.start; q < pr; q++) {
      yaml_node_t *qk = yaml_document_get_node(&p->doc, q->key);
      if (qk->type == YAML_SCALAR_NODE && !strcmp(scalar(qk), scalar(kn)))
        return fail(p, kn, path, "duplicate key (first at line %u)", (unsigned)qk->start_mark.line + 1);
    }
    /* The same key spelt another way (shm.ring: beside shm: {ring:}) is a
     * duplicate all the same: whichever came last would win. */
    const yaml_node_t **first = NULL;
    const struct key *k = NULL;
    for (size_t i = 0; i < NKEYS && !k; i++)
      if (!strcmp(schema[i].path, path)) k = &schema[i];
    if (k) first = &p->key_at[k - schema];
    if (!strcmp(path, PROMPT_SETS)) first = &p->sets_key;
    if (!strcmp(path, MERGE_ROBOTS)) first = &p->robots_key;
    if (!strcmp(path, SIM_CHANGES)) first = &p->changes_key;
    if (first && *first) {
      char e[256];
      vlff_escape(e, sizeof e, scalar(*first), strlen(scalar(*first)), 120);
      return fail(p, kn, path, "duplicate key (first at line %u, written '%s')", (unsigned)(*first)->start_mark.line + 1, e);
    }
    if (first) *first = kn;
    if (!strcmp(path, PROMPT_SETS)) {
      if (parse_prompt_sets(p, vn, cfg)) return -1;
      continue;
    }
    if (!strcmp(path, MERGE_ROBOTS)) {
      if (parse_merge_robots(p, vn, cfg)) return -1;
      continue;
    }
    if (!strcmp(path, SIM_CHANGES)) {
      if (parse_sim_changes(p, vn, cfg)) return -1;
      continue;
    }
    if (k) {
      if (set_key(p, k, vn, cfg)) return -1;
      p->where[k - schema] = vn;
    } else if (has_prefix(path)) {
      char g[96];
      got(vn, g, sizeof g);
      if (vn->type != YAML_MAPPING_NODE) return fail(p, vn, path, "expected a mapping, got %s", g);
      if (walk(p, vn, path, cfg)) return -1;
    } else if (!strcmp(path, "sim.feature_dim")) {
      return fail(p, kn, path, "no longer a key: the simulator renders features of field.feature_dim dimensions");
    } else {
      char near[160];
      if (nearest_key(path, near, sizeof near)) return fail(p, kn, path, "unknown key (did you mean '%s'?)", near);
      return fail(p, kn, path, "unknown key");
    }
  }
  return 0;
}

/* Cross-key checks point at the value in the file when the file set it,
 * else name the file alone: the default was combined with another key. */
static const yaml_node_t *where(struct parse *p, const char *path) {
  for (size_t i = 0; i < NKEYS; i++)
    if (!strcmp(schema[i].path, path)) return p->where[i];
  return NULL;
}

static int fail_cross(struct parse *p, const char *key, const char *fmt, ...) {
  char what[256];
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(what, sizeof what, fmt, ap);
  va_end(ap);
  const yaml_node_t *n = where(p, key);
  if (n) return fail(p, n, key, "%s", what);
  snprintf(p->err, p->errlen, "%s: key '%s': %s", p->name, key, what);
  return -1;
}

/* The same rule as the shm library's (shm/seg.c): POSIX leaves a name
 * with a second '/' implementation-defined and glibc refuses it; "." and
 * ".." would name /dev/shm itself or its parent. */
static const char *shm_name_problem(const char *s) {
  size_t l = strlen(s);
  if (s[0] != '/') return "a name starting with '/'";
  if (l < 2 || l >= 250) return "'/' followed by 1 to 248 characters";
  if (strchr(s + 1, '/')) return "no '/' after the leading one";
  if (!strcmp(s, "/.") || !strcmp(s, "/..")) return "a name other than '.' or '..'";
  return NULL;
}

static int check_shm_names(struct parse *p, struct vlff_config *cfg) {
  static const char *const keys[] = {"shm.ring", "shm.pose_ring", "shm.map", "shm.prompts", "shm.feature_ring"};
  const char *vals[] = {cfg->shm.ring, cfg->shm.pose_ring, cfg->shm.map, cfg->shm.prompts, cfg->shm.feature_ring};
  for (int i = 0; i < 5; i++) {
    const char *why = shm_name_problem(vals[i]);
    char e[256];
    vlff_escape(e, sizeof e, vals[i], strlen(vals[i]), 60);
    if (why) return fail_cross(p, keys[i], "expected a POSIX shared-memory name (%s), got '%s'", why, e);
  }
  /* Two segments of one name would replace each other (the prompt mailbox
   * overwriting the map). The later key is the one blamed. */
  for (int i = 1; i < 5; i++)
    for (int j = 0; j < i; j++)
      if (!strcmp(vals[i], vals[j]))
        return fail_cross(p, keys[i], "expected a segment name distinct from %s, got the same '%s'", keys[j],
                          VLFF_Q(vals[i]));
  return 0;
}

/* dds.namespace: "" or ROS 2's rule for a namespace ('/' then tokens of
 * letters, digits and '_' joined by single '/', none starting with a
 * digit, no '/' at the end), so that every topic name built on it is a
 * valid ROS 2 name. dds.frame_id: a tf2 frame id (no leading '/'). */
static const char *dds_ns_problem(const char *s) {
  if (!*s) return NULL;
  if (s[0] != '/') return "a leading '/'";
  for (const char *t = s + 1;; t++) {
    if (!*t || *t == '/') return "no empty token ('//' or a trailing '/')";
    if (*t >= '0' && *t <= '9') return "tokens that do not start with a digit";
    while (*t && *t != '/') {
      if (!(isalnum((unsigned char)*t) || *t == '_')) return "only letters, digits, '_' and '/'";
      t++;
    }
    if (!*t) return NULL;
  }
}

static int check_frame_id(struct parse *p, const char *key, const char *f) {
  bool ok = *f && *f != '/';
  for (const char *c = f; ok && *c; c++) ok = isalnum((unsigned char)*c) || strchr("_-./", *c);
  if (!ok)
    return fail_cross(p, key, "expected a frame id of letters, digits and _-./ not starting with '/', got '%s'",
                      VLFF_Q(f));
  return 0;
}

static int check_dds(struct parse *p, struct vlff_config *cfg) {
  const char *why = dds_ns_problem(cfg->dds.ns);
  if (why) return fail_cross(p, "dds.namespace", "expected \"\" or a ROS namespace like /robot1 (%s), got '%s'", why,
                             VLFF_Q(cfg->dds.ns));
  if (check_frame_id(p, "dds.frame_id", cfg->dds.frame_id) ||
      check_frame_id(p, "dds.camera_frame_id", cfg->dds.camera_frame_id) ||
      check_frame_id(p, "dds.merge.frame_id", cfg->dds.merge.frame_id))
    return -1;
  if (!strcmp(cfg->dds.frame_id, cfg->dds.camera_frame_id))
    return fail_cross(p, "dds.camera_frame_id", "expected a frame distinct from dds.frame_id, got the same '%s'",
                      VLFF_Q(cfg->dds.frame_id));
  /* A transient-local reader asks every writer for what it kept: a bridge
   * (re)started would post again the prompt sets some writer latched. */
  const struct vlff_cfg_dds_merge *m = &cfg->dds.merge;
  why = dds_ns_problem(m->ns);
  if (why || !*m->ns)
    return fail_cross(p, "dds.merge.namespace", "expected a ROS namespace like /fleet (%s), got '%s'",
                      why ? why : "not empty", VLFF_Q(m->ns));
  for (int i = 0; i < m->robot_count; i++)
    if (!strcmp(m->robots[i].ns, m->ns))
      return fail_cross(p, "dds.merge.namespace", "expected a namespace no robot has, got '%s'", VLFF_Q(m->ns));
  if ((why = shm_name_problem(m->map)))
    return fail_cross(p, "dds.merge.map", "expected a POSIX shared-memory name (%s), got '%s'", why, VLFF_Q(m->map));
  /* vlff-merge creates it: on a robot's computer it would replace that segment */
  const char *const shm_keys[] = {"shm.map", "shm.ring", "shm.pose_ring", "shm.prompts", "shm.feature_ring"};
  const char *const shm_vals[] = {cfg->shm.map, cfg->shm.ring, cfg->shm.pose_ring, cfg->shm.prompts,
                                  cfg->shm.feature_ring};
  for (int i = 0; i < 5; i++)
    if (!strcmp(m->map, shm_vals[i]))
      return fail_cross(p, "dds.merge.map", "expected a segment distinct from %s, got the same '%s'", shm_keys[i],
                        VLFF_Q(m->map));
  for (int a = 0; a < 3; a++)
    if (!(m->bounds[a] < m->bounds[a + 3]))
      return fail_cross(p, "dds.merge.bounds", "expected x0 y0 z0 below x1 y1 z1, got axis %d: %g..%g", a, m->bounds[a],
                        m->bounds[a + 3]);
  double voxels = 1;
  for (int a = 0; a < 3; a++) voxels *= ceil((m->bounds[a + 3] - m->bounds[a]) / m->voxel_size_m);
  if (voxels > (double)(64u << 20))
    return fail_cross(p, "dds.merge.bounds", "expected at most %u voxels of dds.merge.voxel_size_m, got %.0f",
                      64u << 20, voxels);
  if (cfg->dds.qos[VLFF_DDS_PROMPTS_IN].durability != VLFF_DDS_VOLATILE)
    return fail_cross(p, "dds.qos.prompts_in.durability",
                      "expected volatile (a transient-local reader would post again, at each start, the prompt sets "
                      "writers kept), got transient_local");
  return 0;
}

uint64_t vlff_config_dds_message_max(const struct vlff_config *cfg, int id) {
  const struct vlff_cfg_shm *m = &cfg->shm;
  const uint64_t cam = (uint64_t)m->max_width * (uint64_t)m->max_height;
  const uint64_t lab = (uint64_t)m->label_max_width * (uint64_t)m->label_max_height;
  const uint64_t o = VLFF_DDS_MSG_OVERHEAD;
  switch (id) {
  /* vlff-dds' point_step; a growing box's map carries as many far points as
   * the grid holds voxels at most (far_walk.h) */
  case VLFF_DDS_MAP: return (uint64_t)m->map_max_voxels * (cfg->field.grow && m->map_far_max_mb > 0 ? 2 : 1) * 20 + o;
  case VLFF_DDS_MAP_UPDATES: return vlff_config_dds_update_points(cfg) * 24 + o;
  case VLFF_DDS_STATUS: return VLFF_DDS_STATUS_MAX_BYTES;
  case VLFF_DDS_PROMPTS_IN: return (uint64_t)cfg->dds.max_prompt_bytes + o;
  /* a JSON list of the most prompts, each byte \u-escaped at worst */
  case VLFF_DDS_PROMPTS: return (uint64_t)VLFF_SHM_MAX_PROMPTS * (6 * (VLFF_SHM_PROMPT_LEN - 1) + 3) + o;
  case VLFF_DDS_LABEL_IMAGE: return lab * 2 + o;                  /* mono16 */
  case VLFF_DDS_LABEL_IMAGE_COMPRESSED: return lab * 4 + o;       /* PNG: RGB, a filter byte a row, zlib's blocks */
  case VLFF_DDS_CAMERA_IMAGE: return cam * 3 + o;                 /* the ring's colour plane: RGB8 at most */
  case VLFF_DDS_CAMERA_IMAGE_COMPRESSED: return cam * 4 + o;      /* JPEG at quality 100 of noise stays below */
  case VLFF_DDS_CAMERA_INFO: return 2 * o;                        /* 35 doubles, two frame ids */
  case VLFF_DDS_TF: return 2 * o;                                 /* one transform, two frame ids */
  default: return 0;
  }
}

/* The bytes of the switched-on topics' histories but map_updates', and the
 * topic whose history is the largest of them. */
static uint64_t dds_fixed_history(const struct vlff_config *cfg, int *largest) {
  uint64_t sum = 0, most = 0;
  if (largest) *largest = VLFF_DDS_MAP;
  for (int i = 0; i < VLFF_DDS_NTOPICS; i++) {
    if (i == VLFF_DDS_MAP_UPDATES || !cfg->dds.on[i]) continue;
    uint64_t h = (uint64_t)cfg->dds.qos[i].depth * vlff_config_dds_message_max(cfg, i);
    sum += h;
    if (h > most && largest) most = h, *largest = i;
  }
  return sum;
}

static uint64_t dds_history_cap(const struct vlff_config *cfg) {
  return (uint64_t)(cfg->dds.history_max_mb * 1048576.0);
}

uint64_t vlff_config_dds_update_points(const struct vlff_config *cfg) {
  uint64_t fixed = dds_fixed_history(cfg, NULL), cap = dds_history_cap(cfg);
  uint64_t depth = (uint64_t)cfg->dds.qos[VLFF_DDS_MAP_UPDATES].depth;
  /* each update's header too */
  if (!depth || fixed >= cap || cap - fixed <= depth * VLFF_DDS_MSG_OVERHEAD) return 0;
  return (cap - fixed - depth * VLFF_DDS_MSG_OVERHEAD) / (depth * 24);
}

/* Keep-last histories are bounded in samples, not bytes: a depth of 1000
 * whole maps of 2 M voxels would be 40 GB held. Each switched-on topic's
 * depth times its largest message, summed, must fit dds.history_max_mb,
 * with at least one point per update left to map/updates. */
static int check_dds_history(struct parse *p, const struct vlff_config *cfg) {
  int largest;
  uint64_t fixed = dds_fixed_history(cfg, &largest), cap = dds_history_cap(cfg);
  const double mib = 1048576.0;
  const char *key = "dds.qos.map.depth";
  for (size_t i = 0; i < NKEYS; i++)
    if (schema[i].off == F(dds.qos[0].depth) + (size_t)largest * sizeof cfg->dds.qos[0]) key = schema[i].path;
  if (fixed > cap) {
    return fail_cross(p, key,
                      "expected a history that fits dds.history_max_mb (%g MiB), got keep last %d of up to %.1f MiB "
                      "(%.1f MiB with the other topics' histories); lower the depth, switch topics off or raise "
                      "dds.history_max_mb",
                      cfg->dds.history_max_mb, cfg->dds.qos[largest].depth,
                      (double)vlff_config_dds_message_max(cfg, largest) / mib, (double)fixed / mib);
  }
  if (cfg->dds.on[VLFF_DDS_MAP_UPDATES] && vlff_config_dds_update_points(cfg) < 1)
    return fail_cross(p, "dds.qos.map_updates.depth",
                      "expected a depth whose updates fit what dds.history_max_mb (%g MiB) leaves after the other "
                      "topics' %.1f MiB, got keep last %d, which leaves no point per update",
                      cfg->dds.history_max_mb, (double)fixed / mib, cfg->dds.qos[VLFF_DDS_MAP_UPDATES].depth);
  return 0;
}

/* sim.scene_min/max given: not both all 0 (the field's box then). */
static bool sim_box_set(const struct vlff_cfg_sim *sim) {
  for (int i = 0; i < 3; i++)
    if (sim->scene_min[i] != 0 || sim->scene_max[i] != 0) return true;
  return false;
}

static int check_cross(struct parse *p, struct vlff_config *cfg) {
  if (check_dds(p, cfg) || check_dds_history(p, cfg)) return -1;
  if ((long)cfg->sim.range_first + cfg->sim.range_count > cfg->sim.frames)
    return fail_cross(p, "sim.range_count", "expected sim.range_first + sim.range_count within sim.frames (%d), got "
                      "%d + %d", cfg->sim.frames, cfg->sim.range_first, cfg->sim.range_count);
  if (cfg->sim.range_first && !cfg->sim.range_count)
    return fail_cross(p, "sim.range_count", "expected 1 or more frames with sim.range_first %d, got 0",
                      cfg->sim.range_first);
  if (cfg->sim.range_count && cfg->sim.change_count)
    return fail_cross(p, "sim.range_count", "expected 0 with sim.changes (a changing scene is streamed whole), got %d",
                      cfg->sim.range_count);
  /* A tenth of a core is a few training steps a second: below it the node
   * would hold a map it can no longer learn. */
  double b = cfg->node.cpu_budget;
  if (b > 0 && b < 0.1)
    return fail_cross(p, "node.cpu_budget", "expected 0 (no limit) or 0.1 to 256 cores, got %g", b);
  const double *q = cfg->pose.extrinsic + 3;
  double qn = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (!(fabs(qn - 1) <= 0.01))
    return fail_cross(p, "pose.extrinsic", "expected tx ty tz qx qy qz qw with a unit quaternion, got norm %g", qn);
  if (check_shm_names(p, cfg)) return -1;
  if (cfg->field.scene_box_file[0]) {
    char e[400];
    if (vlff_scene_box_read(cfg->field.scene_box_file, cfg->field.scene_min, cfg->field.scene_max, e, sizeof e))
      return fail_cross(p, "field.scene_box_file", "%s", e);
  }
  for (int i = 0; i < 3; i++)
    if (!(cfg->field.scene_min[i] < cfg->field.scene_max[i]))
      return fail_cross(p, "field.scene_max", "expected scene_max > scene_min on every axis, got axis %d with %g <= %g", i,
                  cfg->field.scene_max[i], cfg->field.scene_min[i]);
  {
    const double *lo = cfg->sim.scene_min, *hi = cfg->sim.scene_max;
    for (int i = 0; sim_box_set(&cfg->sim) && i < 3; i++)
      if (!(lo[i] < hi[i]))
        return fail_cross(p, "sim.scene_max", "expected sim.scene_max > sim.scene_min on every axis (or both all 0: "
                          "the field's box), got axis %d with %g <= %g", i, hi[i], lo[i]);
  }
  if (cfg->field.grow)
    for (int i = 0; i < 3; i++) {
      double w = cfg->field.world_limit_m;
      if (!(cfg->field.scene_min[i] >= -w && cfg->field.scene_max[i] <= w))
        return fail_cross(p, "field.scene_min", "expected the first box within field.world_limit_m (%g m) of the "
                          "origin when field.grow is on, got axis %d spanning [%g, %g]",
                          w, i, cfg->field.scene_min[i], cfg->field.scene_max[i]);
    }
  if (cfg->train.occupancy_cell_m != 0 && !cfg->field.grow)
    return fail_cross(p, "train.occupancy_cell_m", "expected 0 unless field.grow is on (a fixed box has "
                      "train.occupancy_resolution cells per axis), got %g",
                      cfg->train.occupancy_cell_m);
  if (cfg->train.occupancy_cell_m != 0 && cfg->train.occupancy_cell_m < 0.01)
    return fail_cross(p, "train.occupancy_cell_m", "expected 0 (from the first box) or a cell of 0.01-10 m, got %g",
                      cfg->train.occupancy_cell_m);
  if (cfg->prompts.active >= cfg->prompts.set_count)
    return fail_cross(p, "prompts.active", "expected an index below %d (the number of prompt sets), got %d",
                cfg->prompts.set_count, cfg->prompts.active);
  if (cfg->shm.mode & 0002)
    return fail_cross(p, "shm.mode", "expected a mode that is not world-writable, got %04o", cfg->shm.mode);
  if (cfg->field.finest_resolution < cfg->field.base_resolution)
    return fail_cross(p, "field.finest_resolution", "expected >= field.base_resolution (%d), got %d",
                cfg->field.base_resolution, cfg->field.finest_resolution);
  if (vlff_config_sim_features_misused(cfg))
    return fail_cross(p, "source.features", "sim features describe only the simulator's scene, never a camera's: "
                      "with source.kind: ring use ring (an extractor) or model, or set "
                      "source.allow_sim_features: true to force it");
  if (!strstr(cfg->prompts.templ, "{}"))
    return fail_cross(p, "prompts.template", "expected a template containing {}, got '%s'", VLFF_Q(cfg->prompts.templ));
  /* The publisher refused it at start, without the line. */
  if (cfg->publish.label_width > cfg->shm.label_max_width || cfg->publish.label_height > cfg->shm.label_max_height)
    return fail_cross(p, cfg->publish.label_width > cfg->shm.label_max_width ? "publish.label_width" : "publish.label_height",
                      "expected a label image within the map segment's shm.label_max_width x label_max_height (%dx%d), "
                      "got %dx%d",
                      cfg->shm.label_max_width, cfg->shm.label_max_height, cfg->publish.label_width,
                      cfg->publish.label_height);
  /* The store never holds more than max_keyframes: training would never start. */
  if (cfg->keyframes.start_after > cfg->keyframes.max_keyframes)
    return fail_cross(p, "keyframes.start_after",
                      "expected at most keyframes.max_keyframes (%d), the most the store holds: training would never "
                      "start, got %d",
                      cfg->keyframes.max_keyframes, cfg->keyframes.start_after);
  return 0;
}

/* A config is a few levels deep and a few hundred events long. libyaml's
 * scanner rechecks every open flow level on each token, so a file of deep
 * brackets costs the square of its depth to load: the limits are checked
 * on the event stream first, which stops at the first level too deep
 * before any of that cost is paid. The loader (yaml_parser_load) compares
 * each anchor with every earlier one, so anchors and aliases are counted
 * here too: 99,990 anchors had cost 188 s of CPU. */
static int limit_error(char *err, size_t errlen, const char *name, const yaml_mark_t *m, const char *what) {
  snprintf(err, errlen, "%s:%u:%u: %s, not a vlff config", name, (unsigned)m->line + 1, (unsigned)m->column + 1,
           what);
  return -1;
}

/* libyaml's parser compares each %TAG directive with every earlier one
 * before it hands out the document's first event, so directives are
 * counted on the token stream, a step below. Nesting is bounded here as
 * well (the scanner's cost per token grows with the flow depth); a scanner
 * error is left to the event pass, which reports the first error of the
 * file, scanner's or parser's. */
static int check_tokens(const char *buf, size_t len, const char *name, char *err, size_t errlen) {
  yaml_parser_t parser;
  if (!yaml_parser_initialize(&parser)) return snprintf(err, errlen, "%s: out of memory", name), -1;
  yaml_parser_set_input_string(&parser, (const unsigned char *)buf, len);
  int depth = 0, directives = 0, rc = 0;
  char what[96];
  for (;;) {
    yaml_token_t t;
    if (!yaml_parser_scan(&parser, &t)) break;
    yaml_token_type_t type = t.type;
    yaml_mark_t m = t.start_mark;
    yaml_token_delete(&t);
    if (type == YAML_STREAM_END_TOKEN) break;
    if (type == YAML_TAG_DIRECTIVE_TOKEN || type == YAML_VERSION_DIRECTIVE_TOKEN) {
      if (++directives > VLFF_CONFIG_MAX_DIRECTIVES) {
        snprintf(what, sizeof what, "more than %d YAML directives (%%TAG, %%YAML)", VLFF_CONFIG_MAX_DIRECTIVES);
        rc = limit_error(err, errlen, name, &m, what);
        break;
      }
    }
    if (type == YAML_BLOCK_SEQUENCE_START_TOKEN || type == YAML_BLOCK_MAPPING_START_TOKEN ||
        type == YAML_FLOW_SEQUENCE_START_TOKEN || type == YAML_FLOW_MAPPING_START_TOKEN)
      depth++;
    if (type == YAML_BLOCK_END_TOKEN || type == YAML_FLOW_SEQUENCE_END_TOKEN || type == YAML_FLOW_MAPPING_END_TOKEN)
      depth--;
    if (depth > VLFF_CONFIG_MAX_DEPTH) {
      snprintf(what, sizeof what, "nesting deeper than %d levels", VLFF_CONFIG_MAX_DEPTH);
      rc = limit_error(err, errlen, name, &m, what);
      break;
    }
  }
  yaml_parser_delete(&parser);
  return rc;
}

static int check_limits(const char *buf, size_t len, const char *name, char *err, size_t errlen) {
  if (check_tokens(buf, len, name, err, errlen)) return -1;
  yaml_parser_t parser;
  if (!yaml_parser_initialize(&parser)) return snprintf(err, errlen, "%s: out of memory", name), -1;
  yaml_parser_set_input_string(&parser, (const unsigned char *)buf, len);
  int depth = 0, rc = 0, anchors = 0, aliases = 0;
  long events = 0;
  char what[96];
  for (;;) {
    yaml_event_t ev;
    if (!yaml_parser_parse(&parser, &ev)) {
      snprintf(err, errlen, "%s:%u:%u: YAML syntax error: %s", name, (unsigned)parser.problem_mark.line + 1,
               (unsigned)parser.problem_mark.column + 1, parser.problem ? parser.problem : "unknown");
      rc = -1;
      break;
    }
    yaml_event_type_t t = ev.type;
    yaml_mark_t m = ev.start_mark;
    bool anchor = (t == YAML_SCALAR_EVENT && ev.data.scalar.anchor) ||
                  (t == YAML_SEQUENCE_START_EVENT && ev.data.sequence_start.anchor) ||
                  (t == YAML_MAPPING_START_EVENT && ev.data.mapping_start.anchor);
    yaml_event_delete(&ev);
    if (t == YAML_STREAM_END_EVENT) break;
    if (t == YAML_SEQUENCE_START_EVENT || t == YAML_MAPPING_START_EVENT) depth++;
    if (t == YAML_SEQUENCE_END_EVENT || t == YAML_MAPPING_END_EVENT) depth--;
    if (depth > VLFF_CONFIG_MAX_DEPTH) {
      snprintf(what, sizeof what, "nesting deeper than %d levels", VLFF_CONFIG_MAX_DEPTH);
      rc = limit_error(err, errlen, name, &m, what);
      break;
    }
    if (++events > VLFF_CONFIG_MAX_EVENTS) {
      snprintf(what, sizeof what, "more than %d YAML nodes", VLFF_CONFIG_MAX_EVENTS);
      rc = limit_error(err, errlen, name, &m, what);
      break;
    }
    if (anchor && ++anchors > VLFF_CONFIG_MAX_ANCHORS) {
      snprintf(what, sizeof what, "more than %d YAML anchors (&name)", VLFF_CONFIG_MAX_ANCHORS);
      rc = limit_error(err, errlen, name, &m, what);
      break;
    }
    if (t == YAML_ALIAS_EVENT && ++aliases > VLFF_CONFIG_MAX_ALIASES) {
      snprintf(what, sizeof what, "more than %d YAML aliases (*name)", VLFF_CONFIG_MAX_ALIASES);
      rc = limit_error(err, errlen, name, &m, what);
      break;
    }
  }
  yaml_parser_delete(&parser);
  return rc;
}

int vlff_config_load_mem(const char *buf, size_t len, const char *name, struct vlff_config *cfg,
                         char *err, size_t errlen) {
  name = VLFF_Q(name); /* the file's name, only ever quoted in messages below */
  struct parse p = {.name = name, .err = err, .errlen = errlen};
  struct vlff_config tmp;
  vlff_config_defaults(&tmp);
  vlff_config_defaults(cfg);
  if (check_limits(buf, len, name, err, errlen)) return -1;
  yaml_parser_t parser;
  if (!yaml_parser_initialize(&parser)) return fail(&p, NULL, NULL, "out of memory");
  yaml_parser_set_input_string(&parser, (const unsigned char *)buf, len);
  if (!yaml_parser_load(&parser, &p.doc)) {
    snprintf(err, errlen, "%s:%u:%u: YAML syntax error: %s", name,
             (unsigned)parser.problem_mark.line + 1, (unsigned)parser.problem_mark.column + 1,
             parser.problem ? parser.problem : "unknown");
    yaml_parser_delete(&parser);
    return -1;
  }
  int rc = 0;
  yaml_node_t *root = yaml_document_get_root_node(&p.doc);
  if (root) { /* an empty file is all defaults */
    if (root->type != YAML_MAPPING_NODE) {
      char g[96];
      got(root, g, sizeof g);
      rc = fail(&p, root, NULL, "expected a mapping at top level, got %s", g);
    } else {
      rc = walk(&p, root, "", &tmp);
    }
  }
  /* A document after the first would be silently ignored: refuse it. */
  if (rc == 0) {
    yaml_document_t extra;
    if (!yaml_parser_load(&parser, &extra)) {
      rc = fail(&p, NULL, NULL, "YAML syntax error after the first document");
    } else {
      if (yaml_document_get_root_node(&extra)) {
        snprintf(err, errlen, "%s:%u:%u: expected one YAML document, got more", name,
                 (unsigned)extra.start_mark.line + 1, (unsigned)extra.start_mark.column + 1);
        rc = -1;
      }
      yaml_document_delete(&extra);
    }
  }
  if (rc == 0) rc = check_cross(&p, &tmp);
  yaml_document_delete(&p.doc);
  yaml_parser_delete(&parser);
  if (rc == 0) *cfg = tmp;
  return rc;
}

const char *vlff_config_default_path(void) {
  pthread_once(&installed.once, find_installed);
  return installed.config;
}

const char *vlff_config_find(const char *path, char *err, size_t errlen) {
  if (path) return path;
  const char *env = getenv("VLFF_CONFIG");
  if (env && *env) return env;
  const char *def = vlff_config_default_path();
  if (access(def, F_OK) == 0) return def;
  snprintf(err, errlen, "no config: no --config given, $VLFF_CONFIG not set, %s: %s", def, strerror(errno));
  return NULL;
}

int vlff_config_load(const char *path, struct vlff_config *cfg, char *err, size_t errlen) {
  vlff_config_defaults(cfg);
  int fd = vlff_open_regular(path, err, errlen);
  if (fd < 0) return -1;
  FILE *f = fdopen(fd, "rb");
  if (!f) {
    snprintf(err, errlen, "%s: cannot open: %s", VLFF_Q(path), strerror(errno));
    close(fd);
    return -1;
  }
  char *buf = NULL;
  size_t cap = 0, len = 0;
  for (;;) {
    if (len == cap) {
      if (cap >= (size_t)16 << 20) {
        fclose(f);
        free(buf);
        snprintf(err, errlen, "%s: larger than 16 MiB, not a config file", VLFF_Q(path));
        return -1;
      }
      cap = cap ? cap * 2 : 8192;
      char *nb = realloc(buf, cap);
      if (!nb) {
        fclose(f);
        free(buf);
        snprintf(err, errlen, "%s: out of memory", VLFF_Q(path));
        return -1;
      }
      buf = nb;
    }
    size_t r = fread(buf + len, 1, cap - len, f);
    len += r;
    if (r == 0) break;
  }
  int bad = ferror(f);
  fclose(f);
  if (bad) {
    free(buf);
    snprintf(err, errlen, "%s: read error", VLFF_Q(path));
    return -1;
  }
  int rc = vlff_config_load_mem(buf, len, path, cfg, err, errlen);
  free(buf);
  return rc;
}

/* ---- dump and hash ------------------------------------------------------ */

/* The shortest form that reads back as the same double: 0.1, not
 * 0.10000000000000001, so that a dump can be pasted into a config; a whole
 * number as one (30, not the equally short 3e+01). */
static void put_double(FILE *out, double x) {
  char b[32];
  if (x == floor(x) && fabs(x) < 1e15) {
    fprintf(out, "%.0f", x);
    return;
  }
  for (int prec = 1; prec <= 17; prec++) {
    snprintf(b, sizeof b, "%.*g", prec, x);
    if (strtod(b, NULL) == x) break;
  }
  fputs(b, out);
}

void vlff_config_dump(const struct vlff_config *cfg, FILE *out) {
  for (size_t i = 0; i < NKEYS; i++) {
    const struct key *k = &schema[i];
    fprintf(out, "%s: ", k->path);
    switch (k->type) {
    case T_INT: fprintf(out, "%d\n", *(const int *)cat(cfg, k)); break;
    case T_MODE: fprintf(out, "0%o\n", *(const int *)cat(cfg, k)); break;
    case T_DOUBLE:
      put_double(out, *(const double *)cat(cfg, k));
      fputc('\n', out);
      break;
    case T_BOOL: fprintf(out, "%s\n", *(const bool *)cat(cfg, k) ? "true" : "false"); break;
    case T_STRING: fprintf(out, "\"%s\"\n", (const char *)cat(cfg, k)); break;
    case T_ENUM: fprintf(out, "%s\n", k->names[*(const int *)cat(cfg, k)]); break;
    case T_DVEC: {
      const double *v = cat(cfg, k);
      fputc('[', out);
      for (size_t j = 0; j < k->size; j++) {
        if (j) fputs(", ", out);
        put_double(out, v[j]);
      }
      fputs("]\n", out);
      break;
    }
    }
  }
  for (int r = 0; r < cfg->dds.merge.robot_count; r++) {
    const struct vlff_cfg_merge_robot *rb = &cfg->dds.merge.robots[r];
    fprintf(out, "%s[%d]: \"%s\" [", MERGE_ROBOTS, r, rb->ns);
    for (int j = 0; j < 4; j++) {
      if (j) fputs(", ", out);
      put_double(out, rb->transform[j]);
    }
    fputs("]\n", out);
  }
  for (int s = 0; s < cfg->prompts.set_count; s++) {
    const struct vlff_prompt_set *set = &cfg->prompts.sets[s];
    fprintf(out, "%s[%d]: \"%s\" [", PROMPT_SETS, s, set->name);
    for (int j = 0; j < set->count; j++) fprintf(out, "%s\"%s\"", j ? ", " : "", set->text[j]);
    fputs("]\n", out);
  }
  for (int c = 0; c < cfg->sim.change_count; c++) {
    const struct vlff_sim_change *ch = &cfg->sim.changes[c];
    fprintf(out, "%s[%d]: {time_s: ", SIM_CHANGES, c);
    put_double(out, ch->time_s);
    fprintf(out, ", object: \"%s\", action: %s", ch->object, sim_actions[ch->action]);
    if (ch->has_to) {
      fputs(", to: [", out);
      put_double(out, ch->to[0]);
      fputs(", ", out);
      put_double(out, ch->to[1]);
      fputc(']', out);
    }
    fputs("}\n", out);
  }
}

bool vlff_config_sim_features_misused(const struct vlff_config *cfg) {
  return cfg->source.features == VLFF_FEAT_SIM && cfg->source.kind == VLFF_SOURCE_RING &&
         !cfg->source.allow_sim_features;
}

void vlff_config_sim_box(const struct vlff_cfg_sim *sim, const struct vlff_cfg_field *field, double lo[3],
                         double hi[3]) {
  const bool set = sim_box_set(sim);
  for (int i = 0; i < 3; i++) {
    lo[i] = set ? sim->scene_min[i] : field->scene_min[i];
    hi[i] = set ? sim->scene_max[i] : field->scene_max[i];
  }
}

uint64_t vlff_config_field_hash(const struct vlff_cfg_field *field) {
  uint64_t h = VLFF_FNV1A64_INIT;
  for (size_t i = 0; i < NKEYS; i++) {
    const struct key *k = &schema[i];
    /* A path says where the box came from; the box itself is hashed. */
    if (strncmp(k->path, "field.", 6) || k->type == T_STRING) continue;
    /* The growth keys change nothing a fixed box's field learns: a fixed
     * field's hash is the one it had before they existed, so its
     * checkpoints still load. */
    if (!field->grow && (!strcmp(k->path, "field.grow") || !strcmp(k->path, "field.world_limit_m"))) continue;
    h = vlff_fnv1a64(h, k->path, strlen(k->path));
    size_t n = k->type == T_DVEC  ? k->size * sizeof(double)
               : k->type == T_INT ? sizeof(int)
               : k->type == T_BOOL ? sizeof(bool)
                                   : sizeof(double);
    /* The schema's offsets are into the whole config; this is its field section. */
    h = vlff_fnv1a64(h, (const char *)field + (k->off - offsetof(struct vlff_config, field)), n);
  }
  return h;
}
