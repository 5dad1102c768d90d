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
#include "tf2_msgs.h"

#define TAG "merge"

static const struct vlff_cli cli = {
    "vlff-merge",
    "Usage: vlff-merge [OPTIONS]\n"
    "Merge the maps that robots' vlff-dds publish (<NS>/vlff/map, <NS>/vlff/prompts) into\n"
    "one map in a shared world frame: each voxel takes the label with the most evidence\n"
    "among the robot points in it (their confidences summed, newer ones and those\n"
    "nearer the robot's camera path, from its <NS>/tf, weighted up; dds.merge.half_life_s).\n"
    "The fleet map goes into the map\n"
    "segment NAME (read it with vlff-shm like a node's) and over DDS as\n"
    "<namespace>/vlff/map and <namespace>/vlff/prompts. The robots, segment, box and\n"
    "namespace are the config's dds.merge; the options below replace them.\n"
    "\n"
    "  -r, --robot NS[@X,Y,Z,YAW]  a robot's namespace and its map -> world transform:\n"
    "                          translation in m, yaw about +z in degrees; without one, the\n"
    "                          transform FRAME -> its map's frame it publishes on <NS>/tf_static\n"
    "                          or <NS>/tf (the identity until one comes); 2 to 8 robots, all\n"
    "                          of them (dds.merge.robots)\n"
    "  -m, --map NAME          the fleet's map segment, created (dds.merge.map)\n"
    "  -b, --bounds X0,Y0,Z0,X1,Y1,Z1  the world box the fleet map covers, m (dds.merge.bounds)\n"
    "      --voxel S           voxel size, m, 0.01..10 (dds.merge.voxel_size_m)\n"
    "  -c, --config FILE       the config (default: $VLFF_CONFIG, then the installed vlff.yaml,\n"
    "                          else the defaults); also dds.domain_id and dds.frame_id\n"
    "  -n, --namespace NS      the fleet's ROS namespace (dds.merge.namespace)\n"
    "      --frame-id FRAME    the fleet's world frame (dds.merge.frame_id, default world)\n"
    "      --seconds S         stop after S seconds\n"
    "  -v, --verbose           log each merge\n"
    "  -V, --version           print the version and exit\n"
    "  -h, --help              print this help and exit\n"
    "\n"
    "Examples:\n"
    "  vlff-merge -c /etc/vlff/fleet.yaml\n"
    "  vlff-merge -r /robot1 -r /robot2@4.0,0,0,90 -m /vlff-fleet -b -5,-5,-1,10,10,3\n",
};

enum { OPT_VOXEL = 256, OPT_SECONDS, OPT_FRAME };

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

/* A transform parent -> child a robot published, parent the fleet's frame. */
struct robot_tf {
  char child[128];
  double rot[9], t[3];
};

struct robot_io {
  dds_entity_t map_r, prompts_r, updates_r, tf_r, tf_static_r; /* tf_static only without a configured transform */
  bool configured;     /* its transform from the config or the command line: tf not read */
  char frame[128];     /* its map's frame_id, from its last whole map */
  struct robot_tf tfs[8]; /* what it published with the fleet's frame as parent, by child */
  int ntfs, tf_used;   /* tf_used: the index of tfs in force, -1 none (the identity) */
  uint32_t left_out_logged; /* its texts left out of the fleet's list, as last logged */
  uint64_t warn;
};

/* Reliable, keeping depth samples (the updates: as many as a robot's
 * vlff-dds keeps for late joiners, by default); transient local to get what
 * writers kept, the latched map, list and static transforms. */
static dds_entity_t endpoint(dds_entity_t pp, const dds_topic_descriptor_t *d, const char *name, bool latched,
                             int depth, bool write) {
  dds_entity_t t = dds_create_topic(pp, d, name, NULL, NULL);
  if (t < 0) return t;
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_durability(q, latched ? DDS_DURABILITY_TRANSIENT_LOCAL : DDS_DURABILITY_VOLATILE);
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, depth);
  dds_entity_t e = write ? dds_create_writer(pp, t, q, NULL) : dds_create_reader(pp, t, q, NULL);
  dds_delete_qos(q);
  return e;
}

static dds_entity_t leaf_endpoint(dds_entity_t pp, const dds_topic_descriptor_t *d, const char *ns, const char *leaf,
                                  int depth, bool write) {
  char name[300];
  if (vlff_dds_topic(name, sizeof name, ns, leaf) < 0) return -1;
  return endpoint(pp, d, name, true, depth, write);
}

/* A PointCloud2's fields as vlff_merge_take_cloud/_update take them (at most
 * 6 looked at: more is refused there by their count). */
struct cloud_fields {
  const char *names[6];
  uint32_t offs[6], n;
  uint8_t types[6];
  int64_t stamp;
};

static void cloud_fields(const sensor_msgs_msg_dds__PointCloud2_ *m, struct cloud_fields *f) {
  memset(f, 0, sizeof *f);
  f->n = m->fields._length;
  for (uint32_t i = 0; i < f->n && i < 6; i++)
    f->names[i] = m->fields._buffer[i].name, f->offs[i] = m->fields._buffer[i].offset,
    f->types[i] = m->fields._buffer[i].count == 1 ? m->fields._buffer[i].datatype : 0;
  f->stamp = (int64_t)m->header.stamp.sec * 1000000000 + m->header.stamp.nanosec;
}

/* A TFMessage: each transform from the fleet's frame kept by child frame.
 * 1 when one changed. */
static int take_tf(struct vlff_merge_robot *r, struct robot_io *io, const tf2_msgs_msg_dds__TFMessage_ *m,
                   const char *world) {
  int changed = 0;
  char why[200];
  for (uint32_t i = 0; i < m->transforms._length; i++) {
    const geometry_msgs_msg_dds__TransformStamped_ *ts = &m->transforms._buffer[i];
    const geometry_msgs_msg_dds__Vector3_ *v = &ts->transform.translation;
    if (ts->header.frame_id && !strcmp(ts->header.frame_id, io->frame)) {
      /* its map -> its camera (vlff-dds's pose): where it has been */
      const double at[3] = {v->x, v->y, v->z};
      int k = vlff_merge_add_path(r, at);
      if (k < 0) {
        r->refused++;
        vlff_warn_limited(&io->warn, TAG, "%s: camera pose refused: position (%g %g %g) not within +-1e5 m", r->ns,
                          at[0], at[1], at[2]);
      }
      changed |= k > 0;
      continue;
    }
    if (!ts->header.frame_id || strcmp(ts->header.frame_id, world) || !ts->child_frame_id) continue;
    const geometry_msgs_msg_dds__Quaternion_ *qq = &ts->transform.rotation;
    double q[4] = {qq->x, qq->y, qq->z, qq->w}, rot[9], t[3] = {v->x, v->y, v->z};
    int bad = vlff_merge_quat(rot, q, why, sizeof why);
    if (!bad && !(fabs(t[0]) <= 1e5 && fabs(t[1]) <= 1e5 && fabs(t[2]) <= 1e5))
      bad = 1, snprintf(why, sizeof why, "translation (%g %g %g): expected metres within +-1e5", t[0], t[1], t[2]);
    if (!bad && (strlen(ts->child_frame_id) >= sizeof io->tfs[0].child || !*ts->child_frame_id))
      bad = 1, snprintf(why, sizeof why, "child frame: expected 1 to %zu bytes", sizeof io->tfs[0].child - 1);
    if (bad) {
      r->refused++;
      vlff_warn_limited(&io->warn, TAG, "%s: transform %s -> %s refused: %s", r->ns, world,
                        VLFF_Q(ts->child_frame_id ? ts->child_frame_id : ""), why);
      continue;
    }
    int k = 0;
    while (k < io->ntfs && strcmp(io->tfs[k].child, ts->child_frame_id)) k++;
    if (k == io->ntfs) {
      if (k == (int)(sizeof io->tfs / sizeof io->tfs[0])) continue; /* frames beyond 8 children of the world: not a map's */
      snprintf(io->tfs[k].child, sizeof io->tfs[k].child, "%s", ts->child_frame_id);
      io->ntfs++;
    }
    if (memcmp(io->tfs[k].rot, rot, sizeof rot) || memcmp(io->tfs[k].t, t, sizeof t)) changed = 1;
    memcpy(io->tfs[k].rot, rot, sizeof rot);
    memcpy(io->tfs[k].t, t, sizeof t);
  }
  return changed;
}

/* The robot's transform from what it published: world -> its map's frame,
 * the identity until that comes. 1 when it changed. */
static int choose_tf(struct vlff_merge_robot *r, struct robot_io *io, const char *world) {
  if (io->configured) return 0;
  int k = 0;
  while (k < io->ntfs && strcmp(io->tfs[k].child, io->frame)) k++;
  static const double eye[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1}, zero[3] = {0, 0, 0};
  const double *rot = k < io->ntfs ? io->tfs[k].rot : eye, *t = k < io->ntfs ? io->tfs[k].t : zero;
  if (!memcmp(r->rot, rot, sizeof r->rot) && !memcmp(r->t, t, sizeof r->t)) return 0;
  memcpy(r->rot, rot, sizeof r->rot);
  memcpy(r->t, t, sizeof r->t);
  if ((k < io->ntfs) != (io->tf_used >= 0) || k < io->ntfs)
    VLFF_INFO(TAG, "%s: map -> world from its tf: %s -> %s, t (%.3f %.3f %.3f)", r->ns, world,
              k < io->ntfs ? VLFF_Q(io->frame) : "(none: the identity)", t[0], t[1], t[2]);
  io->tf_used = k < io->ntfs ? k : -1;
  return 1;
}

/* Takes every sample of reader rd, calling take(sample) on valid ones; ORs
 * their results. */
#define TAKE_ALL(rd, type, take)                                                                                       \
  for (;;) {                                                                                                           \
    void *s_[1] = {NULL};                                                                                              \
    dds_sample_info_t i_;                                                                                              \
    if (dds_take(rd, s_, &i_, 1, 1) <= 0) break;                                                                       \
    if (i_.valid_data) {                                                                                               \
      const type *m = s_[0];                                                                                           \
      take;                                                                                                            \
    }                                                                                                                  \
    dds_return_loan(rd, s_, 1);                                                                                        \
  }

static int take_prompts(struct vlff_merge_robot *r, struct robot_io *io, const char *data) {
  char texts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN], why[256];
  int idx, invalid, n = -1;
  size_t len = strlen(data);
  if (len > 16384)
    snprintf(why, sizeof why, "%zu bytes, more than 16384", len);
  else
    n = vlff_dds_parse_prompts(data, len, texts, &idx, &invalid, why, sizeof why);
  if (n <= 0) {
    r->refused++;
    vlff_warn_limited(&io->warn, TAG, "%s: prompt list refused: %s", r->ns, n == 0 ? "a set index" : why);
    return 0;
  }
  memcpy(r->prompts, texts, sizeof texts);
  r->nprompts = n;
  return 1;
}

static int take_map(struct vlff_merge_robot *r, struct robot_io *io, const sensor_msgs_msg_dds__PointCloud2_ *m,
                    bool update) {
  struct cloud_fields f;
  char why[256];
  cloud_fields(m, &f);
  int rc = update ? vlff_merge_take_update(r, m->width, m->height, m->point_step, m->is_bigendian, f.names, f.offs,
                                           f.types, f.n, m->data._buffer, m->data._length, f.stamp, why, sizeof why)
                  : vlff_merge_take_cloud(r, m->width, m->height, m->point_step, m->is_bigendian, f.names, f.offs,
                                          f.types, f.n, m->data._buffer, m->data._length, f.stamp, why, sizeof why);
  if (rc < 0) {
    r->refused++;
    vlff_warn_limited(&io->warn, TAG, "%s: map%s refused: %s", r->ns, update ? " update" : "", why);
    return 0;
  }
  if (!update && m->header.frame_id) snprintf(io->frame, sizeof io->frame, "%s", m->header.frame_id);
  return update ? rc > 0 : 1;
}

/* New samples of one robot: 1 when its map, prompt list or transform changed. */
static int take_robot(struct vlff_merge_robot *r, struct robot_io *io, const char *world) {
  int changed = 0;
  TAKE_ALL(io->prompts_r, std_msgs_msg_dds__String_, changed |= take_prompts(r, io, m->data))
  TAKE_ALL(io->map_r, sensor_msgs_msg_dds__PointCloud2_, changed |= take_map(r, io, m, false))
  /* Updates wait in the reader until a whole map is held to apply them to
   * (marked read meanwhile, so that they do not wake the loop again). */
  if (!r->xyz) {
    void *b[16] = {NULL};
    dds_sample_info_t bi[16];
    dds_return_t k;
    while ((k = dds_read_mask(io->updates_r, b, bi, 16, 16, DDS_NOT_READ_SAMPLE_STATE)) > 0)
      dds_return_loan(io->updates_r, b, k);
  } else {
    TAKE_ALL(io->updates_r, sensor_msgs_msg_dds__PointCloud2_, changed |= take_map(r, io, m, true))
  }
  TAKE_ALL(io->tf_r, tf2_msgs_msg_dds__TFMessage_, changed |= take_tf(r, io, m, world))
  if (!io->configured) {
    TAKE_ALL(io->tf_static_r, tf2_msgs_msg_dds__TFMessage_, changed |= take_tf(r, io, m, world))
    changed |= choose_tf(r, io, world);
  }
  return changed;
}

/* One robot from the command line (NS[@X,Y,Z,YAW]) or the config. */
static int add_robot(struct vlff_merge_robot *robots, struct robot_io *io, int *nrobots, const char *ns,
                     const double *tf, char *err, size_t errlen) {
  struct vlff_merge_robot *r = &robots[*nrobots];
  if (*nrobots >= VLFF_MERGE_MAX_ROBOTS) {
    snprintf(err, errlen, "more than %d robots", VLFF_MERGE_MAX_ROBOTS);
    return -1;
  }
  if (strlen(ns) >= sizeof r->ns) {
    snprintf(err, errlen, "'%s': namespace too long", VLFF_Q(ns));
    return -1;
  }
  if (check_ns(ns, err, errlen)) return -1;
  for (int i = 0; i < *nrobots; i++)
    if (!strcmp(robots[i].ns, ns)) {
      snprintf(err, errlen, "'%s' given twice", VLFF_Q(ns));
      return -1;
    }
  snprintf(r->ns, sizeof r->ns, "%s", ns);
  vlff_merge_yaw(r->rot, tf ? tf[3] * 3.14159265358979323846 / 180 : 0);
  for (int a = 0; a < 3; a++) r->t[a] = tf ? tf[a] : 0;
  r->nprompts = -1;
  io[*nrobots].configured = tf != NULL;
  io[*nrobots].tf_used = -1;
  snprintf(io[*nrobots].frame, sizeof io[*nrobots].frame, "map");
  ++*nrobots;
  return 0;
}

/* The robots' readers and the fleet's writers; 0, or -1 with err. */
static int open_dds(dds_entity_t pp, dds_entity_t ws, struct vlff_merge_robot *robots, struct robot_io *io,
                    int nrobots, const char *fleet_ns, dds_entity_t *map_w, dds_entity_t *prompts_w, char *err,
                    size_t errlen) {
  for (int i = 0; i < nrobots; i++) {
    io[i].map_r = leaf_endpoint(pp, &sensor_msgs_msg_dds__PointCloud2__desc, robots[i].ns, "map", 1, false);
    io[i].prompts_r = leaf_endpoint(pp, &std_msgs_msg_dds__String__desc, robots[i].ns, "prompts", 1, false);
    io[i].updates_r = leaf_endpoint(pp, &sensor_msgs_msg_dds__PointCloud2__desc, robots[i].ns, "map/updates", 1000, false);
    dds_return_t bad = io[i].map_r < 0 ? io[i].map_r : io[i].prompts_r < 0 ? io[i].prompts_r : io[i].updates_r;
    if (bad >= 0) {
      /* ROS's tf2: static transforms latched on tf_static, others (and the
       * camera poses vlff-dds sends) on tf */
      char name[300];
      if (vlff_dds_topic_of(name, sizeof name - 8, robots[i].ns, VLFF_DDS_TF) < 0) return -1;
      io[i].tf_r = endpoint(pp, &tf2_msgs_msg_dds__TFMessage__desc, name, false, 100, false);
      strcat(name, "_static");
      if (!io[i].configured) io[i].tf_static_r = endpoint(pp, &tf2_msgs_msg_dds__TFMessage__desc, name, true, 100, false);
      bad = io[i].tf_r < 0 ? io[i].tf_r : io[i].tf_static_r;
    }
    if (bad < 0) {
      snprintf(err, errlen, "%.200s: DDS readers: %.200s", robots[i].ns, dds_strretcode(bad));
      return -1;
    }
    dds_waitset_attach(ws, dds_create_readcondition(io[i].map_r, DDS_ANY_STATE), 0);
    dds_waitset_attach(ws, dds_create_readcondition(io[i].prompts_r, DDS_ANY_STATE), 0);
    dds_waitset_attach(ws, dds_create_readcondition(io[i].updates_r, DDS_NOT_READ_SAMPLE_STATE), 0);
    dds_waitset_attach(ws, dds_create_readcondition(io[i].tf_r, DDS_ANY_STATE), 0);
    if (!io[i].configured) dds_waitset_attach(ws, dds_create_readcondition(io[i].tf_static_r, DDS_ANY_STATE), 0);
  }
  *map_w = leaf_endpoint(pp, &sensor_msgs_msg_dds__PointCloud2__desc, fleet_ns, "map", 1, true);
  *prompts_w = leaf_endpoint(pp, &std_msgs_msg_dds__String__desc, fleet_ns, "prompts", 1, true);
  if (*map_w < 0 || *prompts_w < 0) {
    snprintf(err, errlen, "%.200s: DDS writers: %.200s", fleet_ns, dds_strretcode(*map_w < 0 ? *map_w : *prompts_w));
    return -1;
  }
  return 0;
}

/* The fleet map over DDS, as vlff-dds sends a robot's. */
static void send_fleet(dds_entity_t map_w, dds_entity_t prompts_w, struct vlff_map *map,
                       const struct vlff_map_grid *grid, const char *const *texts, int ntexts, char *frame,
                       uint64_t *warn) {
  struct vlff_map_info info = {0};
  info.version = vlff_map_version(map);
  info.grid = *grid;
  uint8_t *data;
  uint32_t n;
  if (vlff_dds_cloud(&info, NULL, 0, &data, &n, NULL) == 0) { /* a merged grid: no far map */
    sensor_msgs_msg_dds__PointField_ fields[5] = {
        {"x", 0, VLFF_DDS_FLOAT32, 1},     {"y", 4, VLFF_DDS_FLOAT32, 1},          {"z", 8, VLFF_DDS_FLOAT32, 1},
        {"label", 12, VLFF_DDS_UINT16, 1}, {"confidence", 16, VLFF_DDS_FLOAT32, 1}};
    struct timespec rt;
    clock_gettime(CLOCK_REALTIME, &rt);
    sensor_msgs_msg_dds__PointCloud2_ msg = {0};
    msg.header.stamp.sec = (int32_t)rt.tv_sec;
    msg.header.stamp.nanosec = (uint32_t)rt.tv_nsec;
    msg.header.frame_id = frame;
    msg.height = 1, msg.width = n;
    msg.fields._length = msg.fields._maximum = 5;
    msg.fields._buffer = fields;
    msg.point_step = VLFF_DDS_POINT_STEP, msg.row_step = n * VLFF_DDS_POINT_STEP;
    msg.data._length = msg.data._maximum = msg.row_step;
    msg.data._buffer = data;
    msg.is_dense = true;
    dds_return_t rc = dds_write(map_w, &msg);
    if (rc < 0) vlff_warn_limited(warn, TAG, "fleet map write: %s", dds_strretcode(rc));
    free(data);
  }
  char *json = vlff_dds_prompt_list_json(texts, ntexts);
  if (json) {
    std_msgs_msg_dds__String_ s = {json};
    dds_write(prompts_w, &s);
    free(json);
  }
}

/* Robots whose texts did not fit the fleet's list: logged when that changes. */
static void log_left_out(struct vlff_merge_robot *robots, struct robot_io *io, int nrobots, uint64_t *count) {
  for (int i = 0; i < nrobots; i++) {
    struct vlff_merge_robot *r = &robots[i];
    if (r->left_out == io[i].left_out_logged) continue;
    io[i].left_out_logged = r->left_out;
    if (!r->left_out) continue;
    ++*count;
    char list[400] = "";
    size_t at = 0;
    int n = 0;
    for (int k = 0; k < r->nprompts; k++)
      if (r->left_out >> k & 1) {
        if (at < sizeof list - 80)
          at += (size_t)snprintf(list + at, sizeof list - at, "%s'%s'", n ? ", " : "", VLFF_Q(r->prompts[k]));
        n++;
      }
    VLFF_WARN(TAG, "%s: %d of its %d prompt texts left out of the fleet's labels (at most %d in all), with the points "
              "labelled with them: %s%s", r->ns, n, r->nprompts, VLFF_SHM_MAX_PROMPTS, list,
              at >= sizeof list - 80 ? ", ..." : "");
  }
}

int main(int argc, char **argv) {
  static const struct option opts[] = {{"robot", required_argument, NULL, 'r'},
                                       {"map", required_argument, NULL, 'm'},
                                       {"bounds", required_argument, NULL, 'b'},
                                       {"voxel", required_argument, NULL, OPT_VOXEL},
                                       {"config", required_argument, NULL, 'c'},
                                       {"namespace", required_argument, NULL, 'n'},
                                       {"frame-id", required_argument, NULL, OPT_FRAME},
                                       {"seconds", required_argument, NULL, OPT_SECONDS},
                                       {"verbose", no_argument, NULL, 'v'},
                                       VLFF_CLI_COMMON_OPTIONS};
  static struct vlff_merge_robot robots[VLFF_MERGE_MAX_ROBOTS];
  static struct robot_io io[VLFF_MERGE_MAX_ROBOTS];
  int nrobots = 0, c, status;
  const char *out = NULL, *path = NULL, *fleet_ns = NULL, *frame = NULL;
  double bounds[6], voxel = 0, seconds = 0;
  bool have_bounds = false, have_voxel = false, verbose = false;
  char err[1024];
  while ((c = vlff_cli_next(&cli, argc, argv, "r:m:b:c:n:v", opts, &status)) != -1) {
    char *end;
    switch (c) {
    case VLFF_CLI_EXIT: return status;
    case 'r': {
      char ns[256];
      const char *at = strchr(optarg, '@');
      size_t l = at ? (size_t)(at - optarg) : strlen(optarg);
      if (l >= sizeof ns) return vlff_cli_usage_error(&cli, "--robot '%s': namespace too long", VLFF_Q(optarg));
      memcpy(ns, optarg, l);
      ns[l] = 0;
      double tf[4] = {0, 0, 0, 0};
      if (at && (parse_doubles(at + 1, tf, 4) < 0 || fabs(tf[0]) > 1e5 || fabs(tf[1]) > 1e5 || fabs(tf[2]) > 1e5 ||
                 fabs(tf[3]) > 360))
        return vlff_cli_usage_error(&cli, "--robot '%s': expected NS@X,Y,Z,YAW (m within +-1e5, degrees within +-360)",
                                    VLFF_Q(optarg));
      if (add_robot(robots, io, &nrobots, ns, at ? tf : NULL, err, sizeof err))
        return vlff_cli_usage_error(&cli, "--robot: %s", err);
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
    case OPT_FRAME: frame = optarg; break;
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
    for (int i = 0; i < cm->robot_count; i++)
      if (add_robot(robots, io, &nrobots, cm->robots[i].ns, cm->robots[i].has_transform ? cm->robots[i].transform : NULL,
                    err, sizeof err))
        return vlff_cli_config_error(err);
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
  if (!frame) frame = cm->frame_id;
  if (!have_bounds) memcpy(bounds, cm->bounds, sizeof bounds);
  if (!have_voxel) voxel = cm->voxel_size_m;
  if (nrobots < 2)
    return vlff_cli_usage_error(&cli, "expected 2 to %d robots (--robot or dds.merge.robots), got %d",
                                VLFF_MERGE_MAX_ROBOTS, nrobots);
  if (check_ns(fleet_ns, err, sizeof err)) return vlff_cli_usage_error(&cli, "--namespace: %s", err);
  for (int i = 0; i < nrobots; i++)
    if (!strcmp(robots[i].ns, fleet_ns))
      return vlff_cli_usage_error(&cli, "--namespace '%s' is a robot's", VLFF_Q(fleet_ns));
  if (!*frame || strlen(frame) >= 128 || strspn(frame, "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-./") != strlen(frame) || *frame == '/')
    return vlff_cli_usage_error(&cli, "--frame-id '%s': expected a tf2 frame id (letters, digits, _-./, no leading /)",
                                VLFF_Q(frame));
  static struct vlff_merge_grid g;
  if (vlff_merge_grid_init(&g, bounds, bounds + 3, voxel, cm->half_life_s, err, sizeof err))
    return vlff_cli_usage_error(&cli, "--bounds/--voxel: %s", err);

  vlff_log_set_level(verbose ? VLFF_LOG_DEBUG : (enum vlff_log_level)cfg.node.log_level);
  vlff_cli_catch_stop();
  /* DDS first: a bad Cyclone config (CYCLONEDDS_URI) fails here, before
   * the fleet's segment exists, rather than leaving an empty one behind. */
  dds_entity_t pp = dds_create_participant((dds_domainid_t)cfg.dds.domain_id, NULL, NULL);
  if (pp < 0)
    return vlff_cli_error(&cli, "DDS participant in domain %d: %s (Cyclone's config: CYCLONEDDS_URI)",
                          cfg.dds.domain_id, dds_strretcode(pp));
  dds_entity_t ws = dds_create_waitset(pp), map_w, prompts_w;
  if (ws < 0 || open_dds(pp, ws, robots, io, nrobots, fleet_ns, &map_w, &prompts_w, err, sizeof err)) {
    dds_delete(pp);
    return vlff_cli_error(&cli, "%s", ws < 0 ? dds_strretcode(ws) : err);
  }
  struct vlff_map_params mp = {g.dims[0] * g.dims[1] * g.dims[2], 0, 0, {0, NULL}};
  struct vlff_map *map = vlff_map_create(out, &mp);
  if (!map) {
    dds_delete(pp);
    return vlff_cli_error(&cli, "map segment '%s': %s", VLFF_Q(out), vlff_shm_last_message());
  }
  VLFF_INFO(TAG, "domain %d: %d robots into %s and %s/vlff/map (frame %s), %u x %u x %u voxels of %.3f m",
            cfg.dds.domain_id, nrobots, out, fleet_ns, frame, g.dims[0], g.dims[1], g.dims[2], voxel);
  uint64_t merges = 0, warn_pub = 0, left_out = 0;
  struct timespec t0;
  clock_gettime(CLOCK_MONOTONIC, &t0);
  while (!vlff_cli_stop) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    if (seconds > 0 && (double)(t.tv_sec - t0.tv_sec) + 1e-9 * (double)(t.tv_nsec - t0.tv_nsec) >= seconds) break;
    dds_waitset_wait(ws, NULL, 0, DDS_MSECS(200));
    int changed = 0;
    for (int i = 0; i < nrobots; i++) changed |= take_robot(&robots[i], &io[i], frame);
    if (!changed) {
      vlff_map_heartbeat(map);
      continue;
    }
    long labelled = vlff_merge_compute(&g, robots, nrobots);
    if (labelled < 0) vlff_warn_limited(&warn_pub, TAG, "no memory to merge the robots' points: the fleet map is empty");
    log_left_out(robots, io, nrobots, &left_out);
    const char *texts[VLFF_SHM_MAX_PROMPTS];
    for (int i = 0; i < g.nprompts; i++) texts[i] = g.prompts[i];
    struct vlff_map_grid grid = {{g.origin[0], g.origin[1], g.origin[2]}, g.voxel, {g.dims[0], g.dims[1], g.dims[2]},
                                 g.labels, g.conf};
    struct vlff_map_update up = {.grid = &grid, .prompts = texts, .prompt_count = g.nprompts};
    if (vlff_map_publish(map, &up) < 0)
      vlff_warn_limited(&warn_pub, TAG, "map segment %s: %s", out, vlff_shm_last_message());
    send_fleet(map_w, prompts_w, map, &grid, texts, g.nprompts, (char *)frame, &warn_pub);
    merges++;
    VLFF_DEBUG(TAG, "merge %" PRIu64 ": %ld labelled voxels, %d labels, %" PRIu64 " points outside the bounds, %" PRIu64
               " points of texts left out", merges, labelled, g.nprompts, g.outside, g.no_label);
  }
  uint64_t refused = 0, no_label = g.no_label;
  for (int i = 0; i < nrobots; i++) refused += robots[i].refused;
  VLFF_INFO(TAG, "stopping: %" PRIu64 " merges, %" PRIu64 " robot messages refused, %" PRIu64
            " times robots' texts left out of the fleet's labels (%" PRIu64 " points at the last merge)",
            merges, refused, left_out, no_label);
  dds_delete(pp);
  vlff_map_detach(map);
  for (int i = 0; i < nrobots; i++) vlff_merge_robot_free(&robots[i]);
  vlff_merge_grid_free(&g);
  return 0;
}
