/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * dds_probe: a DDS subscriber for test_dds_netns.sh, written only against
 * Cyclone DDS's C API and the C that idlc generates from node/dds/idl (no
 * vlff-dds code), as a ROS 2 node or any other DDS program would be. It
 * checks what it receives field by field against the map segment, read with
 * libvlff-shm.
 *
 * Usage: dds_probe MODE DOMAIN NAMESPACE MAP NODE_NAME TIMEOUT_S [FRAMES [compressed]]
 *   final  wait until the node is gone, then until the map followed as
 *          docs/dds.md says (a whole map, the updates stamped after it)
 *          equals the segment's last map and a status matches its status;
 *          prints "maps_sent N" (the bridge's count then); with FRAMES (the
 *          frame ring) also until the prompt list, the label image, the
 *          camera image, its camera info and the camera pose (tf) equal
 *          the segment's and the ring's newest; with "compressed" also until
 *          the label image came as a PNG and the camera image as a JPEG
 *          stamped as the raw ones
 *   late   a reader joining after that: the map comes from the writers'
 *          histories (the whole map and the updates after it); prints
 *          "maps_sent N" from a later status
 *   follow  (NODE_NAME is a map version V) the map followed from whenever
 *          the probe joins, a whole map then updates, until the segment
 *          holds version V and what the probe holds equals it, its last
 *          update numbered V; every later whole map equal to what the
 *          updates built; without the last update the comparison fails
 *   prompts  post bad and good prompt messages to prompts_in and wait for
 *          the bridge's status to count each as expected
 *   stall  a subscriber that never reads: reliable keep-all readers of at
 *          most 4 samples each on every topic the bridge writes, held until
 *          TIMEOUT_S or a signal; prints how many samples it holds
 *   flood  2000 prompt messages as fast as DDS takes them (malformed,
 *          invalid, oversized and valid ones), then waits for the
 *          bridge's status to have counted at least one of each kind;
 *          prints the counts
 *   badmap  a robot gone wrong, for vlff-merge: on <ns>/vlff/map a cloud
 *          whose data is shorter than its points, on <ns>/vlff/prompts a
 *          list that is not JSON (both latched), held until TIMEOUT_S
 *   texts  a robot with 32 prompt texts of its own ("thing 0" ...) and an
 *          empty map (no points), both latched, for vlff-merge: with other
 *          robots' texts more than a fleet's 32; held until TIMEOUT_S
 *   tf     a robot's localisation, for vlff-merge: MAP is X,Y,Z,YAW (m,
 *          degrees about +z) and NODE_NAME PARENT:CHILD; the transform
 *          PARENT -> CHILD latched on <ns>/tf_static (transient local, as
 *          ROS's static_transform_publisher), with a transform between two
 *          other frames in the same message; held until TIMEOUT_S
 * Exit 0 when every check held; "FAIL: ..." lines and 1 otherwise.
 */
#include <math.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include <dds/dds.h>

#include "diagnostic_msgs.h"
#include "sensor_msgs.h"
#include "std_msgs.h"
#include "tf2_msgs.h"
#include "vlff/shm.h"

static int fails;
#define CHECK(cond, ...)                                                                                               \
  do {                                                                                                                 \
    if (!(cond)) {                                                                                                     \
      printf("FAIL: " __VA_ARGS__);                                                                                    \
      printf("\n");                                                                                                    \
      fails++;                                                                                                         \
    }                                                                                                                  \
  } while (0)

static double now_s(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

static float get_f32(const uint8_t *p) {
  uint32_t u = (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
  float f;
  memcpy(&f, &u, 4);
  return f;
}

/* The map message against a snapshot: layout, then every point at a
 * labelled voxel's centre with its label and confidence, each voxel once,
 * all of them. Returns the number of mismatches, the first few printed
 * when verbose. */
static int compare_map(const sensor_msgs_msg_dds__PointCloud2_ *m, const struct vlff_map_info *in, bool verbose) {
  int bad = 0;
#define MISMATCH(...)                                                                                                  \
  do {                                                                                                                 \
    if (verbose && bad < 5) {                                                                                          \
      printf("map mismatch: " __VA_ARGS__);                                                                            \
      printf("\n");                                                                                                    \
    }                                                                                                                  \
    bad++;                                                                                                             \
  } while (0)
  static const struct {
    const char *name;
    uint32_t off;
    uint8_t type;
  } want[5] = {{"x", 0, 7}, {"y", 4, 7}, {"z", 8, 7}, {"label", 12, 4}, {"confidence", 16, 7}};
  if (m->fields._length != 5) MISMATCH("%u fields, expected 5", m->fields._length);
  for (uint32_t i = 0; i < m->fields._length && i < 5; i++) {
    const sensor_msgs_msg_dds__PointField_ *f = &m->fields._buffer[i];
    if (strcmp(f->name, want[i].name) || f->offset != want[i].off || f->datatype != want[i].type || f->count != 1)
      MISMATCH("field %u is %s@%u type %u count %u", i, f->name, f->offset, f->datatype, f->count);
  }
  if (m->is_bigendian || m->height != 1 || m->point_step != 20 || m->row_step != m->width * 20 ||
      m->data._length != m->row_step)
    MISMATCH("layout: bigendian %d height %u point_step %u row_step %u width %u data %u", m->is_bigendian, m->height,
             m->point_step, m->row_step, m->width, m->data._length);
  if (bad) return bad;
  const struct vlff_map_grid *g = &in->grid;
  size_t total = (size_t)g->dims[0] * g->dims[1] * g->dims[2], labelled = 0;
  for (size_t i = 0; i < total; i++) labelled += g->labels[i] <= VLFF_LABEL_MAX;
  if (m->width != labelled) MISMATCH("%u points, the segment has %zu labelled voxels", m->width, labelled);
  uint8_t *seen = calloc(total ? total : 1, 1);
  for (uint32_t p = 0; p < m->width && bad < 50; p++) {
    const uint8_t *d = m->data._buffer + (size_t)p * 20;
    double c[3];
    size_t ix[3];
    bool inside = true;
    for (int a = 0; a < 3; a++) {
      c[a] = get_f32(d + 4 * a);
      double f = (c[a] - g->origin[a]) / g->voxel_size;
      inside = inside && f >= 0 && f < g->dims[a];
      ix[a] = inside ? (size_t)f : 0;
      /* at the voxel's centre, to float precision */
      if (inside && fabs(f - (double)ix[a] - 0.5) > 1e-3) MISMATCH("point %u axis %d not at a voxel centre (%g)", p, a, f);
    }
    if (!inside) {
      MISMATCH("point %u (%g %g %g) outside the grid", p, c[0], c[1], c[2]);
      continue;
    }
    size_t i = ix[0] + g->dims[0] * (ix[1] + g->dims[1] * ix[2]);
    uint16_t label = (uint16_t)(d[12] | d[13] << 8);
    float conf = get_f32(d + 16), want_conf = (float)(g->confidence ? g->confidence[i] : 255) / 255.0f;
    if (seen[i]++) MISMATCH("voxel %zu sent twice", i);
    if (label != g->labels[i]) MISMATCH("point %u label %u, segment %u", p, label, g->labels[i]);
    if (fabsf(conf - want_conf) > 1e-6f) MISMATCH("point %u confidence %g, segment %g", p, conf, want_conf);
  }
  free(seen);
  return bad;
}

static const char *value_of(const diagnostic_msgs_msg_dds__DiagnosticStatus_ *s, const char *key) {
  for (uint32_t i = 0; i < s->values._length; i++)
    if (!strcmp(s->values._buffer[i].key, key)) return s->values._buffer[i].value;
  return NULL;
}

static const diagnostic_msgs_msg_dds__DiagnosticStatus_ *entry(const diagnostic_msgs_msg_dds__DiagnosticArray_ *a,
                                                               const char *name) {
  for (uint32_t i = 0; i < a->status._length; i++)
    if (!strcmp(a->status._buffer[i].name, name)) return &a->status._buffer[i];
  return NULL;
}

static bool num_is(const diagnostic_msgs_msg_dds__DiagnosticStatus_ *s, const char *key, uint64_t want) {
  const char *v = value_of(s, key);
  return v && strtoull(v, NULL, 10) == want;
}

static bool text_is(const diagnostic_msgs_msg_dds__DiagnosticStatus_ *s, const char *key, const char *fmt, double want) {
  char w[48];
  snprintf(w, sizeof w, fmt, want);
  const char *v = value_of(s, key);
  return v && !strcmp(v, w);
}

/* A box corner as the bridge prints it, "x y z" in metres. */
static bool box_is(const diagnostic_msgs_msg_dds__DiagnosticStatus_ *s, const char *key, const double v[3]) {
  char w[96];
  snprintf(w, sizeof w, "%.3f %.3f %.3f", v[0], v[1], v[2]);
  const char *got = value_of(s, key);
  return got && !strcmp(got, w);
}

/* The learner's entry against the segment's status (the node gone). */
static int compare_status(const diagnostic_msgs_msg_dds__DiagnosticArray_ *a, struct vlff_map *m, const char *node,
                          bool verbose) {
  struct vlff_map_status st;
  if (vlff_map_get_status(m, &st) < 0) return 1;
  const diagnostic_msgs_msg_dds__DiagnosticStatus_ *l = entry(a, "vlff: learner");
  int bad = 0;
  if (!l) return 1;
  const char *state = value_of(l, "state");
  bad += !state || strcmp(state, st.state_name);
  bad += !num_is(l, "updates", st.updates) + !num_is(l, "frames_in", st.frames_in) +
         !num_is(l, "frames_lost", st.frames_lost) + !num_is(l, "frames_refused", st.frames_refused) +
         !num_is(l, "keyframes", st.keyframes) + !num_is(l, "iterations", st.iterations) +
         !num_is(l, "map_version", vlff_map_version(m)) + !num_is(l, "label_flips", st.label_flips) +
         !num_is(l, "label_flips_refresh", st.label_flips_refresh) +
         !num_is(l, "label_flips_total", st.label_flips_total) + !text_is(l, "cpu_used", "%.3f", st.cpu_used) +
         !text_is(l, "frame_to_map_ms_p99", "%.1f", st.frame_to_map_ms_p99) +
         !text_is(l, "publish_interval_s", "%.3f", st.publish_interval_s) +
         !text_is(l, "label_flip_frac", "%.4f", st.label_flip_frac) +
         !text_is(l, "mem_keyframes_mb", "%.1f", st.mem_keyframes_mb) +
         !text_is(l, "mem_keyframes_limit_mb", "%.1f", st.mem_keyframes_limit_mb) +
         !text_is(l, "mem_rss_mb", "%.1f", st.mem_rss_mb);
  /* paging and the map's box: every key, whatever its value */
  bad += !num_is(l, "keyframes_paged", st.keyframes_paged) + !num_is(l, "keyframes_paged_out", st.keyframes_paged_out) +
         !num_is(l, "keyframes_paged_in", st.keyframes_paged_in) +
         !num_is(l, "keyframes_dropped", st.keyframes_dropped) +
         !text_is(l, "keyframes_page_mb", "%.1f", st.keyframes_page_mb) +
         !text_is(l, "keyframes_page_limit_mb", "%.1f", st.keyframes_page_limit_mb) +
         !num_is(l, "evidence_paged", st.evidence_paged) + !num_is(l, "evidence_paged_out", st.evidence_paged_out) +
         !num_is(l, "evidence_paged_in", st.evidence_paged_in) + !num_is(l, "evidence_dropped", st.evidence_dropped) +
         !box_is(l, "box_lo", st.box_lo) + !box_is(l, "box_hi", st.box_hi) +
         !num_is(l, "box_growths", st.box_growths) + !num_is(l, "box_refused", st.box_refused);
  for (uint32_t i = 0; i < st.reason_count; i++) {
    char key[64];
    snprintf(key, sizeof key, "refused: %s", st.reason[i].name);
    bad += !num_is(l, key, st.reason[i].count);
  }
  bad += l->level != 3; /* STALE: the writer is gone */
  bad += strcmp(l->hardware_id, node) != 0;
  if (verbose && bad)
    printf("status mismatch: level %u state %s updates %s/%llu iterations %s/%llu hardware_id %s\n", l->level,
           state ? state : "-", value_of(l, "updates") ? value_of(l, "updates") : "-",
           (unsigned long long)st.updates, value_of(l, "iterations") ? value_of(l, "iterations") : "-",
           (unsigned long long)st.iterations, l->hardware_id);
  return bad;
}

static dds_entity_t reader(dds_entity_t pp, const dds_topic_descriptor_t *d, const char *ns, const char *leaf,
                           bool transient) {
  char name[256];
  snprintf(name, sizeof name, "rt%s/vlff/%s", ns, leaf);
  dds_entity_t t = dds_create_topic(pp, d, name, NULL, NULL);
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 1);
  if (transient) dds_qset_durability(q, DDS_DURABILITY_TRANSIENT_LOCAL);
  dds_entity_t r = dds_create_reader(pp, t, q, NULL);
  dds_delete_qos(q);
  return r;
}

/* The newest sample of r, on loan in *s (return it with dds_return_loan
 * (r, s, 1)): 1, or 0 when none came. Readers keep the last sample only. */
static int take_one(dds_entity_t r, void **s) {
  dds_sample_info_t info;
  for (;;) {
    s[0] = NULL;
    dds_return_t n = dds_take(r, s, &info, 1, 1);
    if (n <= 0) return 0;
    if (info.valid_data) return 1;
    dds_return_loan(r, s, n);
  }
}

static int wait_data(dds_entity_t ws, double deadline) {
  double left = deadline - now_s();
  if (left <= 0) return 0;
  dds_waitset_wait(ws, NULL, 0, DDS_MSECS(left > 0.1 ? 100 : (int64_t)(left * 1000) + 1));
  return 1;
}

static dds_entity_t waitset_of(dds_entity_t pp, dds_entity_t r1, dds_entity_t r2) {
  dds_entity_t ws = dds_create_waitset(pp);
  dds_waitset_attach(ws, dds_create_readcondition(r1, DDS_ANY_STATE), 1);
  if (r2) dds_waitset_attach(ws, dds_create_readcondition(r2, DDS_ANY_STATE), 2);
  return ws;
}

/* ------------------------------------------------- following the map */

/* Whole maps (map) and updates (map/updates) as received, replayed the way
 * docs/dds.md tells a subscriber: start from a whole map, apply the updates
 * stamped later than the map held, in stamp order; a later whole map
 * replaces what is held. */
struct cloud_msg {
  int64_t stamp;
  uint32_t version; /* updates */
  uint32_t n;
  uint8_t *data;    /* n points of 20 (whole) or 24 (update) bytes */
};
struct follower {
  dds_entity_t map, upd, ws;
  struct cloud_msg *full, *up;
  size_t nfull, nup, capfull, capup;
  int layout_bad;
};

static int64_t stamp_ns(builtin_interfaces_msg_dds__Time_ t) { return (int64_t)t.sec * 1000000000 + t.nanosec; }

/* The fields the bridge writes, the update's with its version after them. */
static bool layout_ok(const sensor_msgs_msg_dds__PointCloud2_ *m, bool update) {
  static const struct {
    const char *name;
    uint32_t off;
    uint8_t type;
  } want[6] = {{"x", 0, 7}, {"y", 4, 7}, {"z", 8, 7}, {"label", 12, 4}, {"confidence", 16, 7}, {"version", 20, 6}};
  uint32_t nf = update ? 6 : 5, step = update ? 24 : 20;
  bool ok = m->fields._length == nf && !m->is_bigendian && m->height == 1 && m->point_step == step &&
            m->row_step == m->width * step && m->data._length == m->row_step && !strcmp(m->header.frame_id, "map");
  for (uint32_t i = 0; ok && i < nf; i++) {
    const sensor_msgs_msg_dds__PointField_ *f = &m->fields._buffer[i];
    ok = !strcmp(f->name, want[i].name) && f->offset == want[i].off && f->datatype == want[i].type && f->count == 1;
  }
  if (!ok)
    printf("%s layout: %u fields, bigendian %d height %u point_step %u row_step %u width %u data %u frame %s\n",
           update ? "update" : "map", m->fields._length, m->is_bigendian, m->height, m->point_step, m->row_step,
           m->width, m->data._length, m->header.frame_id);
  return ok;
}

static dds_entity_t follow_reader(dds_entity_t pp, const char *ns, const char *leaf, int depth) {
  char name[256];
  snprintf(name, sizeof name, "rt%s/vlff/%s", ns, leaf);
  dds_entity_t t = dds_create_topic(pp, &sensor_msgs_msg_dds__PointCloud2__desc, name, NULL, NULL);
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, depth);
  dds_qset_durability(q, DDS_DURABILITY_TRANSIENT_LOCAL);
  dds_entity_t r = dds_create_reader(pp, t, q, NULL);
  dds_delete_qos(q);
  return r;
}

static void follower_open(struct follower *f, dds_entity_t pp, const char *ns) {
  memset(f, 0, sizeof *f);
  f->map = follow_reader(pp, ns, "map", 100);
  f->upd = follow_reader(pp, ns, "map/updates", 1000);
  f->ws = waitset_of(pp, f->map, f->upd);
}

/* Takes what came on both topics; the number of messages. */
static int follower_take(struct follower *f) {
  int got = 0;
  for (int u = 0; u < 2; u++) {
    dds_entity_t r = u ? f->upd : f->map;
    for (;;) {
      void *s[16] = {NULL};
      dds_sample_info_t info[16];
      dds_return_t n = dds_take(r, s, info, 16, 16);
      if (n <= 0) break;
      for (int k = 0; k < n; k++) {
        if (!info[k].valid_data) continue;
        const sensor_msgs_msg_dds__PointCloud2_ *m = s[k];
        if (!layout_ok(m, u)) {
          f->layout_bad++;
          continue;
        }
        struct cloud_msg **list = u ? &f->up : &f->full;
        size_t *len = u ? &f->nup : &f->nfull, *cap = u ? &f->capup : &f->capfull;
        if (*len == *cap) {
          *cap = *cap ? 2 * *cap : 64;
          *list = realloc(*list, *cap * sizeof **list);
        }
        struct cloud_msg *c = &(*list)[(*len)++];
        c->stamp = stamp_ns(m->header.stamp);
        c->n = m->width;
        c->data = malloc(m->data._length + 1);
        memcpy(c->data, m->data._buffer, m->data._length);
        c->version = 0;
        if (u && m->width) {
          const uint8_t *v = m->data._buffer + 20;
          c->version = (uint32_t)v[0] | (uint32_t)v[1] << 8 | (uint32_t)v[2] << 16 | (uint32_t)v[3] << 24;
        }
        got++;
      }
      dds_return_loan(r, s, n);
    }
  }
  return got;
}

static void follower_close(struct follower *f) {
  for (size_t i = 0; i < f->nfull; i++) free(f->full[i].data);
  for (size_t i = 0; i < f->nup; i++) free(f->up[i].data);
  free(f->full);
  free(f->up);
}

/* A point's voxel in g, or SIZE_MAX when it is not at a voxel centre. */
static size_t voxel_of(const struct vlff_map_grid *g, const uint8_t *d) {
  size_t ix[3];
  for (int a = 0; a < 3; a++) {
    double c = get_f32(d + 4 * a), f = (c - g->origin[a]) / g->voxel_size;
    if (!(f >= 0 && f < g->dims[a]) || fabs(f - floor(f) - 0.5) > 1e-3) return SIZE_MAX;
    ix[a] = (size_t)f;
  }
  return ix[0] + g->dims[0] * (ix[1] + g->dims[1] * ix[2]);
}

static void apply_points(const struct vlff_map_grid *g, const struct cloud_msg *c, uint32_t step, uint16_t *label,
                         float *conf, int *bad) {
  for (uint32_t p = 0; p < c->n; p++) {
    const uint8_t *d = c->data + (size_t)p * step;
    size_t i = voxel_of(g, d);
    if (i == SIZE_MAX) {
      (*bad)++;
      continue;
    }
    label[i] = (uint16_t)(d[12] | d[13] << 8);
    conf[i] = get_f32(d + 16);
  }
}

/* Mismatches between what a subscriber holds and a whole map (labelled
 * voxels, their labels and confidences). */
static size_t held_vs_full(const struct vlff_map_grid *g, const uint16_t *label, const float *conf,
                           const struct cloud_msg *c) {
  size_t total = (size_t)g->dims[0] * g->dims[1] * g->dims[2], bad = 0;
  uint16_t *l2 = malloc(total * 2);
  float *c2 = malloc(total * 4);
  for (size_t i = 0; i < total; i++) l2[i] = VLFF_LABEL_UNKNOWN, c2[i] = 0;
  int outside = 0;
  apply_points(g, c, 20, l2, c2, &outside);
  for (size_t i = 0; i < total; i++) {
    bool a = label[i] <= VLFF_LABEL_MAX, b = l2[i] <= VLFF_LABEL_MAX;
    bad += a != b || (a && (label[i] != l2[i] || conf[i] != c2[i]));
  }
  free(l2);
  free(c2);
  return bad + (size_t)outside;
}

struct replay {
  size_t fulls_used, fulls_differing, updates_applied;
  uint32_t last_version; /* of the last update applied */
  int64_t held_stamp;
  int outside;
};

/* Replays f into label/conf over g's geometry; skip: an update index left
 * out (SIZE_MAX: none). 0, or -1 when no whole map came. */
static int replay(const struct follower *f, const struct vlff_map_grid *g, size_t skip, uint16_t *label, float *conf,
                  struct replay *r) {
  memset(r, 0, sizeof *r);
  if (!f->nfull) return -1;
  size_t total = (size_t)g->dims[0] * g->dims[1] * g->dims[2], first = 0;
  for (size_t i = 1; i < f->nfull; i++)
    if (f->full[i].stamp < f->full[first].stamp) first = i;
  for (size_t i = 0; i < total; i++) label[i] = VLFF_LABEL_UNKNOWN, conf[i] = 0;
  apply_points(g, &f->full[first], 20, label, conf, &r->outside);
  r->held_stamp = f->full[first].stamp;
  r->fulls_used = 1;
  /* both lists arrive in their writer's order, which is stamp order */
  size_t u = 0, w = 0;
  for (;;) {
    while (w < f->nfull && f->full[w].stamp <= r->held_stamp) w++;
    while (u < f->nup && f->up[u].stamp <= r->held_stamp) u++;
    bool take_up = u < f->nup && (w >= f->nfull || f->up[u].stamp <= f->full[w].stamp);
    if (take_up) {
      if (u != skip) {
        apply_points(g, &f->up[u], 24, label, conf, &r->outside);
        r->updates_applied++;
        r->last_version = f->up[u].version;
      }
      r->held_stamp = f->up[u].stamp;
      /* a whole map of the same version: what it holds must be what the updates built */
      for (size_t k = w; k < f->nfull && f->full[k].stamp == r->held_stamp; k++) {
        r->fulls_used++;
        r->fulls_differing += held_vs_full(g, label, conf, &f->full[k]) != 0;
      }
      u++;
    } else if (w < f->nfull) {
      /* a newer whole map replaces what is held */
      r->fulls_used++;
      r->fulls_differing += held_vs_full(g, label, conf, &f->full[w]) != 0;
      for (size_t i = 0; i < total; i++) label[i] = VLFF_LABEL_UNKNOWN, conf[i] = 0;
      apply_points(g, &f->full[w], 20, label, conf, &r->outside);
      r->held_stamp = f->full[w].stamp;
    } else {
      break;
    }
  }
  return 0;
}

/* What is held as a whole map message (5 fields, 20 bytes a point), for
 * compare_map against the segment. */
static void held_cloud(const struct vlff_map_grid *g, const uint16_t *label, const float *conf,
                       sensor_msgs_msg_dds__PointCloud2_ *m, sensor_msgs_msg_dds__PointField_ fields[5]) {
  static const sensor_msgs_msg_dds__PointField_ want[5] = {
      {"x", 0, 7, 1}, {"y", 4, 7, 1}, {"z", 8, 7, 1}, {"label", 12, 4, 1}, {"confidence", 16, 7, 1}};
  size_t total = (size_t)g->dims[0] * g->dims[1] * g->dims[2], n = 0;
  for (size_t i = 0; i < total; i++) n += label[i] <= VLFF_LABEL_MAX;
  memcpy(fields, want, sizeof want);
  memset(m, 0, sizeof *m);
  m->height = 1;
  m->width = (uint32_t)n;
  m->fields._length = m->fields._maximum = 5;
  m->fields._buffer = fields;
  m->point_step = 20;
  m->row_step = (uint32_t)n * 20;
  m->data._length = m->data._maximum = m->row_step;
  m->data._buffer = malloc(n * 20 + 1);
  uint8_t *p = m->data._buffer;
  for (size_t i = 0; i < total; i++) {
    if (label[i] > VLFF_LABEL_MAX) continue;
    size_t ix = i % g->dims[0], iy = (i / g->dims[0]) % g->dims[1], iz = i / ((size_t)g->dims[0] * g->dims[1]);
    float xyz[3] = {(float)(g->origin[0] + ((double)ix + 0.5) * g->voxel_size),
                    (float)(g->origin[1] + ((double)iy + 0.5) * g->voxel_size),
                    (float)(g->origin[2] + ((double)iz + 0.5) * g->voxel_size)};
    memcpy(p, xyz, 12); /* little-endian hosts (the bridge's own tests run there) */
    p[12] = (uint8_t)label[i], p[13] = (uint8_t)(label[i] >> 8), p[14] = p[15] = 0;
    memcpy(p + 16, &conf[i], 4);
    p += 20;
  }
}

/* What f holds now against the snapshot's map: mismatches (compare_map's),
 * the replay's counts in *r. */
static int follower_compare(const struct follower *f, const struct vlff_map_info *in, size_t skip, bool verbose,
                            struct replay *r) {
  const struct vlff_map_grid *g = &in->grid;
  size_t total = (size_t)g->dims[0] * g->dims[1] * g->dims[2];
  uint16_t *label = malloc(total * 2 + 2);
  float *conf = malloc(total * 4 + 4);
  int bad;
  if (replay(f, g, skip, label, conf, r) < 0) {
    bad = -1;
  } else {
    sensor_msgs_msg_dds__PointCloud2_ m;
    sensor_msgs_msg_dds__PointField_ fields[5];
    held_cloud(g, label, conf, &m, fields);
    bad = compare_map(&m, in, verbose) + r->outside;
    free(m.data._buffer);
  }
  free(label);
  free(conf);
  return bad;
}

/* follow: the map followed from wherever this subscriber joins (a whole
 * map, then updates), until the segment holds version final and what is
 * held equals it; every later whole map must equal what the updates
 * built; the same replay without the last update must differ (the check
 * sees a dropped update). */
static int follow(dds_entity_t pp, const char *ns, struct vlff_map *m, uint64_t final, double deadline) {
  struct follower f;
  follower_open(&f, pp, ns);
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(m);
  struct vlff_map_info in;
  int bad = -1;
  struct replay r = {0};
  while (wait_data(f.ws, deadline)) {
    if (!follower_take(&f) || vlff_map_version(m) != final) continue;
    if (vlff_map_snapshot_take(m, snap) < 0 || vlff_map_snapshot_info(snap, &in) < 0 || in.version != final) continue;
    bad = follower_compare(&f, &in, SIZE_MAX, false, &r);
    if (!bad && r.last_version == (uint32_t)final) break;
  }
  if (bad) bad = vlff_map_snapshot_take(m, snap) < 0 || vlff_map_snapshot_info(snap, &in) < 0
                     ? -1
                     : follower_compare(&f, &in, SIZE_MAX, true, &r);
  printf("follow: %zu whole maps and %zu updates received, %zu whole maps and %zu updates applied; "
         "held version %u, segment %llu\n",
         f.nfull, f.nup, r.fulls_used, r.updates_applied, r.last_version, (unsigned long long)in.version);
  CHECK(f.nfull > 0, "no whole map received");
  CHECK(!f.layout_bad, "%d messages not in the bridge's layout", f.layout_bad);
  CHECK(bad == 0, "what the subscriber holds differs from the segment's map (%d mismatches)", bad);
  CHECK(r.last_version == (uint32_t)final, "the last update applied brings version %u, the segment holds %llu",
        r.last_version, (unsigned long long)final);
  CHECK(r.fulls_differing == 0, "%zu later whole maps differ from what the updates built", r.fulls_differing);
  CHECK(r.updates_applied > 0, "no update applied: the updates were not tested");
  /* the check must see a lost update: the last one applied, left out */
  size_t last = SIZE_MAX;
  for (size_t i = 0; i < f.nup; i++)
    if (f.up[i].version == r.last_version) last = i;
  struct replay r2;
  int bad2 = last == SIZE_MAX ? 0 : follower_compare(&f, &in, last, false, &r2);
  printf("follow: without the last update, %d mismatches\n", bad2);
  CHECK(bad2 > 0, "leaving the last update out changes nothing: the comparison cannot see a lost update");
  follower_close(&f);
  vlff_map_snapshot_free(snap);
  return 0;
}

/* final and late: the latest map and status against the segment, until
 * both match or the deadline. */
static int check_map_status(dds_entity_t pp, const char *ns, struct vlff_map *m, const char *node, double deadline,
                            bool late) {
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(m);
  struct vlff_map_info in;
  if (!snap || vlff_map_snapshot_take(m, snap) < 0 || vlff_map_snapshot_info(snap, &in) < 0) {
    printf("FAIL: snapshot: %s\n", vlff_shm_last_message());
    return 1;
  }
  /* the map as a subscriber follows it: a whole map, then updates */
  struct follower f;
  follower_open(&f, pp, ns);
  struct replay r;
  dds_entity_t sr = reader(pp, &diagnostic_msgs_msg_dds__DiagnosticArray__desc, ns, "status", false);
  dds_entity_t ws = f.ws;
  dds_waitset_attach(ws, dds_create_readcondition(sr, DDS_ANY_STATE), 3);
  int map_ok = 0, status_ok = 0, maps = 0, statuses = 0, last_map_bad = -1, last_status_bad = -1;
  long long sent = -1, sent_first = -1;
  int status_after_map = 0;
  while ((!map_ok || !status_ok || (late && status_after_map < 2)) && wait_data(ws, deadline)) {
    void *s[1];
    int got = follower_take(&f);
    if (got) {
      maps += got;
      last_map_bad = follower_compare(&f, &in, SIZE_MAX, false, &r);
      struct timespec rt;
      clock_gettime(CLOCK_REALTIME, &rt);
      double age = f.nfull ? (double)rt.tv_sec - (double)(f.full[f.nfull - 1].stamp / 1000000000) : 0;
      CHECK(!f.layout_bad, "%d map messages not in the bridge's layout", f.layout_bad);
      CHECK(age > -5 && age < 600, "map stamp is %g s from now", age);
      if (!last_map_bad) map_ok = 1;
    }
    if (take_one(sr, s)) {
      const diagnostic_msgs_msg_dds__DiagnosticArray_ *a = s[0];
      statuses++;
      const diagnostic_msgs_msg_dds__DiagnosticStatus_ *br = entry(a, "vlff-dds: bridge");
      const char *v = br ? value_of(br, "maps_sent") : NULL;
      if (v) sent = strtoll(v, NULL, 10);
      if (sent_first < 0) sent_first = sent;
      last_status_bad = compare_status(a, m, node, true) + !(br && num_is(br, "map_version_sent", in.version));
      if (!last_status_bad) status_ok = 1;
      if (map_ok) status_after_map++;
      dds_return_loan(sr, s, 1);
    }
  }
  size_t total = (size_t)in.grid.dims[0] * in.grid.dims[1] * in.grid.dims[2], labelled = 0;
  for (size_t i = 0; i < total; i++) labelled += in.grid.labels[i] <= VLFF_LABEL_MAX;
  if (!map_ok && f.nfull) last_map_bad = follower_compare(&f, &in, SIZE_MAX, true, &r);
  printf("%s: %d maps (%zu whole, %zu updates), %d status messages received; map version %llu, %zu labelled of %zu "
         "voxels\n",
         late ? "late" : "final", maps, f.nfull, f.nup, statuses, (unsigned long long)in.version, labelled, total);
  follower_close(&f);
  CHECK(labelled > 0, "the segment's map has no labelled voxel: nothing was compared");
  if (!map_ok) printf("FAIL: no map received equal to the segment's (last compare: %d mismatches)\n", last_map_bad);
  if (!status_ok) printf("FAIL: no status received matching the segment's (last compare: %d mismatches)\n", last_status_bad);
  if (late)
    CHECK(sent == sent_first, "the bridge resent the map while nothing changed (maps_sent %lld then %lld)", sent_first,
          sent);
  printf("maps_sent %lld\n", sent);
  vlff_map_snapshot_free(snap);
  return !map_ok || !status_ok;
}

static void post(dds_entity_t w, const char *text) {
  std_msgs_msg_dds__String_ msg = {(char *)text};
  dds_return_t rc = dds_write(w, &msg);
  CHECK(rc == DDS_RETCODE_OK, "write to prompts_in: %s", dds_strretcode(rc));
}

static int check_prompts(dds_entity_t pp, const char *ns, double deadline) {
  char name[256];
  snprintf(name, sizeof name, "rt%s/vlff/prompts_in", ns);
  dds_entity_t t = dds_create_topic(pp, &std_msgs_msg_dds__String__desc, name, NULL, NULL);
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_history(q, DDS_HISTORY_KEEP_ALL, 0);
  dds_entity_t w = dds_create_writer(pp, t, q, NULL);
  dds_delete_qos(q);
  dds_publication_matched_status_t pm = {0};
  while (now_s() < deadline && (dds_get_publication_matched_status(w, &pm), pm.current_count < 1))
    dds_sleepfor(DDS_MSECS(50));
  CHECK(pm.current_count >= 1, "prompts_in: no bridge matched");
  size_t big = 5000;
  char *huge = malloc(big + 1);
  memset(huge, 'a', big);
  huge[0] = '[', huge[1] = '"', huge[big - 2] = '"', huge[big - 1] = ']', huge[big] = 0;
  post(w, huge);                          /* oversized */
  post(w, "chair, table");                /* malformed: not JSON */
  post(w, "{\"prompts\": [\"chair\"]}");  /* malformed: not a list */
  post(w, "[\"chair\", \"chair\"]");      /* invalid: repeated */
  post(w, "[\"bad\\ttab\"]");             /* invalid: a control character */
  post(w, "[\"chair\", \"table\"]");      /* posted */
  post(w, "[\"door\"]");                  /* flood: right after a post */
  free(huge);
  dds_entity_t sr = reader(pp, &diagnostic_msgs_msg_dds__DiagnosticArray__desc, ns, "status", false);
  dds_entity_t ws = waitset_of(pp, sr, 0);
  static const char *const keys[] = {"prompts_refused_oversized", "prompts_refused_malformed", "prompts_refused_invalid",
                                     "prompts_posted", "prompts_refused_flood", "prompts_refused_busy"};
  static const uint64_t want[] = {1, 2, 2, 1, 1, 0};
  int ok = 0;
  char last[512] = "";
  while (!ok && wait_data(ws, deadline)) {
    void *s[1];
    if (!take_one(sr, s)) continue;
    const diagnostic_msgs_msg_dds__DiagnosticStatus_ *br = entry(s[0], "vlff-dds: bridge");
    ok = br != NULL;
    size_t n = 0;
    for (int i = 0; br && i < 6; i++) {
      const char *v = value_of(br, keys[i]);
      ok = ok && num_is(br, keys[i], want[i]);
      n += (size_t)snprintf(last + n, n < sizeof last ? sizeof last - n : 0, "%s=%s ", keys[i], v ? v : "-");
    }
    dds_return_loan(sr, s, 1);
  }
  printf("prompts: %s\n", last);
  CHECK(ok, "the bridge's prompt counts are not oversized 1, malformed 2, invalid 2, posted 1, flood 1, busy 0");
  return 0;
}

/* The prompt list as the bridge writes it (a JSON list, json-c's plain
 * form): prompts hold no control characters, so only '"' and '\' escape. */
static void prompt_json(const struct vlff_map_snapshot *snap, int count, char *out, size_t len) {
  size_t n = 0;
  out[n++] = '[';
  for (int i = 0; i < count && n + 8 < len; i++) {
    const char *t = vlff_map_snapshot_prompt(snap, (uint16_t)i);
    if (i) out[n++] = ',';
    out[n++] = '"';
    for (; t && *t && n + 4 < len; t++) {
      if (*t == '"' || *t == '\\') out[n++] = '\\';
      out[n++] = *t;
    }
    out[n++] = '"';
  }
  out[n++] = ']';
  out[n] = 0;
}

struct images {
  dds_entity_t prompts, label, camera, info, tf, ws, zlabel, zcamera;
  bool prompts_ok, label_ok, camera_ok, info_ok, tf_ok, zlabel_ok, zcamera_ok;
  builtin_interfaces_msg_dds__Time_ label_stamp, camera_stamp, zlabel_stamp, zcamera_stamp;
  char why[7][200];
};

static void images_readers(dds_entity_t pp, const char *ns, struct images *im, bool compressed) {
  im->prompts = reader(pp, &std_msgs_msg_dds__String__desc, ns, "prompts", true);
  im->label = reader(pp, &sensor_msgs_msg_dds__Image__desc, ns, "label_image", false);
  im->camera = reader(pp, &sensor_msgs_msg_dds__Image__desc, ns, "camera/image_raw", false);
  im->info = reader(pp, &sensor_msgs_msg_dds__CameraInfo__desc, ns, "camera/camera_info", false);
  char name[256];
  snprintf(name, sizeof name, "rt%s/tf", ns);
  dds_entity_t t = dds_create_topic(pp, &tf2_msgs_msg_dds__TFMessage__desc, name, NULL, NULL);
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 1);
  im->tf = dds_create_reader(pp, t, q, NULL);
  dds_delete_qos(q);
  im->ws = dds_create_waitset(pp);
  dds_entity_t rs[5] = {im->prompts, im->label, im->camera, im->info, im->tf};
  for (int i = 0; i < 5; i++) dds_waitset_attach(im->ws, dds_create_readcondition(rs[i], DDS_ANY_STATE), i);
  im->zlabel_ok = im->zcamera_ok = !compressed;
  if (compressed) {
    im->zlabel = reader(pp, &sensor_msgs_msg_dds__CompressedImage__desc, ns, "label_image/compressed", false);
    im->zcamera = reader(pp, &sensor_msgs_msg_dds__CompressedImage__desc, ns, "camera/image_raw/compressed", false);
    dds_waitset_attach(im->ws, dds_create_readcondition(im->zlabel, DDS_ANY_STATE), 5);
    dds_waitset_attach(im->ws, dds_create_readcondition(im->zcamera, DDS_ANY_STATE), 6);
  }
}

static bool same_time(builtin_interfaces_msg_dds__Time_ a, builtin_interfaces_msg_dds__Time_ b) {
  return a.sec == b.sec && a.nanosec == b.nanosec;
}

/* A CompressedImage: its format, the encoder's magic bytes at the start, the
 * camera frame. */
static bool compressed_ok(const sensor_msgs_msg_dds__CompressedImage_ *c, bool png, char *why, size_t len) {
  static const uint8_t png_magic[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'}, jpeg_magic[3] = {0xff, 0xd8, 0xff};
  const uint8_t *magic = png ? png_magic : jpeg_magic;
  uint32_t n = png ? 8 : 3;
  bool ok = !strcmp(c->format, png ? "png" : "jpeg") && c->data._length > 64 && !memcmp(c->data._buffer, magic, n) &&
            !strcmp(c->header.frame_id, "camera");
  snprintf(why, len, "%s: format %s, %u bytes, frame %s", png ? "png" : "jpeg", c->format, c->data._length,
           c->header.frame_id);
  return ok;
}

/* What came last on each topic against the segment's last version and the
 * ring's newest frame, until every one matches or the deadline. */
static int check_images(struct images *im, struct vlff_map *m, const char *frames, double deadline) {
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(m);
  struct vlff_map_info in;
  if (!snap || vlff_map_snapshot_take(m, snap) < 0 || vlff_map_snapshot_info(snap, &in) < 0) {
    printf("FAIL: snapshot: %s\n", vlff_shm_last_message());
    return 1;
  }
  struct vlff_ring *ring = vlff_ring_attach(frames, VLFF_RECORD_FRAME);
  if (!ring) {
    printf("FAIL: frame ring %s: %s\n", frames, vlff_shm_last_message());
    return 1;
  }
  size_t cap = vlff_ring_slot_size(ring);
  uint8_t *rec = malloc(cap);
  struct vlff_ring_view view;
  ssize_t len = rec ? vlff_ring_read_latest(ring, rec, cap, &view) : -1;
  if (len < 0 || vlff_frame_validate(rec, (size_t)len) < 0) {
    printf("FAIL: the ring's newest frame: %s\n", vlff_shm_last_message());
    return 1;
  }
  const struct vlff_frame_hdr *h = (const struct vlff_frame_hdr *)rec;
  const struct vlff_plane *pl = &h->plane[VLFF_PLANE_COLOR];
  const uint8_t *px = vlff_frame_plane(rec, VLFF_PLANE_COLOR);
  char want_prompts[VLFF_SHM_MAX_PROMPTS * (VLFF_SHM_PROMPT_LEN * 2 + 3) + 3];
  prompt_json(snap, in.prompt_count, want_prompts, sizeof want_prompts);
  CHECK(in.has_label_image, "the segment has no label image: nothing to compare");
  CHECK(h->flags & VLFF_FRAME_POSE_VALID, "the ring's frame has no pose: nothing to compare");
  bool want_z = im->zlabel != 0;
  while (!(im->prompts_ok && im->label_ok && im->camera_ok && im->info_ok && im->tf_ok &&
           (!want_z || (im->zlabel_ok && im->zcamera_ok && same_time(im->zlabel_stamp, im->label_stamp) &&
                        same_time(im->zcamera_stamp, im->camera_stamp)))) &&
         wait_data(im->ws, deadline)) {
    void *s[1];
    if (want_z && take_one(im->zlabel, s)) {
      const sensor_msgs_msg_dds__CompressedImage_ *c = s[0];
      im->zlabel_ok = compressed_ok(c, true, im->why[5], sizeof im->why[5]);
      im->zlabel_stamp = c->header.stamp;
      dds_return_loan(im->zlabel, s, 1);
    }
    if (want_z && take_one(im->zcamera, s)) {
      const sensor_msgs_msg_dds__CompressedImage_ *c = s[0];
      im->zcamera_ok = compressed_ok(c, false, im->why[6], sizeof im->why[6]);
      im->zcamera_stamp = c->header.stamp;
      dds_return_loan(im->zcamera, s, 1);
    }
    if (take_one(im->prompts, s)) {
      const std_msgs_msg_dds__String_ *p = s[0];
      im->prompts_ok = !strcmp(p->data, want_prompts);
      snprintf(im->why[0], sizeof im->why[0], "prompts '%.80s', segment '%.80s'", p->data, want_prompts);
      dds_return_loan(im->prompts, s, 1);
    }
    if (take_one(im->label, s)) {
      const sensor_msgs_msg_dds__Image_ *a = s[0];
      const struct vlff_map_label_image *li = &in.label_image;
      bool ok = a->width == li->width && a->height == li->height && !strcmp(a->encoding, "mono16") &&
                a->step == li->width * 2 && a->is_bigendian == 0 && a->data._length == li->width * li->height * 2 &&
                !strcmp(a->header.frame_id, "camera");
      size_t diff = 0;
      for (size_t i = 0; ok && i < (size_t)li->width * li->height; i++)
        diff += (uint16_t)(a->data._buffer[2 * i] | a->data._buffer[2 * i + 1] << 8) != li->labels[i];
      im->label_ok = ok && !diff;
      im->label_stamp = a->header.stamp;
      snprintf(im->why[1], sizeof im->why[1], "label image %ux%u %s step %u frame %s, %zu labels differ; segment %ux%u",
               a->width, a->height, a->encoding, a->step, a->header.frame_id, diff, li->width, li->height);
      dds_return_loan(im->label, s, 1);
    }
    if (take_one(im->camera, s)) {
      const sensor_msgs_msg_dds__Image_ *a = s[0];
      bool ok = a->width == pl->width && a->height == pl->height && a->step == pl->stride &&
                a->data._length == (size_t)pl->stride * pl->height && pl->format == VLFF_PIX_RGB8 &&
                !strcmp(a->encoding, "rgb8") && px && !memcmp(a->data._buffer, px, a->data._length);
      im->camera_ok = ok;
      im->camera_stamp = a->header.stamp;
      snprintf(im->why[2], sizeof im->why[2], "camera %ux%u %s step %u (ring %ux%u format %u stride %u)%s", a->width,
               a->height, a->encoding, a->step, pl->width, pl->height, pl->format, pl->stride,
               ok ? "" : ", or the pixels differ");
      dds_return_loan(im->camera, s, 1);
    }
    if (take_one(im->info, s)) {
      const sensor_msgs_msg_dds__CameraInfo_ *c = s[0];
      im->info_ok = c->width == pl->width && c->height == pl->height && fabs(c->k[0] - h->fx) < 1e-9 &&
                    fabs(c->k[4] - h->fy) < 1e-9 && fabs(c->k[2] - (h->cx - 0.5)) < 1e-9 &&
                    fabs(c->k[5] - (h->cy - 0.5)) < 1e-9 && c->k[8] == 1 && c->p[0] == c->k[0] && c->p[10] == 1;
      snprintf(im->why[3], sizeof im->why[3], "camera_info %ux%u fx %g fy %g cx %g cy %g (ring fx %g cx %g)", c->width,
               c->height, c->k[0], c->k[4], c->k[2], c->k[5], h->fx, h->cx);
      dds_return_loan(im->info, s, 1);
    }
    if (take_one(im->tf, s)) {
      const tf2_msgs_msg_dds__TFMessage_ *t = s[0];
      bool ok = t->transforms._length == 1;
      if (ok) {
        const geometry_msgs_msg_dds__TransformStamped_ *ts = &t->transforms._buffer[0];
        const geometry_msgs_msg_dds__Quaternion_ *q = &ts->transform.rotation;
        /* the quaternion's rotation matrix against the pose's */
        double R[9] = {1 - 2 * (q->y * q->y + q->z * q->z), 2 * (q->x * q->y - q->z * q->w), 2 * (q->x * q->z + q->y * q->w),
                       2 * (q->x * q->y + q->z * q->w), 1 - 2 * (q->x * q->x + q->z * q->z), 2 * (q->y * q->z - q->x * q->w),
                       2 * (q->x * q->z - q->y * q->w), 2 * (q->y * q->z + q->x * q->w), 1 - 2 * (q->x * q->x + q->y * q->y)};
        double err = fabs(ts->transform.translation.x - h->pose[3]) + fabs(ts->transform.translation.y - h->pose[7]) +
                     fabs(ts->transform.translation.z - h->pose[11]);
        for (int i = 0; i < 9; i++) err += fabs(R[i] - h->pose[4 * (i / 3) + i % 3]);
        ok = err < 1e-6 && !strcmp(ts->header.frame_id, "map") && !strcmp(ts->child_frame_id, "camera");
        snprintf(im->why[4], sizeof im->why[4], "tf %s -> %s t (%g %g %g), error %g against the ring's pose",
                 ts->header.frame_id, ts->child_frame_id, ts->transform.translation.x, ts->transform.translation.y,
                 ts->transform.translation.z, err);
      }
      im->tf_ok = ok;
      dds_return_loan(im->tf, s, 1);
    }
  }
  const bool oks[7] = {im->prompts_ok, im->label_ok,  im->camera_ok, im->info_ok,
                       im->tf_ok,      im->zlabel_ok && (!want_z || same_time(im->zlabel_stamp, im->label_stamp)),
                       im->zcamera_ok && (!want_z || same_time(im->zcamera_stamp, im->camera_stamp))};
  static const char *const names[7] = {"prompt list", "label image", "camera image", "camera info",
                                       "tf", "compressed label image (stamped as the raw one)",
                                       "compressed camera image (stamped as the raw one)"};
  for (int i = 0; i < 7; i++)
    if (!oks[i])
      printf("FAIL: no %s received equal to the segment's or ring's (last: %s)\n", names[i],
             im->why[i][0] ? im->why[i] : "none received");
  printf("images: prompt list %s; %ux%u label image, %ux%u camera image, camera info and tf equal the segment's and "
         "ring's\n",
         want_prompts, in.label_image.width, in.label_image.height, pl->width, pl->height);
  free(rec);
  vlff_ring_close(ring);
  vlff_map_snapshot_free(snap);
  int bad = 0;
  for (int i = 0; i < 7; i++) bad += !oks[i];
  if (want_z && !bad) printf("images: %s; %s\n", im->why[5], im->why[6]);
  return bad;
}

static int stall(dds_entity_t pp, const char *ns, double deadline) {
  static const char *const leaves[] = {"map", "status", "prompts", "label_image", "camera/image_raw",
                                       "camera/camera_info"};
  static const dds_topic_descriptor_t *const descs[] = {
      &sensor_msgs_msg_dds__PointCloud2__desc, &diagnostic_msgs_msg_dds__DiagnosticArray__desc,
      &std_msgs_msg_dds__String__desc,         &sensor_msgs_msg_dds__Image__desc,
      &sensor_msgs_msg_dds__Image__desc,       &sensor_msgs_msg_dds__CameraInfo__desc};
  dds_entity_t rs[6];
  for (int i = 0; i < 6; i++) {
    char name[256];
    snprintf(name, sizeof name, "rt%s/vlff/%s", ns, leaves[i]);
    dds_entity_t t = dds_create_topic(pp, descs[i], name, NULL, NULL);
    dds_qos_t *q = dds_create_qos();
    dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
    dds_qset_history(q, DDS_HISTORY_KEEP_ALL, 0);
    dds_qset_resource_limits(q, 4, DDS_LENGTH_UNLIMITED, 4);
    if (i == 0 || i == 2) dds_qset_durability(q, DDS_DURABILITY_TRANSIENT_LOCAL);
    rs[i] = dds_create_reader(pp, t, q, NULL);
    dds_delete_qos(q);
    CHECK(rs[i] > 0, "stall reader %s: %s", leaves[i], dds_strretcode(rs[i]));
  }
  printf("stall: readers up\n");
  fflush(stdout);
  while (now_s() < deadline) dds_sleepfor(DDS_MSECS(200));
  for (int i = 0; i < 6; i++) {
    void *buf[8] = {NULL};
    dds_sample_info_t info[8];
    dds_return_t n = dds_read(rs[i], buf, info, 8, 8); /* at the end only */
    printf("stall: %s holds %d samples\n", leaves[i], (int)n);
    if (n > 0) dds_return_loan(rs[i], buf, n);
  }
  return 0;
}

static int flood(dds_entity_t pp, const char *ns, double deadline) {
  char name[256];
  snprintf(name, sizeof name, "rt%s/vlff/prompts_in", ns);
  dds_entity_t t = dds_create_topic(pp, &std_msgs_msg_dds__String__desc, name, NULL, NULL);
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_SECS(5));
  dds_qset_history(q, DDS_HISTORY_KEEP_ALL, 0);
  dds_entity_t w = dds_create_writer(pp, t, q, NULL);
  dds_delete_qos(q);
  dds_publication_matched_status_t pm = {0};
  while (now_s() < deadline && (dds_get_publication_matched_status(w, &pm), pm.current_count < 1))
    dds_sleepfor(DDS_MSECS(50));
  CHECK(pm.current_count >= 1, "prompts_in: no bridge matched");
  char *huge = malloc(20001);
  memset(huge, '[', 20000);
  huge[20000] = 0;
  static const char *const kinds[] = {"[\"chair\",", "[\"a\", \"a\"]", NULL, "[\"lamp\", \"rug\"]"};
  int sent = 0;
  for (int i = 0; i < 2000 && now_s() < deadline; i++) {
    const char *text = kinds[i % 4] ? kinds[i % 4] : huge;
    std_msgs_msg_dds__String_ msg = {(char *)text};
    if (dds_write(w, &msg) == DDS_RETCODE_OK) sent++;
  }
  free(huge);
  printf("flood: %d messages written\n", sent);
  dds_entity_t sr = reader(pp, &diagnostic_msgs_msg_dds__DiagnosticArray__desc, ns, "status", false);
  dds_entity_t ws = waitset_of(pp, sr, 0);
  static const char *const keys[] = {"prompts_refused_malformed", "prompts_refused_invalid", "prompts_refused_oversized",
                                     "prompts_refused_flood", "prompts_posted"};
  int ok = 0;
  char last[512] = "";
  while (!ok && wait_data(ws, deadline)) {
    void *s[1];
    if (!take_one(sr, s)) continue;
    const diagnostic_msgs_msg_dds__DiagnosticStatus_ *br = entry(s[0], "vlff-dds: bridge");
    ok = br != NULL;
    size_t n = 0;
    for (int i = 0; br && i < 5; i++) {
      const char *v = value_of(br, keys[i]);
      ok = ok && v && (i == 4 || strtoull(v, NULL, 10) > 0);
      n += (size_t)snprintf(last + n, n < sizeof last ? sizeof last - n : 0, "%s=%s ", keys[i], v ? v : "-");
    }
    dds_return_loan(sr, s, 1);
  }
  printf("flood: %s\n", last);
  CHECK(ok, "the bridge's status never counted each kind of the flood");
  return 0;
}

/* A robot's map (width points of vlff-dds's layout in len bytes of data)
 * and prompt list, both latched as vlff-dds writes them, held until the
 * deadline. */
static int robot_writes(dds_entity_t pp, const char *ns, const char *what, uint32_t width, uint8_t *data, uint32_t len,
                        char *prompts, double deadline) {
  char name[2][256];
  snprintf(name[0], sizeof name[0], "rt%s/vlff/map", ns);
  snprintf(name[1], sizeof name[1], "rt%s/vlff/prompts", ns);
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_durability(q, DDS_DURABILITY_TRANSIENT_LOCAL);
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 1);
  dds_entity_t mw = dds_create_writer(pp, dds_create_topic(pp, &sensor_msgs_msg_dds__PointCloud2__desc, name[0], NULL, NULL), q, NULL);
  dds_entity_t pw = dds_create_writer(pp, dds_create_topic(pp, &std_msgs_msg_dds__String__desc, name[1], NULL, NULL), q, NULL);
  dds_delete_qos(q);
  sensor_msgs_msg_dds__PointField_ fields[5] = {{"x", 0, 7, 1}, {"y", 4, 7, 1}, {"z", 8, 7, 1}, {"label", 12, 4, 1},
                                                {"confidence", 16, 7, 1}};
  sensor_msgs_msg_dds__PointCloud2_ m = {0};
  m.header.frame_id = "map";
  m.height = 1, m.width = width;
  m.fields._length = m.fields._maximum = 5;
  m.fields._buffer = fields;
  m.point_step = 20, m.row_step = 20 * width;
  m.data._length = m.data._maximum = len;
  m.data._buffer = data;
  m.is_dense = true;
  std_msgs_msg_dds__String_ p = {prompts};
  CHECK(dds_write(pw, &p) == DDS_RETCODE_OK && dds_write(mw, &m) == DDS_RETCODE_OK, "%s: writes failed", what);
  printf("%s: written\n", what);
  fflush(stdout);
  while (now_s() < deadline) dds_sleepfor(DDS_MSECS(200));
  return 0;
}

static int badmap(dds_entity_t pp, const char *ns, double deadline) {
  static uint8_t data[40];
  static char list[] = "chair, table";
  return robot_writes(pp, ns, "badmap", 1000, data, sizeof data, list, deadline); /* 1000 points in 40 bytes */
}

static int many_texts(dds_entity_t pp, const char *ns, double deadline) {
  char json[32 * 16] = "[";
  for (int i = 0; i < 32; i++)
    snprintf(json + strlen(json), sizeof json - strlen(json), "%s\"thing %d\"", i ? ", " : "", i);
  strcat(json, "]");
  return robot_writes(pp, ns, "texts", 0, NULL, 0, json, deadline);
}

static int static_tf(dds_entity_t pp, const char *ns, const char *xyzyaw, const char *frames, double deadline) {
  char name[256], parent[64], child[64];
  double v[4];
  if (sscanf(xyzyaw, "%lf,%lf,%lf,%lf", &v[0], &v[1], &v[2], &v[3]) != 4 ||
      sscanf(frames, "%63[^:]:%63s", parent, child) != 2) {
    printf("FAIL: tf: expected X,Y,Z,YAW and PARENT:CHILD, got '%s' '%s'\n", xyzyaw, frames);
    return 1;
  }
  snprintf(name, sizeof name, "rt%s/tf_static", ns);
  dds_qos_t *q = dds_create_qos();
  dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_durability(q, DDS_DURABILITY_TRANSIENT_LOCAL);
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 1);
  dds_entity_t w = dds_create_writer(pp, dds_create_topic(pp, &tf2_msgs_msg_dds__TFMessage__desc, name, NULL, NULL), q, NULL);
  dds_delete_qos(q);
  geometry_msgs_msg_dds__TransformStamped_ ts[2];
  memset(ts, 0, sizeof ts);
  double h = v[3] * 3.14159265358979323846 / 360; /* half the yaw */
  ts[0].header.frame_id = "base_link", ts[0].child_frame_id = "camera";
  ts[0].transform.rotation.w = 1;
  ts[1].header.frame_id = parent, ts[1].child_frame_id = child;
  ts[1].transform.translation.x = v[0], ts[1].transform.translation.y = v[1], ts[1].transform.translation.z = v[2];
  ts[1].transform.rotation.z = sin(h), ts[1].transform.rotation.w = cos(h);
  tf2_msgs_msg_dds__TFMessage_ m = {0};
  m.transforms._length = m.transforms._maximum = 2;
  m.transforms._buffer = ts;
  CHECK(dds_write(w, &m) == DDS_RETCODE_OK, "tf: write failed");
  printf("tf: written\n");
  fflush(stdout);
  while (now_s() < deadline) dds_sleepfor(DDS_MSECS(200));
  return 0;
}

int main(int argc, char **argv) {
  if (argc < 7 || argc > 9) {
    fprintf(stderr, "usage: dds_probe final|late|prompts|stall|flood|badmap|texts|tf|follow DOMAIN NAMESPACE MAP NODE_NAME TIMEOUT_S [FRAMES "
                    "[compressed]]\n");
    return 2;
  }
  const char *mode = argv[1], *ns = argv[3], *mapname = argv[4], *node = argv[5], *frames = argc >= 8 ? argv[7] : NULL;
  bool compressed = argc == 9 && !strcmp(argv[8], "compressed");
  double deadline = now_s() + atof(argv[6]);
  dds_entity_t pp = dds_create_participant((dds_domainid_t)atoi(argv[2]), NULL, NULL);
  if (pp < 0) {
    printf("FAIL: participant: %s\n", dds_strretcode(pp));
    return 1;
  }
  /* Volatile topics: the readers exist before the bridge's last samples. */
  struct images im = {0};
  if (frames) images_readers(pp, ns, &im, compressed);
  if (!strcmp(mode, "prompts")) {
    check_prompts(pp, ns, deadline);
  } else if (!strcmp(mode, "stall")) {
    stall(pp, ns, deadline);
  } else if (!strcmp(mode, "flood")) {
    flood(pp, ns, deadline);
  } else if (!strcmp(mode, "badmap")) {
    badmap(pp, ns, deadline);
  } else if (!strcmp(mode, "texts")) {
    fails += many_texts(pp, ns, deadline);
  } else if (!strcmp(mode, "tf")) {
    fails += static_tf(pp, ns, mapname, node, deadline);
  } else if (!strcmp(mode, "follow")) {
    struct vlff_map *m;
    while (!(m = vlff_map_attach(mapname)) && now_s() < deadline) dds_sleepfor(DDS_MSECS(100));
    if (!m) {
      printf("FAIL: %s: %s\n", mapname, vlff_shm_last_message());
      return 1;
    }
    follow(pp, ns, m, strtoull(node, NULL, 10), deadline);
    vlff_map_detach(m);
  } else {
    /* The probe may start before the node has created the segment. */
    struct vlff_map *m;
    while (!(m = vlff_map_attach(mapname)) && now_s() < deadline) dds_sleepfor(DDS_MSECS(100));
    if (!m) {
      printf("FAIL: %s: %s\n", mapname, vlff_shm_last_message());
      return 1;
    }
    /* final: the node is stopped by the test; its last map is the one to get. */
    while (vlff_map_writer_alive(m, 5000000000ull) && now_s() < deadline) dds_sleepfor(DDS_MSECS(100));
    CHECK(!vlff_map_writer_alive(m, 5000000000ull), "the node did not stop");
    CHECK(vlff_map_version(m) > 0, "the node published no map");
    if (!fails) fails += check_map_status(pp, ns, m, node, deadline, !strcmp(mode, "late"));
    if (!fails && frames) fails += check_images(&im, m, frames, deadline);
    vlff_map_detach(m);
  }
  dds_delete(pp);
  printf("%s\n", fails ? "probe FAILED" : "probe ok");
  return fails ? 1 : 0;
}
