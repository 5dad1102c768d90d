/* SPDX-License-Identifier: BSD-3-Clause */
/* vlff-dds's bridge: the map segment and mailbox on one side, Cyclone DDS on
 * the other (dds.h). */
#include "dds.h"

#include <errno.h>
#include <inttypes.h>
#include <json-c/json.h>
#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include <dds/dds.h>

#include "cli.h"
#include "diagnostic_msgs.h"
#include "far_walk.h"
#include "hash.h"
#include "log.h"
#include "palette.h"
#include "sensor_msgs.h"
#include "std_msgs.h"
#include "tf2_msgs.h"
#include "vlff/escape.h"
#ifdef VLFF_DDS_CV
#include "cvshim.h"
#endif

#define TAG "dds"

int vlff_dds_topic(char *out, size_t len, const char *ns, const char *leaf) {
  int n = snprintf(out, len, "rt%s/vlff/%s", ns, leaf);
  return n < 0 || (size_t)n >= len ? -1 : 0;
}

static const struct {
  const char *key, *leaf; /* leaf NULL: rt<ns>/tf */
} topics[VLFF_DDS_NTOPICS] = {
    [VLFF_DDS_MAP] = {"map", "map"},
    [VLFF_DDS_STATUS] = {"status", "status"},
    [VLFF_DDS_PROMPTS_IN] = {"prompts_in", "prompts_in"},
    [VLFF_DDS_PROMPTS] = {"prompts", "prompts"},
    [VLFF_DDS_LABEL_IMAGE] = {"label_image", "label_image"},
    [VLFF_DDS_LABEL_IMAGE_COMPRESSED] = {"label_image_compressed", "label_image/compressed"},
    [VLFF_DDS_CAMERA_IMAGE] = {"camera_image", "camera/image_raw"},
    [VLFF_DDS_CAMERA_IMAGE_COMPRESSED] = {"camera_image_compressed", "camera/image_raw/compressed"},
    [VLFF_DDS_CAMERA_INFO] = {"camera_info", "camera/camera_info"},
    [VLFF_DDS_TF] = {"tf", NULL},
    [VLFF_DDS_MAP_UPDATES] = {"map_updates", "map/updates"},
};

const char *vlff_dds_topic_key(int id) { return id >= 0 && id < VLFF_DDS_NTOPICS ? topics[id].key : NULL; }

int vlff_dds_topic_of(char *out, size_t len, const char *ns, int id) {
  if (id < 0 || id >= VLFF_DDS_NTOPICS) return -1;
  if (topics[id].leaf) return vlff_dds_topic(out, len, ns, topics[id].leaf);
  int n = snprintf(out, len, "rt%s/tf", ns);
  return n < 0 || (size_t)n >= len ? -1 : 0;
}

int vlff_dds_can_compress(void) {
#ifdef VLFF_DDS_CV
  return 1;
#else
  return 0;
#endif
}

const char *vlff_dds_encoding(uint32_t fmt) {
  switch (fmt) {
  case VLFF_PIX_RGB8: return "rgb8";
  case VLFF_PIX_BGR8: return "bgr8";
  case VLFF_PIX_MONO8: return "mono8";
  case VLFF_PIX_MONO16: return "mono16";
  case VLFF_PIX_BAYER_RG8: return "bayer_rggb8";
  case VLFF_PIX_BAYER_BG8: return "bayer_bggr8";
  case VLFF_PIX_BAYER_GR8: return "bayer_grbg8";
  case VLFF_PIX_BAYER_GB8: return "bayer_gbrg8";
  default: return NULL;
  }
}

char *vlff_dds_prompt_list_json(const char *const texts[], int count) {
  json_object *a = json_object_new_array();
  for (int i = 0; a && i < count; i++) {
    json_object *e = json_object_new_string(texts[i] ? texts[i] : "");
    if (!e || json_object_array_add(a, e)) {
      json_object_put(e);
      json_object_put(a);
      a = NULL;
    }
  }
  char *out = a ? strdup(json_object_to_json_string_ext(a, JSON_C_TO_STRING_PLAIN | JSON_C_TO_STRING_NOSLASHESCAPE))
                : NULL;
  json_object_put(a);
  if (!out) errno = ENOMEM;
  return out;
}

char *vlff_dds_prompt_json(const struct vlff_map_snapshot *snap, int count) {
  const char *texts[VLFF_SHM_MAX_PROMPTS];
  if (count > VLFF_SHM_MAX_PROMPTS) count = VLFF_SHM_MAX_PROMPTS;
  for (int i = 0; i < count; i++) texts[i] = vlff_map_snapshot_prompt(snap, (uint16_t)i);
  return vlff_dds_prompt_list_json(texts, count);
}

int vlff_dds_parse_prompts(const char *data, size_t len, char texts[][VLFF_SHM_PROMPT_LEN], int *set_index,
                           int *invalid, char *why, size_t whylen) {
  *invalid = 0;
  *set_index = -1;
  json_tokener *tok = json_tokener_new_ex(4); /* a list of strings nests 2 deep */
  if (!tok) {
    snprintf(why, whylen, "out of memory");
    return -1;
  }
  json_object *root = json_tokener_parse_ex(tok, data, (int)len);
  enum json_tokener_error jerr = json_tokener_get_error(tok);
  size_t end = json_tokener_get_parse_end(tok);
  if (!root && jerr == json_tokener_continue) {
    /* A number ends only where input does: the NUL says it has. */
    root = json_tokener_parse_ex(tok, "", 1);
    jerr = json_tokener_get_error(tok);
    end = len;
  }
  int count = -1;
  if (!root || jerr != json_tokener_success || end != len) {
    snprintf(why, whylen, "not JSON (%s)", root && jerr == json_tokener_success ? "text after the value"
                                                                                 : json_tokener_error_desc(jerr));
  } else if (json_object_is_type(root, json_type_int)) {
    /* vlff-shm set-prompts -i N: a configured set by index, as that takes it;
     * the learner refuses an index it does not have. */
    errno = 0;
    int64_t i = json_object_get_int64(root);
    if (errno || i < 0 || i > INT32_MAX) {
      snprintf(why, whylen, "expected a prompt set index in 0..2147483647, got %s", json_object_to_json_string(root));
      *invalid = 1;
    } else {
      *set_index = (int)i;
      count = 0;
    }
  } else if (!json_object_is_type(root, json_type_array)) {
    snprintf(why, whylen, "expected a JSON list of prompt texts or a set index, got a JSON %s",
             json_type_to_name(json_object_get_type(root)));
  } else {
    size_t n = json_object_array_length(root);
    const char *ptr[VLFF_SHM_MAX_PROMPTS];
    if (n < 1 || n > VLFF_SHM_MAX_PROMPTS) {
      snprintf(why, whylen, "expected 1 to %d prompts, got %zu", VLFF_SHM_MAX_PROMPTS, n);
      *invalid = 1;
    } else {
      count = (int)n;
      for (size_t i = 0; i < n && count >= 0; i++) {
        json_object *e = json_object_array_get_idx(root, i);
        if (!json_object_is_type(e, json_type_string)) {
          snprintf(why, whylen, "prompt %zu: expected a JSON string, got a JSON %s", i,
                   json_type_to_name(json_object_get_type(e)));
          count = -1;
          break;
        }
        /* A NUL inside the string would cut the text short unseen. */
        size_t l = (size_t)json_object_get_string_len(e);
        const char *s = json_object_get_string(e);
        if (l >= VLFF_SHM_PROMPT_LEN || strlen(s) != l) {
          snprintf(why, whylen, "prompt %zu: expected 1 to %d bytes without NUL, got %zu", i, VLFF_SHM_PROMPT_LEN - 1,
                   l);
          *invalid = 1;
          count = -1;
          break;
        }
        memcpy(texts[i], s, l + 1);
        ptr[i] = texts[i];
      }
      if (count > 0 && vlff_prompt_check(ptr, count) < 0) {
        snprintf(why, whylen, "%s", vlff_shm_last_message());
        *invalid = 1;
        count = -1;
      }
    }
  }
  json_object_put(root);
  json_tokener_free(tok);
  return count;
}

static void put_f32(uint8_t *p, float f) {
  uint32_t u;
  memcpy(&u, &f, 4);
  for (int i = 0; i < 4; i++) p[i] = (uint8_t)(u >> (8 * i));
}

/* A map point: centre, label, confidence (0..255). */
static void put_xyz(uint8_t *p, const double c[3], uint16_t l, uint8_t conf) {
  for (int a = 0; a < 3; a++) put_f32(p + 4 * a, (float)c[a]);
  p[12] = (uint8_t)l;
  p[13] = (uint8_t)(l >> 8);
  p[14] = p[15] = 0;
  put_f32(p + 16, (float)conf / 255.0f);
}

void vlff_dds_put_point(uint8_t *p, const struct vlff_map_grid *g, size_t i) {
  size_t ix = i % g->dims[0], iy = (i / g->dims[0]) % g->dims[1], iz = i / ((size_t)g->dims[0] * g->dims[1]);
  const double c[3] = {g->origin[0] + ((double)ix + 0.5) * g->voxel_size,
                       g->origin[1] + ((double)iy + 0.5) * g->voxel_size,
                       g->origin[2] + ((double)iz + 0.5) * g->voxel_size};
  put_xyz(p, c, g->labels[i], g->confidence ? g->confidence[i] : 255);
}

static void put_far(void *ctx, const double c[3], uint16_t label, uint8_t conf) {
  uint8_t **p = ctx;
  put_xyz(*p, c, label, conf);
  *p += VLFF_DDS_POINT_STEP;
}

int vlff_dds_cloud(const struct vlff_map_info *info, const struct vlff_map_far *far, size_t far_max, uint8_t **out,
                   uint32_t *npoints, size_t *far_left) {
  const struct vlff_map_grid *g = &info->grid;
  size_t total = (size_t)g->dims[0] * g->dims[1] * g->dims[2];
  if (!g->labels) total = 0;
  struct vlff_far_pick pick;
  if (vlff_far_pick(far, g, far_max, &pick)) {
    errno = ENOMEM;
    return -1;
  }
  if (far_left) *far_left = pick.left;
  size_t n = pick.points;
  for (size_t i = 0; i < total; i++) n += g->labels[i] <= VLFF_LABEL_MAX;
  uint8_t *buf = n <= UINT32_MAX / VLFF_DDS_POINT_STEP ? malloc(n ? n * VLFF_DDS_POINT_STEP : 1) : NULL;
  if (!buf) {
    vlff_far_pick_free(&pick);
    errno = ENOMEM;
    return -1;
  }
  uint8_t *p = buf;
  for (size_t i = 0; i < total; i++) {
    if (g->labels[i] > VLFF_LABEL_MAX) continue;
    vlff_dds_put_point(p, g, i);
    p += VLFF_DDS_POINT_STEP;
  }
  vlff_far_emit(far, g, &pick, put_far, &p); /* what the window left behind: pick.points */
  vlff_far_pick_free(&pick);
  *out = buf;
  *npoints = (uint32_t)n;
  return 0;
}

/* ------------------------------------------------------------ the bridge */

struct vlff_dds {
  struct vlff_dds_opts o;
  dds_entity_t pp, w[VLFF_DDS_NTOPICS], prompts_r, ws, prompts_cond;
  struct vlff_map *map;
  struct vlff_map_snapshot *snap;
  struct vlff_prompts *mailbox;
  struct vlff_ring *ring; /* the camera's frame ring */
  uint8_t *rec;           /* its newest record */
  size_t rec_cap;
  uint64_t ring_head, ring_next_attach, last_camera_ns, last_label_ns, label_sent;
  bool have_frame; /* rec holds a valid frame, read at ring_head */
  char *prompts_sent;     /* the prompt list's JSON last sent */
  uint64_t snap_version;  /* the version and generation in snap */
  uint32_t snap_generation;
  bool prompts_pending, label_pending; /* in snap, not sent yet */
  bool ring_has_pose;     /* poses come from the frames */
  uint64_t sent_version, far_sent; /* far_sent: the far map's version in the last whole map */
  uint32_t sent_generation;
  /* Following the map: shadow is the grid as subscribers know it (the last
   * whole map sent and the updates after it); upd the changed voxels not
   * sent yet, as update points. */
  uint16_t *shadow_labels;
  uint8_t *shadow_conf;
  size_t shadow_n;
  uint8_t *upd;
  size_t upd_n, upd_cap;
  int64_t snap_stamp, last_stamp; /* the version's header stamp (ns of system time), the latest given */
  bool full_pending;
  const char *full_why;           /* why the whole map goes out (-v) */
  uint64_t full_version, last_full_ns, updates_since_full;
  char *full_prompts;             /* the prompt list's JSON at the last whole map */
  uint64_t pending_seq; /* last post whose answer is not logged yet */
  uint64_t last_post_ns;
  volatile sig_atomic_t stop;
  struct vlff_dds_counts c;
  uint64_t warn_attach, warn_map, warn_far, warn_prompt, warn_mailbox, warn_write, warn_ring, warn_image;
};

static void set_err(char *err, size_t errlen, const char *what, dds_return_t rc) {
  snprintf(err, errlen, "%s: %s", what, dds_strretcode(rc));
}

static const dds_topic_descriptor_t *descriptor(int id) {
  switch (id) {
  case VLFF_DDS_MAP:
  case VLFF_DDS_MAP_UPDATES: return &sensor_msgs_msg_dds__PointCloud2__desc;
  case VLFF_DDS_STATUS: return &diagnostic_msgs_msg_dds__DiagnosticArray__desc;
  case VLFF_DDS_PROMPTS_IN:
  case VLFF_DDS_PROMPTS: return &std_msgs_msg_dds__String__desc;
  case VLFF_DDS_LABEL_IMAGE:
  case VLFF_DDS_CAMERA_IMAGE: return &sensor_msgs_msg_dds__Image__desc;
  case VLFF_DDS_LABEL_IMAGE_COMPRESSED:
  case VLFF_DDS_CAMERA_IMAGE_COMPRESSED: return &sensor_msgs_msg_dds__CompressedImage__desc;
  case VLFF_DDS_CAMERA_INFO: return &sensor_msgs_msg_dds__CameraInfo__desc;
  default: return &tf2_msgs_msg_dds__TFMessage__desc;
  }
}

/* The topic's QoS as configured. A keep-last history on a reliable writer
 * never blocks it: a reader that does not keep up loses the oldest. */
static dds_qos_t *topic_qos(const struct vlff_cfg_dds_qos *c) {
  dds_qos_t *q = dds_create_qos();
  if (!q) return NULL;
  if (c->reliability == VLFF_DDS_RELIABLE)
    dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  else
    dds_qset_reliability(q, DDS_RELIABILITY_BEST_EFFORT, 0);
  dds_qset_durability(q, c->durability == VLFF_DDS_TRANSIENT_LOCAL ? DDS_DURABILITY_TRANSIENT_LOCAL
                                                                   : DDS_DURABILITY_VOLATILE);
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, c->depth);
  /* What a late joiner gets is the durability service's history in
   * Cyclone (keep last 1 unless said): the same depth. */
  if (c->durability == VLFF_DDS_TRANSIENT_LOCAL)
    dds_qset_durability_service(q, 0, DDS_HISTORY_KEEP_LAST, c->depth, DDS_LENGTH_UNLIMITED, DDS_LENGTH_UNLIMITED,
                                DDS_LENGTH_UNLIMITED);
  return q;
}

/* Writer (or, for prompts_in, reader) of topic id. */
static dds_entity_t make_endpoint(struct vlff_dds *b, int id, char *err, size_t errlen) {
  char name[300];
  if (vlff_dds_topic_of(name, sizeof name, b->o.dds.ns, id) < 0) {
    snprintf(err, errlen, "topic name for %s too long", topics[id].key);
    return -1;
  }
  dds_entity_t t = dds_create_topic(b->pp, descriptor(id), name, NULL, NULL);
  if (t < 0) {
    set_err(err, errlen, name, t);
    return t;
  }
  dds_qos_t *q = topic_qos(&b->o.dds.qos[id]);
  if (!q) {
    snprintf(err, errlen, "%s: out of memory", name);
    return -1;
  }
  if (id == VLFF_DDS_PROMPTS_IN) {
    /* Bounded in samples: a flood costs at most depth messages held. */
    dds_qset_resource_limits(q, b->o.dds.qos[id].depth, DDS_LENGTH_UNLIMITED, DDS_LENGTH_UNLIMITED);
  }
  dds_entity_t e = id == VLFF_DDS_PROMPTS_IN ? dds_create_reader(b->pp, t, q, NULL) : dds_create_writer(b->pp, t, q, NULL);
  dds_delete_qos(q);
  if (e < 0) set_err(err, errlen, name, e);
  return e;
}

struct vlff_dds *vlff_dds_create(const struct vlff_dds_opts *opts, char *err, size_t errlen) {
  struct vlff_dds *b = calloc(1, sizeof *b);
  if (!b) {
    snprintf(err, errlen, "out of memory");
    return NULL;
  }
  b->o = *opts;
  if (b->o.dds.on[VLFF_DDS_MAP_UPDATES] && !b->o.update_points_max) {
    snprintf(err, errlen, "dds.qos.map_updates.depth: dds.history_max_mb leaves no point per map update");
    free(b);
    return NULL;
  }
#ifndef VLFF_DDS_CV
  for (int id = VLFF_DDS_LABEL_IMAGE_COMPRESSED; id <= VLFF_DDS_CAMERA_IMAGE_COMPRESSED; id += 2)
    if (b->o.dds.on[id]) {
      snprintf(err, errlen, "dds.%s: this build has no image encoder (built without OpenCV)", topics[id].key);
      free(b);
      return NULL;
    }
#endif
  b->pp = dds_create_participant((dds_domainid_t)opts->dds.domain_id, NULL, NULL);
  if (b->pp < 0) {
    set_err(err, errlen, "DDS participant", b->pp);
    free(b);
    return NULL;
  }
  b->ws = dds_create_waitset(b->pp);
  if (b->ws < 0) {
    set_err(err, errlen, "waitset", b->ws);
    goto fail;
  }
  for (int id = 0; id < VLFF_DDS_NTOPICS; id++) {
    if (!opts->dds.on[id]) continue;
    dds_entity_t e = make_endpoint(b, id, err, errlen);
    if (e < 0) goto fail;
    if (id == VLFF_DDS_PROMPTS_IN)
      b->prompts_r = e;
    else
      b->w[id] = e;
  }
  if (b->prompts_r) {
    b->prompts_cond = dds_create_readcondition(b->prompts_r, DDS_ANY_STATE);
    dds_return_t rc = b->prompts_cond < 0 ? b->prompts_cond : dds_waitset_attach(b->ws, b->prompts_cond, 0);
    if (rc < 0) {
      set_err(err, errlen, "prompts condition", rc);
      goto fail;
    }
  }
  return b;
fail:
  dds_delete(b->pp);
  free(b);
  return NULL;
}

void vlff_dds_stop(struct vlff_dds *b) { b->stop = 1; }
const struct vlff_dds_counts *vlff_dds_counts(const struct vlff_dds *b) { return &b->c; }

void vlff_dds_destroy(struct vlff_dds *b) {
  if (!b) return;
  dds_delete(b->pp);
  vlff_map_snapshot_free(b->snap);
  vlff_map_detach(b->map);
  vlff_prompts_close(b->mailbox);
  vlff_ring_close(b->ring);
  free(b->rec);
  free(b->prompts_sent);
  free(b->full_prompts);
  free(b->shadow_labels);
  free(b->shadow_conf);
  free(b->upd);
  free(b);
}

static uint64_t mono_ns(void) { return vlff_shm_now_ns(); }

/* A CLOCK_MONOTONIC time as ROS time (system time), for header stamps. */
static builtin_interfaces_msg_dds__Time_ ros_time(uint64_t mono) {
  struct timespec rt;
  clock_gettime(CLOCK_REALTIME, &rt);
  uint64_t now_rt = (uint64_t)rt.tv_sec * 1000000000ull + (uint64_t)rt.tv_nsec;
  uint64_t age = mono ? mono_ns() - mono : 0;
  uint64_t t = now_rt > age ? now_rt - age : 0;
  builtin_interfaces_msg_dds__Time_ out = {(int32_t)(t / 1000000000ull), (uint32_t)(t % 1000000000ull)};
  return out;
}

static builtin_interfaces_msg_dds__Time_ stamp_time(int64_t ns) {
  builtin_interfaces_msg_dds__Time_ out = {(int32_t)(ns / 1000000000), (uint32_t)(ns % 1000000000)};
  return out;
}

/* A version's header stamp, fixed when the bridge first reads the version
 * so that its whole map and its update carry the same one, and increasing
 * from version to version whatever the system clock does: subscribers
 * order the two topics by it (docs/dds.md, "Following the map"). */
static int64_t version_stamp(struct vlff_dds *b, uint64_t publish_ns) {
  builtin_interfaces_msg_dds__Time_ t = ros_time(publish_ns);
  int64_t ns = (int64_t)t.sec * 1000000000 + t.nanosec;
  if (ns <= b->last_stamp) ns = b->last_stamp + 1;
  b->last_stamp = ns;
  return ns;
}

static void drop_map(struct vlff_dds *b) {
  b->snap_version = 0;
  vlff_map_snapshot_free(b->snap);
  vlff_map_detach(b->map);
  b->snap = NULL;
  b->map = NULL;
}

/* The map segment, attached when it exists; NULL until then. */
static struct vlff_map *get_map(struct vlff_dds *b) {
  if (b->map) return b->map;
  b->map = vlff_map_attach(b->o.map);
  if (!b->map) {
    vlff_warn_limited(&b->warn_attach, TAG, "map segment %s: %s (waiting for the node)", VLFF_Q(b->o.map),
                      vlff_shm_last_message());
    return NULL;
  }
  b->snap = vlff_map_snapshot_new(b->map);
  if (!b->snap) {
    drop_map(b);
    return NULL;
  }
  VLFF_INFO(TAG, "attached to %s", VLFF_Q(b->o.map));
  return b->map;
}

/* A sequence's buffer from read-only data (dds_write only reads it). */
static uint8_t *unconst(const void *p) {
  uint8_t *q;
  memcpy(&q, &p, sizeof q);
  return q;
}

static bool host_big_endian(void) {
  const uint16_t one = 1;
  return *(const uint8_t *)&one == 0;
}

static bool write_ok(struct vlff_dds *b, int id, const void *msg) {
  dds_return_t rc = dds_write(b->w[id], msg);
  if (rc < 0) vlff_warn_limited(&b->warn_write, TAG, "%s write: %s", topics[id].key, dds_strretcode(rc));
  return rc >= 0;
}

static bool send_map(struct vlff_dds *b, const struct vlff_map_info *info) {
  uint8_t *data;
  uint32_t n;
  struct vlff_map_far far = {0};
  size_t left = 0;
  if (vlff_map_snapshot_far(b->snap, &far) < 0) far.nblocks = 0;
  const size_t far_max = b->map ? (size_t)vlff_map_capacity(b->map) : 0;
  if (vlff_dds_cloud(info, &far, far_max, &data, &n, &left) < 0) {
    vlff_warn_limited(&b->warn_map, TAG, "map version %" PRIu64 ": no memory for %s's points", info->version,
                      VLFF_Q(b->o.map));
    return false;
  }
  sensor_msgs_msg_dds__PointField_ fields[5] = {
      {"x", 0, VLFF_DDS_FLOAT32, 1},     {"y", 4, VLFF_DDS_FLOAT32, 1},          {"z", 8, VLFF_DDS_FLOAT32, 1},
      {"label", 12, VLFF_DDS_UINT16, 1}, {"confidence", 16, VLFF_DDS_FLOAT32, 1},
  };
  sensor_msgs_msg_dds__PointCloud2_ msg = {0};
  msg.header.stamp = stamp_time(b->snap_stamp);
  msg.header.frame_id = b->o.dds.frame_id;
  msg.height = 1;
  msg.width = n;
  msg.fields._length = msg.fields._maximum = 5;
  msg.fields._buffer = fields;
  msg.is_bigendian = false;
  msg.point_step = VLFF_DDS_POINT_STEP;
  msg.row_step = n * VLFF_DDS_POINT_STEP;
  msg.data._length = msg.data._maximum = msg.row_step;
  msg.data._buffer = data;
  msg.is_dense = true;
  bool ok = write_ok(b, VLFF_DDS_MAP, &msg);
  free(data);
  if (!ok) return false;
  if (left)
    vlff_warn_limited(&b->warn_far, TAG, "map version %" PRIu64 ": %zu far voxels beyond the grid left out (at most %zu, "
                      "as many as the grid holds voxels, the nearest blocks first)", info->version, left, far_max);
  b->sent_version = info->version;
  b->sent_generation = info->generation;
  b->far_sent = vlff_map_snapshot_far_version(b->snap);
  b->c.maps_sent++;
  VLFF_DEBUG(TAG, "map version %" PRIu64 ": %u points (whole: %s)", info->version, n, b->full_why);
  return true;
}

/* The changed voxels not sent yet, as one update stamped and numbered with
 * the snapshot's version. */
static bool send_updates(struct vlff_dds *b, const struct vlff_map_info *info) {
  uint32_t n = (uint32_t)b->upd_n, v = (uint32_t)info->version;
  for (uint32_t k = 0; k < n; k++) {
    uint8_t *p = b->upd + (size_t)k * VLFF_DDS_UPDATE_STEP + VLFF_DDS_POINT_STEP;
    for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
  }
  sensor_msgs_msg_dds__PointField_ fields[6] = {
      {"x", 0, VLFF_DDS_FLOAT32, 1},         {"y", 4, VLFF_DDS_FLOAT32, 1},
      {"z", 8, VLFF_DDS_FLOAT32, 1},         {"label", 12, VLFF_DDS_UINT16, 1},
      {"confidence", 16, VLFF_DDS_FLOAT32, 1}, {"version", 20, VLFF_DDS_UINT32, 1},
  };
  sensor_msgs_msg_dds__PointCloud2_ msg = {0};
  msg.header.stamp = stamp_time(b->snap_stamp);
  msg.header.frame_id = b->o.dds.frame_id;
  msg.height = 1;
  msg.width = n;
  msg.fields._length = msg.fields._maximum = 6;
  msg.fields._buffer = fields;
  msg.is_bigendian = false;
  msg.point_step = VLFF_DDS_UPDATE_STEP;
  msg.row_step = n * VLFF_DDS_UPDATE_STEP;
  msg.data._length = msg.data._maximum = msg.row_step;
  msg.data._buffer = b->upd;
  msg.is_dense = true;
  if (!write_ok(b, VLFF_DDS_MAP_UPDATES, &msg)) return false;
  b->sent_version = info->version;
  b->sent_generation = info->generation;
  b->c.map_updates_sent++;
  b->c.map_update_points += n;
  VLFF_DEBUG(TAG, "map version %" PRIu64 ": update of %u voxels", info->version, n);
  return true;
}

/* What a voxel shows a subscriber: its label, and its confidence when it
 * is labelled (free and unknown voxels are not points of the whole map). */
static bool voxel_differs(const struct vlff_dds *b, const struct vlff_map_grid *g, size_t i) {
  uint16_t l = g->labels[i];
  uint8_t c = g->confidence ? g->confidence[i] : 255;
  return l != b->shadow_labels[i] || (l <= VLFF_LABEL_MAX && c != b->shadow_conf[i]);
}

/* The shadow made the snapshot's grid whole: after a whole copy (the
 * first, a restarted writer, a log overrun, a new geometry). 0 or -1. */
static int shadow_reset(struct vlff_dds *b, const struct vlff_map_grid *g) {
  size_t total = g->labels ? (size_t)g->dims[0] * g->dims[1] * g->dims[2] : 0;
  if (total != b->shadow_n) {
    free(b->shadow_labels);
    free(b->shadow_conf);
    b->shadow_labels = malloc(total ? total * 2 : 1);
    b->shadow_conf = malloc(total ? total : 1);
    b->shadow_n = b->shadow_labels && b->shadow_conf ? total : 0;
    if (!b->shadow_n && total) return -1;
  }
  if (total) memcpy(b->shadow_labels, g->labels, total * 2);
  for (size_t i = 0; i < total; i++) b->shadow_conf[i] = g->confidence ? g->confidence[i] : 255;
  return 0;
}

/* The voxels the follow changed that a subscriber sees change, appended to
 * the pending update and written into the shadow. 0 or -1 (no memory). */
static int collect_updates(struct vlff_dds *b, const struct vlff_map_grid *g) {
  const struct vlff_map_range *runs;
  size_t nruns = vlff_map_snapshot_changes(b->snap, &runs, NULL);
  for (size_t r = 0; r < nruns; r++) {
    for (size_t i = runs[r].first; i < (size_t)runs[r].first + runs[r].count && i < b->shadow_n; i++) {
      if (!voxel_differs(b, g, i)) continue;
      if (b->upd_n >= b->o.update_points_max) return -2; /* its share of dds.history_max_mb */
      if (b->upd_n == b->upd_cap) {
        size_t cap = b->upd_cap ? 2 * b->upd_cap : 256;
        uint8_t *u = cap <= UINT32_MAX / VLFF_DDS_UPDATE_STEP ? realloc(b->upd, cap * VLFF_DDS_UPDATE_STEP) : NULL;
        if (!u) return -1;
        b->upd = u;
        b->upd_cap = cap;
      }
      vlff_dds_put_point(b->upd + b->upd_n++ * VLFF_DDS_UPDATE_STEP, g, i);
      b->shadow_labels[i] = g->labels[i];
      b->shadow_conf[i] = g->confidence ? g->confidence[i] : 255;
    }
  }
  return 0;
}

/* The prompt list, when it differs from the one last sent. */
static bool send_prompt_list(struct vlff_dds *b, const struct vlff_map_info *info) {
  char *json = vlff_dds_prompt_json(b->snap, info->prompt_count);
  if (!json) return false;
  if (b->prompts_sent && !strcmp(json, b->prompts_sent)) {
    free(json);
    return true;
  }
  std_msgs_msg_dds__String_ msg = {json};
  if (!write_ok(b, VLFF_DDS_PROMPTS, &msg)) {
    free(json);
    return false;
  }
  free(b->prompts_sent);
  b->prompts_sent = json;
  b->c.prompt_lists_sent++;
  return true;
}

static int valid_pose(const double P[16]) {
  for (int i = 0; i < 16; i++)
    if (!isfinite(P[i])) return 0;
  return 1;
}

/* The camera's pose: a camera-to-world matrix as the transform
 * frame_id -> camera_frame_id. */
static void send_tf(struct vlff_dds *b, uint64_t t, const double P[16]) {
  double q[4]; /* w x y z */
  vlff_pose_quaternion(P, q);
  geometry_msgs_msg_dds__TransformStamped_ ts = {0};
  ts.header.stamp = ros_time(t);
  ts.header.frame_id = b->o.dds.frame_id;
  ts.child_frame_id = b->o.dds.camera_frame_id;
  ts.transform.translation.x = P[3];
  ts.transform.translation.y = P[7];
  ts.transform.translation.z = P[11];
  ts.transform.rotation.w = q[0];
  ts.transform.rotation.x = q[1];
  ts.transform.rotation.y = q[2];
  ts.transform.rotation.z = q[3];
  tf2_msgs_msg_dds__TFMessage_ msg = {0};
  msg.transforms._length = msg.transforms._maximum = 1;
  msg.transforms._buffer = &ts;
  if (write_ok(b, VLFF_DDS_TF, &msg)) b->c.tf_sent++;
}

#ifdef VLFF_DDS_CV
static void send_compressed(struct vlff_dds *b, int id, builtin_interfaces_msg_dds__Time_ stamp, const uint8_t *rgb,
                            uint32_t w, uint32_t h, int png) {
  uint8_t *enc = NULL;
  size_t n = 0;
  char err[160];
  if (vlff_cv_compress_rgb(rgb, (size_t)w * 3, (int)w, (int)h, png, b->o.dds.jpeg_quality, &enc, &n, err, sizeof err)) {
    vlff_warn_limited(&b->warn_image, TAG, "%s: a %ux%u image: %s", topics[id].key, w, h, err);
    return;
  }
  sensor_msgs_msg_dds__CompressedImage_ msg = {0};
  msg.header.stamp = stamp;
  msg.header.frame_id = b->o.dds.camera_frame_id;
  msg.format = png ? "png" : "jpeg";
  msg.data._length = msg.data._maximum = (uint32_t)n;
  msg.data._buffer = enc;
  write_ok(b, id, &msg);
  free(enc);
}
#endif

static void send_label_image(struct vlff_dds *b, const struct vlff_map_label_image *li) {
  builtin_interfaces_msg_dds__Time_ stamp = ros_time(li->t_ns);
  size_t px = (size_t)li->width * li->height;
  if (b->w[VLFF_DDS_LABEL_IMAGE]) {
    sensor_msgs_msg_dds__Image_ msg = {0};
    msg.header.stamp = stamp;
    msg.header.frame_id = b->o.dds.camera_frame_id;
    msg.height = li->height;
    msg.width = li->width;
    msg.encoding = "mono16";
    msg.is_bigendian = host_big_endian();
    msg.step = li->width * 2;
    msg.data._length = msg.data._maximum = (uint32_t)(px * 2);
    msg.data._buffer = unconst(li->labels);
    if (write_ok(b, VLFF_DDS_LABEL_IMAGE, &msg)) b->c.label_images_sent++;
  }
#ifdef VLFF_DDS_CV
  if (b->w[VLFF_DDS_LABEL_IMAGE_COMPRESSED]) {
    uint8_t *rgb = malloc(px * 3 + 1);
    if (rgb) {
      for (size_t i = 0; i < px; i++) {
        uint16_t l = li->labels[i];
        uint8_t *o = rgb + 3 * i;
        if (l <= VLFF_LABEL_MAX) memcpy(o, vlff_label_color(l), 3);
        else o[0] = o[1] = o[2] = l == VLFF_LABEL_FREE ? 40 : 0;
      }
      send_compressed(b, VLFF_DDS_LABEL_IMAGE_COMPRESSED, stamp, rgb, li->width, li->height, 1);
      free(rgb);
    }
  }
#endif
  if (b->w[VLFF_DDS_TF] && !b->ring_has_pose && valid_pose(li->pose)) send_tf(b, li->t_ns, li->pose);
}

/* What tells two label images apart: their stamp and their labels. */
static uint64_t label_key(const struct vlff_map_label_image *li) {
  uint64_t h = vlff_fnv1a64(VLFF_FNV1A64_INIT, &li->t_ns, sizeof li->t_ns);
  return vlff_fnv1a64(h, li->labels, (size_t)li->width * li->height * sizeof *li->labels);
}

/* The label image is a stream, like the camera's: an image that has not
 * changed is sent again each RESEND_S, so a subscriber that joined or
 * came back after a link was down (volatile: nothing is kept for it) has
 * the current one within that time, whatever the learner's refresh rate. */
#define RESEND_S 1.0
static bool label_stale(const struct vlff_dds *b) {
  return b->label_sent && (b->w[VLFF_DDS_LABEL_IMAGE] || b->w[VLFF_DDS_LABEL_IMAGE_COMPRESSED]) &&
         (double)(mono_ns() - b->last_label_ns) >= RESEND_S * 1e9;
}

static void mark_full(struct vlff_dds *b, const char *why) {
  if (!b->full_pending) b->full_why = why;
  b->full_pending = true;
}

/* The map segment, followed: a new version's changes are read once into
 * the snapshot (vlff_map_snapshot_follow); the voxels a subscriber sees
 * change go out as an update, the whole map only when a subscriber could
 * not follow otherwise (a whole copy: the first, a restarted writer, a log
 * overrun, a new geometry; new prompts, which rename the labels; more
 * updates since the last whole map than the updates' history keeps for a
 * late joiner) and every dds.map_full_period_s while the map changes. The
 * prompt list and label image go out from the same snapshot; each write
 * that failed is retried at the next poll, the label image when the rate
 * allows. */
static void poll_map(struct vlff_dds *b) {
  struct vlff_map *m = get_map(b);
  if (!m) return;
  uint64_t v = vlff_map_version(m), now = mono_ns();
  uint32_t gen = vlff_map_generation(m);
  struct vlff_map_info info;
  bool maps = b->w[VLFF_DDS_MAP] || b->w[VLFF_DDS_MAP_UPDATES];
  bool fresh = false;
  bool period_due = b->w[VLFF_DDS_MAP] && b->updates_since_full &&
                    (double)(now - b->last_full_ns) >= b->o.dds.map_full_period_s * 1e9;
  if (v && (v != b->snap_version || gen != b->snap_generation)) {
    int whole = vlff_map_snapshot_follow(m, b->snap);
    if (whole < 0 || vlff_map_snapshot_info(b->snap, &info) < 0) {
      vlff_warn_limited(&b->warn_map, TAG, "map segment %s: %s", VLFF_Q(b->o.map), vlff_shm_last_message());
      if (errno == EPIPE) drop_map(b);
      return;
    }
    b->snap_version = info.version;
    b->snap_generation = info.generation;
    b->snap_stamp = version_stamp(b, info.publish_ns);
    fresh = true;
    if (maps) {
      int upd = whole == 1 ? 0 : collect_updates(b, &info.grid);
      if (whole == 1 || upd < 0) {
        /* A whole copy, no memory for the update, or an update larger than
         * its share of the histories: subscribers get the whole map, which
         * the shadow then is. */
        b->upd_n = 0;
        mark_full(b, whole == 1 ? "a whole copy of the segment"
                     : upd == -2 ? "an update larger than its share of dds.history_max_mb"
                                 : "no memory for an update");
        if (shadow_reset(b, &info.grid) < 0) {
          vlff_warn_limited(&b->warn_map, TAG, "map version %" PRIu64 ": no memory to follow %s", info.version,
                            VLFF_Q(b->o.map));
          drop_map(b);
          return;
        }
      }
      char *json = vlff_dds_prompt_json(b->snap, info.prompt_count);
      if (json && b->full_prompts && strcmp(json, b->full_prompts)) mark_full(b, "new prompts");
      free(json);
      /* the whole map carries the far map; map/updates the grid's changes */
      if (vlff_map_snapshot_far_version(b->snap) != b->far_sent) mark_full(b, "a new far map");
    }
    b->prompts_pending = b->w[VLFF_DDS_PROMPTS] != 0;
    /* The label image is re-rendered for the same view as the field learns
     * (a refresh of the map): a new image is one whose view or labels
     * changed, not only its stamp. */
    b->label_pending = info.has_label_image && label_key(&info.label_image) != b->label_sent &&
                       (b->w[VLFF_DDS_LABEL_IMAGE] || b->w[VLFF_DDS_LABEL_IMAGE_COMPRESSED] || b->w[VLFF_DDS_TF]);
  } else if (!b->full_pending && !b->upd_n && !period_due && !b->prompts_pending && !b->label_pending &&
             !label_stale(b)) {
    return;
  } else if (vlff_map_snapshot_info(b->snap, &info) < 0) {
    return;
  }
  if (period_due) mark_full(b, "dds.map_full_period_s");
  /* A late joiner applies the updates after the whole map it gets: the
   * updates' history must still hold all of them. */
  const struct vlff_cfg_dds_qos *uq = &b->o.dds.qos[VLFF_DDS_MAP_UPDATES];
  if (b->upd_n && (!b->w[VLFF_DDS_MAP_UPDATES] ||
                   (uq->durability == VLFF_DDS_TRANSIENT_LOCAL && b->updates_since_full >= (uint64_t)uq->depth)))
    mark_full(b, b->w[VLFF_DDS_MAP_UPDATES] ? "the updates' history is full" : "dds.map_updates is off");
  bool full_now = false;
  if (b->full_pending && !b->w[VLFF_DDS_MAP]) b->full_pending = false;
  if (b->full_pending && send_map(b, &info)) {
    b->full_pending = false;
    b->full_version = info.version;
    b->last_full_ns = now;
    b->updates_since_full = 0;
    free(b->full_prompts);
    b->full_prompts = vlff_dds_prompt_json(b->snap, info.prompt_count);
    full_now = true;
  }
  if (b->upd_n && !b->w[VLFF_DDS_MAP_UPDATES]) b->upd_n = 0;
  if (b->upd_n && send_updates(b, &info)) {
    b->upd_n = 0;
    /* the whole map of the same version already holds it */
    if (!full_now) b->updates_since_full++;
  }
  /* a version that changed nothing subscribers see: they hold it already */
  if (fresh && maps && !b->full_pending && !b->upd_n) b->sent_version = info.version;
  if (b->prompts_pending && send_prompt_list(b, &info)) b->prompts_pending = false;
  if (label_stale(b) && info.has_label_image) b->label_pending = true;
  if (b->label_pending && (!b->last_label_ns || (double)(now - b->last_label_ns) >= 1e9 / b->o.dds.image_hz)) {
    send_label_image(b, &info.label_image);
    b->label_sent = label_key(&info.label_image);
    b->last_label_ns = now;
    b->label_pending = false;
  }
}

static int valid_intrinsics(const struct vlff_frame_hdr *h) {
  const double k[4] = {h->fx, h->fy, h->cx, h->cy};
  for (int i = 0; i < 4; i++)
    if (!isfinite(k[i]) || (i < 2 && k[i] <= 0)) return 0;
  return (h->flags & VLFF_FRAME_INTRINSICS_VALID) != 0;
}

/* CameraInfo of a frame's pinhole intrinsics, K and P in ROS's (OpenCV's)
 * convention, whose principal point is half a pixel left of and above the
 * ring's (pixel centres at +0.5 there). */
static void send_camera_info(struct vlff_dds *b, builtin_interfaces_msg_dds__Time_ stamp, const struct vlff_frame_hdr *h) {
  const struct vlff_plane *pl = &h->plane[VLFF_PLANE_COLOR];
  double d[5] = {0, 0, 0, 0, 0}, cx = h->cx - 0.5, cy = h->cy - 0.5;
  sensor_msgs_msg_dds__CameraInfo_ msg = {0};
  msg.header.stamp = stamp;
  msg.header.frame_id = b->o.dds.camera_frame_id;
  msg.height = pl->height;
  msg.width = pl->width;
  msg.distortion_model = "plumb_bob";
  msg.d._length = msg.d._maximum = 5;
  msg.d._buffer = d;
  const double k[9] = {h->fx, 0, cx, 0, h->fy, cy, 0, 0, 1};
  const double r[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  const double p[12] = {h->fx, 0, cx, 0, 0, h->fy, cy, 0, 0, 0, 1, 0};
  memcpy(msg.k, k, sizeof k);
  memcpy(msg.r, r, sizeof r);
  memcpy(msg.p, p, sizeof p);
  write_ok(b, VLFF_DDS_CAMERA_INFO, &msg);
}

/* The frame ring's newest frame, at most dds.image_hz a second. */
static void poll_camera(struct vlff_dds *b) {
  if (!(b->w[VLFF_DDS_CAMERA_IMAGE] || b->w[VLFF_DDS_CAMERA_IMAGE_COMPRESSED] || b->w[VLFF_DDS_CAMERA_INFO] ||
        b->w[VLFF_DDS_TF]) ||
      !*b->o.frames)
    return;
  uint64_t now = mono_ns();
  if (!b->ring) {
    if (now < b->ring_next_attach) return;
    b->ring_next_attach = now + 1000000000ull;
    b->ring = vlff_ring_attach(b->o.frames, VLFF_RECORD_FRAME);
    if (!b->ring) {
      vlff_warn_limited(&b->warn_ring, TAG, "frame ring %s: %s (retrying every second)", VLFF_Q(b->o.frames),
                        vlff_shm_last_message());
      return;
    }
    size_t cap = vlff_ring_slot_size(b->ring);
    uint8_t *rec = cap == b->rec_cap ? b->rec : realloc(b->rec, cap);
    if (!rec) {
      vlff_warn_limited(&b->warn_ring, TAG, "no memory for a %zu-byte frame of %s", cap, VLFF_Q(b->o.frames));
      vlff_ring_close(b->ring);
      b->ring = NULL;
      return;
    }
    b->rec = rec;
    b->rec_cap = cap;
    b->ring_head = 0;
    b->have_frame = false;
    VLFF_INFO(TAG, "attached to frame ring %s", VLFF_Q(b->o.frames));
  }
  uint64_t head = vlff_ring_head(b->ring);
  double since = b->last_camera_ns ? (double)(now - b->last_camera_ns) : INFINITY;
  if (since < 1e9 / b->o.dds.image_hz) return;
  /* No new frame: the last one again each RESEND_S, as the label image, so
   * that a subscriber that joined late or came back after a link was down
   * (the topics are volatile) gets the camera's latest image and pose. */
  if (head == b->ring_head && !(b->have_frame && since >= RESEND_S * 1e9)) return;
  if (head != b->ring_head) {
    struct vlff_ring_view view;
    ssize_t len = vlff_ring_read_latest(b->ring, b->rec, b->rec_cap, &view);
    if (len < 0) {
      if (errno == EPIPE) {
        VLFF_INFO(TAG, "frame ring %s was replaced; attaching again", VLFF_Q(b->o.frames));
        vlff_ring_close(b->ring);
        b->ring = NULL;
      }
      return;
    }
    b->ring_head = head;
    b->have_frame = vlff_frame_validate(b->rec, (size_t)len) == 0;
    if (!b->have_frame) {
      b->last_camera_ns = now;
      vlff_warn_limited(&b->warn_ring, TAG, "frame ring %s: a malformed frame record, skipped", VLFF_Q(b->o.frames));
      return;
    }
  }
  b->last_camera_ns = now;
  const struct vlff_frame_hdr *h = (const struct vlff_frame_hdr *)b->rec;
  const struct vlff_plane *pl = &h->plane[VLFF_PLANE_COLOR];
  const uint8_t *px = vlff_frame_plane(b->rec, VLFF_PLANE_COLOR);
  builtin_interfaces_msg_dds__Time_ stamp = ros_time(h->t_host_ns);
  const char *enc = vlff_dds_encoding(pl->format);
  if (px && b->w[VLFF_DDS_CAMERA_IMAGE]) {
    if (!enc) {
      vlff_warn_limited(&b->warn_image, TAG, "frame ring %s: pixel format %s has no ROS encoding", VLFF_Q(b->o.frames),
                        vlff_pixfmt_name(pl->format));
    } else {
      sensor_msgs_msg_dds__Image_ msg = {0};
      msg.header.stamp = stamp;
      msg.header.frame_id = b->o.dds.camera_frame_id;
      msg.height = pl->height;
      msg.width = pl->width;
      msg.encoding = (char *)enc;
      msg.is_bigendian = pl->format == VLFF_PIX_MONO16 && host_big_endian();
      msg.step = pl->stride;
      msg.data._length = msg.data._maximum = (uint32_t)((size_t)pl->stride * pl->height);
      msg.data._buffer = unconst(px);
      if (write_ok(b, VLFF_DDS_CAMERA_IMAGE, &msg)) b->c.camera_images_sent++;
    }
  }
#ifdef VLFF_DDS_CV
  if (px && b->w[VLFF_DDS_CAMERA_IMAGE_COMPRESSED]) {
    size_t need = (size_t)pl->width * pl->height * 3;
    uint8_t *rgb = malloc(need + 1);
    char err[160];
    if (!rgb)
      vlff_warn_limited(&b->warn_image, TAG, "no memory for a %ux%u image", pl->width, pl->height);
    else if (vlff_cv_to_rgb(px, pl->stride, (int)pl->width, (int)pl->height, (vlff_pix_t)pl->format, rgb,
                            (size_t)pl->width * 3, err, sizeof err))
      vlff_warn_limited(&b->warn_image, TAG, "frame ring %s: a %ux%u %s image: %s", VLFF_Q(b->o.frames), pl->width,
                        pl->height, vlff_pixfmt_name(pl->format), err);
    else
      send_compressed(b, VLFF_DDS_CAMERA_IMAGE_COMPRESSED, stamp, rgb, pl->width, pl->height, 0);
    free(rgb);
  }
#endif
  if (b->w[VLFF_DDS_CAMERA_INFO] && valid_intrinsics(h)) send_camera_info(b, stamp, h);
  if ((h->flags & VLFF_FRAME_POSE_VALID) && valid_pose(h->pose)) {
    b->ring_has_pose = true;
    if (b->w[VLFF_DDS_TF]) send_tf(b, h->pose_t_ns ? h->pose_t_ns : h->t_host_ns, h->pose);
  }
}

/* Key-value lists of the status, built in fixed storage. */
#define MAX_KV (48 + VLFF_SHM_MAX_REASONS)
/* two statuses of MAX_KV pairs (CDR: two lengths), name, message, hardware id */
_Static_assert(2 * (MAX_KV * (48 + 48 + 8) + 96 + 2 * VLFF_CFG_STR) + VLFF_DDS_MSG_OVERHEAD <=
                   VLFF_DDS_STATUS_MAX_BYTES,
               "the status fits the size dds.history_max_mb counts for it");
struct kvs {
  diagnostic_msgs_msg_dds__KeyValue_ kv[MAX_KV];
  char key[MAX_KV][48], val[MAX_KV][48];
  uint32_t n;
};

static void kv(struct kvs *k, const char *key, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
static void kv(struct kvs *k, const char *key, const char *fmt, ...) {
  if (k->n >= MAX_KV) return;
  snprintf(k->key[k->n], sizeof k->key[0], "%s", key);
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(k->val[k->n], sizeof k->val[0], fmt, ap);
  va_end(ap);
  k->kv[k->n].key = k->key[k->n];
  k->kv[k->n].value = k->val[k->n];
  k->n++;
}

static void send_status(struct vlff_dds *b) {
  static struct kvs lk, bk; /* one bridge per process (main) */
  lk.n = bk.n = 0;
  diagnostic_msgs_msg_dds__DiagnosticStatus_ st[2] = {{0}};
  char lmsg[96], bmsg[96];
  struct vlff_map *m = get_map(b);
  struct vlff_map_status s;
  int have = m && vlff_map_get_status(m, &s) == 0;
  if (m && !have && errno == EPIPE) drop_map(b);
  st[0].name = "vlff: learner";
  st[0].hardware_id = b->o.hardware_id;
  if (!have) {
    st[0].level = VLFF_DDS_STALE;
    snprintf(lmsg, sizeof lmsg, m ? "no status in %s yet" : "no map segment %s", b->o.map);
  } else {
    int alive = vlff_map_writer_alive(m, 5000000000ull);
    st[0].level = !alive ? VLFF_DDS_STALE
                  : !strcmp(s.state_name, "error") ? VLFF_DDS_ERROR
                  : s.error_flags ? VLFF_DDS_WARN : VLFF_DDS_OK;
    snprintf(lmsg, sizeof lmsg, "%s%s", s.state_name, alive ? "" : " (writer gone)");
    kv(&lk, "state", "%s", s.state_name);
    kv(&lk, "state_code", "%" PRId32, s.state);
    kv(&lk, "error_flags", "0x%" PRIx32, s.error_flags);
    kv(&lk, "updates", "%" PRIu64, s.updates);
    kv(&lk, "frames_in", "%" PRIu64, s.frames_in);
    kv(&lk, "frames_lost", "%" PRIu64, s.frames_lost);
    kv(&lk, "frames_refused", "%" PRIu64, s.frames_refused);
    kv(&lk, "keyframes", "%" PRIu64, s.keyframes);
    kv(&lk, "keyframes_evicted", "%" PRIu64, s.keyframes_evicted);
    kv(&lk, "iterations", "%" PRIu64, s.iterations);
    kv(&lk, "iterations_per_s", "%.3f", s.iterations_per_s);
    kv(&lk, "fps_in", "%.3f", s.fps_in);
    kv(&lk, "loss", "%.6g", s.loss);
    kv(&lk, "psnr", "%.3f", s.psnr);
    /* how current and how still the map is, the CPU the node takes: as
     * vlff-shm stat prints them (-1 while unknown) */
    kv(&lk, "cpu_budget", "%.3f", s.cpu_budget);
    kv(&lk, "cpu_used", "%.3f", s.cpu_used);
    kv(&lk, "frame_to_map_ms_p50", "%.1f", s.frame_to_map_ms_p50);
    kv(&lk, "frame_to_map_ms_p99", "%.1f", s.frame_to_map_ms_p99);
    kv(&lk, "publish_interval_s", "%.3f", s.publish_interval_s);
    kv(&lk, "label_flips", "%" PRIu64, s.label_flips);
    kv(&lk, "label_flips_refresh", "%" PRIu64, s.label_flips_refresh);
    kv(&lk, "label_flips_total", "%" PRIu64, s.label_flips_total);
    kv(&lk, "label_flip_frac", "%.4f", s.label_flip_frac);
    /* memory against its limits, MiB (-1 while unknown) */
    kv(&lk, "mem_keyframes_mb", "%.1f", s.mem_keyframes_mb);
    kv(&lk, "mem_keyframes_limit_mb", "%.1f", s.mem_keyframes_limit_mb);
    kv(&lk, "mem_evidence_mb", "%.1f", s.mem_evidence_mb);
    kv(&lk, "mem_evidence_limit_mb", "%.1f", s.mem_evidence_limit_mb);
    kv(&lk, "mem_field_mb", "%.1f", s.mem_field_mb);
    kv(&lk, "mem_rss_mb", "%.1f", s.mem_rss_mb);
    /* what went to the page files, came back or was dropped, and the map's
     * box: as vlff-shm stat prints them */
    kv(&lk, "keyframes_paged", "%" PRIu64, s.keyframes_paged);
    kv(&lk, "keyframes_paged_out", "%" PRIu64, s.keyframes_paged_out);
    kv(&lk, "keyframes_paged_in", "%" PRIu64, s.keyframes_paged_in);
    kv(&lk, "keyframes_dropped", "%" PRIu64, s.keyframes_dropped);
    kv(&lk, "keyframes_page_mb", "%.1f", s.keyframes_page_mb);
    kv(&lk, "keyframes_page_limit_mb", "%.1f", s.keyframes_page_limit_mb);
    kv(&lk, "evidence_paged", "%" PRIu64, s.evidence_paged);
    kv(&lk, "evidence_paged_out", "%" PRIu64, s.evidence_paged_out);
    kv(&lk, "evidence_paged_in", "%" PRIu64, s.evidence_paged_in);
    kv(&lk, "evidence_dropped", "%" PRIu64, s.evidence_dropped);
    kv(&lk, "box_lo", "%.3f %.3f %.3f", s.box_lo[0], s.box_lo[1], s.box_lo[2]);
    kv(&lk, "box_hi", "%.3f %.3f %.3f", s.box_hi[0], s.box_hi[1], s.box_hi[2]);
    kv(&lk, "box_growths", "%" PRIu64, s.box_growths);
    kv(&lk, "box_refused", "%" PRIu64, s.box_refused);
    kv(&lk, "map_version", "%" PRIu64, vlff_map_version(m));
    for (uint32_t i = 0; i < s.reason_count && i < VLFF_SHM_MAX_REASONS; i++) {
      char key[48];
      snprintf(key, sizeof key, "refused: %s", s.reason[i].name);
      kv(&lk, key, "%" PRIu64, s.reason[i].count);
    }
  }
  st[0].message = lmsg;
  st[0].values._length = st[0].values._maximum = lk.n;
  st[0].values._buffer = lk.kv;

  const struct vlff_dds_counts *c = &b->c;
  uint64_t refused = c->prompts_oversized + c->prompts_flood + c->prompts_malformed + c->prompts_invalid + c->prompts_busy;
  st[1].name = "vlff-dds: bridge";
  st[1].hardware_id = b->o.hardware_id;
  st[1].level = VLFF_DDS_OK;
  snprintf(bmsg, sizeof bmsg, "%" PRIu64 " maps and %" PRIu64 " updates sent, %" PRIu64 " prompt sets posted, %" PRIu64
           " refused", c->maps_sent, c->map_updates_sent, c->prompts_posted, refused);
  st[1].message = bmsg;
  kv(&bk, "maps_sent", "%" PRIu64, c->maps_sent);
  kv(&bk, "map_updates_sent", "%" PRIu64, c->map_updates_sent);
  kv(&bk, "map_update_points", "%" PRIu64, c->map_update_points);
  kv(&bk, "map_version_sent", "%" PRIu64, b->sent_version);
  kv(&bk, "prompt_lists_sent", "%" PRIu64, c->prompt_lists_sent);
  kv(&bk, "label_images_sent", "%" PRIu64, c->label_images_sent);
  kv(&bk, "camera_images_sent", "%" PRIu64, c->camera_images_sent);
  kv(&bk, "tf_sent", "%" PRIu64, c->tf_sent);
  kv(&bk, "prompts_posted", "%" PRIu64, c->prompts_posted);
  kv(&bk, "prompts_refused_oversized", "%" PRIu64, c->prompts_oversized);
  kv(&bk, "prompts_refused_flood", "%" PRIu64, c->prompts_flood);
  kv(&bk, "prompts_refused_malformed", "%" PRIu64, c->prompts_malformed);
  kv(&bk, "prompts_refused_invalid", "%" PRIu64, c->prompts_invalid);
  kv(&bk, "prompts_refused_busy", "%" PRIu64, c->prompts_busy);
  st[1].values._length = st[1].values._maximum = bk.n;
  st[1].values._buffer = bk.kv;

  diagnostic_msgs_msg_dds__DiagnosticArray_ msg = {0};
  msg.header.stamp = ros_time(0);
  msg.header.frame_id = b->o.dds.frame_id;
  msg.status._length = msg.status._maximum = 2;
  msg.status._buffer = st;
  if (write_ok(b, VLFF_DDS_STATUS, &msg)) b->c.status_sent++;
}

static void refuse(struct vlff_dds *b, uint64_t *count, const char *fmt, const char *why) {
  (*count)++;
  vlff_warn_limited(&b->warn_prompt, TAG, fmt, why);
}

static void take_prompt(struct vlff_dds *b, const char *data) {
  size_t len = strlen(data);
  char why[256];
  if (len > (size_t)b->o.dds.max_prompt_bytes) {
    snprintf(why, sizeof why, "%zu bytes, more than dds.max_prompt_bytes (%d)", len, b->o.dds.max_prompt_bytes);
    refuse(b, &b->c.prompts_oversized, "prompts_in: refused a message of %s", why);
    return;
  }
  char texts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
  int invalid, set_index;
  int n = vlff_dds_parse_prompts(data, len, texts, &set_index, &invalid, why, sizeof why);
  if (n < 0) {
    refuse(b, invalid ? &b->c.prompts_invalid : &b->c.prompts_malformed, "prompts_in: refused: %s", why);
    return;
  }
  /* The rate bounds what reaches the mailbox, so it counts posts; what is
   * refused above costs a bounded parse and no post. */
  uint64_t now = mono_ns();
  double gap_ns = 1e9 / b->o.dds.prompt_rate_hz;
  if (b->last_post_ns && (double)(now - b->last_post_ns) < gap_ns) {
    snprintf(why, sizeof why, "%.3g per second (dds.prompt_rate_hz)", b->o.dds.prompt_rate_hz);
    refuse(b, &b->c.prompts_flood, "prompts_in: refused a prompt set beyond %s", why);
    return;
  }
  b->last_post_ns = now;
  if (!b->mailbox) b->mailbox = vlff_prompts_attach(b->o.prompts);
  const char *ptr[VLFF_SHM_MAX_PROMPTS];
  for (int i = 0; i < n; i++) ptr[i] = texts[i];
  if (!b->mailbox || vlff_prompts_try_post(b->mailbox, n ? ptr : NULL, n, set_index) < 0) {
    int e = errno;
    snprintf(why, sizeof why, "%s: %s", b->o.prompts, vlff_shm_last_message());
    refuse(b, &b->c.prompts_busy, "prompts_in: not posted, mailbox %s", why);
    if (e == EPIPE) {
      vlff_prompts_close(b->mailbox);
      b->mailbox = NULL;
    }
    return;
  }
  b->c.prompts_posted++;
  b->pending_seq = vlff_prompts_last_post(b->mailbox);
  if (n)
    VLFF_INFO(TAG, "prompts_in: posted %d prompts as request %" PRIu64, n, b->pending_seq);
  else
    VLFF_INFO(TAG, "prompts_in: posted prompt set %d as request %" PRIu64, set_index, b->pending_seq);
}

static void take_prompts(struct vlff_dds *b) {
  for (;;) {
    void *samples[8] = {NULL};
    dds_sample_info_t info[8];
    dds_return_t n = dds_take(b->prompts_r, samples, info, 8, 8);
    if (n <= 0) return;
    for (int i = 0; i < n; i++)
      if (info[i].valid_data) take_prompt(b, ((const std_msgs_msg_dds__String_ *)samples[i])->data);
    dds_return_loan(b->prompts_r, samples, n);
  }
}

/* The learner's answer to the last post, logged once it comes. */
static void check_answer(struct vlff_dds *b) {
  if (!b->pending_seq || !b->mailbox) return;
  char reason[128];
  int a = vlff_prompts_wait_answer(b->mailbox, b->pending_seq, 0, reason, sizeof reason);
  if (a == VLFF_PROMPT_ACCEPTED)
    VLFF_INFO(TAG, "prompts_in: request %" PRIu64 " accepted by the learner", b->pending_seq);
  else if (a == VLFF_PROMPT_REFUSED)
    vlff_warn_limited(&b->warn_mailbox, TAG, "prompts_in: request %" PRIu64 " refused by the learner: %s",
                      b->pending_seq, VLFF_Q(reason));
  else if (errno == ETIMEDOUT)
    return;
  b->pending_seq = 0;
}

int vlff_dds_run(struct vlff_dds *b) {
  uint64_t start = mono_ns(), poll_ns = (uint64_t)(1e9 / b->o.dds.poll_hz);
  uint64_t status_ns = (uint64_t)(1e9 / b->o.dds.status_hz), next_status = start, next_poll = start;
  while (!b->stop && !vlff_cli_stop) {
    uint64_t now = mono_ns();
    if (b->o.run_seconds > 0 && (double)(now - start) >= b->o.run_seconds * 1e9) break;
    if (now >= next_poll) {
      poll_map(b);
      poll_camera(b);
      check_answer(b);
      next_poll = now + poll_ns;
    }
    if (b->w[VLFF_DDS_STATUS] && now >= next_status) {
      send_status(b);
      next_status = now + status_ns;
    }
    uint64_t next = next_poll;
    if (b->w[VLFF_DDS_STATUS] && next_status < next) next = next_status;
    now = mono_ns();
    dds_duration_t wait = next > now ? (dds_duration_t)(next - now) : 0;
    dds_return_t rc = dds_waitset_wait(b->ws, NULL, 0, wait);
    if (rc < 0 && rc != DDS_RETCODE_TIMEOUT) {
      VLFF_ERROR(TAG, "waitset: %s", dds_strretcode(rc));
      return -1;
    }
    if (b->prompts_r) take_prompts(b);
  }
  return 0;
}
