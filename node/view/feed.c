/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * feed.c - from the map segment and the frame ring to Foxglove messages.
 *
 * The feed keeps a copy of the last map version it sent (labels, confidence,
 * prompts, grid geometry). A new version is compared with that copy brick by brick:
 * the voxel channel gets the voxels whose label or confidence changed, the scene
 * channel the bricks that hold such a voxel (Foxglove replaces an entity by id, so a
 * brick is the smallest unit it can update). A change of prompts or geometry
 * recolours or moves everything, so it is sent whole. A new subscriber gets the whole
 * copy, built once per version and shared.
 */
#include "clock.h"
#include "json.h"
#include "cvshim.h"
#include "far_walk.h"

#include "log.h"

#include <errno.h>
#include <math.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define NS 1000000000ull

struct feed_map {
  struct vlff_map *map;
  struct vlff_map_snapshot *snap;
  uint64_t next_attach_ns;
  int reported; /* an attach failure was reported; say it once */
  /* the state last sent */
  uint64_t version, publish_ns, far_version;
  uint32_t generation;
  double origin[3], vs;
  uint32_t dims[3];
  size_t n;
  uint16_t *labels;
  uint8_t *conf;
  int prompt_count;
  char prompts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
  uint8_t *brick_sent; /* 1 if the scene holds a non-empty entity for the brick */
  uint64_t occupied, free_, unknown;
  uint64_t label_counts[VLFF_SHM_MAX_PROMPTS];
  uint64_t label_image_t_ns;
};

struct vlff_feed {
  struct vlff_feed_params p;
  uint64_t mono_to_real;
  struct feed_map m;
  /* frame ring */
  struct vlff_ring *ring;
  uint64_t ring_next_attach_ns, ring_head, last_image_ns, last_map_ns;
  int ring_reported;
  void *rec;
  size_t rec_cap;
  uint32_t *changed; /* indices of the voxels a delta carries */
  size_t changed_cap;
  uint64_t fps_head, fps_t_ns;
  double fps;
  bool ring_has_pose; /* a frame of the ring has carried a pose: poses come from the frames */
  uint64_t last_status_ns;
  unsigned last_wanted; /* the channels subscribed at the last poll */
  /* the latest message of each channel; the map ones are built on demand */
  struct vlff_view_msg *current[VLFF_VIEW_CH_COUNT + 1];
  uint64_t encoded[VLFF_VIEW_CH_COUNT + 1]; /* messages built, per channel */
  uint64_t encode_failures;
  uint8_t *rgb; /* a camera frame converted to RGB8 for the encoder */
  size_t rgb_cap;
  uint8_t *pts; /* packed points for the point cloud */
  size_t pts_cap;
  uint8_t *depth; /* a frame's depth as packed uint16 millimetres */
  size_t depth_cap;
  uint8_t *cells; /* the grid's cells */
  size_t cells_cap;
  uint64_t last_grid_ns;
  bool grid_owed; /* the map changed since the last grid sent */
  uint64_t too_large; /* grids and depth images not sent for their size (rate-limited log) */
  uint64_t far_cut;   /* whole clouds that left far voxels out (rate-limited log) */
};

/* Foxglove stamps are wall-clock; the segments' are CLOCK_MONOTONIC. */
static uint64_t to_real(const struct vlff_feed *f, uint64_t mono_ns) { return mono_ns + f->mono_to_real; }

/* A prompt's colour: hues spaced by the golden angle, so that neighbouring labels
 * differ and the colour of a label never depends on how many prompts there are. */
static void label_rgb(unsigned label, uint8_t rgb[3]) {
  double h = fmod(label * 0.618033988749895 + 0.05, 1.0) * 6.0, s = 0.7, v = 0.95;
  int i = (int)h;
  double fr = h - i, p = v * (1 - s), q = v * (1 - s * fr), t = v * (1 - s * (1 - fr));
  double r, g, b;
  switch (i) {
  case 0: r = v, g = t, b = p; break;
  case 1: r = q, g = v, b = p; break;
  case 2: r = p, g = v, b = t; break;
  case 3: r = p, g = q, b = v; break;
  case 4: r = t, g = p, b = v; break;
  default: r = v, g = p, b = q; break;
  }
  rgb[0] = (uint8_t)lround(r * 255);
  rgb[1] = (uint8_t)lround(g * 255);
  rgb[2] = (uint8_t)lround(b * 255);
}

/* Every message the feed builds starts here, so that encoded[] counts them all. */
static struct vlff_view_msg *feed_msg(struct vlff_feed *f, int ch, size_t cap) {
  f->encoded[ch]++;
  return vlff_view_msg_new(ch, cap);
}

static int wants(unsigned wanted, int ch) { return (wanted >> ch) & 1u; }

static void set_current(struct vlff_feed *f, int ch, struct vlff_view_msg *m) {
  vlff_view_msg_unref(f->current[ch]);
  f->current[ch] = vlff_view_msg_ref(m);
}

struct vlff_feed *vlff_feed_new(const struct vlff_feed_params *p) {
  struct vlff_feed *f = calloc(1, sizeof *f);
  if (!f) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "out of memory");
    return NULL;
  }
  f->p = *p;
  if (f->p.brick < 1) f->p.brick = 8;
  if (!f->p.cloud_piece_bytes) f->p.cloud_piece_bytes = 1u << 20;
  if (!(f->p.grid_hz > 0)) f->p.grid_hz = 1;
  if (!f->p.world_frame || !*f->p.world_frame) f->p.world_frame = "world";
  if (!f->p.camera_frame || !*f->p.camera_frame) f->p.camera_frame = "camera";
  f->mono_to_real = vlff_wall_ns() - vlff_now_ns();
  return f;
}

static void map_forget(struct feed_map *m) {
  vlff_map_snapshot_free(m->snap);
  vlff_map_detach(m->map);
  free(m->labels);
  free(m->conf);
  free(m->brick_sent);
  memset(m, 0, sizeof *m);
}

void vlff_feed_free(struct vlff_feed *f) {
  if (!f) return;
  map_forget(&f->m);
  vlff_ring_close(f->ring);
  free(f->rec);
  free(f->changed);
  free(f->rgb);
  free(f->pts);
  free(f->depth);
  free(f->cells);
  for (int c = 0; c <= VLFF_VIEW_CH_COUNT; c++) vlff_view_msg_unref(f->current[c]);
  free(f);
}

uint64_t vlff_feed_version(const struct vlff_feed *f) { return f->m.version; }

uint64_t vlff_feed_encoded(const struct vlff_feed *f, int ch) {
  return ch >= 1 && ch <= VLFF_VIEW_CH_COUNT ? f->encoded[ch] : 0;
}

/* ------------------------------------------------------------ map messages */

static int is_occupied(uint16_t l) { return l <= VLFF_LABEL_MAX; }

static void brick_range(const struct feed_map *m, uint32_t b, uint32_t lo[3], uint32_t hi[3], uint32_t edge) {
  uint32_t nb[3];
  for (int a = 0; a < 3; a++) nb[a] = (m->dims[a] + edge - 1) / edge;
  uint32_t c[3] = {b % nb[0], (b / nb[0]) % nb[1], b / (nb[0] * nb[1])};
  for (int a = 0; a < 3; a++) {
    lo[a] = c[a] * edge;
    hi[a] = lo[a] + edge < m->dims[a] ? lo[a] + edge : m->dims[a];
  }
}

static uint32_t brick_count(const struct feed_map *m, uint32_t edge) {
  uint64_t n = 1;
  for (int a = 0; a < 3; a++) n *= (m->dims[a] + edge - 1) / edge;
  return (uint32_t)n;
}

static void write_brick_entity(struct jw *w, const struct feed_map *m, const char *frame, uint32_t b, uint32_t edge,
                               uint64_t t, const uint8_t (*rgb)[3], int *first) {
  uint32_t lo[3], hi[3];
  brick_range(m, b, lo, hi, edge);
  jw_s(w, *first ? "{" : ",{");
  *first = 0;
  jw_s(w, "\"timestamp\":");
  jw_time(w, t);
  jw_s(w, ",\"frame_id\":");
  jw_str(w, frame);
  jw_f(w, ",\"id\":\"brick-%u\",\"lifetime\":{\"sec\":0,\"nsec\":0},\"frame_locked\":true,"
          "\"metadata\":[],\"arrows\":[],\"cubes\":[",
       b);
  int n = 0;
  double s = m->vs * 0.96; /* a hair smaller, so that neighbouring cubes read as voxels */
  for (uint32_t k = lo[2]; k < hi[2]; k++)
    for (uint32_t j = lo[1]; j < hi[1]; j++)
      for (uint32_t i = lo[0]; i < hi[0]; i++) {
        size_t idx = i + (size_t)m->dims[0] * (j + (size_t)m->dims[1] * k);
        uint16_t l = m->labels[idx];
        if (!is_occupied(l)) continue;
        const uint8_t *c = l < VLFF_SHM_MAX_PROMPTS ? rgb[l] : rgb[VLFF_SHM_MAX_PROMPTS];
        jw_f(w,
             "%s{\"pose\":{\"position\":{\"x\":%.4f,\"y\":%.4f,\"z\":%.4f},\"orientation\":{\"x\":0,\"y\":0,\"z\":0,"
             "\"w\":1}},\"size\":{\"x\":%.4f,\"y\":%.4f,\"z\":%.4f},\"color\":{\"r\":%.3f,\"g\":%.3f,\"b\":%.3f,\"a\":1}}",
             n++ ? "," : "", m->origin[0] + (i + 0.5) * m->vs, m->origin[1] + (j + 0.5) * m->vs,
             m->origin[2] + (k + 0.5) * m->vs, s, s, s, c[0] / 255.0, c[1] / 255.0, c[2] / 255.0);
      }
  jw_s(w, "],\"spheres\":[],\"cylinders\":[],\"lines\":[],\"triangles\":[],\"texts\":[],\"models\":[]}");
}

static int brick_has_voxels(const struct feed_map *m, uint32_t b, uint32_t edge) {
  uint32_t lo[3], hi[3];
  brick_range(m, b, lo, hi, edge);
  for (uint32_t k = lo[2]; k < hi[2]; k++)
    for (uint32_t j = lo[1]; j < hi[1]; j++)
      for (uint32_t i = lo[0]; i < hi[0]; i++)
        if (is_occupied(m->labels[i + (size_t)m->dims[0] * (j + (size_t)m->dims[1] * k)])) return 1;
  return 0;
}

static void palette(uint8_t rgb[VLFF_SHM_MAX_PROMPTS + 1][3]) {
  for (unsigned l = 0; l < VLFF_SHM_MAX_PROMPTS; l++) label_rgb(l, rgb[l]);
  /* a label without a prompt (the map names more labels than prompts) is grey */
  rgb[VLFF_SHM_MAX_PROMPTS][0] = rgb[VLFF_SHM_MAX_PROMPTS][1] = rgb[VLFF_SHM_MAX_PROMPTS][2] = 128;
}

/* A scene piece's message, its deletions opened. */
static struct vlff_view_msg *scene_piece(struct vlff_feed *f, struct jw *w, uint64_t t, int whole) {
  *w = (struct jw){feed_msg(f, VLFF_VIEW_CH_SCENE, 4096), 0};
  if (!w->m) return NULL;
  w->m->t_ns = t;
  w->m->version = f->m.version;
  w->m->whole = whole;
  jw_s(w, "{\"deletions\":[");
  return w->m;
}

/* The scene message: the listed bricks (dirty == NULL: every brick; full also
 * deletes every entity the client may hold from an earlier map), in pieces of at
 * most cloud_piece_bytes (chained through next) as the point cloud is: Foxglove
 * replaces entities by id, so bricks split over several SceneUpdates make the
 * same scene, and a client of a map whose cubes exceed the queue limit (about 190
 * bytes a voxel: 32 MiB is some 170 k voxels) still gets it whole. The deletions
 * go in the first piece. Updates brick_sent. */
static struct vlff_view_msg *scene_msg(struct vlff_feed *f, const uint8_t *dirty, uint32_t edge, uint64_t t,
                                       int update_sent) {
  struct feed_map *m = &f->m;
  uint32_t nb = brick_count(m, edge);
  uint8_t rgb[VLFF_SHM_MAX_PROMPTS + 1][3];
  palette(rgb);
  /* a brick's entity is at most its cubes (under 256 bytes each) and a header */
  size_t brick_max = (size_t)edge * edge * edge * 256 + 512, bound = f->p.cloud_piece_bytes;
  struct jw w;
  struct vlff_view_msg *head = scene_piece(f, &w, t, !dirty);
  if (!head) return NULL;
  struct vlff_view_msg **link = &head->next;
  int first = 1;
  if (!dirty) {
    jw_s(&w, "{\"timestamp\":");
    jw_time(&w, t);
    jw_s(&w, ",\"type\":1,\"id\":\"\"}");
    first = 0;
  } else {
    for (uint32_t b = 0; b < nb; b++) {
      if (!dirty[b] || !m->brick_sent[b] || brick_has_voxels(m, b, edge)) continue;
      jw_s(&w, first ? "{\"timestamp\":" : ",{\"timestamp\":");
      jw_time(&w, t);
      jw_f(&w, ",\"type\":0,\"id\":\"brick-%u\"}", b);
      first = 0;
      if (update_sent) m->brick_sent[b] = 0;
    }
  }
  jw_s(&w, "],\"entities\":[");
  first = 1;
  int failed = 0;
  for (uint32_t b = 0; b < nb; b++) {
    if (dirty && !dirty[b]) continue;
    int has = brick_has_voxels(m, b, edge);
    if (update_sent) m->brick_sent[b] = (uint8_t)has;
    /* after a failure the loop goes on for brick_sent, which must follow the map */
    if (!has || failed) continue;
    if (!first && w.m->len + brick_max > bound) {
      /* this piece is full: closed, and the next one started */
      jw_s(&w, "]}");
      failed |= w.failed;
      if (!scene_piece(f, &w, t, !dirty)) {
        failed = 1;
        continue;
      }
      *link = w.m, link = &w.m->next;
      jw_s(&w, "],\"entities\":[");
      first = 1;
    }
    write_brick_entity(&w, m, f->p.world_frame, b, edge, t, (const uint8_t(*)[3])rgb, &first);
  }
  if (w.m) {
    jw_s(&w, "]}");
    failed |= w.failed;
  }
  if (failed) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "out of memory for the /map scene");
    vlff_view_msg_unref(head); /* the pieces go with it */
    return NULL;
  }
  return head;
}

/* A /map/voxels piece's head: piece of pieces (0-based) of one version's message,
 * full on the first piece of a whole map only, so that a reader that knows no
 * pieces (full: forget every voxel not listed) still ends with the whole map: the
 * first piece replaces its copy, the later ones add to it as a change does. */
static void write_map_header(struct jw *w, const struct feed_map *m, int full, uint32_t piece, uint32_t pieces) {
  jw_f(w, "{\"version\":%llu,\"full\":%s,\"piece\":%u,\"pieces\":%u,\"publish_mono_ns\":%llu,"
          "\"origin\":[%.6f,%.6f,%.6f],\"voxel_size\":%.6f,",
       (unsigned long long)m->version, full ? "true" : "false", piece, pieces, (unsigned long long)m->publish_ns,
       m->origin[0], m->origin[1], m->origin[2], m->vs);
  jw_f(w, "\"dims\":[%u,%u,%u],\"prompts\":[", m->dims[0], m->dims[1], m->dims[2]);
  for (int i = 0; i < m->prompt_count; i++) {
    if (i) jw_s(w, ",");
    jw_str(w, m->prompts[i]);
  }
  jw_s(w, "],\"colors\":[");
  for (int i = 0; i < m->prompt_count; i++) {
    uint8_t c[3];
    label_rgb((unsigned)i, c);
    jw_f(w, "%s\"#%02x%02x%02x\"", i ? "," : "", c[0], c[1], c[2]);
  }
  jw_f(w, "],\"occupied\":%llu,\"voxels\":[", (unsigned long long)m->occupied);
}

/* The voxels a /map/voxels message lists, in index order: the listed ones, or
 * (idx NULL) every occupied one. */
struct vox_iter {
  const struct feed_map *m;
  const uint32_t *idx;
  size_t n, k;
};
static int vox_next(struct vox_iter *it, size_t *i) {
  if (it->idx) {
    if (it->k >= it->n) return 0;
    *i = it->idx[it->k++];
    return 1;
  }
  while (it->k < it->m->n && !is_occupied(it->m->labels[it->k])) it->k++;
  if (it->k >= it->m->n) return 0;
  *i = it->k++;
  return 1;
}
/* Voxel i's triple with its leading comma into e (48 bytes); its length. */
static size_t vox_entry(char *e, const struct feed_map *m, size_t i) {
  return (size_t)snprintf(e, 48, ",%zu,%u,%u", i, m->labels[i], m->conf[i]);
}

/* A piece of /map/voxels, its head written. */
static struct vlff_view_msg *voxels_piece(struct vlff_feed *f, struct jw *w, uint64_t t, int whole, uint32_t piece,
                                          uint32_t pieces) {
  *w = (struct jw){feed_msg(f, VLFF_VIEW_CH_VOXELS, 4096), 0};
  if (!w->m) return NULL;
  w->m->t_ns = t;
  w->m->version = f->m.version;
  w->m->whole = whole;
  write_map_header(w, &f->m, whole && !piece, piece, pieces);
  return w->m;
}

/* /map/voxels: the listed voxels (idx == NULL: every occupied voxel, the whole
 * map), in pieces of at most cloud_piece_bytes (chained through next) as the
 * point cloud is, so that a map whose JSON exceeds a client's queue limit (13 to
 * 15 bytes a voxel) still reaches it. Each piece repeats the head (version,
 * geometry, prompts) and says which piece of how many it is; at least one piece,
 * so that a version without changes still tells clients its number. */
static struct vlff_view_msg *voxels_msg(struct vlff_feed *f, const uint32_t *idx, size_t n, uint64_t t) {
  const struct feed_map *m = &f->m;
  int whole = !idx;
  struct jw w;
  struct vlff_view_msg *head = voxels_piece(f, &w, t, whole, 0, 0);
  if (!head) return NULL;
  /* the room for triples beside a head: the head measured, with room for the
   * piece numbers' digits and the closing "]}" */
  size_t bound = f->p.cloud_piece_bytes, hl = head->len + 2 * 10 + 2, room = bound > hl ? bound - hl : 0;
  /* the pieces counted first, cut where the writing below cuts them */
  char e[48];
  size_t i, used = 0;
  uint32_t pieces = 1;
  for (struct vox_iter it = {m, idx, n, 0}; vox_next(&it, &i);) {
    size_t l = vox_entry(e, m, i);
    if (used && used + l > room) pieces++, used = 0;
    used += l;
  }
  head->len = 0;
  write_map_header(&w, m, whole, 0, pieces);
  struct vlff_view_msg **link = &head->next;
  uint32_t piece = 0;
  int failed = 0;
  used = 0;
  for (struct vox_iter it = {m, idx, n, 0}; vox_next(&it, &i);) {
    size_t l = vox_entry(e, m, i);
    if (used && used + l > room) {
      jw_s(&w, "]}");
      failed |= w.failed;
      if (failed || !voxels_piece(f, &w, t, whole, ++piece, pieces)) {
        failed = 1;
        break;
      }
      *link = w.m, link = &w.m->next;
      used = 0;
    }
    jw_raw(&w, used ? e : e + 1, used ? l : l - 1); /* the first triple of a piece without its comma */
    used += l;
  }
  if (!failed) {
    jw_s(&w, "]}");
    failed = w.failed;
  }
  if (failed) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "out of memory for /map/voxels");
    vlff_view_msg_unref(head); /* the pieces go with it */
    return NULL;
  }
  return head;
}

/* A point of the cloud (view.h: VLFF_VIEW_CLOUD_STRIDE bytes, little-endian). */
static void pack_xyz(uint8_t *o, const double centre[3], uint16_t l, uint8_t conf, const uint8_t (*rgb)[3]) {
  for (int a = 0; a < 3; a++) {
    const float c = (float)centre[a];
    uint32_t u;
    memcpy(&u, &c, 4);
    for (int b = 0; b < 4; b++) o[4 * a + b] = (uint8_t)(u >> (8 * b));
  }
  if (is_occupied(l)) {
    memcpy(o + 12, l < VLFF_SHM_MAX_PROMPTS ? rgb[l] : rgb[VLFF_SHM_MAX_PROMPTS], 3);
    o[15] = 255;
  } else {
    memset(o + 12, 0, 4); /* no longer occupied: transparent */
  }
  o[16] = (uint8_t)l;
  o[17] = (uint8_t)(l >> 8);
  o[18] = conf;
  o[19] = 0;
}

/* Voxel idx of the map copy as a point of the cloud. */
static void pack_point(uint8_t *o, const struct feed_map *m, size_t idx, const uint8_t (*rgb)[3]) {
  size_t i = idx % m->dims[0], j = idx / m->dims[0] % m->dims[1], k = idx / m->dims[0] / m->dims[1];
  const double c[3] = {m->origin[0] + (i + 0.5) * m->vs, m->origin[1] + (j + 0.5) * m->vs,
                       m->origin[2] + (k + 0.5) * m->vs};
  pack_xyz(o, c, m->labels[idx], m->conf ? m->conf[idx] : 255, rgb);
}

/* Far voxels into the cloud being built (far_walk.h). */
struct far_pack {
  uint8_t *o;
  const uint8_t (*rgb)[3];
};

static void pack_far(void *ctx, const double centre[3], uint16_t label, uint8_t conf) {
  struct far_pack *fp = ctx;
  pack_xyz(fp->o, centre, label, conf, fp->rgb);
  fp->o += VLFF_VIEW_CLOUD_STRIDE;
}

/* The point cloud of the listed voxels (idx == NULL: every occupied voxel and
 * the far map's labelled voxels beyond the grid, the whole map), in pieces of
 * at most cloud_piece_bytes. A new far map sends the map whole
 * (map_needs_full). */
static struct vlff_view_msg *cloud_msg(struct vlff_feed *f, const uint32_t *idx, size_t n, uint64_t t) {
  const struct feed_map *m = &f->m;
  struct vlff_map_far far = {0};
  const struct vlff_map_grid g = {{m->origin[0], m->origin[1], m->origin[2]}, m->vs, {m->dims[0], m->dims[1], m->dims[2]},
                                  m->labels, m->conf};
  struct vlff_far_pick pick = {0};
  const size_t far_max = m->map ? (size_t)vlff_map_capacity(m->map) : 0;
  if (!idx && m->snap && vlff_map_snapshot_far(m->snap, &far) == 0 && vlff_far_pick(&far, &g, far_max, &pick))
    vlff_log(VLFF_LOG_WARN, "vlff-view", "/map/points: no memory to choose the far map's points: the grid alone");
  if (pick.left)
    vlff_warn_limited(&f->far_cut, "vlff-view", "/map/points: %zu far voxels beyond the grid left out (at most %zu, "
                      "as many as the grid holds voxels, the nearest blocks first)", pick.left, far_max);
  const size_t nfar = pick.points;
  if (!idx) n = (size_t)m->occupied + nfar;
  size_t need = (n ? n : 1) * VLFF_VIEW_CLOUD_STRIDE;
  if (need > f->pts_cap) {
    uint8_t *p = realloc(f->pts, need);
    if (!p) {
      vlff_log(VLFF_LOG_WARN, "vlff-view", "out of memory for a point cloud of %zu points", n);
      vlff_far_pick_free(&pick);
      return NULL;
    }
    f->pts = p, f->pts_cap = need;
  }
  uint8_t rgb[VLFF_SHM_MAX_PROMPTS + 1][3];
  palette(rgb);
  size_t k = 0;
  if (idx) {
    for (; k < n; k++) pack_point(f->pts + k * VLFF_VIEW_CLOUD_STRIDE, m, idx[k], (const uint8_t(*)[3])rgb);
  } else {
    for (size_t i = 0; i < m->n && k < n - nfar; i++)
      if (is_occupied(m->labels[i])) pack_point(f->pts + k++ * VLFF_VIEW_CLOUD_STRIDE, m, i, (const uint8_t(*)[3])rgb);
    struct far_pack fp = {f->pts + k * VLFF_VIEW_CLOUD_STRIDE, (const uint8_t(*)[3])rgb};
    k += vlff_far_emit(&far, &g, &pick, pack_far, &fp); /* exactly nfar */
  }
  vlff_far_pick_free(&pick);
  int pieces = 0;
  struct vlff_view_msg *c =
      vlff_view_cloud_msgs(VLFF_VIEW_CH_CLOUD, f->p.world_frame, f->pts, k, t, f->p.cloud_piece_bytes, &pieces);
  f->encoded[VLFF_VIEW_CH_CLOUD] += (uint64_t)pieces;
  for (struct vlff_view_msg *p = c; p; p = p->next) p->version = m->version, p->whole = !idx;
  return c;
}

/* Grows *buf to at least need bytes: 0, or -1 out of memory (logged). */
static int grow(uint8_t **buf, size_t *cap, size_t need, const char *what) {
  if (need <= *cap) return 0;
  uint8_t *p = realloc(*buf, need);
  if (!p) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "out of memory for %s of %zu bytes", what, need);
    return -1;
  }
  *buf = p, *cap = need;
  return 0;
}

/* /map/grid from the map copy: one cell per column (i, j) of the grid, its
 * corner at the map's origin. Seen from above (no grid_slice), a column's cell is
 * its highest occupied voxel (elevation: that voxel's top above the map's
 * lowest plane); a column without one is free when any of its voxels is free,
 * else unknown, transparent, elevation 0. As a slice, a cell is the voxel of the
 * layer holding grid_z (elevation: that height above the lowest plane); a height
 * outside the map gives unknown cells. */
static struct vlff_view_msg *grid_msg(struct vlff_feed *f, uint64_t t) {
  const struct feed_map *m = &f->m;
  uint32_t cols = m->dims[0], rows = m->dims[1];
  size_t bytes = (size_t)cols * rows * VLFF_VIEW_GRID_STRIDE;
  if (f->p.max_message_bytes && bytes > f->p.max_message_bytes) {
    vlff_warn_limited(&f->too_large, "vlff-view", "/map/grid: a %ux%u grid is %zu bytes, above half of --max-queue-mb "
                      "(%zu bytes): not sent", cols, rows, bytes, f->p.max_message_bytes);
    return NULL;
  }
  if (grow(&f->cells, &f->cells_cap, (size_t)cols * rows * VLFF_VIEW_GRID_STRIDE + 1, "the grid")) return NULL;
  uint8_t rgb[VLFF_SHM_MAX_PROMPTS + 1][3];
  palette(rgb);
  int slice = f->p.grid_slice;
  double zk = slice ? floor((f->p.grid_z - m->origin[2]) / m->vs) : 0;
  size_t layer = (size_t)cols * rows;
  for (uint32_t j = 0; j < rows; j++)
    for (uint32_t i = 0; i < cols; i++) {
      uint8_t *o = f->cells + ((size_t)j * cols + i) * VLFF_VIEW_GRID_STRIDE;
      size_t col = i + (size_t)cols * j, idx = SIZE_MAX;
      uint16_t l = VLFF_LABEL_UNKNOWN;
      float elev = 0;
      if (slice) {
        if (zk >= 0 && zk < m->dims[2]) {
          idx = col + layer * (size_t)zk;
          l = m->labels[idx];
          elev = (float)(f->p.grid_z - m->origin[2]);
        }
      } else {
        for (uint32_t k = m->dims[2]; k-- > 0;) {
          uint16_t v = m->labels[col + layer * k];
          if (is_occupied(v)) {
            idx = col + layer * k, l = v, elev = (float)((k + 1) * m->vs);
            break;
          }
          if (v == VLFF_LABEL_FREE) l = VLFF_LABEL_FREE;
        }
      }
      if (is_occupied(l)) {
        memcpy(o, l < VLFF_SHM_MAX_PROMPTS ? rgb[l] : rgb[VLFF_SHM_MAX_PROMPTS], 3);
        o[3] = 255;
      } else {
        memset(o, 0, 4);
      }
      o[4] = (uint8_t)l;
      o[5] = (uint8_t)(l >> 8);
      o[6] = idx != SIZE_MAX && is_occupied(l) ? m->conf[idx] : 0;
      o[7] = 0;
      uint32_t u;
      memcpy(&u, &elev, 4);
      for (int b = 0; b < 4; b++) o[8 + b] = (uint8_t)(u >> (8 * b));
    }
  f->encoded[VLFF_VIEW_CH_GRID]++;
  struct vlff_view_msg *g = vlff_view_grid_msg(VLFF_VIEW_CH_GRID, f->p.world_frame, t, m->origin, m->vs, cols, rows,
                                               f->cells);
  if (g) g->version = m->version;
  return g;
}

/* The grid when one is owed (the map changed since the last) and the rate
 * allows: a grid is the whole projection, so a client needs only the latest. */
static int grid_poll(struct vlff_feed *f, unsigned wanted, struct vlff_view_msg **out, int cap) {
  uint64_t now = vlff_now_ns();
  if (!f->grid_owed || !f->m.labels || cap < 1 || now - f->last_grid_ns < (uint64_t)(1e9 / f->p.grid_hz)) return 0;
  if (!wants(wanted, VLFF_VIEW_CH_GRID)) {
    /* nobody to send it to: a first subscriber gets one built then */
    set_current(f, VLFF_VIEW_CH_GRID, NULL);
    return 0;
  }
  f->last_grid_ns = now; /* a grid not built (too large, no memory) is tried again at the rate */
  struct vlff_view_msg *g = grid_msg(f, to_real(f, f->m.publish_ns));
  if (!g) return 0;
  f->grid_owed = false;
  set_current(f, VLFF_VIEW_CH_GRID, g);
  out[0] = g;
  return 1;
}

static void count_labels(struct feed_map *m) {
  m->occupied = m->free_ = m->unknown = 0;
  memset(m->label_counts, 0, sizeof m->label_counts);
  for (size_t i = 0; i < m->n; i++) {
    uint16_t l = m->labels[i];
    if (l == VLFF_LABEL_FREE) m->free_++;
    else if (l == VLFF_LABEL_UNKNOWN) m->unknown++;
    else {
      m->occupied++;
      if (l < VLFF_SHM_MAX_PROMPTS) m->label_counts[l]++;
    }
  }
}

/* A foxglove.CompressedImage of packed RGB8 pixels: JPEG (the camera) or PNG (the
 * labels, whose colours must stay exact). NULL, the failure logged (rate-limited),
 * when the encoder fails. */
static struct vlff_view_msg *compressed_msg(struct vlff_feed *f, int ch, uint64_t t, const uint8_t *rgb, size_t stride,
                                            uint32_t w, uint32_t h, int png) {
  uint8_t *enc = NULL;
  size_t n = 0;
  char err[160];
  if (vlff_cv_compress_rgb(rgb, stride, (int)w, (int)h, png, VLFF_VIEW_JPEG_QUALITY, &enc, &n, err, sizeof err)) {
    vlff_warn_limited(&f->encode_failures, "vlff-view", "a %ux%u image for %s: %s", w, h, vlff_view_channel(ch)->topic,
                      err);
    return NULL;
  }
  struct jw w_ = {feed_msg(f, ch, n / 3 * 4 + 256), 0};
  if (w_.m) {
    w_.m->t_ns = t;
    jw_s(&w_, "{\"timestamp\":");
    jw_time(&w_, t);
    jw_s(&w_, ",\"frame_id\":");
    jw_str(&w_, f->p.camera_frame);
    jw_f(&w_, ",\"format\":\"%s\",\"data\":", png ? "png" : "jpeg");
    jw_b64(&w_, enc, n);
    jw_s(&w_, "}");
  }
  free(enc);
  return w_.m ? jw_finish(&w_) : NULL;
}

static struct vlff_view_msg *label_image_msg(struct vlff_feed *f, const struct vlff_map_label_image *li) {
  size_t px = (size_t)li->width * li->height;
  uint8_t *rgb = malloc(px * 3 + 1);
  if (!rgb) return NULL;
  uint8_t pal[VLFF_SHM_MAX_PROMPTS][3];
  for (unsigned l = 0; l < VLFF_SHM_MAX_PROMPTS; l++) label_rgb(l, pal[l]);
  for (size_t i = 0; i < px; i++) {
    uint16_t l = li->labels[i];
    uint8_t *o = rgb + 3 * i;
    if (l < VLFF_SHM_MAX_PROMPTS) memcpy(o, pal[l], 3);
    else if (l == VLFF_LABEL_FREE) o[0] = o[1] = o[2] = 40;
    else if (l == VLFF_LABEL_UNKNOWN) o[0] = o[1] = o[2] = 0;
    else o[0] = o[1] = o[2] = 128;
  }
  struct vlff_view_msg *m =
      compressed_msg(f, VLFF_VIEW_CH_LABELS, to_real(f, li->t_ns), rgb, (size_t)li->width * 3, li->width, li->height, 1);
  free(rgb);
  return m;
}

/* Row-major camera-to-world matrix to a FrameTransform world -> camera. */
static struct vlff_view_msg *pose_msg(struct vlff_feed *f, uint64_t t, const double P[16]) {
  double q[4]; /* w x y z */
  vlff_pose_quaternion(P, q);
  double qw = q[0], qx = q[1], qy = q[2], qz = q[3];
  struct jw w = {feed_msg(f, VLFF_VIEW_CH_POSE, 512), 0};
  if (!w.m) return NULL;
  w.m->t_ns = t;
  jw_s(&w, "{\"timestamp\":");
  jw_time(&w, t);
  jw_s(&w, ",\"parent_frame_id\":");
  jw_str(&w, f->p.world_frame);
  jw_s(&w, ",\"child_frame_id\":");
  jw_str(&w, f->p.camera_frame);
  jw_f(&w,
       ",\"translation\":{\"x\":%.6f,\"y\":%.6f,\"z\":%.6f},"
       "\"rotation\":{\"x\":%.9f,\"y\":%.9f,\"z\":%.9f,\"w\":%.9f}}",
       P[3], P[7], P[11], qx, qy, qz, qw);
  return jw_finish(&w);
}

static int valid_pose(const double P[16]) {
  for (int i = 0; i < 16; i++)
    if (!isfinite(P[i])) return 0;
  return 1;
}

static void map_attach(struct vlff_feed *f, uint64_t now) {
  struct feed_map *m = &f->m;
  if (m->map || now < m->next_attach_ns) return;
  m->next_attach_ns = now + NS;
  m->map = vlff_map_attach(f->p.map_name);
  if (!m->map) {
    if (!m->reported)
      vlff_log(VLFF_LOG_WARN, "vlff-view", "map %s: %s; retrying every second", f->p.map_name, vlff_shm_last_message());
    m->reported = 1;
    return;
  }
  m->snap = vlff_map_snapshot_new(m->map);
  if (!m->snap) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "map %s: no memory for a snapshot", f->p.map_name);
    vlff_map_detach(m->map);
    m->map = NULL;
    return;
  }
  vlff_log(VLFF_LOG_INFO, "vlff-view", "attached to map %s", f->p.map_name);
  m->reported = 0;
}

/* Brings m->snap up to a map version not read yet, copying only what the
 * map's change log says changed (vlff_map_snapshot_follow), and its info:
 * 0, or -1 when there is none (no map, no new version, or the segment was
 * replaced: then it is forgotten, to attach again). */
static int map_take_version(struct vlff_feed *f, struct vlff_map_info *info) {
  struct feed_map *m = &f->m;
  map_attach(f, vlff_now_ns());
  if (!m->map) return -1;
  uint64_t v = vlff_map_version(m->map);
  if (v == 0 || (v == m->version && vlff_map_generation(m->map) == m->generation)) return -1;
  /* The node publishes what each keyframe saw at once and refreshes the rest
   * in slices: many versions a second. A client gets them at most map_hz a
   * second, each update holding everything that changed since its last (the
   * change log spans versions), so a browser redraws at a rate it keeps up
   * with. */
  uint64_t now = vlff_now_ns();
  if (m->version && f->p.map_hz > 0 && now - f->last_map_ns < (uint64_t)(1e9 / f->p.map_hz)) return -1;
  if (vlff_map_snapshot_follow(m->map, m->snap) < 0) {
    if (errno == EPIPE) {
      vlff_log(VLFF_LOG_WARN, "vlff-view", "map %s was replaced by a new one; attaching again", f->p.map_name);
      uint64_t keep = m->version;
      map_forget(m);
      m->version = keep; /* clients keep their map until the new segment publishes */
    }
    return -1;
  }
  f->last_map_ns = now;
  return vlff_map_snapshot_info(m->snap, info) != 0 ? -1 : 0;
}

/* Whether the snapshot must be sent whole: a first map, a new geometry, new
 * prompts or a new far map (/map/points carries it with the whole map). */
static int map_needs_full(const struct feed_map *m, const struct vlff_map_info *info) {
  const struct vlff_map_grid *g = &info->grid;
  size_t n = (size_t)g->dims[0] * g->dims[1] * g->dims[2];
  int full = !m->labels || n != m->n || memcmp(g->dims, m->dims, sizeof m->dims) ||
             memcmp(g->origin, m->origin, sizeof m->origin) || g->voxel_size != m->vs ||
             info->prompt_count != m->prompt_count || vlff_map_snapshot_far_version(m->snap) != m->far_version;
  for (int i = 0; !full && i < info->prompt_count && i < VLFF_SHM_MAX_PROMPTS; i++) {
    const char *p = vlff_map_snapshot_prompt(m->snap, (uint16_t)i);
    full = strcmp(p ? p : "", m->prompts[i]) != 0;
  }
  return full;
}

/* The copy of the map replaced by the snapshot's grid: 0, or -1 out of
 * memory (the map is forgotten). */
static int map_copy_whole(struct feed_map *m, const struct vlff_map_grid *g, uint32_t edge) {
  size_t n = (size_t)g->dims[0] * g->dims[1] * g->dims[2];
  free(m->labels);
  free(m->conf);
  free(m->brick_sent);
  m->n = n;
  memcpy(m->dims, g->dims, sizeof m->dims);
  memcpy(m->origin, g->origin, sizeof m->origin);
  m->vs = g->voxel_size;
  m->labels = malloc(n * sizeof *m->labels + 1);
  m->conf = malloc(n + 1);
  m->brick_sent = calloc(brick_count(m, edge) + 1, 1);
  if (!m->labels || !m->conf || !m->brick_sent) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "out of memory for a %zu-voxel map", n);
    map_forget(m);
    return -1;
  }
  memcpy(m->labels, g->labels, n * sizeof *m->labels);
  if (g->confidence) memcpy(m->conf, g->confidence, n);
  else memset(m->conf, 255, n);
  return 0;
}

/* Appends msg to out when there is room, else drops it. */
static void emit(struct vlff_view_msg **out, int *nout, int cap, struct vlff_view_msg *msg) {
  if (msg && *nout < cap) out[(*nout)++] = msg;
  else vlff_view_msg_unref(msg);
}

/* The whole map's messages, which also become the channels' current ones. */
static int map_whole_msgs(struct vlff_feed *f, unsigned wanted, uint32_t edge, uint64_t t, struct vlff_view_msg **out,
                          int cap) {
  int nout = 0;
  count_labels(&f->m);
  /* a channel nobody subscribes to is not encoded: vlff_feed_current builds it
   * for its first subscriber */
  struct vlff_view_msg *s = wants(wanted, VLFF_VIEW_CH_SCENE) ? scene_msg(f, NULL, edge, t, 1) : NULL;
  struct vlff_view_msg *vx = wants(wanted, VLFF_VIEW_CH_VOXELS) ? voxels_msg(f, NULL, 0, t) : NULL;
  struct vlff_view_msg *pc = wants(wanted, VLFF_VIEW_CH_CLOUD) ? cloud_msg(f, NULL, 0, t) : NULL;
  set_current(f, VLFF_VIEW_CH_SCENE, s);
  set_current(f, VLFF_VIEW_CH_VOXELS, vx);
  set_current(f, VLFF_VIEW_CH_CLOUD, pc);
  /* the small voxel message first: it is not queued behind the scene */
  emit(out, &nout, cap, vx);
  emit(out, &nout, cap, pc);
  emit(out, &nout, cap, s);
  return nout;
}

/* Copies the voxels of g that changed into the map, listing their indices
 * in f->changed (index order) and marking their bricks in dirty: their
 * count, or -1 out of memory (the map is forgotten). Only the runs the
 * map's change log named since the last version read are compared (all of
 * the grid when the snapshot was copied whole). */
static long map_take_changes(struct vlff_feed *f, const struct vlff_map_grid *g, uint32_t edge, uint8_t *dirty) {
  struct feed_map *m = &f->m;
  const uint8_t *gc = g->confidence;
  size_t changed = 0;
  uint32_t nb0 = (m->dims[0] + edge - 1) / edge, nb1 = (m->dims[1] + edge - 1) / edge;
  const struct vlff_map_range *runs;
  int all;
  size_t nruns = vlff_map_snapshot_changes(m->snap, &runs, &all);
  struct vlff_map_range whole = {0, (uint32_t)m->n};
  if (all) runs = &whole, nruns = 1;
  for (size_t r = 0; r < nruns; r++) {
    size_t end = (size_t)runs[r].first + runs[r].count;
    /* the library keeps runs inside the grid; the viewer's copy is of the
     * same geometry (map_needs_full) */
    if (end > m->n) end = m->n;
    for (size_t idx = runs[r].first; idx < end; idx++) {
      uint8_t c = gc ? gc[idx] : 255;
      if (g->labels[idx] == m->labels[idx] && c == m->conf[idx]) continue;
      uint32_t i = (uint32_t)(idx % m->dims[0]), j = (uint32_t)(idx / m->dims[0] % m->dims[1]),
               k = (uint32_t)(idx / m->dims[0] / m->dims[1]);
      if (changed == f->changed_cap) {
        size_t nc = f->changed_cap ? f->changed_cap * 2 : 4096;
        uint32_t *p = realloc(f->changed, nc * sizeof *p);
        if (!p) {
          vlff_log(VLFF_LOG_WARN, "vlff-view", "out of memory for a map delta");
          map_forget(m);
          return -1;
        }
        f->changed = p;
        f->changed_cap = nc;
      }
      f->changed[changed++] = (uint32_t)idx;
      m->labels[idx] = g->labels[idx];
      m->conf[idx] = c;
      dirty[i / edge + nb0 * (j / edge + nb1 * (k / edge))] = 1;
    }
  }
  return (long)changed;
}

/* The delta's messages: the changed voxels, in index order, and the bricks
 * holding them; -1 out of memory. */
static int map_delta_msgs(struct vlff_feed *f, const struct vlff_map_grid *g, unsigned wanted, uint32_t edge,
                          uint64_t t, struct vlff_view_msg **out, int cap) {
  struct feed_map *m = &f->m;
  int nout = 0;
  uint8_t *dirty = calloc(brick_count(m, edge), 1);
  if (!dirty) return -1;
  long nchanged = map_take_changes(f, g, edge, dirty);
  if (nchanged < 0) {
    free(dirty);
    return -1;
  }
  size_t changed = (size_t)nchanged;
  count_labels(m);
  struct vlff_view_msg *vx = wants(wanted, VLFF_VIEW_CH_VOXELS) ? voxels_msg(f, f->changed, changed, t) : NULL,
                       *s = NULL;
  /* a version that changed no voxel still reaches the voxel channel (clients
   * learn the version); the scene has nothing to replace then */
  if (changed && wants(wanted, VLFF_VIEW_CH_SCENE)) s = scene_msg(f, dirty, edge, t, 1);
  struct vlff_view_msg *pc = changed && wants(wanted, VLFF_VIEW_CH_CLOUD) ? cloud_msg(f, f->changed, changed, t) : NULL;
  free(dirty);
  emit(out, &nout, cap, vx);
  emit(out, &nout, cap, pc);
  emit(out, &nout, cap, s);
  /* the whole map for new subscribers is rebuilt when first asked for */
  set_current(f, VLFF_VIEW_CH_SCENE, NULL);
  set_current(f, VLFF_VIEW_CH_VOXELS, NULL);
  set_current(f, VLFF_VIEW_CH_CLOUD, NULL);
  return nout;
}

/* A newer label image than the one kept, and the camera pose it carries
 * when the frames carry none. */
static int map_label_image_msgs(struct vlff_feed *f, const struct vlff_map_info *info, unsigned wanted,
                                struct vlff_view_msg **out, int cap) {
  struct feed_map *m = &f->m;
  int nout = 0;
  if (!info->has_label_image || info->label_image.t_ns == m->label_image_t_ns) return 0;
  m->label_image_t_ns = info->label_image.t_ns;
  /* a newer image than the one kept: a later subscriber waits for the next */
  set_current(f, VLFF_VIEW_CH_LABELS, NULL);
  if (wants(wanted, VLFF_VIEW_CH_LABELS) && nout < cap) {
    struct vlff_view_msg *li = label_image_msg(f, &info->label_image);
    if (li) {
      out[nout++] = li;
      set_current(f, VLFF_VIEW_CH_LABELS, li);
    }
  }
  /* the camera pose comes from the frames when they carry one, else from here */
  if ((!f->ring || !f->ring_has_pose) && wants(wanted, VLFF_VIEW_CH_POSE) && valid_pose(info->label_image.pose) &&
      nout < cap) {
    struct vlff_view_msg *pm = pose_msg(f, to_real(f, info->label_image.t_ns), info->label_image.pose);
    if (pm) {
      out[nout++] = pm;
      set_current(f, VLFF_VIEW_CH_POSE, pm);
    }
  }
  return nout;
}

/* Reads a new map version, if any, and appends its messages: the whole map
 * or the delta, then a new label image. */
static int map_poll(struct vlff_feed *f, unsigned wanted, struct vlff_view_msg **out, int cap) {
  struct feed_map *m = &f->m;
  struct vlff_map_info info;
  if (map_take_version(f, &info)) return 0;
  const struct vlff_map_grid *g = &info.grid;
  int full = map_needs_full(m, &info);
  uint64_t t = to_real(f, info.publish_ns);
  uint32_t edge = f->p.brick;
  if (full && map_copy_whole(m, g, edge)) return 0;
  m->prompt_count = info.prompt_count > VLFF_SHM_MAX_PROMPTS ? VLFF_SHM_MAX_PROMPTS : info.prompt_count;
  for (int i = 0; i < m->prompt_count; i++) {
    const char *p = vlff_map_snapshot_prompt(m->snap, (uint16_t)i);
    snprintf(m->prompts[i], sizeof m->prompts[i], "%s", p ? p : "");
  }
  m->version = info.version;
  m->publish_ns = info.publish_ns;
  m->generation = info.generation;
  m->far_version = vlff_map_snapshot_far_version(m->snap);
  int nout = full ? map_whole_msgs(f, wanted, edge, t, out, cap) : map_delta_msgs(f, g, wanted, edge, t, out, cap);
  if (nout < 0) return 0;
  f->grid_owed = true;
  return nout + map_label_image_msgs(f, &info, wanted, out + nout, cap - nout);
}

/* ----------------------------------------------------------- camera frames */

/* A foxglove.CameraCalibration of the frame's pinhole intrinsics: no distortion (the
 * frames in the ring are undistorted by their driver), K and P in OpenCV's
 * convention, whose principal point is half a pixel left of and above the ring's. */
static struct vlff_view_msg *calib_msg(struct vlff_feed *f, uint64_t t, const struct vlff_frame_hdr *h) {
  const struct vlff_plane *pl = &h->plane[VLFF_PLANE_COLOR];
  struct jw w = {feed_msg(f, VLFF_VIEW_CH_CALIB, 768), 0};
  if (!w.m) return NULL;
  w.m->t_ns = t;
  double cx = h->cx - 0.5, cy = h->cy - 0.5;
  jw_s(&w, "{\"timestamp\":");
  jw_time(&w, t);
  jw_s(&w, ",\"frame_id\":");
  jw_str(&w, f->p.camera_frame);
  jw_f(&w,
       ",\"width\":%u,\"height\":%u,\"distortion_model\":\"plumb_bob\",\"D\":[0,0,0,0,0],"
       "\"K\":[%.9g,0,%.9g,0,%.9g,%.9g,0,0,1],\"R\":[1,0,0,0,1,0,0,0,1],\"P\":[%.9g,0,%.9g,0,0,%.9g,%.9g,0,0,0,1,0]}",
       pl->width, pl->height, h->fx, cx, h->fy, cy, h->fx, cx, h->fy, cy);
  return jw_finish(&w);
}

static int valid_intrinsics(const struct vlff_frame_hdr *h) {
  const double k[4] = {h->fx, h->fy, h->cx, h->cy};
  for (int i = 0; i < 4; i++)
    if (!isfinite(k[i]) || (i < 2 && k[i] <= 0)) return 0;
  return (h->flags & VLFF_FRAME_INTRINSICS_VALID) != 0;
}

static int frame_encode(struct vlff_feed *f, unsigned build, struct vlff_view_msg **out, int cap);

/* A foxglove.RawImage 16UC1 of the frame's depth plane in millimetres: uint16
 * millimetres as they are, float32 metres rounded to the millimetre (0 where
 * not finite, not positive, or beyond 65.535 m, which 16 bits cannot hold).
 * NULL for a frame without depth. */
static struct vlff_view_msg *depth_msg(struct vlff_feed *f, uint64_t t, const struct vlff_frame_hdr *h) {
  const struct vlff_plane *pl = &h->plane[VLFF_PLANE_DEPTH];
  const uint8_t *px = h->nplanes > 1 ? vlff_frame_plane(f->rec, VLFF_PLANE_DEPTH) : NULL;
  if (!px || (pl->format != VLFF_PIX_DEPTH_U16_MM && pl->format != VLFF_PIX_DEPTH_F32_M)) return NULL;
  uint32_t w = pl->width, hh = pl->height;
  if (f->p.max_message_bytes && (size_t)w * hh * 2 > f->p.max_message_bytes) {
    vlff_warn_limited(&f->too_large, "vlff-view", "/camera/depth: a %ux%u depth image is %zu bytes, above half of "
                      "--max-queue-mb (%zu bytes): not sent", w, hh, (size_t)w * hh * 2, f->p.max_message_bytes);
    return NULL;
  }
  if (grow(&f->depth, &f->depth_cap, (size_t)w * hh * 2 + 1, "a depth image")) return NULL;
  for (uint32_t y = 0; y < hh; y++) {
    const uint8_t *row = px + (size_t)y * pl->stride;
    uint8_t *o = f->depth + (size_t)y * w * 2;
    for (uint32_t x = 0; x < w; x++) {
      uint16_t mm;
      if (pl->format == VLFF_PIX_DEPTH_U16_MM) {
        memcpy(&mm, row + 2 * x, 2);
      } else {
        float d;
        memcpy(&d, row + 4 * x, 4);
        mm = isfinite(d) && d > 0 && d * 1000.0f < 65535.5f ? (uint16_t)lroundf(d * 1000.0f) : 0;
      }
      o[2 * x] = (uint8_t)mm;
      o[2 * x + 1] = (uint8_t)(mm >> 8);
    }
  }
  f->encoded[VLFF_VIEW_CH_DEPTH]++;
  return vlff_view_depth_msg(VLFF_VIEW_CH_DEPTH, f->p.camera_frame, t, w, hh, f->depth);
}

static int frames_poll(struct vlff_feed *f, unsigned wanted, struct vlff_view_msg **out, int cap) {
  if (!f->p.frames_name || !*f->p.frames_name || cap < 1) return 0;
  uint64_t now = vlff_now_ns();
  if (!f->ring) {
    if (now < f->ring_next_attach_ns) return 0;
    f->ring_next_attach_ns = now + NS;
    f->ring = vlff_ring_attach(f->p.frames_name, VLFF_RECORD_FRAME);
    if (!f->ring) {
      if (!f->ring_reported)
        vlff_log(VLFF_LOG_WARN, "vlff-view", "frame ring %s: %s; retrying every second", f->p.frames_name,
                vlff_shm_last_message());
      f->ring_reported = 1;
      return 0;
    }
    f->ring_reported = 0;
    free(f->rec);
    f->rec_cap = vlff_ring_slot_size(f->ring);
    f->rec = malloc(f->rec_cap);
    if (!f->rec) {
      vlff_log(VLFF_LOG_WARN, "vlff-view", "no memory for a %zu-byte frame", f->rec_cap);
      vlff_ring_close(f->ring);
      f->ring = NULL;
      return 0;
    }
    f->ring_head = 0;
    vlff_log(VLFF_LOG_INFO, "vlff-view", "attached to frame ring %s", f->p.frames_name);
  }
  uint64_t head = vlff_ring_head(f->ring);
  if (now - f->fps_t_ns >= NS) {
    if (f->fps_t_ns) f->fps = (double)(head - f->fps_head) * 1e9 / (double)(now - f->fps_t_ns);
    f->fps_head = head;
    f->fps_t_ns = now;
  }
  /* the ring is watched for the status either way; frames are read for subscribers */
  if (!(wanted & (1u << VLFF_VIEW_CH_IMAGE | 1u << VLFF_VIEW_CH_POSE | 1u << VLFF_VIEW_CH_CALIB |
                  1u << VLFF_VIEW_CH_DEPTH)))
    return 0;
  if (head == f->ring_head || (f->p.image_hz > 0 && now - f->last_image_ns < (uint64_t)(1e9 / f->p.image_hz)))
    return 0;
  f->ring_head = head;
  f->last_image_ns = now;
  return frame_encode(f, wanted, out, cap);
}

/* Reads the ring's latest frame and appends its messages for the channels in build
 * (image, pose), each also kept as its channel's current one. */
static int frame_encode(struct vlff_feed *f, unsigned build, struct vlff_view_msg **out, int cap) {
  unsigned wanted = build;
  struct vlff_ring_view info;
  ssize_t len = vlff_ring_read_latest(f->ring, f->rec, f->rec_cap, &info);
  if (len < 0) {
    if (errno == EPIPE) {
      vlff_log(VLFF_LOG_WARN, "vlff-view", "frame ring %s was replaced; attaching again", f->p.frames_name);
      vlff_ring_close(f->ring);
      f->ring = NULL;
    }
    return 0;
  }
  if (vlff_frame_validate(f->rec, (size_t)len) != 0) return 0;
  const struct vlff_frame_hdr *h = f->rec;
  const struct vlff_plane *pl = &h->plane[VLFF_PLANE_COLOR];
  const uint8_t *px = vlff_frame_plane(f->rec, VLFF_PLANE_COLOR);
  uint64_t t = to_real(f, h->t_host_ns);
  int nout = 0;
  if (px && wants(wanted, VLFF_VIEW_CH_IMAGE) && nout < cap) {
    size_t need = (size_t)pl->width * pl->height * 3;
    if (need > f->rgb_cap) {
      uint8_t *p = realloc(f->rgb, need);
      if (p) f->rgb = p, f->rgb_cap = need;
    }
    char err[160];
    struct vlff_view_msg *im = NULL;
    if (need > f->rgb_cap) {
      vlff_warn_limited(&f->encode_failures, "vlff-view", "no memory for a %ux%u image", pl->width, pl->height);
    } else if (vlff_cv_to_rgb(px, pl->stride, (int)pl->width, (int)pl->height, (vlff_pix_t)pl->format, f->rgb,
                              (size_t)pl->width * 3, err, sizeof err)) {
      /* mono16 and formats the shim does not know are not shown */
      vlff_warn_limited(&f->encode_failures, "vlff-view", "frame ring %s: a %ux%u image of format %u: %s",
                        f->p.frames_name, pl->width, pl->height, pl->format, err);
    } else {
      im = compressed_msg(f, VLFF_VIEW_CH_IMAGE, t, f->rgb, (size_t)pl->width * 3, pl->width, pl->height, 0);
    }
    if (im) {
      out[nout++] = im;
      set_current(f, VLFF_VIEW_CH_IMAGE, im);
    }
  }
  if (wants(wanted, VLFF_VIEW_CH_CALIB) && valid_intrinsics(h) && nout < cap) {
    struct vlff_view_msg *cm = calib_msg(f, t, h);
    if (cm) {
      out[nout++] = cm;
      set_current(f, VLFF_VIEW_CH_CALIB, cm);
    }
  }
  if (wants(wanted, VLFF_VIEW_CH_DEPTH) && nout < cap) {
    struct vlff_view_msg *dm = depth_msg(f, t, h);
    if (dm) {
      out[nout++] = dm;
      set_current(f, VLFF_VIEW_CH_DEPTH, dm);
    }
  }
  bool has_pose = (h->flags & VLFF_FRAME_POSE_VALID) && valid_pose(h->pose);
  if (has_pose) f->ring_has_pose = true;
  if (has_pose && wants(wanted, VLFF_VIEW_CH_POSE) && nout < cap) {
    struct vlff_view_msg *pm = pose_msg(f, to_real(f, h->pose_t_ns ? h->pose_t_ns : h->t_host_ns), h->pose);
    if (pm) {
      out[nout++] = pm;
      set_current(f, VLFF_VIEW_CH_POSE, pm);
    }
  }
  return nout;
}

/* ------------------------------------------------------------------ status */

/* A number as JSON, printed as vlff-shm stat prints it; null when not finite. */
static void jw_num(struct jw *w, const char *fmt, double v) {
  if (isfinite(v)) jw_f(w, fmt, v);
  else jw_s(w, "null");
}

/* The learner's own status from the map segment (vlff_map_get_status); null
 * before its writer set one (or for a segment without a writer yet). */
static void write_learner(struct jw *w, struct vlff_map *map) {
  struct vlff_map_status st;
  if (!map || vlff_map_get_status(map, &st) < 0) {
    jw_s(w, "null");
    return;
  }
  uint64_t now = vlff_now_ns();
  jw_s(w, "{\"state\":");
  jw_str(w, st.state_name);
  jw_f(w, ",\"state_code\":%d,\"error_flags\":%u,\"age_s\":%.3f,\"updates\":%llu,\"frames_in\":%llu,"
          "\"frames_lost\":%llu,\"frames_refused\":%llu,\"refused\":[",
       (int)st.state, (unsigned)st.error_flags, now > st.t_ns ? (double)(now - st.t_ns) / 1e9 : 0.0,
       (unsigned long long)st.updates, (unsigned long long)st.frames_in, (unsigned long long)st.frames_lost,
       (unsigned long long)st.frames_refused);
  for (uint32_t i = 0; i < st.reason_count; i++) {
    jw_s(w, i ? ",{\"reason\":" : "{\"reason\":");
    jw_str(w, st.reason[i].name);
    jw_f(w, ",\"count\":%llu}", (unsigned long long)st.reason[i].count);
  }
  jw_f(w, "],\"keyframes\":%llu,\"keyframes_evicted\":%llu,\"iterations\":%llu,\"iterations_per_s\":",
       (unsigned long long)st.keyframes, (unsigned long long)st.keyframes_evicted, (unsigned long long)st.iterations);
  jw_num(w, "%.3f", st.iterations_per_s);
  jw_s(w, ",\"fps_in\":");
  jw_num(w, "%.3f", st.fps_in);
  const char *keys[4] = {"loss", "loss_rgb", "loss_depth", "loss_feat"};
  const double vals[4] = {st.loss, st.loss_rgb, st.loss_depth, st.loss_feat};
  for (int i = 0; i < 4; i++) {
    jw_f(w, ",\"%s\":", keys[i]);
    jw_num(w, "%.6g", vals[i]);
  }
  jw_s(w, ",\"psnr\":");
  jw_num(w, "%.3f", st.psnr);
  /* How current and how still the map is, the CPU and memory the writer
   * takes: as vlff-shm stat prints them (-1 while unknown). */
  const char *more[] = {"cpu_budget",       "cpu_used",
                        "frame_to_map_ms_p50", "frame_to_map_ms_p99",
                        "publish_interval_s", "mem_keyframes_mb",
                        "mem_keyframes_limit_mb", "mem_evidence_mb",
                        "mem_evidence_limit_mb", "mem_field_mb",
                        "mem_rss_mb"};
  const char *fmt[] = {"%.3f", "%.3f", "%.1f", "%.1f", "%.3f", "%.1f", "%.1f", "%.1f", "%.1f", "%.1f", "%.1f"};
  const double mv[] = {st.cpu_budget,       st.cpu_used,           st.frame_to_map_ms_p50,
                       st.frame_to_map_ms_p99, st.publish_interval_s, st.mem_keyframes_mb,
                       st.mem_keyframes_limit_mb, st.mem_evidence_mb,   st.mem_evidence_limit_mb,
                       st.mem_field_mb,       st.mem_rss_mb};
  _Static_assert(sizeof more / sizeof *more == sizeof mv / sizeof *mv && sizeof fmt == sizeof more, "one key per value");
  for (size_t i = 0; i < sizeof mv / sizeof *mv; i++) {
    jw_f(w, ",\"%s\":", more[i]);
    jw_num(w, fmt[i], mv[i]);
  }
  jw_f(w, ",\"label_flips\":%llu,\"label_flips_refresh\":%llu,\"label_flips_total\":%llu,\"label_flip_frac\":",
       (unsigned long long)st.label_flips, (unsigned long long)st.label_flips_refresh,
       (unsigned long long)st.label_flips_total);
  jw_num(w, "%.4f", st.label_flip_frac);
  /* What went to the page files, came back or was dropped, and the map's
   * box (arrays of x, y, z): as vlff-shm stat prints them. */
  const char *count_keys[] = {"keyframes_paged", "keyframes_paged_out", "keyframes_paged_in", "keyframes_dropped",
                              "evidence_paged",  "evidence_paged_out",  "evidence_paged_in",  "evidence_dropped",
                              "box_growths",     "box_refused"};
  const uint64_t counts[] = {st.keyframes_paged, st.keyframes_paged_out, st.keyframes_paged_in, st.keyframes_dropped,
                             st.evidence_paged,  st.evidence_paged_out,  st.evidence_paged_in,  st.evidence_dropped,
                             st.box_growths,     st.box_refused};
  _Static_assert(sizeof count_keys / sizeof *count_keys == sizeof counts / sizeof *counts, "one key per count");
  for (size_t i = 0; i < sizeof counts / sizeof *counts; i++)
    jw_f(w, ",\"%s\":%llu", count_keys[i], (unsigned long long)counts[i]);
  jw_s(w, ",\"keyframes_page_mb\":");
  jw_num(w, "%.1f", st.keyframes_page_mb);
  jw_s(w, ",\"keyframes_page_limit_mb\":");
  jw_num(w, "%.1f", st.keyframes_page_limit_mb);
  for (int c = 0; c < 2; c++) {
    const double *v = c ? st.box_hi : st.box_lo;
    jw_s(w, c ? ",\"box_hi\":[" : ",\"box_lo\":[");
    for (int a = 0; a < 3; a++) {
      if (a) jw_s(w, ",");
      jw_num(w, "%.3f", v[a]);
    }
    jw_s(w, "]");
  }
  jw_s(w, "}");
}

static struct vlff_view_msg *status_msg(struct vlff_feed *f, const struct vlff_view_counters *c) {
  struct feed_map *m = &f->m;
  uint64_t t = vlff_wall_ns();
  struct jw w = {feed_msg(f, VLFF_VIEW_CH_STATUS, 2048), 0};
  if (!w.m) return NULL;
  w.m->t_ns = t;
  jw_s(&w, "{\"map\":{\"segment\":");
  jw_str(&w, f->p.map_name);
  jw_f(&w, ",\"attached\":%s,\"version\":%llu,\"generation\":%u,\"age_s\":", m->map ? "true" : "false",
       (unsigned long long)m->version, m->generation);
  uint64_t age = m->map ? vlff_map_age_ns(m->map) : UINT64_MAX;
  if (age == UINT64_MAX) jw_s(&w, "null");
  else jw_f(&w, "%.3f", (double)age / 1e9);
  jw_f(&w, ",\"writer_alive\":%s,\"prompts\":[",
       m->map && vlff_map_writer_alive(m->map, 2 * NS) ? "true" : "false");
  for (int i = 0; i < m->prompt_count; i++) {
    if (i) jw_s(&w, ",");
    jw_str(&w, m->prompts[i]);
  }
  jw_f(&w, "],\"dims\":[%u,%u,%u],\"voxel_size\":%.6f,\"origin\":[%.6f,%.6f,%.6f],", m->dims[0], m->dims[1],
       m->dims[2], m->vs, m->origin[0], m->origin[1], m->origin[2]);
  jw_f(&w, "\"occupied\":%llu,\"free\":%llu,\"unknown\":%llu,\"label_counts\":[", (unsigned long long)m->occupied,
       (unsigned long long)m->free_, (unsigned long long)m->unknown);
  for (int i = 0; i < m->prompt_count; i++) jw_f(&w, "%s%llu", i ? "," : "", (unsigned long long)m->label_counts[i]);
  jw_s(&w, "]},\"learner\":");
  write_learner(&w, m->map);
  jw_s(&w, ",\"frames\":{\"segment\":");
  jw_str(&w, f->p.frames_name ? f->p.frames_name : "");
  jw_f(&w, ",\"attached\":%s,\"head\":%llu,\"generation\":%u,\"fps\":%.2f},", f->ring ? "true" : "false",
       (unsigned long long)(f->ring ? vlff_ring_head(f->ring) : 0), f->ring ? vlff_ring_generation(f->ring) : 0,
       f->fps);
  jw_f(&w,
       "\"viewer\":{\"clients\":%d,\"connections\":%llu,\"dropped_slow\":%llu,\"refused\":%llu,\"bad_requests\":%llu,"
       "\"prompts_posted\":%llu,\"messages_sent\":%llu,\"bytes_sent\":%llu,\"http_refused\":{",
       c->clients, (unsigned long long)c->connections, (unsigned long long)c->dropped_slow,
       (unsigned long long)c->refused, (unsigned long long)c->bad_requests, (unsigned long long)c->prompts_posted,
       (unsigned long long)c->messages_sent, (unsigned long long)c->bytes_sent);
  for (int i = 0; i < VLFF_VIEW_HTTP_N; i++)
    jw_f(&w, "%s\"%d\":%llu", i ? "," : "", vlff_view_http_status(i), (unsigned long long)c->http_refused[i]);
  jw_s(&w, "}}}");
  return jw_finish(&w);
}

int vlff_feed_poll(struct vlff_feed *f, const struct vlff_view_counters *c, unsigned wanted, struct vlff_view_msg **out,
                   int out_cap) {
  uint64_t before = f->m.version;
  f->last_wanted = wanted;
  int n = map_poll(f, wanted, out, out_cap);
  n += grid_poll(f, wanted, out + n, out_cap - n);
  n += frames_poll(f, wanted, out + n, out_cap - n);
  uint64_t now = vlff_now_ns();
  if (n < out_cap && wants(wanted, VLFF_VIEW_CH_STATUS) && (f->m.version != before || now - f->last_status_ns >= NS)) {
    struct vlff_view_msg *s = status_msg(f, c);
    if (s) {
      out[n++] = s;
      set_current(f, VLFF_VIEW_CH_STATUS, s);
    }
    f->last_status_ns = now;
  }
  return n;
}

/* The label image (and the pose it carries) of the map version last read, built
 * now for a first subscriber of ch. */
static void label_image_current(struct vlff_feed *f, int ch) {
  struct vlff_map_info info;
  if (!f->m.snap || !f->m.version || vlff_map_snapshot_info(f->m.snap, &info) != 0 || !info.has_label_image) return;
  struct vlff_view_msg *m = NULL;
  if (ch == VLFF_VIEW_CH_LABELS) m = label_image_msg(f, &info.label_image);
  else if (valid_pose(info.label_image.pose)) m = pose_msg(f, to_real(f, info.label_image.t_ns), info.label_image.pose);
  set_current(f, ch, m);
  vlff_view_msg_unref(m);
}

struct vlff_view_msg *vlff_feed_current(struct vlff_feed *f, int ch, const struct vlff_view_counters *c) {
  if (ch < 1 || ch > VLFF_VIEW_CH_COUNT) return NULL;
  /* A channel nobody subscribed to at the last poll was not kept current: its
   * latest is built now from the segments (the frame ring's newest frame, the label
   * image of the map version last read), never handed out from an earlier
   * subscriber's time. The status is built now always: it names the clients and
   * counts of this moment. */
  int kept = wants(f->last_wanted, ch);
  if (ch == VLFF_VIEW_CH_STATUS) {
    static const struct vlff_view_counters none;
    struct vlff_view_msg *s = status_msg(f, c ? c : &none);
    set_current(f, ch, s);
    vlff_view_msg_unref(s);
  } else if (!kept && (ch == VLFF_VIEW_CH_IMAGE || ch == VLFF_VIEW_CH_CALIB || ch == VLFF_VIEW_CH_POSE ||
                        ch == VLFF_VIEW_CH_DEPTH)) {
    set_current(f, ch, NULL);
    if (f->ring && (ch != VLFF_VIEW_CH_POSE || f->ring_has_pose)) {
      struct vlff_view_msg *tmp[2];
      int n = frame_encode(f, 1u << ch, tmp, 2);
      for (int i = 0; i < n; i++) vlff_view_msg_unref(tmp[i]);
    }
    if (ch == VLFF_VIEW_CH_POSE && !f->current[ch] && (!f->ring || !f->ring_has_pose)) label_image_current(f, ch);
  } else if (!kept && ch == VLFF_VIEW_CH_LABELS) {
    label_image_current(f, ch);
  } else if (ch == VLFF_VIEW_CH_GRID && f->grid_owed) {
    /* the map changed since the latest grid (waiting on the rate): the first
     * grid is of the map the client's other channels hold */
    set_current(f, ch, NULL);
  }
  if (!f->current[ch] && f->m.labels && f->m.version) {
    uint64_t t = to_real(f, f->m.publish_ns);
    /* deltas are not built while nobody subscribes to the scene: the whole scene
     * sent now is what its clients hold from here on */
    if (ch == VLFF_VIEW_CH_SCENE) f->current[ch] = scene_msg(f, NULL, f->p.brick, t, 1);
    else if (ch == VLFF_VIEW_CH_VOXELS) f->current[ch] = voxels_msg(f, NULL, 0, t);
    else if (ch == VLFF_VIEW_CH_CLOUD) f->current[ch] = cloud_msg(f, NULL, 0, t);
    else if (ch == VLFF_VIEW_CH_GRID) f->current[ch] = grid_msg(f, t);
  }
  return vlff_view_msg_ref(f->current[ch]);
}
