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
#include "log.h"
#include "sensor_msgs.h"
#include "std_msgs.h"
#include "vlff/escape.h"

#define TAG "dds"

int vlff_dds_topic(char *out, size_t len, const char *ns, const char *leaf) {
  int n = snprintf(out, len, "rt%s/vlff/%s", ns, leaf);
  return n < 0 || (size_t)n >= len ? -1 : 0;
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

int vlff_dds_cloud(const struct vlff_map_info *info, uint8_t **out, uint32_t *npoints) {
  const struct vlff_map_grid *g = &info->grid;
  size_t total = (size_t)g->dims[0] * g->dims[1] * g->dims[2];
  if (!g->labels) total = 0;
  size_t n = 0;
  for (size_t i = 0; i < total; i++) n += g->labels[i] <= VLFF_LABEL_MAX;
  uint8_t *buf = malloc(n ? n * VLFF_DDS_POINT_STEP : 1);
  if (!buf) {
    errno = ENOMEM;
    return -1;
  }
  uint8_t *p = buf;
  for (size_t i = 0; i < total; i++) {
    uint16_t l = g->labels[i];
    if (l > VLFF_LABEL_MAX) continue;
    size_t ix = i % g->dims[0], iy = (i / g->dims[0]) % g->dims[1], iz = i / ((size_t)g->dims[0] * g->dims[1]);
    put_f32(p, (float)(g->origin[0] + ((double)ix + 0.5) * g->voxel_size));
    put_f32(p + 4, (float)(g->origin[1] + ((double)iy + 0.5) * g->voxel_size));
    put_f32(p + 8, (float)(g->origin[2] + ((double)iz + 0.5) * g->voxel_size));
    p[12] = (uint8_t)l;
    p[13] = (uint8_t)(l >> 8);
    p[14] = p[15] = 0;
    put_f32(p + 16, (float)(g->confidence ? g->confidence[i] : 255) / 255.0f);
    p += VLFF_DDS_POINT_STEP;
  }
  *out = buf;
  *npoints = (uint32_t)n;
  return 0;
}

/* ------------------------------------------------------------ the bridge */

struct vlff_dds {
  struct vlff_dds_opts o;
  dds_entity_t pp, map_w, status_w, prompts_r, ws, prompts_cond;
  struct vlff_map *map;
  struct vlff_map_snapshot *snap;
  struct vlff_prompts *mailbox;
  uint64_t sent_version;
  uint32_t sent_generation;
  uint64_t pending_seq; /* last post whose answer is not logged yet */
  uint64_t last_post_ns;
  volatile sig_atomic_t stop;
  struct vlff_dds_counts c;
  uint64_t warn_attach, warn_map, warn_prompt, warn_mailbox, warn_write;
};

static void set_err(char *err, size_t errlen, const char *what, dds_return_t rc) {
  snprintf(err, errlen, "%s: %s", what, dds_strretcode(rc));
}

static dds_entity_t make_topic(struct vlff_dds *b, const dds_topic_descriptor_t *desc, const char *leaf, char *err,
                               size_t errlen) {
  char name[256];
  if (vlff_dds_topic(name, sizeof name, b->o.dds.ns, leaf) < 0) {
    snprintf(err, errlen, "topic name for %s too long", leaf);
    return -1;
  }
  dds_entity_t t = dds_create_topic(b->pp, desc, name, NULL, NULL);
  if (t < 0) set_err(err, errlen, name, t);
  return t;
}

struct vlff_dds *vlff_dds_create(const struct vlff_dds_opts *opts, char *err, size_t errlen) {
  struct vlff_dds *b = calloc(1, sizeof *b);
  if (!b) {
    snprintf(err, errlen, "out of memory");
    return NULL;
  }
  b->o = *opts;
  b->pp = dds_create_participant((dds_domainid_t)opts->dds.domain_id, NULL, NULL);
  if (b->pp < 0) {
    set_err(err, errlen, "DDS participant", b->pp);
    free(b);
    return NULL;
  }
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  if (opts->dds.map) {
    dds_entity_t t = make_topic(b, &sensor_msgs_msg_dds__PointCloud2__desc, "map", err, errlen);
    if (t < 0) goto fail;
    /* Keep last 1 on a reliable writer never blocks it: a reader that does not
     * keep up gets the newest map, and a late one gets it from the history. */
    dds_qos_t *mq = dds_create_qos();
    dds_copy_qos(mq, q);
    dds_qset_durability(mq, DDS_DURABILITY_TRANSIENT_LOCAL);
    dds_qset_history(mq, DDS_HISTORY_KEEP_LAST, 1);
    b->map_w = dds_create_writer(b->pp, t, mq, NULL);
    dds_delete_qos(mq);
    if (b->map_w < 0) {
      set_err(err, errlen, "map writer", b->map_w);
      goto fail;
    }
  }
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 10);
  if (opts->dds.status) {
    dds_entity_t t = make_topic(b, &diagnostic_msgs_msg_dds__DiagnosticArray__desc, "status", err, errlen);
    if (t < 0) goto fail;
    b->status_w = dds_create_writer(b->pp, t, q, NULL);
    if (b->status_w < 0) {
      set_err(err, errlen, "status writer", b->status_w);
      goto fail;
    }
  }
  b->ws = dds_create_waitset(b->pp);
  if (b->ws < 0) {
    set_err(err, errlen, "waitset", b->ws);
    goto fail;
  }
  if (opts->dds.prompts_in) {
    dds_entity_t t = make_topic(b, &std_msgs_msg_dds__String__desc, "prompts_in", err, errlen);
    if (t < 0) goto fail;
    b->prompts_r = dds_create_reader(b->pp, t, q, NULL);
    if (b->prompts_r < 0) {
      set_err(err, errlen, "prompts reader", b->prompts_r);
      goto fail;
    }
    b->prompts_cond = dds_create_readcondition(b->prompts_r, DDS_ANY_STATE);
    dds_return_t rc = b->prompts_cond < 0 ? b->prompts_cond : dds_waitset_attach(b->ws, b->prompts_cond, 0);
    if (rc < 0) {
      set_err(err, errlen, "prompts condition", rc);
      goto fail;
    }
  }
  dds_delete_qos(q);
  return b;
fail:
  dds_delete_qos(q);
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

static void drop_map(struct vlff_dds *b) {
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

static void send_map(struct vlff_dds *b) {
  struct vlff_map *m = get_map(b);
  if (!m) return;
  uint64_t v = vlff_map_version(m);
  uint32_t gen = vlff_map_generation(m);
  if (v == 0 || (v == b->sent_version && gen == b->sent_generation)) return;
  struct vlff_map_info info;
  if (vlff_map_snapshot_take(m, b->snap) < 0 || vlff_map_snapshot_info(b->snap, &info) < 0) {
    vlff_warn_limited(&b->warn_map, TAG, "map segment %s: %s", VLFF_Q(b->o.map), vlff_shm_last_message());
    if (errno == EPIPE) drop_map(b);
    return;
  }
  uint8_t *data;
  uint32_t n;
  if (vlff_dds_cloud(&info, &data, &n) < 0) {
    vlff_warn_limited(&b->warn_map, TAG, "map version %" PRIu64 ": no memory for %s's points", info.version,
                      VLFF_Q(b->o.map));
    return;
  }
  sensor_msgs_msg_dds__PointField_ fields[5] = {
      {"x", 0, VLFF_DDS_FLOAT32, 1},     {"y", 4, VLFF_DDS_FLOAT32, 1},          {"z", 8, VLFF_DDS_FLOAT32, 1},
      {"label", 12, VLFF_DDS_UINT16, 1}, {"confidence", 16, VLFF_DDS_FLOAT32, 1},
  };
  sensor_msgs_msg_dds__PointCloud2_ msg = {0};
  msg.header.stamp = ros_time(info.publish_ns);
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
  dds_return_t rc = dds_write(b->map_w, &msg);
  free(data);
  if (rc < 0) {
    vlff_warn_limited(&b->warn_write, TAG, "map write: %s", dds_strretcode(rc));
    return;
  }
  b->sent_version = info.version;
  b->sent_generation = info.generation;
  b->c.maps_sent++;
  VLFF_DEBUG(TAG, "map version %" PRIu64 ": %u points", info.version, n);
}

/* Key-value lists of the status, built in fixed storage. */
#define MAX_KV (24 + VLFF_SHM_MAX_REASONS)
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
  snprintf(bmsg, sizeof bmsg, "%" PRIu64 " maps sent, %" PRIu64 " prompt sets posted, %" PRIu64 " refused", c->maps_sent,
           c->prompts_posted, refused);
  st[1].message = bmsg;
  kv(&bk, "maps_sent", "%" PRIu64, c->maps_sent);
  kv(&bk, "map_version_sent", "%" PRIu64, b->sent_version);
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
  dds_return_t rc = dds_write(b->status_w, &msg);
  if (rc < 0)
    vlff_warn_limited(&b->warn_write, TAG, "status write: %s", dds_strretcode(rc));
  else
    b->c.status_sent++;
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
      if (b->map_w) send_map(b);
      check_answer(b);
      next_poll = now + poll_ns;
    }
    if (b->status_w && now >= next_status) {
      send_status(b);
      next_status = now + status_ns;
    }
    uint64_t next = next_poll;
    if (b->status_w && next_status < next) next = next_status;
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
