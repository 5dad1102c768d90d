/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * vlff-merge: several robots' maps over DDS merged into one fleet map, in a
 * local map segment and over DDS (merge.h), until SIGINT/SIGTERM.
 */
#include "cli.h"
#include "config.h"
#include "dds.h"
#include "log.h"
#include "merge.h"
#include "vlff/escape.h"

#include <dds/dds.h>
#include <errno.h>
#include <getopt.h>
#include <inttypes.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "sensor_msgs.h"
#include "std_msgs.h"

#define TAG "merge"

static const struct vlff_cli cli = {
    "vlff-merge",
    "Usage: vlff-merge [OPTIONS]\n"
    "Merge the maps that robots' vlff-dds publish (<NS>/vlff/map, <NS>/vlff/prompts) into\n"
    "one map in a shared world frame: each voxel takes the label of the most confident\n"
    "robot point in it (the most recent on a tie). The fleet map goes into the map\n"
    "segment NAME (read it with vlff-shm like a node's) and over DDS as\n"
    "<namespace>/vlff/map and <namespace>/vlff/prompts. The robots, segment, box and\n"
    "namespace are the config's dds.merge; the options below replace them.\n"
    "\n"
    "  -r, --robot NS[@X,Y,Z,YAW]  a robot's namespace and its map -> world transform:\n"
    "                          translation in m, yaw about +z in degrees (default 0,0,0,0);\n"
    "                          2 to 8 robots, all of them (dds.merge.robots)\n"
    "  -m, --map NAME          the fleet's map segment, created (dds.merge.map)\n"
    "  -b, --bounds X0,Y0,Z0,X1,Y1,Z1  the world box the fleet map covers, m (dds.merge.bounds)\n"
    "      --voxel S           voxel size, m, 0.01..10 (dds.merge.voxel_size_m)\n"
    "  -c, --config FILE       the config (default: $VLFF_CONFIG, then the installed vlff.yaml,\n"
    "                          else the defaults); also dds.domain_id and dds.frame_id\n"
    "  -n, --namespace NS      the fleet's ROS namespace (dds.merge.namespace)\n"
    "      --seconds S         stop after S seconds\n"
    "  -v, --verbose           log each merge\n"
    "  -V, --version           print the version and exit\n"
    "  -h, --help              print this help and exit\n"
    "\n"
    "Examples:\n"
    "  vlff-merge -c /etc/vlff/fleet.yaml\n"
    "  vlff-merge -r /robot1 -r /robot2@4.0,0,0,90 -m /vlff-fleet -b -5,-5,-1,10,10,3\n",
};

enum { OPT_VOXEL = 256, OPT_SECONDS };

static int parse_doubles(const char *s, double *out, int n) {
  for (int i = 0; i < n; i++) {
    char *end;
    errno = 0;
    out[i] = strtod(s, &end);
    if (errno || end == s || !isfinite(out[i]) || (i < n - 1 ? *end != ',' : *end != 0)) return -1;
    s = end + 1;
  }
  return 0;
}

/* A namespace by the config's rule (dds.namespace), via a config of its own. */
static int check_ns(const char *ns, char *err, size_t errlen) {
  static struct vlff_config tmp;
  char yaml[600];
  if (strlen(ns) > 200 || strchr(ns, '\'') || strchr(ns, '\n')) {
    snprintf(err, errlen, "namespace '%s': expected a ROS namespace like /robot1", VLFF_Q(ns));
    return -1;
  }
  snprintf(yaml, sizeof yaml, "dds:\n  namespace: '%s'\n", ns);
  return vlff_config_load_mem(yaml, strlen(yaml), "(namespace)", &tmp, err, errlen);
}

struct robot_io {
  dds_entity_t map_r, prompts_r, updates_r;
  uint64_t warn;
};

/* Reliable and transient local, keeping depth samples (the updates: as many
 * as a robot's vlff-dds keeps for late joiners, by default). */
static dds_entity_t reader(dds_entity_t pp, const dds_topic_descriptor_t *d, const char *ns, const char *leaf,
                           int depth) {
  char name[300];
  if (vlff_dds_topic(name, sizeof name, ns, leaf) < 0) return -1;
  dds_entity_t t = dds_create_topic(pp, d, name, NULL, NULL);
  if (t < 0) return t;
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_durability(q, DDS_DURABILITY_TRANSIENT_LOCAL);
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, depth);
  dds_entity_t r = dds_create_reader(pp, t, q, NULL);
  dds_delete_qos(q);
  return r;
}

static dds_entity_t writer(dds_entity_t pp, const dds_topic_descriptor_t *d, const char *ns, const char *leaf) {
  char name[300];
  if (vlff_dds_topic(name, sizeof name, ns, leaf) < 0) return -1;
  dds_entity_t t = dds_create_topic(pp, d, name, NULL, NULL);
  if (t < 0) return t;
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_durability(q, DDS_DURABILITY_TRANSIENT_LOCAL);
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 1);
  dds_entity_t w = dds_create_writer(pp, t, q, NULL);
  dds_delete_qos(q);
  return w;
}

/* New samples of one robot: 1 when its map or prompt list changed. */
static int take_robot(struct vlff_merge_robot *r, struct robot_io *io) {
  int changed = 0;
  void *s[1];
  dds_sample_info_t info;
  char why[256];
  for (;;) {
    s[0] = NULL;
    if (dds_take(io->prompts_r, s, &info, 1, 1) <= 0) break;
    if (info.valid_data) {
      const char *data = ((const std_msgs_msg_dds__String_ *)s[0])->data;
      char texts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
      int idx, invalid, n = -1;
      size_t len = strlen(data);
      if (len > 16384)
        snprintf(why, sizeof why, "%zu bytes, more than 16384", len);
      else
        n = vlff_dds_parse_prompts(data, len, texts, &idx, &invalid, why, sizeof why);
      if (n <= 0) {
        r->refused++;
        vlff_warn_limited(&io->warn, TAG, "%s: prompt list refused: %s", r->ns, n == 0 ? "a set index" : why);
      } else {
        memcpy(r->prompts, texts, sizeof texts);
        r->nprompts = n;
        changed = 1;
      }
    }
    dds_return_loan(io->prompts_r, s, 1);
  }
  for (;;) {
    s[0] = NULL;
    if (dds_take(io->map_r, s, &info, 1, 1) <= 0) break;
    if (info.valid_data) {
      const sensor_msgs_msg_dds__PointCloud2_ *m = s[0];
      const char *names[5] = {NULL};
      uint32_t offs[5] = {0};
      uint8_t types[5] = {0};
      uint32_t nf = m->fields._length;
      for (uint32_t i = 0; i < nf && i < 5; i++)
        names[i] = m->fields._buffer[i].name, offs[i] = m->fields._buffer[i].offset,
        types[i] = m->fields._buffer[i].count == 1 ? m->fields._buffer[i].datatype : 0;
      int64_t stamp = (int64_t)m->header.stamp.sec * 1000000000 + m->header.stamp.nanosec;
      if (vlff_merge_take_cloud(r, m->width, m->height, m->point_step, m->is_bigendian, names, offs, types, nf,
                                m->data._buffer, m->data._length, stamp, why, sizeof why) < 0) {
        r->refused++;
        vlff_warn_limited(&io->warn, TAG, "%s: map refused: %s", r->ns, why);
      } else {
        changed = 1;
      }
    }
    dds_return_loan(io->map_r, s, 1);
  }
  /* Updates wait in the reader until a whole map is held to apply them to
   * (marked read meanwhile, so that they do not wake the loop again). */
  if (!r->xyz) {
    void *b[16] = {NULL};
    dds_sample_info_t bi[16];
    dds_return_t k;
    while ((k = dds_read_mask(io->updates_r, b, bi, 16, 16, DDS_NOT_READ_SAMPLE_STATE)) > 0)
      dds_return_loan(io->updates_r, b, k);
  }
  for (; r->xyz;) {
    s[0] = NULL;
    if (dds_take(io->updates_r, s, &info, 1, 1) <= 0) break;
    if (info.valid_data) {
      const sensor_msgs_msg_dds__PointCloud2_ *m = s[0];
      const char *names[6] = {NULL};
      uint32_t offs[6] = {0};
      uint8_t types[6] = {0};
      uint32_t nf = m->fields._length;
      for (uint32_t i = 0; i < nf && i < 6; i++)
        names[i] = m->fields._buffer[i].name, offs[i] = m->fields._buffer[i].offset,
        types[i] = m->fields._buffer[i].count == 1 ? m->fields._buffer[i].datatype : 0;
      int64_t stamp = (int64_t)m->header.stamp.sec * 1000000000 + m->header.stamp.nanosec;
      int rc = vlff_merge_take_update(r, m->width, m->height, m->point_step, m->is_bigendian, names, offs, types, nf,
                                      m->data._buffer, m->data._length, stamp, why, sizeof why);
      if (rc < 0) {
        r->refused++;
        vlff_warn_limited(&io->warn, TAG, "%s: map update refused: %s", r->ns, why);
      } else if (rc > 0) {
        changed = 1;
      }
    }
    dds_return_loan(io->updates_r, s, 1);
  }
  return changed;
}

int main(int argc, char **argv) {
  static const struct option opts[] = {{"robot", required_argument, NULL, 'r'},
                                       {"map", required_argument, NULL, 'm'},
                                       {"bounds", required_argument, NULL, 'b'},
                                       {"voxel", required_argument, NULL, OPT_VOXEL},
                                       {"config", required_argument, NULL, 'c'},
                                       {"namespace", required_argument, NULL, 'n'},
                                       {"seconds", required_argument, NULL, OPT_SECONDS},
                                       {"verbose", no_argument, NULL, 'v'},
                                       VLFF_CLI_COMMON_OPTIONS};
  static struct vlff_merge_robot robots[VLFF_MERGE_MAX_ROBOTS];
  static struct robot_io io[VLFF_MERGE_MAX_ROBOTS];
  int nrobots = 0, c, status;
  const char *out = NULL, *path = NULL, *fleet_ns = NULL;
  double bounds[6], voxel = 0, seconds = 0;
  bool have_bounds = false, have_voxel = false, verbose = false;
  char err[1024];
  while ((c = vlff_cli_next(&cli, argc, argv, "r:m:b:c:n:v", opts, &status)) != -1) {
    char *end;
    switch (c) {
    case VLFF_CLI_EXIT: return status;
    case 'r': {
      if (nrobots >= VLFF_MERGE_MAX_ROBOTS) return vlff_cli_usage_error(&cli, "more than %d robots", VLFF_MERGE_MAX_ROBOTS);
      struct vlff_merge_robot *r = &robots[nrobots];
      const char *at = strchr(optarg, '@');
      size_t l = at ? (size_t)(at - optarg) : strlen(optarg);
      if (l >= sizeof r->ns) return vlff_cli_usage_error(&cli, "--robot '%s': namespace too long", VLFF_Q(optarg));
      memcpy(r->ns, optarg, l);
      r->ns[l] = 0;
      double tf[4] = {0, 0, 0, 0};
      if (at && (parse_doubles(at + 1, tf, 4) < 0 || fabs(tf[0]) > 1e5 || fabs(tf[1]) > 1e5 || fabs(tf[2]) > 1e5 ||
                 fabs(tf[3]) > 360))
        return vlff_cli_usage_error(&cli, "--robot '%s': expected NS@X,Y,Z,YAW (m within +-1e5, degrees within +-360)",
                                    VLFF_Q(optarg));
      if (check_ns(r->ns, err, sizeof err)) return vlff_cli_usage_error(&cli, "--robot: %s", err);
      for (int i = 0; i < nrobots; i++)
        if (!strcmp(robots[i].ns, r->ns)) return vlff_cli_usage_error(&cli, "--robot '%s' given twice", VLFF_Q(r->ns));
      memcpy(r->t, tf, sizeof r->t);
      r->yaw = tf[3] * 3.14159265358979323846 / 180;
      r->nprompts = -1;
      nrobots++;
      break;
    }
    case 'm': out = optarg; break;
    case 'b':
      if (parse_doubles(optarg, bounds, 6) < 0)
        return vlff_cli_usage_error(&cli, "--bounds '%s': expected six numbers X0,Y0,Z0,X1,Y1,Z1", VLFF_Q(optarg));
      have_bounds = true;
      break;
    case OPT_VOXEL:
      if (parse_doubles(optarg, &voxel, 1) < 0)
        return vlff_cli_usage_error(&cli, "--voxel '%s' is not a number", VLFF_Q(optarg));
      have_voxel = true;
      break;
    case 'c': path = optarg; break;
    case 'n': fleet_ns = optarg; break;
    case 'v': verbose = true; break;
    case OPT_SECONDS:
      errno = 0;
      seconds = strtod(optarg, &end);
      if (errno || end == optarg || *end || !(seconds > 0 && seconds <= 1e9))
        return vlff_cli_usage_error(&cli, "--seconds '%s' is not a number in (0, 1e9]", VLFF_Q(optarg));
      break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", VLFF_Q(argv[optind - 1]));
    }
  }
  if (optind != argc) return vlff_cli_usage_error(&cli, "unexpected argument '%s'", VLFF_Q(argv[optind]));
  static struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  const char *found = vlff_config_find(path, err, sizeof err);
  if (found && vlff_config_load(found, &cfg, err, sizeof err)) return vlff_cli_config_error(err);
  /* The config's fleet where the command line does not replace it. */
  const struct vlff_cfg_dds_merge *cm = &cfg.dds.merge;
  if (!nrobots)
    for (int i = 0; i < cm->robot_count && i < VLFF_MERGE_MAX_ROBOTS; i++, nrobots++) {
      snprintf(robots[i].ns, sizeof robots[i].ns, "%s", cm->robots[i].ns);
      memcpy(robots[i].t, cm->robots[i].transform, sizeof robots[i].t);
      robots[i].yaw = cm->robots[i].transform[3] * 3.14159265358979323846 / 180;
      robots[i].nprompts = -1;
    }
  if (!out) out = cm->map;
  /* One of the node's segments on this machine: creating it would replace it
   * (the config refuses them for dds.merge.map). */
  const char *const shm_keys[] = {"shm.map", "shm.ring", "shm.pose_ring", "shm.prompts", "shm.feature_ring"};
  const char *const shm_vals[] = {cfg.shm.map, cfg.shm.ring, cfg.shm.pose_ring, cfg.shm.prompts, cfg.shm.feature_ring};
  for (int i = 0; i < 5; i++)
    if (!strcmp(out, shm_vals[i]))
      return vlff_cli_usage_error(&cli, "--map '%s': expected a segment distinct from %s, the node's", VLFF_Q(out),
                                  shm_keys[i]);
  if (!fleet_ns) fleet_ns = cm->ns;
  if (!have_bounds) memcpy(bounds, cm->bounds, sizeof bounds);
  if (!have_voxel) voxel = cm->voxel_size_m;
  if (nrobots < 2)
    return vlff_cli_usage_error(&cli, "expected 2 to %d robots (--robot or dds.merge.robots), got %d",
                                VLFF_MERGE_MAX_ROBOTS, nrobots);
  if (check_ns(fleet_ns, err, sizeof err)) return vlff_cli_usage_error(&cli, "--namespace: %s", err);
  for (int i = 0; i < nrobots; i++)
    if (!strcmp(robots[i].ns, fleet_ns))
      return vlff_cli_usage_error(&cli, "--namespace '%s' is a robot's", VLFF_Q(fleet_ns));
  static struct vlff_merge_grid g;
  if (vlff_merge_grid_init(&g, bounds, bounds + 3, voxel, err, sizeof err))
    return vlff_cli_usage_error(&cli, "--bounds/--voxel: %s", err);

  vlff_log_set_level(verbose ? VLFF_LOG_DEBUG : (enum vlff_log_level)cfg.node.log_level);
  vlff_cli_catch_stop();
  struct vlff_map_params mp = {g.dims[0] * g.dims[1] * g.dims[2], 0, 0, {0, NULL}};
  struct vlff_map *map = vlff_map_create(out, &mp);
  if (!map) return vlff_cli_error(&cli, "map segment '%s': %s", VLFF_Q(out), vlff_shm_last_message());
  dds_entity_t pp = dds_create_participant((dds_domainid_t)cfg.dds.domain_id, NULL, NULL);
  if (pp < 0) return vlff_cli_error(&cli, "DDS participant: %s", dds_strretcode(pp));
  dds_entity_t ws = dds_create_waitset(pp);
  for (int i = 0; i < nrobots; i++) {
    io[i].map_r = reader(pp, &sensor_msgs_msg_dds__PointCloud2__desc, robots[i].ns, "map", 1);
    io[i].prompts_r = reader(pp, &std_msgs_msg_dds__String__desc, robots[i].ns, "prompts", 1);
    io[i].updates_r = reader(pp, &sensor_msgs_msg_dds__PointCloud2__desc, robots[i].ns, "map/updates", 1000);
    if (io[i].map_r < 0 || io[i].prompts_r < 0 || io[i].updates_r < 0)
      return vlff_cli_error(&cli, "%s: DDS readers", robots[i].ns);
    dds_waitset_attach(ws, dds_create_readcondition(io[i].map_r, DDS_ANY_STATE), 0);
    dds_waitset_attach(ws, dds_create_readcondition(io[i].prompts_r, DDS_ANY_STATE), 0);
    dds_waitset_attach(ws, dds_create_readcondition(io[i].updates_r, DDS_NOT_READ_SAMPLE_STATE), 0);
  }
  dds_entity_t map_w = writer(pp, &sensor_msgs_msg_dds__PointCloud2__desc, fleet_ns, "map");
  dds_entity_t prompts_w = writer(pp, &std_msgs_msg_dds__String__desc, fleet_ns, "prompts");
  if (map_w < 0 || prompts_w < 0) return vlff_cli_error(&cli, "%s: DDS writers", fleet_ns);
  VLFF_INFO(TAG, "domain %d: %d robots into %s and %s/vlff/map, %u x %u x %u voxels of %.3f m", cfg.dds.domain_id,
            nrobots, out, fleet_ns, g.dims[0], g.dims[1], g.dims[2], voxel);
  uint64_t merges = 0, warn_pub = 0;
  struct timespec t0;
  clock_gettime(CLOCK_MONOTONIC, &t0);
  while (!vlff_cli_stop) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    if (seconds > 0 && (double)(t.tv_sec - t0.tv_sec) + 1e-9 * (double)(t.tv_nsec - t0.tv_nsec) >= seconds) break;
    dds_waitset_wait(ws, NULL, 0, DDS_MSECS(200));
    int changed = 0;
    for (int i = 0; i < nrobots; i++) changed |= take_robot(&robots[i], &io[i]);
    if (!changed) {
      vlff_map_heartbeat(map);
      continue;
    }
    size_t labelled = vlff_merge_compute(&g, robots, nrobots);
    const char *texts[VLFF_SHM_MAX_PROMPTS];
    for (int i = 0; i < g.nprompts; i++) texts[i] = g.prompts[i];
    struct vlff_map_grid grid = {{g.origin[0], g.origin[1], g.origin[2]}, g.voxel, {g.dims[0], g.dims[1], g.dims[2]},
                                 g.labels, g.conf};
    struct vlff_map_update up = {.grid = &grid, .prompts = texts, .prompt_count = g.nprompts};
    if (vlff_map_publish(map, &up) < 0)
      vlff_warn_limited(&warn_pub, TAG, "map segment %s: %s", out, vlff_shm_last_message());
    /* the same over DDS, as vlff-dds sends a robot's */
    struct vlff_map_info info = {0};
    info.version = vlff_map_version(map);
    info.grid = grid;
    uint8_t *data;
    uint32_t n;
    if (vlff_dds_cloud(&info, &data, &n) == 0) {
      sensor_msgs_msg_dds__PointField_ fields[5] = {
          {"x", 0, VLFF_DDS_FLOAT32, 1},     {"y", 4, VLFF_DDS_FLOAT32, 1},          {"z", 8, VLFF_DDS_FLOAT32, 1},
          {"label", 12, VLFF_DDS_UINT16, 1}, {"confidence", 16, VLFF_DDS_FLOAT32, 1}};
      struct timespec rt;
      clock_gettime(CLOCK_REALTIME, &rt);
      sensor_msgs_msg_dds__PointCloud2_ msg = {0};
      msg.header.stamp.sec = (int32_t)rt.tv_sec;
      msg.header.stamp.nanosec = (uint32_t)rt.tv_nsec;
      msg.header.frame_id = cfg.dds.frame_id;
      msg.height = 1, msg.width = n;
      msg.fields._length = msg.fields._maximum = 5;
      msg.fields._buffer = fields;
      msg.point_step = VLFF_DDS_POINT_STEP, msg.row_step = n * VLFF_DDS_POINT_STEP;
      msg.data._length = msg.data._maximum = msg.row_step;
      msg.data._buffer = data;
      msg.is_dense = true;
      dds_return_t rc = dds_write(map_w, &msg);
      if (rc < 0) vlff_warn_limited(&warn_pub, TAG, "fleet map write: %s", dds_strretcode(rc));
      free(data);
    }
    char *json = vlff_dds_prompt_list_json(texts, g.nprompts);
    if (json) {
      std_msgs_msg_dds__String_ s = {json};
      dds_write(prompts_w, &s);
      free(json);
    }
    merges++;
    VLFF_DEBUG(TAG, "merge %" PRIu64 ": %zu labelled voxels, %d labels, %" PRIu64 " points outside the bounds",
               merges, labelled, g.nprompts, g.outside);
  }
  uint64_t refused = 0;
  for (int i = 0; i < nrobots; i++) refused += robots[i].refused;
  VLFF_INFO(TAG, "stopping: %" PRIu64 " merges, %" PRIu64 " robot messages refused", merges, refused);
  dds_delete(pp);
  vlff_map_detach(map);
  for (int i = 0; i < nrobots; i++) vlff_merge_robot_free(&robots[i]);
  vlff_merge_grid_free(&g);
  return 0;
}
