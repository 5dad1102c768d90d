/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * The viewer's feed against a map segment published in this process: the first
 * version goes out whole, later ones as exactly the changed voxels and the bricks
 * holding them (an emptied brick deleted), a version without changes as an empty
 * delta, a prompt change whole again; channels nobody wants are not encoded (the
 * feed's count of encoded messages stays put), and a new subscriber gets the whole
 * current map. The point cloud: the whole map in pieces under the piece bound, a
 * change as the changed voxels, in the frame given. The voxels: the whole map and a
 * change in pieces under the piece bound, numbered, full on the whole map's first.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <json-c/json.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "unit.h"
#include "view.h"

enum { NX = 10, NY = 9, NZ = 8, N = NX * NY * NZ, ALL = 0x7e };
static char name[64];
static uint16_t labels[N];
static uint8_t conf[N];
static uint16_t limg[12];
static const char *prompts[3] = {"wall", "floor", "chair"};
static const char *prompts2[2] = {"door", "floor"};

static size_t at(int i, int j, int k) { return (size_t)i + NX * ((size_t)j + NY * (size_t)k); }

static int publish(struct vlff_map *m, const char *const *p, int np) {
  struct vlff_map_grid g = {{-1, 0, 0.5}, 0.25, {NX, NY, NZ}, labels, conf};
  struct vlff_map_label_image li = {4, 3, limg, NULL, 100, 100, 2, 1.5,
                                    {1, 0, 0, 1, 0, 1, 0, 2, 0, 0, 1, 3, 0, 0, 0, 1}, vlff_shm_now_ns()};
  struct vlff_map_update up = {.grid = &g, .prompts = p, .prompt_count = np, .label_image = &li};
  return vlff_map_publish(m, &up);
}

/* A message's payload is exactly len bytes of one JSON text, not NUL-terminated. */
static json_object *parse(struct vlff_view_msg *m) {
  char *copy = strndup((const char *)vlff_view_msg_payload(m), m->len);
  json_object *o = json_tokener_parse(copy);
  free(copy);
  assert_non_null(o);
  return o;
}

struct polled {
  json_object *msg[VLFF_VIEW_CH_COUNT + 1];
  int count[VLFF_VIEW_CH_COUNT + 1];
};

static void poll_feed(struct vlff_feed *f, unsigned wanted, struct polled *out) {
  struct vlff_view_counters c = {0};
  struct vlff_view_msg *m[16];
  memset(out, 0, sizeof *out);
  int n = vlff_feed_poll(f, &c, wanted, m, 16);
  for (int i = 0; i < n; i++) {
    int ch = m[i]->channel;
    assert_true(ch >= 1 && ch <= VLFF_VIEW_CH_COUNT);
    json_object *o = parse(m[i]);
    json_object_put(out->msg[ch]);
    out->msg[ch] = o;
    out->count[ch]++;
    vlff_view_msg_unref(m[i]);
  }
}

static void free_polled(struct polled *p) {
  for (int c = 0; c <= VLFF_VIEW_CH_COUNT; c++) json_object_put(p->msg[c]);
}

static json_object *get(json_object *o, const char *k) {
  json_object *v = NULL;
  assert_true(json_object_object_get_ex(o, k, &v));
  return v;
}

static int cube_count(json_object *scene) {
  json_object *ents = get(scene, "entities");
  int n = 0;
  for (size_t i = 0; i < json_object_array_length(ents); i++)
    n += (int)json_object_array_length(get(json_object_array_get_idx(ents, i), "cubes"));
  return n;
}

static int setup(void **state) {
  snprintf(name, sizeof name, "/vlff-test-view-%d", getpid());
  for (size_t i = 0; i < N; i++) labels[i] = VLFF_LABEL_FREE, conf[i] = 200;
  for (int i = 0; i < NX; i++)
    for (int j = 0; j < NY; j++) labels[at(i, j, 0)] = 1; /* a floor */
  labels[at(5, 5, 1)] = 2;                                /* a chair voxel */
  labels[at(9, 8, 7)] = 0;                                /* alone in its brick */
  return 0;
}

static int teardown(void **state) {
  vlff_shm_unlink(name);
  return 0;
}

static void test_feed(void **state) {
  struct vlff_feed_params fp = {.map_name = name, .frames_name = "", .image_hz = 2, .brick = 4};
  struct vlff_feed *f = vlff_feed_new(&fp);
  struct polled p;
  assert_non_null(f);

  poll_feed(f, ALL, &p); /* no map yet: status only, saying so */
  assert_int_equal(p.count[VLFF_VIEW_CH_STATUS], 1);
  assert_int_equal(p.count[VLFF_VIEW_CH_VOXELS], 0);
  assert_false(json_object_get_boolean(get(get(p.msg[VLFF_VIEW_CH_STATUS], "map"), "attached")));
  free_polled(&p);

  struct vlff_map_params mp = {N, 8, 8, {0, NULL}};
  struct vlff_map *m = vlff_map_create(name, &mp);
  assert_non_null(m);
  assert_int_equal(publish(m, prompts, 3), 0);
  usleep(1100000); /* the feed tries to attach once a second */
  poll_feed(f, ALL, &p);
  json_object *vx = p.msg[VLFF_VIEW_CH_VOXELS], *sc = p.msg[VLFF_VIEW_CH_SCENE];
  assert_non_null(vx);
  assert_non_null(sc);
  assert_true(json_object_get_boolean(get(vx, "full")));
  assert_int_equal(json_object_get_int(get(vx, "occupied")), NX * NY + 2);
  assert_int_equal(json_object_array_length(get(vx, "voxels")), 3 * (NX * NY + 2));
  assert_int_equal(cube_count(sc), NX * NY + 2);
  assert_int_equal(json_object_get_int(get(json_object_array_get_idx(get(sc, "deletions"), 0), "type")), 1);
  assert_string_equal(json_object_get_string(json_object_array_get_idx(get(vx, "prompts"), 2)), "chair");
  assert_int_equal(p.count[VLFF_VIEW_CH_LABELS], 1);
  assert_int_equal(p.count[VLFF_VIEW_CH_POSE], 1); /* from the label image: no frame ring */
  json_object *tr = get(p.msg[VLFF_VIEW_CH_POSE], "translation");
  assert_true(json_object_get_double(get(tr, "z")) == 3.0);
  free_polled(&p);

  /* three changes: a relabel, a voxel freed (emptying its brick), a confidence */
  labels[at(5, 5, 1)] = 0;
  labels[at(9, 8, 7)] = VLFF_LABEL_FREE;
  conf[at(0, 0, 0)] = 17;
  assert_int_equal(publish(m, prompts, 3), 0);
  poll_feed(f, ALL, &p);
  vx = p.msg[VLFF_VIEW_CH_VOXELS];
  sc = p.msg[VLFF_VIEW_CH_SCENE];
  assert_false(json_object_get_boolean(get(vx, "full")));
  json_object *v = get(vx, "voxels");
  assert_int_equal(json_object_array_length(v), 9);
  size_t want[3][3] = {{at(0, 0, 0), 1, 17}, {at(5, 5, 1), 0, 200}, {at(9, 8, 7), VLFF_LABEL_FREE, 200}};
  for (int t = 0; t < 3; t++)
    for (int c = 0; c < 3; c++) assert_int_equal(json_object_get_int(json_object_array_get_idx(v, 3 * t + c)), want[t][c]);
  assert_int_equal(json_object_get_int(get(vx, "occupied")), NX * NY + 1);
  /* the bricks of (0,0,0) and (5,5,1) come again whole; (9,8,7)'s is deleted */
  json_object *ents = get(sc, "entities"), *dels = get(sc, "deletions");
  assert_int_equal(json_object_array_length(ents), 2);
  assert_int_equal(cube_count(sc), 16 + 16 + 1);
  assert_int_equal(json_object_array_length(dels), 1);
  assert_int_equal(json_object_get_int(get(json_object_array_get_idx(dels, 0), "type")), 0);
  free_polled(&p);

  /* a version without changes: an empty delta, nothing for the scene */
  assert_int_equal(publish(m, prompts, 3), 0);
  poll_feed(f, ALL, &p);
  assert_int_equal(json_object_array_length(get(p.msg[VLFF_VIEW_CH_VOXELS], "voxels")), 0);
  assert_int_equal(p.count[VLFF_VIEW_CH_SCENE], 0);
  free_polled(&p);

  /* nobody on the scene: it is not encoded; a new subscriber gets it whole */
  labels[at(1, 1, 1)] = 2;
  assert_int_equal(publish(m, prompts, 3), 0);
  poll_feed(f, 1u << VLFF_VIEW_CH_VOXELS, &p);
  assert_int_equal(p.count[VLFF_VIEW_CH_SCENE], 0);
  assert_int_equal(p.count[VLFF_VIEW_CH_LABELS], 0);
  assert_int_equal(json_object_array_length(get(p.msg[VLFF_VIEW_CH_VOXELS], "voxels")), 3);
  free_polled(&p);
  struct vlff_view_msg *cur = vlff_feed_current(f, VLFF_VIEW_CH_SCENE, NULL);
  assert_non_null(cur);
  json_object *whole = parse(cur);
  assert_int_equal(cube_count(whole), NX * NY + 2);
  json_object_put(whole);
  vlff_view_msg_unref(cur);

  /* pieces of at most 8 KiB: the same scene in several SceneUpdates of whole
   * bricks, the first one deleting all */
  struct vlff_feed_params fp2 = fp;
  fp2.cloud_piece_bytes = 8192;
  struct vlff_feed *f2 = vlff_feed_new(&fp2);
  assert_non_null(f2);
  poll_feed(f2, 0, &p);
  free_polled(&p);
  cur = vlff_feed_current(f2, VLFF_VIEW_CH_SCENE, NULL);
  assert_non_null(cur);
  int pieces = 0, cubes = 0;
  for (struct vlff_view_msg *piece = cur; piece; piece = piece->next, pieces++) {
    assert_true(piece->len <= 8192);
    assert_true(piece->whole);
    json_object *o = parse(piece);
    json_object *d = get(o, "deletions");
    assert_int_equal(json_object_array_length(d), pieces ? 0 : 1);
    if (!pieces) assert_int_equal(json_object_get_int(get(json_object_array_get_idx(d, 0), "type")), 1);
    cubes += cube_count(o);
    json_object_put(o);
  }
  assert_true(pieces >= 2);
  assert_int_equal(cubes, NX * NY + 2);
  vlff_view_msg_unref(cur);
  vlff_feed_free(f2);

  /* new prompts recolour everything: whole again */
  assert_int_equal(publish(m, prompts2, 2), 0);
  poll_feed(f, ALL, &p);
  assert_true(json_object_get_boolean(get(p.msg[VLFF_VIEW_CH_VOXELS], "full")));
  assert_string_equal(json_object_get_string(json_object_array_get_idx(get(p.msg[VLFF_VIEW_CH_VOXELS], "prompts"), 0)),
                      "door");
  assert_int_equal(vlff_feed_version(f), 5);
  free_polled(&p);

  /* nobody subscribes: a version with changes, a new label image and a status due
   * cost no encoding on any channel, while the feed's copy follows the map */
  uint64_t before[VLFF_VIEW_CH_COUNT + 1];
  for (int c = 1; c <= VLFF_VIEW_CH_COUNT; c++) before[c] = vlff_feed_encoded(f, c);
  labels[at(2, 2, 2)] = 1;
  assert_int_equal(publish(m, prompts2, 2), 0);
  poll_feed(f, 0, &p);
  for (int c = 1; c <= VLFF_VIEW_CH_COUNT; c++) {
    assert_int_equal(p.count[c], 0);
    assert_int_equal(vlff_feed_encoded(f, c), before[c]);
  }
  assert_int_equal(vlff_feed_version(f), 6);
  free_polled(&p);

  /* one subscriber, on the status: only the status is encoded */
  labels[at(3, 3, 3)] = 1;
  assert_int_equal(publish(m, prompts2, 2), 0);
  poll_feed(f, 1u << VLFF_VIEW_CH_STATUS, &p);
  assert_int_equal(p.count[VLFF_VIEW_CH_STATUS], 1);
  for (int c = 1; c <= VLFF_VIEW_CH_COUNT; c++)
    assert_int_equal(vlff_feed_encoded(f, c), before[c] + (c == VLFF_VIEW_CH_STATUS));
  free_polled(&p);

  /* a first voxel subscriber gets the whole map, the changes made unseen included */
  cur = vlff_feed_current(f, VLFF_VIEW_CH_VOXELS, NULL);
  assert_non_null(cur);
  whole = parse(cur);
  assert_true(json_object_get_boolean(get(whole, "full")));
  assert_int_equal(json_object_get_int(get(whole, "version")), 7);
  assert_int_equal(json_object_get_int(get(whole, "occupied")), NX * NY + 4);
  assert_int_equal(vlff_feed_encoded(f, VLFF_VIEW_CH_VOXELS), before[VLFF_VIEW_CH_VOXELS] + 1);
  json_object_put(whole);
  vlff_view_msg_unref(cur);

  vlff_feed_free(f);
  vlff_map_detach(m);
}

/* Partial publishes (the map's change log): a client gets exactly the voxels
 * whose value changed, though the logged runs hold unchanged ones too, and a
 * feed left behind by more publishes than the log holds still sends exactly
 * what changed since its last version. */
static int publish_runs(struct vlff_map *m, const struct vlff_map_range *r, size_t n) {
  struct vlff_map_grid g = {{-1, 0, 0.5}, 0.25, {NX, NY, NZ}, labels, conf};
  struct vlff_map_update up = {.grid = &g, .ranges = r, .range_count = n};
  return vlff_map_publish(m, &up);
}

static void test_feed_follows_log(void **state) {
  (void)state;
  struct vlff_feed_params fp = {.map_name = name, .frames_name = "", .image_hz = 2, .brick = 4};
  struct vlff_feed *f = vlff_feed_new(&fp);
  struct polled p;
  struct vlff_map_params mp = {N, 8, 8, {0, NULL}};
  struct vlff_map *m = vlff_map_create(name, &mp);
  assert_non_null(m);
  assert_int_equal(publish(m, prompts, 3), 0);
  usleep(1100000); /* the feed tries to attach once a second */
  poll_feed(f, ALL, &p);
  assert_true(json_object_get_boolean(get(p.msg[VLFF_VIEW_CH_VOXELS], "full")));
  free_polled(&p);

  /* a run of a whole row, one voxel of it changed */
  labels[at(4, 6, 2)] = 2;
  struct vlff_map_range row = {(uint32_t)at(0, 6, 2), NX};
  assert_int_equal(publish_runs(m, &row, 1), 0);
  poll_feed(f, ALL, &p);
  json_object *v = get(p.msg[VLFF_VIEW_CH_VOXELS], "voxels");
  assert_false(json_object_get_boolean(get(p.msg[VLFF_VIEW_CH_VOXELS], "full")));
  assert_int_equal(json_object_array_length(v), 3);
  assert_int_equal(json_object_get_int(json_object_array_get_idx(v, 0)), at(4, 6, 2));
  assert_int_equal(json_object_array_length(get(p.msg[VLFF_VIEW_CH_SCENE], "entities")), 1);
  free_polled(&p);

  /* 200 publishes of three one-voxel runs each, unread: more runs than this
   * map's log holds (256) */
  static uint16_t sent[N];
  memcpy(sent, labels, sizeof sent);
  for (int i = 0; i < 200; i++) {
    size_t a = (size_t)(i * 7) % N, b = (a + 1) % N, c = (a + 2) % N;
    labels[a] = (uint16_t)(i % 3);
    struct vlff_map_range r[3] = {{(uint32_t)a, 1}, {(uint32_t)b, 1}, {(uint32_t)c, 1}};
    assert_int_equal(publish_runs(m, r, 3), 0);
  }
  int want = 0;
  for (size_t i = 0; i < N; i++) want += labels[i] != sent[i];
  assert_true(want > 50);
  poll_feed(f, ALL, &p);
  assert_false(json_object_get_boolean(get(p.msg[VLFF_VIEW_CH_VOXELS], "full")));
  v = get(p.msg[VLFF_VIEW_CH_VOXELS], "voxels");
  assert_int_equal(json_object_array_length(v), 3 * (size_t)want);
  for (int t = 0; t < want; t++) {
    int idx = json_object_get_int(json_object_array_get_idx(v, 3 * t));
    assert_true(labels[idx] != sent[idx]);
    assert_int_equal(json_object_get_int(json_object_array_get_idx(v, 3 * t + 1)), labels[idx]);
  }
  free_polled(&p);
  /* and nothing more: the next version with no change sends an empty delta */
  assert_int_equal(publish_runs(m, NULL, 0), 0);
  poll_feed(f, ALL, &p);
  assert_int_equal(json_object_array_length(get(p.msg[VLFF_VIEW_CH_VOXELS], "voxels")), 0);
  free_polled(&p);
  vlff_feed_free(f);
  vlff_map_detach(m);
}

static char ring_name[64];

/* A 8x6 RGB frame at the host time t, its camera at height z. */
static void put_frame(struct vlff_ring *r, uint64_t t, double z) {
  uint64_t seq;
  struct vlff_frame_hdr *h = vlff_ring_reserve(r, &seq);
  assert_non_null(h);
  uint64_t len = vlff_frame_layout(h, vlff_ring_slot_size(r), 8, 6, VLFF_PIX_RGB8, VLFF_PIX_NONE);
  assert_true(len > 0);
  memset((uint8_t *)h + h->plane[0].offset, 90, h->plane[0].size);
  h->t_host_ns = t;
  h->frame_id = seq;
  h->flags = VLFF_FRAME_POSE_VALID | VLFF_FRAME_INTRINSICS_VALID;
  h->fx = h->fy = 6, h->cx = 4, h->cy = 3;
  double P[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, z, 0, 0, 0, 1};
  memcpy(h->pose, P, sizeof P);
  h->pose_t_ns = t;
  assert_int_equal(vlff_ring_commit(r, len), 0);
}

static uint64_t current_t(struct vlff_feed *f, int ch) {
  struct vlff_view_msg *m = vlff_feed_current(f, ch, NULL);
  assert_non_null(m);
  uint64_t t = m->t_ns;
  vlff_view_msg_unref(m);
  return t;
}

/* A channel that had no subscriber for a while: a new subscriber's first message is
 * the latest in the segments, not the one last sent to an earlier subscriber; the
 * status is built at the moment, with the counts of that moment. */
static void test_fresh(void **state) {
  snprintf(ring_name, sizeof ring_name, "/vlff-test-view-ring-%d", getpid());
  struct vlff_ring_params rp = {VLFF_RECORD_FRAME, 4, vlff_frame_slot_size(8, 6, VLFF_PIX_RGB8, VLFF_PIX_NONE),
                                {0, NULL}};
  struct vlff_ring *r = vlff_ring_create(ring_name, &rp);
  assert_non_null(r);
  struct vlff_map_params mp = {N, 8, 8, {0, NULL}};
  struct vlff_map *m = vlff_map_create(name, &mp);
  assert_non_null(m);
  uint64_t t0 = vlff_shm_now_ns();
  put_frame(r, t0, 1.0);
  assert_int_equal(publish(m, prompts, 3), 0);
  struct vlff_feed_params fp = {.map_name = name, .frames_name = ring_name, .image_hz = 0, .brick = 4};
  struct vlff_feed *f = vlff_feed_new(&fp);
  assert_non_null(f);
  struct polled p;
  poll_feed(f, ALL, &p); /* the segments exist: attached at the first poll */
  assert_int_equal(p.count[VLFF_VIEW_CH_IMAGE], 1);
  assert_int_equal(p.count[VLFF_VIEW_CH_LABELS], 1);
  free_polled(&p);
  uint64_t img0 = current_t(f, VLFF_VIEW_CH_IMAGE), lab0 = current_t(f, VLFF_VIEW_CH_LABELS);

  /* everybody leaves; a newer frame and map version come meanwhile */
  poll_feed(f, 0, &p);
  free_polled(&p);
  usleep(20000);
  uint64_t t1 = vlff_shm_now_ns();
  put_frame(r, t1, 2.5);
  assert_int_equal(publish(m, prompts, 3), 0);
  poll_feed(f, 0, &p);
  free_polled(&p);

  assert_true(current_t(f, VLFF_VIEW_CH_IMAGE) - img0 == t1 - t0);
  struct vlff_view_msg *pm = vlff_feed_current(f, VLFF_VIEW_CH_POSE, NULL);
  assert_non_null(pm);
  assert_true(pm->t_ns - img0 == t1 - t0);
  json_object *pose = parse(pm);
  assert_true(json_object_get_double(get(get(pose, "translation"), "z")) == 2.5);
  json_object_put(pose);
  vlff_view_msg_unref(pm);
  assert_true(current_t(f, VLFF_VIEW_CH_LABELS) > lab0);

  /* the status names the clients of now, not those of the last status sent */
  struct vlff_view_counters c = {0};
  c.clients = 5;
  struct vlff_view_msg *out[16];
  int n = vlff_feed_poll(f, &c, 1u << VLFF_VIEW_CH_STATUS, out, 16);
  for (int i = 0; i < n; i++) vlff_view_msg_unref(out[i]);
  c.clients = 1;
  struct vlff_view_msg *sm = vlff_feed_current(f, VLFF_VIEW_CH_STATUS, &c);
  assert_non_null(sm);
  json_object *st = parse(sm);
  assert_int_equal(json_object_get_int(get(get(st, "viewer"), "clients")), 1);
  json_object_put(st);
  vlff_view_msg_unref(sm);

  vlff_feed_free(f);
  vlff_map_detach(m);
  vlff_ring_close(r);
  vlff_shm_unlink(ring_name);
}

/* The points of a /map/points piece: its payload ends with them (the data field
 * is the last), k of them. */
static const uint8_t *piece_points(struct vlff_view_msg *m, size_t k) {
  assert_true(m->len > k * VLFF_VIEW_CLOUD_STRIDE);
  return vlff_view_msg_payload(m) + m->len - k * VLFF_VIEW_CLOUD_STRIDE;
}

/* Whether the payload holds the bytes s[n]. */
static int holds(struct vlff_view_msg *m, const char *s, size_t n) {
  const uint8_t *p = vlff_view_msg_payload(m);
  for (size_t i = 0; i + n <= m->len; i++)
    if (!memcmp(p + i, s, n)) return 1;
  return 0;
}

/* Channel ch's first message of a poll wanting only it, or NULL. */
static struct vlff_view_msg *poll_one(struct vlff_feed *f, int ch) {
  struct vlff_view_counters c = {0};
  struct vlff_view_msg *out[16], *m = NULL;
  int n = vlff_feed_poll(f, &c, 1u << ch, out, 16);
  for (int i = 0; i < n; i++) {
    if (out[i]->channel == ch && !m) m = vlff_view_msg_ref(out[i]);
    vlff_view_msg_unref(out[i]);
  }
  return m;
}
static struct vlff_view_msg *poll_cloud(struct vlff_feed *f) { return poll_one(f, VLFF_VIEW_CH_CLOUD); }
static struct vlff_view_msg *poll_grid(struct vlff_feed *f) { return poll_one(f, VLFF_VIEW_CH_GRID); }
static struct vlff_view_msg *poll_voxels(struct vlff_feed *f) { return poll_one(f, VLFF_VIEW_CH_VOXELS); }

/* The cell (i, j) of a grid message: the cells are its payload's last bytes. */
static const uint8_t *grid_cell(struct vlff_view_msg *g, int i, int j) {
  return vlff_view_msg_payload(g) + g->len - (size_t)NX * NY * VLFF_VIEW_GRID_STRIDE +
         ((size_t)j * NX + (size_t)i) * VLFF_VIEW_GRID_STRIDE;
}

static uint16_t cell_label(struct vlff_view_msg *g, int i, int j) {
  const uint8_t *c = grid_cell(g, i, j);
  return (uint16_t)(c[4] | c[5] << 8);
}

/* /map/grid: one per map change at most grid_hz a second, the current map's to a
 * first subscriber while one is owed, and none above max_message_bytes (a grid
 * above a client's queue limit would drop the client). */
static void test_grid(void **state) {
  (void)state;
  const size_t bytes = (size_t)NX * NY * VLFF_VIEW_GRID_STRIDE;
  struct vlff_map_params mp = {N, 8, 8, {0, NULL}};
  struct vlff_map *m = vlff_map_create(name, &mp);
  assert_non_null(m);
  assert_int_equal(publish(m, prompts, 3), 0);
  /* one byte too small for the grid: nothing sent, nothing encoded */
  struct vlff_feed_params fp = {.map_name = name, .frames_name = "", .brick = 4, .grid_hz = 0.1,
                                .max_message_bytes = bytes - 1};
  struct vlff_feed *small = vlff_feed_new(&fp);
  assert_non_null(small);
  usleep(1100000); /* the feed tries to attach once a second */
  assert_null(poll_grid(small));
  assert_null(vlff_feed_current(small, VLFF_VIEW_CH_GRID, NULL));
  assert_int_equal(vlff_feed_encoded(small, VLFF_VIEW_CH_GRID), 0);
  vlff_feed_free(small);

  fp.max_message_bytes = bytes + 1024;
  struct vlff_feed *f = vlff_feed_new(&fp);
  assert_non_null(f);
  usleep(1100000);
  struct vlff_view_msg *g = poll_grid(f);
  assert_non_null(g);
  assert_true(g->len > bytes && g->len <= bytes + 1024);
  /* seen from above: the floor, the chair on it, the lone voxel at the top */
  assert_int_equal(cell_label(g, 0, 0), 1);
  assert_int_equal(cell_label(g, 5, 5), 2);
  assert_int_equal(cell_label(g, 9, 8), 0);
  float elev;
  memcpy(&elev, grid_cell(g, 5, 5) + 8, 4);
  assert_true(elev == 0.5f); /* the chair voxel's top: 2 voxels of 0.25 m above the map's floor */
  assert_int_equal(grid_cell(g, 5, 5)[3], 255);
  assert_int_equal(grid_cell(g, 5, 5)[6], 200);
  vlff_view_msg_unref(g);
  assert_null(poll_grid(f)); /* no change, no grid */

  /* a change within the rate's period: owed, not sent; a first subscriber gets
   * the changed map's grid */
  labels[at(5, 5, 1)] = VLFF_LABEL_FREE;
  assert_int_equal(publish(m, prompts, 3), 0);
  assert_null(poll_grid(f));
  g = vlff_feed_current(f, VLFF_VIEW_CH_GRID, NULL);
  assert_non_null(g);
  assert_int_equal(cell_label(g, 5, 5), 1);
  vlff_view_msg_unref(g);
  assert_int_equal(vlff_feed_encoded(f, VLFF_VIEW_CH_GRID), 2);
  vlff_feed_free(f);
  vlff_map_detach(m);
}

static void test_cloud(void **state) {
  (void)state;
  /* 1100 bytes: 29 points of 20 bytes beside the head (512 bytes and the frame) */
  struct vlff_feed_params fp = {.map_name = name, .frames_name = "", .image_hz = 2, .brick = 4,
                                .cloud_piece_bytes = 1100, .world_frame = "odom"};
  struct vlff_feed *f = vlff_feed_new(&fp);
  struct vlff_map_params mp = {N, 8, 8, {0, NULL}};
  struct vlff_map *m = vlff_map_create(name, &mp);
  assert_non_null(f);
  assert_non_null(m);
  assert_int_equal(publish(m, prompts, 3), 0);
  usleep(1100000); /* the feed tries to attach once a second */
  struct vlff_view_msg *whole = poll_cloud(f);
  assert_non_null(whole);
  /* NX * NY + 2 occupied voxels in pieces of 29 points, each under the bound */
  const size_t occupied = NX * NY + 2, per = 29;
  size_t pieces = 0, seen = 0, labels_seen[3] = {0};
  for (struct vlff_view_msg *p = whole; p; p = p->next, pieces++) {
    size_t k = occupied - seen < per ? occupied - seen : per;
    assert_true(p->len <= 1100);
    assert_true(p->whole);
    assert_true(holds(p, "\x12\x04odom", 6)); /* frame_id: field 2, 4 bytes */
    const uint8_t *pt = piece_points(p, k);
    for (size_t i = 0; i < k; i++, pt += VLFF_VIEW_CLOUD_STRIDE) {
      uint16_t l = (uint16_t)(pt[16] | pt[17] << 8);
      assert_true(l < 3);
      assert_int_equal(pt[15], 255); /* occupied: opaque */
      assert_int_equal(pt[18], 200); /* the confidence */
      labels_seen[l]++;
    }
    seen += k;
  }
  assert_int_equal(seen, occupied);
  assert_int_equal(pieces, (occupied + per - 1) / per);
  assert_int_equal(labels_seen[1], NX * NY);
  assert_int_equal(vlff_feed_encoded(f, VLFF_VIEW_CH_CLOUD), pieces);
  /* a first subscriber gets the same whole map */
  struct vlff_view_msg *cur = vlff_feed_current(f, VLFF_VIEW_CH_CLOUD, NULL);
  assert_ptr_equal(cur, whole);
  vlff_view_msg_unref(cur);
  vlff_view_msg_unref(whole);

  /* one voxel freed, one labelled: a change of two points, the freed one transparent */
  labels[at(5, 5, 1)] = VLFF_LABEL_FREE;
  labels[at(2, 2, 3)] = 0;
  assert_int_equal(publish(m, prompts, 3), 0);
  struct vlff_view_msg *delta = poll_cloud(f);
  assert_non_null(delta);
  assert_null(delta->next);
  assert_false(delta->whole);
  const uint8_t *pt = piece_points(delta, 2);
  /* index order: (5, 5, 1) before (2, 2, 3) */
  assert_int_equal(pt[16] | pt[17] << 8, VLFF_LABEL_FREE);
  assert_int_equal(pt[15], 0);
  uint32_t u = (uint32_t)pt[0] | (uint32_t)pt[1] << 8 | (uint32_t)pt[2] << 16 | (uint32_t)pt[3] << 24;
  float x;
  memcpy(&x, &u, 4);
  assert_true(x > -1 + 5.5 * 0.25 - 1e-4 && x < -1 + 5.5 * 0.25 + 1e-4);
  assert_int_equal(pt[20 + 16] | pt[20 + 17] << 8, 0);
  assert_int_equal(pt[20 + 15], 255);
  vlff_view_msg_unref(delta);
  vlff_map_detach(m);
  vlff_feed_free(f);
}

/* A map beyond its grid (vlff/shm.h "The far map"): the whole cloud holds
 * the far map's labelled voxels too, at their centres, after the grid's;
 * those of a far block the grid covers are the grid's, not points again. */
static void test_cloud_far(void **state) {
  (void)state;
  struct vlff_feed_params fp = {.map_name = name, .frames_name = "", .brick = 4, .cloud_piece_bytes = 1 << 20,
                                .world_frame = "odom"};
  /* room for 8192 voxels: the cloud carries as many far points at most */
  struct vlff_map_params mp = {8192, 8, 8, {0, NULL}};
  const uint16_t E3 = VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE;
  /* block (0, 0, 0) holds the grid's first 10 x-voxels of its first row and
   * 6 beyond it (x 10-15); block (1, 0, 0) lies beyond the grid, all chair */
  const struct vlff_map_far_block blocks[2] = {{{0, 0, 0}, 0}, {{1, 0, 0}, 3}};
  const struct vlff_map_far_run runs[4] = {
      {0, 10, 50, 0}, {0, 6, 60, 0}, {VLFF_LABEL_UNKNOWN, (uint16_t)(E3 - 16), 0, 0}, {2, E3, 77, 0}};
  const struct vlff_map_far far = {{-1, 0, 0.5}, 0.25, 2, 4, blocks, runs};
  struct vlff_map *m = vlff_map_create_far(name, &mp, vlff_map_far_bytes(2, 4));
  assert_non_null(m);
  assert_int_equal(vlff_map_set_far(m, &far), 0);
  assert_int_equal(publish(m, prompts, 3), 0);
  struct vlff_feed *f = vlff_feed_new(&fp);
  assert_non_null(f);
  usleep(1100000); /* the feed tries to attach once a second */
  struct vlff_view_msg *whole = poll_cloud(f);
  assert_non_null(whole);
  assert_null(whole->next);
  const size_t occupied = NX * NY + 2, total = occupied + 6 + E3;
  const uint8_t *pt = piece_points(whole, total), *first = pt + occupied * VLFF_VIEW_CLOUD_STRIDE,
                *last = pt + (total - 1) * VLFF_VIEW_CLOUD_STRIDE;
  float c[3];
  memcpy(c, first, 12); /* little-endian floats, as this host's */
  assert_float_equal(c[0], -1 + 10.5 * 0.25, 1e-5);
  assert_float_equal(c[1], 0.125, 1e-5);
  assert_float_equal(c[2], 0.5 + 0.125, 1e-5);
  assert_int_equal(first[16] | first[17] << 8, 0);
  assert_int_equal(first[15], 255);
  assert_int_equal(first[18], 60);
  memcpy(c, last, 12); /* block (1, 0, 0)'s last voxel: lattice (31, 15, 15) */
  assert_float_equal(c[0], -1 + 31.5 * 0.25, 1e-5);
  assert_float_equal(c[1], 15.5 * 0.25, 1e-5);
  assert_float_equal(c[2], 0.5 + 15.5 * 0.25, 1e-5);
  assert_int_equal(last[16] | last[17] << 8, 2);
  assert_int_equal(last[18], 77);
  vlff_view_msg_unref(whole);
  vlff_feed_free(f);
  vlff_map_detach(m);
}

/* The voxels of a /map/voxels message in pieces (under bound each, numbered 0..n-1
 * in a row, full on the first piece of a whole map only, every piece with the
 * version's head) into idx/lab/cf, in order: their count; *npieces the pieces. */
static size_t voxel_pieces(struct vlff_view_msg *head, size_t bound, int whole, uint32_t *idx, uint16_t *lab,
                           uint8_t *cf, size_t cap, int *npieces) {
  int pieces = 0, total = -1;
  size_t k = 0;
  uint64_t version = head->version;
  for (struct vlff_view_msg *p = head; p; p = p->next, pieces++) {
    assert_true(p->len <= bound);
    assert_int_equal(p->whole, whole);
    assert_int_equal(p->version, version);
    json_object *o = parse(p);
    assert_int_equal(json_object_get_int(get(o, "piece")), pieces);
    if (total < 0) total = json_object_get_int(get(o, "pieces"));
    assert_int_equal(json_object_get_int(get(o, "pieces")), total);
    assert_int_equal(json_object_get_boolean(get(o, "full")), whole && !pieces);
    assert_int_equal(json_object_get_int64(get(o, "version")), (int64_t)version);
    assert_int_equal(json_object_array_length(get(o, "prompts")), 3);
    json_object *v = get(o, "voxels");
    size_t n = json_object_array_length(v);
    assert_int_equal(n % 3, 0);
    assert_true(n > 0);
    for (size_t i = 0; i < n; i += 3, k++) {
      assert_true(k < cap);
      idx[k] = (uint32_t)json_object_get_int(json_object_array_get_idx(v, i));
      lab[k] = (uint16_t)json_object_get_int(json_object_array_get_idx(v, i + 1));
      cf[k] = (uint8_t)json_object_get_int(json_object_array_get_idx(v, i + 2));
      if (k) assert_true(idx[k] > idx[k - 1]); /* index order, each voxel once */
    }
    json_object_put(o);
  }
  assert_int_equal(pieces, total);
  *npieces = pieces;
  return k;
}

/* /map/voxels in pieces under the piece bound: the whole map (every occupied voxel
 * once, with its label and confidence) and a change (exactly the changed voxels),
 * each piece numbered and carrying the version's head. */
static void test_voxel_pieces(void **state) {
  (void)state;
  const size_t bound = 600; /* some 30 triples beside the head */
  struct vlff_feed_params fp = {.map_name = name, .frames_name = "", .image_hz = 2, .brick = 4,
                                .cloud_piece_bytes = bound};
  struct vlff_feed *f = vlff_feed_new(&fp);
  struct vlff_map_params mp = {N, 8, 8, {0, NULL}};
  struct vlff_map *m = vlff_map_create(name, &mp);
  assert_non_null(f);
  assert_non_null(m);
  assert_int_equal(publish(m, prompts, 3), 0);
  usleep(1100000); /* the feed tries to attach once a second */
  struct vlff_view_msg *vx = poll_voxels(f);
  assert_non_null(vx);
  static uint32_t idx[N];
  static uint16_t lab[N];
  static uint8_t cf[N];
  int pieces = 0;
  size_t k = voxel_pieces(vx, bound, 1, idx, lab, cf, N, &pieces);
  assert_int_equal(k, NX * NY + 2);
  assert_true(pieces >= 3);
  for (size_t i = 0; i < k; i++) {
    assert_int_equal(lab[i], labels[idx[i]]);
    assert_int_equal(cf[i], 200);
  }
  assert_int_equal(vlff_feed_encoded(f, VLFF_VIEW_CH_VOXELS), (uint64_t)pieces);
  /* a first subscriber gets the same pieces */
  struct vlff_view_msg *cur = vlff_feed_current(f, VLFF_VIEW_CH_VOXELS, NULL);
  assert_ptr_equal(cur, vx);
  vlff_view_msg_unref(cur);
  vlff_view_msg_unref(vx);

  /* the floor relabelled and the chair voxel freed: a change of 91 voxels, in pieces */
  for (int i = 0; i < NX; i++)
    for (int j = 0; j < NY; j++) labels[at(i, j, 0)] = 2;
  labels[at(5, 5, 1)] = VLFF_LABEL_FREE;
  assert_int_equal(publish(m, prompts, 3), 0);
  vx = poll_voxels(f);
  assert_non_null(vx);
  k = voxel_pieces(vx, bound, 0, idx, lab, cf, N, &pieces);
  assert_int_equal(k, NX * NY + 1);
  assert_true(pieces >= 3);
  for (size_t i = 0; i < NX * NY; i++) {
    assert_int_equal(idx[i], i); /* the floor, in index order */
    assert_int_equal(lab[i], 2);
  }
  assert_int_equal(idx[NX * NY], at(5, 5, 1));
  assert_int_equal(lab[NX * NY], VLFF_LABEL_FREE);
  vlff_view_msg_unref(vx);
  vlff_map_detach(m);
  vlff_feed_free(f);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test_setup_teardown(test_feed, setup, teardown),
    cmocka_unit_test_setup_teardown(test_fresh, setup, teardown),
    cmocka_unit_test_setup_teardown(test_feed_follows_log, setup, teardown),
    cmocka_unit_test_setup_teardown(test_cloud, setup, teardown),
    cmocka_unit_test_setup_teardown(test_cloud_far, setup, teardown),
    cmocka_unit_test_setup_teardown(test_voxel_pieces, setup, teardown),
    cmocka_unit_test_setup_teardown(test_grid, setup, teardown))
