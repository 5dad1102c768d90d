/*
 * Why measured depth decides "occupied": the field's density at a voxel
 * centre is a poor occupancy test for thin surfaces (a wall 2 cm thick
 * crosses a 10 cm voxel off its centre); where the sensor saw a surface we
 * know the voxel holds one, and the field only supplies its meaning.
 */
#include "publish.h"
#include "clock.h"
#include "files.h" /* vlff_write_file_atomic */
#include "hash.h"

#include <errno.h>
#include <limits.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "bounds.h"
#include "evidence.h"
#include "far.h"
#include "hold.h"
#include "lattice.h"
#include "log.h"
#include "palette.h"
#include "regions.h"
#include "select.h"
#include "mem.h"
#include "vlff/shm.h"
#include "vlff/escape.h"

#define TAG "publish"

_Static_assert(VLFF_MAX_PROMPTS <= VLFF_FIELD_MAX_PROMPTS, "the node's prompts must fit the field");
#define QBLOCK 4096 /* points per block of the evidence's cosine queries */

struct vlff_publisher {
  struct vlff_map *map;
  const struct vlff_source_hooks *hooks; /* NULL: none */
  double origin[3], voxel;
  struct vlff_cfg_field field; /* its box and growth: the bounds for poses and growth */
  /* A growing box (field.grow): origin = origin0 + k0 x voxel after
   * growths and refits (the same k0, the same bits), at most max_voxels
   * (shm.map_max_voxels; the segment grows to it, publisher_regrid). */
  double origin0[3];
  long k0[3];
  size_t max_voxels;
  long long grown;
  /* The grid grew since the last publish: the next writes it whole, as it
   * is (its labels are still right; only readers' geometry is new). */
  bool regridded;
  /* The far map (far.h): what the window left when it slid at its cap;
   * NULL for a fixed box. far_owed: the next publish carries it. */
  struct vlff_far *far;
  bool far_owed;
  /* The far files last written beside each checkpoint's grid (the node
   * alternates two): rewritten only when their generation changed. */
  struct saved_far {
    char path[VLFF_CFG_PATH + 64];
    struct far_file {
      uint64_t gen;                  /* of what it holds; UINT64_MAX: unknown */
      uint64_t ino, size, mtime_ns; /* the file as written (0, 0, 0: none) */
    } far, evfar;
  } saved[2];
  int saved_next;
  long long slides;
  size_t far_limit; /* bytes: shm.map_far_max_mb */
  double far_retry_s, far_warned_s; /* a far map the segment refused: tried again from then; the last drop said */
  uint32_t far_gen; /* the segment's generation the far map was published to */
  uint64_t heartbeat_warned;       /* vlff_warn_limited's */
  uint32_t dims[3];
  size_t nvox;
  uint8_t *observed;   /* rays passed through */
  uint16_t *hits;      /* measured surface points inside */
  float *hit_sum;      /* [nvox][3] sum of those points */
  uint16_t *labels;
  uint8_t *conf;
  /* query batch */
  size_t *qidx;
  float *qxyz, *qdens, *qmargin;
  int *qlabel;
  /* label image */
  int lw, lh;
  uint16_t *img_labels;
  uint8_t *img_conf;
  int *img_lab;
  float *img_score;
  /* The latest camera's label pixels, split by its measured depth: those
   * with a surface point (labelled by a 3D query there) and holes
   * (rendered). Without depth, or with label_image: render, all are holes.
   * snap_xyz: the surface points as labelled, moved onto the field's
   * surface within the sensor's noise (vlff_field_snap_surface). */
  bool surface;
  uint32_t *sel_pix, *hole_pix;
  size_t nsel, nhole;
  float *sel_xyz, *snap_xyz, *sel_score;
  int *sel_lab;
  /* Regions (regions.h, publish.region_weight; with evidence only): the
   * surface pixels' colours of the latest camera's image (sel_col, made at
   * set_camera, which keeps no image), grouped with their measured points
   * when an image begins; the pixels' sums as the pieces label them
   * (sel_vec [pixels][ik], ik: the image's prompts), voted when it ends. */
  struct vlff_regions *regions;
  float region_weight;
  float *sel_col, *sel_vec;
  int ik;
  struct vlff_view cam;
  bool have_cam;
  uint64_t cam_t_ns;
  long long cam_frame;
  double free_density;
  /* Evidence (evidence.h): NULL when publish.evidence_weight is 0. */
  struct vlff_evidence *ev;
  float ev_weight;
  int D;
  size_t ev_budget; /* bytes: publish.evidence_max_mb */
  bool ev_full_said, ev_overflow_said; /* logged once each per map (a mapping reset starts over) */
  bool ev_paged_said, ev_page_error_said;
  int page_mb;                          /* publish.evidence_page_mb */
  char page_path[VLFF_CFG_PATH + 32];     /* the page file, "" without */
  float *qcos; /* [QBLOCK][VLFF_FIELD_MAX_PROMPTS] the field's cosines of a block of points */
  uint16_t *qrays; /* [QBLOCK] the field's exposure there (vlff_field_exposure) */
  int trust_rays;  /* publish.field_trust_rays */
  double lost_ratio;  /* publish.lost_class_ratio */
  uint64_t lost_mask, lost_mask_stamp; /* the prompts last reported lost (evidence.h, "Lost classes"), and of which prompts */
  double last_publish_s, last_heartbeat_s;
  /* Incremental publication: the voxels observe() touched since they were
   * last relabelled (flag per voxel, and their list), the runs a partial
   * publish logs, the voxel counts by state (kept as voxels are relabelled),
   * the next slice of the round-robin refresh, and whether the next publish
   * must be whole (nothing published yet, a reset or a load, new prompts). */
  uint8_t *dirty;
  size_t *dirty_idx, ndirty;
  struct vlff_map_range *runs;
  uint16_t *pub_labels; /* the grid as last published */
  uint8_t *pub_conf;
  size_t n_labelled, n_free;
  size_t refresh_at; /* the next voxel of the round-robin refresh */
  /* Every other refresh round passes over settled voxels (settled()):
   * whether this round does, and the prompt stamp of the last round that
   * relabelled every voxel (a skipping round needs the same prompts). */
  bool skip_settled;
  uint64_t full_round_stamp;
  /* The label image a round owes, rendered a piece per publish_image call
   * (IMAGE_PIECE_S each) from a copy of the camera it began with, so that
   * keyframes admitted meanwhile (set_camera) neither wait for the whole
   * image nor change it halfway: tail is TAIL_NONE, TAIL_IMAGE (ipix of
   * the inhole + insel pixels done, holes first) or TAIL_SCORE (the image
   * published, its scores owed). px_s: seconds a pixel took, as measured;
   * piece_px: a fixed piece size instead (0: by px_s). */
  int tail;
  struct vlff_view icam;
  uint32_t *isel_pix, *ihole_pix;
  size_t insel, inhole, ipix;
  uint64_t icam_t_ns, istamp; /* istamp: embeddings_hash when the image began */
  long long icam_frame;
  double px_s;
  size_t piece_px;
  /* A refresh slice stops after about SLICE_PIECE_S of queries: vox_s,
   * seconds a queried voxel took (a running mean over slices), or
   * piece_vox queried voxels instead (0: by vox_s). */
  double vox_s;
  size_t piece_vox;
  bool need_full;
  uint64_t prompts_hash;
  struct vlff_hold *hold; /* the published labels held between publishes (hold.h) */
  uint64_t hold_prompts;  /* a hash of the prompt embeddings the held labels index */
  /* Seen through (publish.h, "Depth that passes through"): per voxel, flags
   * of the view being observed (THRU_*) and the run of views whose rays
   * passed through it without ending in it (low bits); the voxels the view
   * touched, listed once each. */
  uint8_t *thru;
  uint32_t *thru_list;
  size_t nthru;
  long long cleared; /* surfaces seen through since create */
};


void vlff_publisher_destroy(struct vlff_publisher *p) {
  if (!p) return;
  vlff_far_destroy(p->far);
  vlff_map_detach(p->map);
  vlff_evidence_destroy(p->ev);
  vlff_hold_destroy(p->hold);
  vlff_regions_destroy(p->regions);
  VLFF_FREE_ALL(p->thru, p->thru_list);
  VLFF_FREE_ALL(p->observed, p->hits, p->hit_sum, p->labels, p->conf, p->qidx, p->qxyz, p->qdens,
                p->qmargin, p->qlabel, p->img_labels, p->img_conf, p->img_lab, p->img_score,
                p->sel_pix, p->hole_pix, p->isel_pix, p->ihole_pix, p->sel_xyz, p->snap_xyz, p->sel_score,
                p->sel_lab, p->qcos, p->qrays, p->sel_col, p->sel_vec,
                p->dirty, p->dirty_idx, p->runs, p->pub_labels, p->pub_conf, p);
}

struct vlff_publisher *vlff_publisher_create(const struct vlff_cfg_publish *pub, const struct vlff_cfg_shm *shm,
                                             const struct vlff_cfg_field *field, const struct vlff_source_hooks *hooks,
                                             char *err, size_t errlen) {
  struct vlff_publisher *p = calloc(1, sizeof *p);
  if (!p) return snprintf(err, errlen, "out of memory"), NULL;
  p->hooks = hooks;
  p->free_density = pub->free_density;
  p->voxel = vlff_map_grid_plan(field->scene_min, field->scene_max, pub->voxel_size_m, (size_t)shm->map_max_voxels,
                                p->dims);
  p->nvox = (size_t)p->dims[0] * p->dims[1] * p->dims[2];
  if (p->voxel > VLFF_MAP_VOXEL_MAX_M) {
    snprintf(err, errlen,
             "the scene box needs voxels of %.0f m to fit shm.map_max_voxels (%d), more than a map may have (%g m): "
             "raise shm.map_max_voxels or give a smaller box",
             p->voxel, shm->map_max_voxels, VLFF_MAP_VOXEL_MAX_M);
    vlff_publisher_destroy(p);
    return NULL;
  }
  if (p->voxel > pub->voxel_size_m)
    VLFF_WARN(TAG, "publish.voxel_size_m %.3f m needs more than shm.map_max_voxels; using %.3f m",
              pub->voxel_size_m, p->voxel);
  for (int i = 0; i < 3; i++) p->origin[i] = p->origin0[i] = field->scene_min[i];
  p->field = *field;
  p->max_voxels = (size_t)shm->map_max_voxels;
  p->far_limit = (size_t)shm->map_far_max_mb << 20;
  if (field->grow && !(p->far = vlff_far_create(p->origin0, p->voxel, p->far_limit))) {
    snprintf(err, errlen, "out of memory");
    vlff_publisher_destroy(p);
    return NULL;
  }
  /* The first publish says the far map, none too: a segment taken over
   * holds the one a previous run published, of its own voxels and prompts. */
  p->far_owed = p->far != NULL;
  p->lw = pub->label_width;
  p->lh = pub->label_height;
  if (p->lw > shm->label_max_width || p->lh > shm->label_max_height) {
    snprintf(err, errlen, "publish.label_width x label_height (%dx%d) exceeds shm.label_max_width x height (%dx%d)",
             p->lw, p->lh, shm->label_max_width, shm->label_max_height);
    vlff_publisher_destroy(p);
    return NULL;
  }
  size_t n = p->nvox, li = (size_t)p->lw * p->lh;
  p->observed = calloc(n, 1);
  p->hits = calloc(n, sizeof *p->hits);
  p->hit_sum = calloc(n * 3, sizeof *p->hit_sum);
  p->labels = malloc(n * sizeof *p->labels);
  p->conf = malloc(n);
  p->qidx = malloc(n * sizeof *p->qidx);
  p->qxyz = malloc(n * 3 * sizeof *p->qxyz);
  p->qdens = malloc(n * sizeof *p->qdens);
  p->qmargin = malloc(n * sizeof *p->qmargin);
  p->qlabel = malloc(n * sizeof *p->qlabel);
  p->img_labels = malloc(li * sizeof *p->img_labels);
  p->img_conf = malloc(li);
  p->img_lab = malloc(li * sizeof *p->img_lab);
  p->img_score = malloc(li * sizeof *p->img_score);
  p->surface = pub->label_image == VLFF_LABEL_IMAGE_SURFACE;
  p->sel_pix = malloc(li * sizeof *p->sel_pix);
  p->hole_pix = malloc(li * sizeof *p->hole_pix);
  p->isel_pix = malloc(li * sizeof *p->isel_pix);
  p->ihole_pix = malloc(li * sizeof *p->ihole_pix);
  p->sel_xyz = malloc(li * 3 * sizeof *p->sel_xyz);
  p->snap_xyz = malloc(li * 3 * sizeof *p->snap_xyz);
  p->sel_score = malloc(li * sizeof *p->sel_score);
  p->sel_lab = malloc(li * sizeof *p->sel_lab);
  p->dirty = calloc(n, 1);
  p->dirty_idx = malloc(n * sizeof *p->dirty_idx);
  p->runs = malloc((n / 2 + 1) * sizeof *p->runs);
  p->pub_labels = malloc(n * sizeof *p->pub_labels);
  p->pub_conf = malloc(n);
  p->need_full = true;
  p->hold = vlff_hold_create(n, pub->label_hysteresis);
  p->thru = calloc(n, 1);
  p->thru_list = malloc(n * sizeof *p->thru_list);
  p->D = field->feature_dim;
  p->ev_budget = (size_t)pub->evidence_max_mb << 20; /* also bounds a saved map's evidence read without it */
  p->page_mb = pub->evidence_page_mb;
  if (pub->evidence_weight > 0) {
    p->ev = vlff_evidence_for(pub, field, VLFF_MAX_PROMPTS, err, errlen);
    p->ev_weight = (float)pub->evidence_weight;
    p->trust_rays = pub->field_trust_rays;
    p->lost_ratio = pub->lost_class_ratio;
    p->qcos = malloc(QBLOCK * VLFF_FIELD_MAX_PROMPTS * sizeof *p->qcos);
    p->qrays = malloc(QBLOCK * sizeof *p->qrays);
    if (pub->region_weight > 0 && p->surface) {
      p->region_weight = (float)pub->region_weight;
      p->regions = vlff_regions_create(p->lw, p->lh);
      p->sel_col = malloc(li * 3 * sizeof *p->sel_col);
      p->sel_vec = malloc(li * VLFF_FIELD_MAX_PROMPTS * sizeof *p->sel_vec);
    }
    if (!p->ev || !p->qcos || !p->qrays ||
        (p->region_weight > 0 && (!p->regions || !p->sel_col || !p->sel_vec))) {
      if (p->ev) snprintf(err, errlen, "out of memory");
      vlff_publisher_destroy(p);
      return NULL;
    }
  }
  if (!p->observed || !p->hits || !p->hit_sum || !p->labels || !p->conf || !p->qidx || !p->qxyz ||
      !p->qdens || !p->qmargin || !p->qlabel || !p->img_labels || !p->img_conf ||
      !p->img_lab || !p->img_score || !p->sel_pix || !p->hole_pix || !p->isel_pix || !p->ihole_pix || !p->sel_xyz ||
      !p->snap_xyz || !p->sel_score ||
      !p->sel_lab || !p->dirty || !p->dirty_idx || !p->runs || !p->pub_labels || !p->pub_conf || !p->hold ||
      !p->thru || !p->thru_list) {
    snprintf(err, errlen, "out of memory for a %u x %u x %u map", p->dims[0], p->dims[1], p->dims[2]);
    vlff_publisher_destroy(p);
    return NULL;
  }
  for (size_t i = 0; i < n; i++) p->labels[i] = VLFF_LABEL_UNKNOWN;
  memset(p->conf, 0, n);
  /* A growing map's segment starts with room for its first box and grows
   * with it (publisher_regrid), up to shm.map_max_voxels; a fixed box's
   * holds the capacity from the start, as it always did. A node restarted
   * after its map grew asks for the size its segment has: a segment of
   * another size would be replaced, not taken over, and its readers would
   * see the version start again. */
  uint32_t cap = field->grow ? (uint32_t)n : (uint32_t)shm->map_max_voxels;
  struct vlff_shm_info had;
  const bool was = field->grow && vlff_shm_stat(shm->map, &had) == 0 && had.kind == VLFF_SHM_KIND_MAP;
  if (was && had.slot_size > cap && had.slot_size <= (uint64_t)shm->map_max_voxels) cap = (uint32_t)had.slot_size;
  /* ... and the room its far map had (far.h), within shm.map_far_max_mb. */
  uint64_t far_cap = 0;
  struct vlff_map *old = was ? vlff_map_attach(shm->map) : NULL;
  if (old && vlff_map_far_capacity(old) <= (uint64_t)p->far_limit + p->far_limit / 4 + 64)
    far_cap = vlff_map_far_capacity(old);
  vlff_map_detach(old);
  struct vlff_map_params mp = {.max_voxels = cap,
                               .label_max_width = (uint32_t)shm->label_max_width,
                               .label_max_height = (uint32_t)shm->label_max_height,
                               .perm = {.mode = (mode_t)shm->mode, .group = shm->group}};
  p->map = vlff_map_create_far(shm->map, &mp, far_cap);
  if (!p->map) {
    snprintf(err, errlen, "map segment %s: %s", shm->map, vlff_shm_last_message());
    vlff_publisher_destroy(p);
    return NULL;
  }
  p->last_publish_s = -1;
  VLFF_INFO(TAG, "map %s: %u x %u x %u voxels of %.3f m (its segment: %u voxels)", shm->map, p->dims[0], p->dims[1],
            p->dims[2], p->voxel, mp.max_voxels);
  return p;
}

/* File: magic, dims, voxel, origin; observed u8[n], hits u16[n],
 * hit_sum f32[3n]; (VLFFOBS3) the see-through marks u8[n] (THRU_KEPT bits),
 * the surfaces cleared (i64), the hash of the prompt embeddings the held
 * labels index (u64) and the label hold (hold.h, 3 bytes a voxel); (VLFFOBS4)
 * the lost classes (evidence.h, VLFF_EVIDENCE_LOST_BYTES); the evidence's
 * length (u64) and bytes (evidence.h; 0 without evidence); FNV-1a 64 of
 * everything before it. VLFFOBS3 files (without the lost classes: found
 * again by the first census), VLFFOBS2 files (without the marks and the
 * hold) and VLFFOBS1 files (without the evidence too) still load. */
enum { THRU_LISTED = 0x80, THRU_HIT = 0x40, THRU_PASSED = 0x20, THRU_GONE = 0x10, THRU_NEW = 0x08, THRU_RUN = 0x03 };
/* The marks a voxel keeps between views (the rest are the view's being
 * observed): what a checkpoint saves. */
enum { THRU_KEPT = THRU_GONE | THRU_NEW | THRU_RUN };
#define OBS_MAGIC "VLFFOBS4"
#define OBS_MAGIC_V3 "VLFFOBS3"
#define OBS_MAGIC_V2 "VLFFOBS2"
#define OBS_MAGIC_V1 "VLFFOBS1"

struct obs_header {
  char magic[8];
  uint32_t dims[3];
  uint32_t pad;
  double voxel, origin[3];
};

/* The bytes of a VLFFOBS3 file's marks and hold, between hit_sum and the
 * evidence's length; a VLFFOBS4 file's lost classes follow them. */
static size_t obs_v3_size(const struct vlff_publisher *p) { return p->nvox + 16 + vlff_hold_save_size(p->hold); }
static size_t obs_v4_size(const struct vlff_publisher *p) { return obs_v3_size(p) + VLFF_EVIDENCE_LOST_BYTES; }

static int save_far_files(struct vlff_publisher *p, const char *path, char *err, size_t errlen);

/* Written as it is made: the grids, then the evidence a megabyte at a time
 * (with paging it holds every voxel the robot has seen, most of it not in
 * memory), the checksum taken as the bytes go. */
int vlff_publisher_save(struct vlff_publisher *p, const char *path, char *err, size_t errlen) {
  size_t n = p->nvox, evn = p->ev ? vlff_evidence_save_size(p->ev) : 0;
  size_t len = sizeof(struct obs_header) + n + n * 2 + n * 12 + obs_v4_size(p) + 8;
  const size_t piece = (size_t)1 << 20, rec = 5 + (size_t)p->D * 2;
  uint8_t *buf = malloc(len > piece + rec ? len : piece + rec);
  if (!buf) return snprintf(err, errlen, "%s: out of memory", path), -1;
  struct obs_header h = {.voxel = p->voxel};
  memcpy(h.magic, OBS_MAGIC, 8);
  memcpy(h.dims, p->dims, sizeof h.dims);
  memcpy(h.origin, p->origin, sizeof h.origin);
  uint8_t *q = buf;
  memcpy(q, &h, sizeof h), q += sizeof h;
  memcpy(q, p->observed, n), q += n;
  memcpy(q, p->hits, n * 2), q += n * 2;
  memcpy(q, p->hit_sum, n * 12), q += n * 12;
  /* Between keyframes no voxel holds a view's marks (thru_commit cleared
   * them); masked all the same, so the file holds only what load accepts. */
  for (size_t i = 0; i < n; i++) q[i] = p->thru[i] & THRU_KEPT;
  q += n;
  int64_t cleared = p->cleared;
  memcpy(q, &cleared, 8), q += 8;
  memcpy(q, &p->hold_prompts, 8), q += 8;
  vlff_hold_save(p->hold, q), q += vlff_hold_save_size(p->hold);
  vlff_evidence_lost_save(p->ev, q), q += VLFF_EVIDENCE_LOST_BYTES;
  uint64_t ev64 = evn;
  memcpy(q, &ev64, 8), q += 8;
  struct vlff_atomic a;
  if (vlff_atomic_begin(&a, path, 0644, err, errlen) < 0) return free(buf), -1;
  uint64_t sum = vlff_fnv1a64(VLFF_FNV1A64_INIT, buf, (size_t)(q - buf));
  bool ok = vlff_write_all(a.fd, buf, (size_t)(q - buf)) == 0;
  uint64_t cursor = 0, written = 0;
  for (size_t k; ok && evn && (k = vlff_evidence_save_part(p->ev, &cursor, buf, piece + rec)) > 0; written += k) {
    sum = vlff_fnv1a64(sum, buf, k);
    ok = vlff_write_all(a.fd, buf, k) == 0;
  }
  ok = ok && written == evn && vlff_write_all(a.fd, &sum, 8) == 0;
  free(buf);
  if (!ok) {
    if (err && errlen) snprintf(err, errlen, "%s: write failed: %s", VLFF_Q(a.tmp), strerror(errno));
    vlff_atomic_abort(&a);
    return -1;
  }
  if (vlff_atomic_commit(&a, err, errlen)) return -1;
  return p->far ? save_far_files(p, path, err, errlen) : 0;
}

const char *const vlff_publisher_files[3] = {"", ".far", ".evfar"};
enum { FILE_FAR = 1, FILE_EVFAR = 2 }; /* in vlff_publisher_files */

/* The file beside a checkpoint's grid file: path + ext. */
static int beside(char *out, size_t cap, const char *path, const char *ext, char *err, size_t errlen) {
  if (snprintf(out, cap, "%s%s", path, ext) < (int)cap) return 0;
  return snprintf(err, errlen, "%s%s: path too long", path, ext), -1;
}

/* The file at path as it is now (all 0: none). */
static struct far_file file_id(const char *path, uint64_t gen) {
  struct stat st;
  if (stat(path, &st)) return (struct far_file){.gen = gen};
  return (struct far_file){gen, (uint64_t)st.st_ino, (uint64_t)st.st_size,
                           (uint64_t)st.st_mtim.tv_sec * 1000000000u + (uint64_t)st.st_mtim.tv_nsec};
}

/* A far file is written, or its name kept free, unless the one there is
 * the one written of this generation: the same file, size and time (one
 * removed, replaced or written over since is written again). */
static bool far_current(const char *file, const struct far_file *had, uint64_t gen) {
  const struct far_file now = file_id(file, gen);
  return had->gen == gen && now.ino == had->ino && now.size == had->size && now.mtime_ns == had->mtime_ns;
}

/* The far map beside the grid (far.h), and the evidence the grid left in
 * the page file (evidence.h): the same checkpoint's, or none. Rewritten
 * only when they changed since this grid file's last save (learned state
 * is written only when it changed), when the file there is not the one
 * written then, or when the last write read a record back from a failing
 * page file (written as a record of nothing: tried again). A failed write
 * removes its file and the far evidence beside it, never leaving another
 * checkpoint's beside this grid. */
static int save_far_files(struct vlff_publisher *p, const char *path, char *err, size_t errlen) {
  struct saved_far *sv = NULL;
  for (int i = 0; i < 2 && !sv; i++)
    if (!strcmp(p->saved[i].path, path)) sv = &p->saved[i];
  if (!sv) {
    sv = &p->saved[p->saved_next], p->saved_next ^= 1;
    *sv = (struct saved_far){.far.gen = UINT64_MAX, .evfar.gen = UINT64_MAX};
    if (snprintf(sv->path, sizeof sv->path, "%s", path) >= (int)sizeof sv->path) sv->path[0] = 0;
  }
  char fp[VLFF_CFG_PATH + 80];
  const uint64_t fg = vlff_far_generation(p->far);
  if (beside(fp, sizeof fp, path, vlff_publisher_files[FILE_FAR], err, errlen)) return -1;
  if (!far_current(fp, &sv->far, fg)) {
    sv->far.gen = UINT64_MAX;
    if (vlff_far_save(p->far, fp, err, errlen)) {
      unlink(fp);
      sv->evfar.gen = UINT64_MAX;
      if (p->ev && !beside(fp, sizeof fp, path, vlff_publisher_files[FILE_EVFAR], NULL, 0)) unlink(fp);
      return -1;
    }
    sv->far = file_id(fp, fg);
  }
  if (!p->ev) return 0;
  const uint64_t eg = vlff_evidence_far_generation(p->ev);
  if (beside(fp, sizeof fp, path, vlff_publisher_files[FILE_EVFAR], err, errlen)) return -1;
  if (!far_current(fp, &sv->evfar, eg)) {
    sv->evfar.gen = UINT64_MAX;
    const long long perr = vlff_evidence_page_errors(p->ev);
    if (vlff_evidence_save_far(p->ev, fp, err, errlen)) return unlink(fp), -1;
    if (vlff_evidence_page_errors(p->ev) == perr) sv->evfar = file_id(fp, eg);
  }
  return 0;
}

/* A saved map is read a piece at a time, never held whole: its evidence
 * may be a larger budget's (publish.evidence_max_mb lowered since), and
 * only the part this budget holds is loaded. */
enum { OBS_CHUNK = 1 << 20, EV_THIN_MAX = 16 };
struct obs_reader {
  int fd;
  const char *path;
  uint64_t size; /* the file's */
  uint64_t base; /* where the offsets asked for count from */
  uint8_t *buf;  /* OBS_CHUNK bytes of the file from start */
  uint64_t start;
  size_t have;
};

/* n bytes at offset off (from base) into dst; errors name the byte, not the
 * file (the caller's message does). */
static int obs_read(void *ctx, uint64_t off, void *dst, size_t n, char *err, size_t errlen) {
  struct obs_reader *r = ctx;
  off += r->base;
  if (off > r->size || n > r->size - off) {
    snprintf(err, errlen, "ends before byte %llu", (unsigned long long)(off + n));
    return -1;
  }
  /* More than the window (the grids): straight into dst. Otherwise the
   * window moves to off when n bytes there are not in it. */
  const bool direct = n > OBS_CHUNK, refill = !direct && (off < r->start || off + n > r->start + r->have);
  const size_t want = direct ? n : r->size - off < OBS_CHUNK ? (size_t)(r->size - off) : OBS_CHUNK;
  if ((direct || refill) && vlff_read_at(r->fd, off, direct ? dst : r->buf, want)) {
    snprintf(err, errlen, "read error at byte %llu: %s", (unsigned long long)off, strerror(errno));
    return -1;
  }
  if (direct) return 0;
  if (refill) r->start = off, r->have = want;
  memcpy(dst, r->buf + (off - r->start), n);
  return 0;
}

/* obs_read with the file named in the error. */
static int obs_get(struct obs_reader *r, uint64_t off, void *dst, size_t n, char *err, size_t errlen) {
  char e[128];
  if (!obs_read(r, off, dst, n, e, sizeof e)) return 0;
  snprintf(err, errlen, "%s: %s", r->path, e);
  return -1;
}

static int publisher_regrid(struct vlff_publisher *p, const int32_t sh[3], const uint32_t nd[3], char *err,
                            size_t errlen);
static void far_restore_voxel(void *ctx, size_t i, uint16_t label, uint8_t conf);

/* A voxel that holds something: observed (free space or a surface), owed a
 * relabel, seen through, or labelled (what was published is what was
 * labelled). A refitted grid keeps every one. */
static bool voxel_held(const struct vlff_publisher *p, size_t v) {
  return p->observed[v] || p->hits[v] || p->thru[v] || p->dirty[v] || p->labels[v] != VLFF_LABEL_UNKNOWN;
}

/* Whether the grid shifted by sh into nd would drop a voxel that holds
 * something. */
static bool drops_held(const struct vlff_publisher *p, const int32_t sh[3], const uint32_t nd[3]) {
  for (size_t v = 0; v < p->nvox; v++)
    if (vlff_lattice_index(v, p->dims, sh, nd) < 0 && voxel_held(p, v)) return true;
  return false;
}

/* A growing map takes a saved grid on its lattice (the grid it had grown or
 * been refitted to when saved) that holds every voxel the map holds now:
 * 1 when it did, 0 when the grid is not such (the geometry check refuses it
 * then), -1 with err when it could not (publisher_regrid). */
static int grow_to_saved(struct vlff_publisher *p, const struct obs_header *h, char *err, size_t errlen) {
  int32_t sh[3];
  if (!p->field.grow || h->voxel != p->voxel || vlff_lattice_cells(h->dims) > p->max_voxels ||
      !vlff_lattice_saved(p->origin0, p->voxel, p->k0, p->dims, h->origin, h->dims, sh) ||
      drops_held(p, sh, h->dims))
    return 0;
  return publisher_regrid(p, sh, h->dims, err, errlen) ? -1 : 1;
}

int vlff_publisher_load(struct vlff_publisher *p, const char *path, char *err, size_t errlen) {
  size_t n = p->nvox, grids = sizeof(struct obs_header) + n + n * 2 + n * 12;
  struct obs_reader r = {.fd = vlff_open_regular(path, err, errlen), .path = path};
  if (r.fd < 0) return -1;
  int rc = -1;
  uint8_t *g = NULL, *marks = NULL;
  struct stat st;
  if (fstat(r.fd, &st) < 0) {
    snprintf(err, errlen, "%s: cannot stat: %s", path, strerror(errno));
    goto out;
  }
  r.size = (uint64_t)st.st_size;
  r.buf = malloc(OBS_CHUNK);
  if (!r.buf) {
    snprintf(err, errlen, "%s: out of memory", path);
    goto out;
  }
  struct obs_header h;
  uint64_t sum, evn = 0, len = r.size;
  if (len < sizeof h) {
    snprintf(err, errlen, "%s: %llu bytes, too short for an observation grid", path, (unsigned long long)len);
    goto out;
  }
  if (obs_get(&r, 0, &h, sizeof h, err, errlen)) goto out;
  /* A grown map's file: this map grows to it first (the geometry check
   * below refuses any other grid). Growing changes nothing observed, so a
   * file refused after it leaves the map as it was, only larger. */
  char why[256];
  if (grow_to_saved(p, &h, why, sizeof why) < 0) {
    snprintf(err, errlen, "%s: growing to the saved grid: %s", path, why);
    goto out;
  }
  n = p->nvox, grids = sizeof(struct obs_header) + n + n * 2 + n * 12;
  g = malloc(grids - sizeof(struct obs_header));
  if (!g) {
    snprintf(err, errlen, "%s: out of memory", path);
    goto out;
  }
  const int v1 = !memcmp(h.magic, OBS_MAGIC_V1, 8), v2 = !memcmp(h.magic, OBS_MAGIC_V2, 8),
            v3 = !memcmp(h.magic, OBS_MAGIC_V3, 8);
  if (!v1 && !v2 && !v3 && memcmp(h.magic, OBS_MAGIC, 8)) {
    snprintf(err, errlen, "%s: not an observation grid (magic %.8s)", path, h.magic);
    goto out;
  }
  /* VLFFOBS3: the see-through marks and the label hold follow the grids;
   * VLFFOBS4: the lost classes after them. */
  const size_t v3n = v1 || v2 ? 0 : v3 ? obs_v3_size(p) : obs_v4_size(p), evn_at = grids + v3n;
  const uint8_t *lost = NULL; /* in marks: the lost classes (VLFFOBS4) */
  if (!v1 && len >= evn_at + 16 && obs_get(&r, evn_at, &evn, 8, err, errlen)) goto out;
  /* The whole file is hashed before anything is taken from it: evidence
   * over EV_THIN_MAX times this budget, besides what the page file may add
   * (its records, 3 bytes shorter each than a saved one, counted twice over
   * for that), is refused unread, so a file claiming gigabytes (sparse, or
   * from a budget more than that much larger) costs seconds at most, not
   * minutes. */
  const uint64_t ev_most = (uint64_t)EV_THIN_MAX * p->ev_budget + ((uint64_t)p->page_mb << 21);
  if (evn > ev_most) {
    snprintf(err, errlen,
             "%s: its evidence claims %llu MB, more than %d times publish.evidence_max_mb (%zu MB) and twice "
             "publish.evidence_page_mb (%d MB): refused unread",
             path, (unsigned long long)(evn >> 20), EV_THIN_MAX, p->ev_budget >> 20, p->page_mb);
    goto out;
  }
  uint64_t want = v1 ? grids + 8 : evn_at + 8 + evn + 8;
  if (evn > len || len != want) {
    snprintf(err, errlen, "%s: %llu bytes, expected %llu for a %ux%ux%u grid", path, (unsigned long long)len,
             (unsigned long long)want, p->dims[0], p->dims[1], p->dims[2]);
    goto out;
  }
  if (memcmp(h.dims, p->dims, sizeof h.dims) || h.voxel != p->voxel || memcmp(h.origin, p->origin, sizeof h.origin)) {
    snprintf(err, errlen, "%s: not an observation grid of this map's geometry", path);
    goto out;
  }
  uint64_t hash = VLFF_FNV1A64_INIT;
  for (uint64_t off = 0; off < want - 8; off += OBS_CHUNK) {
    size_t m = want - 8 - off < OBS_CHUNK ? (size_t)(want - 8 - off) : OBS_CHUNK;
    if (vlff_read_at(r.fd, off, r.buf, m)) {
      snprintf(err, errlen, "%s: read error at byte %llu: %s", path, (unsigned long long)off, strerror(errno));
      goto out;
    }
    r.start = off, r.have = m;
    hash = vlff_fnv1a64(hash, r.buf, m);
  }
  if (obs_get(&r, want - 8, &sum, 8, err, errlen)) goto out;
  if (hash != sum) {
    snprintf(err, errlen, "%s: checksum mismatch (corrupt file)", path);
    goto out;
  }
  if (obs_get(&r, sizeof h, g, grids - sizeof h, err, errlen)) goto out;
  /* The marks and the hold are checked whole before anything changes: a
   * file whose checksum holds may still have been written by another
   * program (or a bug) with values no observation makes. */
  int64_t cleared = 0;
  uint64_t hold_prompts = 0;
  if (v3n) {
    marks = malloc(v3n);
    if (!marks) {
      snprintf(err, errlen, "%s: out of memory", path);
      goto out;
    }
    if (obs_get(&r, grids, marks, v3n, err, errlen)) goto out;
    for (size_t i = 0; i < n; i++)
      if (marks[i] & ~THRU_KEPT) {
        snprintf(err, errlen, "%s: voxel %zu has see-through marks 0x%02x (known: 0x%02x)", path, i, marks[i],
                 THRU_KEPT);
        goto out;
      }
    memcpy(&cleared, marks + n, 8);
    memcpy(&hold_prompts, marks + n + 8, 8);
    if (cleared < 0) {
      snprintf(err, errlen, "%s: %lld surfaces cleared, a negative count", path, (long long)cleared);
      goto out;
    }
    /* Validated into a scratch hold first: a refused one leaves the map's. */
    char herr[192];
    struct vlff_hold *tmp = vlff_hold_create(n, 0);
    if (!tmp) {
      snprintf(err, errlen, "%s: out of memory", path);
      goto out;
    }
    const size_t hn = vlff_hold_save_size(p->hold);
    int hrc = vlff_hold_load(tmp, marks + n + 16, hn, herr, sizeof herr);
    vlff_hold_destroy(tmp);
    if (hrc) {
      snprintf(err, errlen, "%s: %s", path, herr);
      goto out;
    }
    if (v3n > obs_v3_size(p)) {
      lost = marks + n + 16 + hn;
      if (vlff_evidence_lost_check(lost, VLFF_FIELD_MAX_PROMPTS, herr, sizeof herr)) {
        snprintf(err, errlen, "%s: %s", path, herr);
        goto out;
      }
    }
  }
  /* The evidence first: it is checked whole before anything changes. A file
   * without evidence leaves the node's empty; evidence the node no longer
   * keeps (publish.evidence_weight 0) is ignored. */
  if (p->ev && evn) {
    char eerr[256];
    r.base = evn_at + 8;
    int erc = vlff_evidence_load_from(p->ev, obs_read, &r, evn, eerr, sizeof eerr);
    if (erc < 0) {
      snprintf(err, errlen, "%s: %s", path, eerr);
      goto out;
    }
    /* The map's observations hold without it, as in a file saved without
     * evidence. */
    if (erc > 0) {
      VLFF_WARN(TAG, "%s: %s; the map goes on without it", VLFF_Q(path), eerr);
      vlff_evidence_reset(p->ev);
    } else {
      if (vlff_evidence_evicted(p->ev))
        VLFF_WARN(TAG, "%s: its evidence holds more voxels than publish.evidence_max_mb (%zu MB, %zu voxels); the "
                       "%lld least-observed were given up",
                  VLFF_Q(path), p->ev_budget >> 20, vlff_evidence_capacity(p->ev), vlff_evidence_evicted(p->ev));
      /* What the last census found lost goes on being read from this
       * evidence (for the same prompts), from the first publish on. */
      if (lost) vlff_evidence_lost_set(p->ev, lost);
    }
  } else if (p->ev) {
    vlff_evidence_reset(p->ev);
  }
  memcpy(p->observed, g, n);
  memcpy(p->hits, g + n, n * 2);
  memcpy(p->hit_sum, g + n * 3, n * 12);
  /* An older file has no marks or hold: labels are decided afresh. */
  if (v3n) {
    memcpy(p->thru, marks, n);
    p->cleared = cleared;
    p->hold_prompts = hold_prompts;
    vlff_hold_load(p->hold, marks + n + 16, vlff_hold_save_size(p->hold), err, errlen); /* checked above */
  } else {
    memset(p->thru, 0, n);
    vlff_hold_reset(p->hold);
  }
  p->nthru = 0;
  p->need_full = true; /* every voxel may have changed */
  rc = 0;
  /* What the window had left behind, beside the grid's file (far.h). */
  char fp[VLFF_CFG_PATH + 80], ferr[400];
  if (p->far && !beside(fp, sizeof fp, path, vlff_publisher_files[FILE_FAR], ferr, sizeof ferr)) {
    int fr = vlff_far_load(p->far, fp, ferr, sizeof ferr);
    if (fr < 0)
      VLFF_WARN(TAG, "far map not restored (the map reads unknown beyond its window until the robot returns): %s",
                ferr);
    p->far_owed = fr == 0 || p->far_owed;
    long long dropped = 0;
    if (p->ev && !beside(fp, sizeof fp, path, vlff_publisher_files[FILE_EVFAR], ferr, sizeof ferr) &&
        vlff_evidence_load_far(p->ev, fp, &dropped, ferr, sizeof ferr) < 0)
      VLFF_WARN(TAG, "evidence beyond the map's window not restored (its voxels read the field until seen again): %s",
                ferr);
    if (dropped)
      VLFF_WARN(TAG, "%s: %lld voxels' evidence beyond the map's window given up: no page file holds them "
                     "(publish.evidence_page_mb)",
                VLFF_Q(fp), dropped);
  }
out:
  VLFF_FREE_ALL(g, marks, r.buf);
  close(r.fd);
  return rc;
}

const struct vlff_evidence *vlff_publisher_evidence(const struct vlff_publisher *p) { return p->ev; }

/* The map's grid and everything kept per voxel, from dims shifted by sh
 * into nd (grown or refitted on its lattice, lattice.h): all allocated
 * before anything changes (0; -1 with err, naming the grid: out of memory,
 * or the map's segment could not grow, with vlff_map_reserve's reason).
 * Every voxel that holds something keeps its place in the world: growths
 * and refits never drop one (drops_held); a slide (publisher_slide) gives
 * those it drops to the far map first. */
static int publisher_regrid(struct vlff_publisher *p, const int32_t sh[3], const uint32_t nd[3], char *err,
                            size_t errlen) {
  const size_t n = vlff_lattice_cells(nd);
  const uint32_t od[3] = {p->dims[0], p->dims[1], p->dims[2]};
  /* The segment first: a larger one holding the published map as it is takes
   * its name (vlff_map_reserve; readers follow it), or nothing changes. A
   * quarter more than this grid, up to shm.map_max_voxels: a robot walking on
   * moves it a few times per building, not at every growth. */
  if (p->map && n > vlff_map_capacity(p->map)) {
    size_t want = n + n / 4 < p->max_voxels ? n + n / 4 : p->max_voxels;
    if (vlff_map_reserve(p->map, want) < 0)
      return snprintf(err, errlen, "map: its segment could not grow to %zu voxels for %ux%ux%u: %s", want, nd[0],
                      nd[1], nd[2], vlff_shm_last_message()),
             -1;
    VLFF_INFO(TAG, "map: its segment now holds %zu voxels (%.1f MiB)", want,
              (double)want * 6 / (1 << 20));
  }
  /* kept: what was observed and published where */
  uint8_t *observed = vlff_lattice_regrid(p->observed, 1, 0, od, sh, nd);
  uint8_t *conf = vlff_lattice_regrid(p->conf, 1, 0, od, sh, nd);
  uint16_t *hits = vlff_lattice_regrid(p->hits, 2, 0, od, sh, nd);
  uint16_t *labels = vlff_lattice_regrid(p->labels, 2, 0xff, od, sh, nd);
  float *hit_sum = vlff_lattice_regrid(p->hit_sum, 12, 0, od, sh, nd);
  uint16_t *pub_labels = vlff_lattice_regrid(p->pub_labels, 2, 0xff, od, sh, nd);
  uint8_t *pub_conf = vlff_lattice_regrid(p->pub_conf, 1, 0, od, sh, nd);
  uint8_t *thru = vlff_lattice_regrid(p->thru, 1, 0, od, sh, nd);
  /* the voxels owed a relabel, and scratch */
  uint8_t *dirty = vlff_lattice_regrid(p->dirty, 1, 0, od, sh, nd);
  size_t *qidx = malloc(n * sizeof *qidx), *dirty_idx = malloc(n * sizeof *dirty_idx);
  float *qxyz = malloc(n * 3 * sizeof *qxyz), *qdens = malloc(n * sizeof *qdens),
        *qmargin = malloc(n * sizeof *qmargin);
  int *qlabel = malloc(n * sizeof *qlabel);
  struct vlff_map_range *runs = malloc((n / 2 + 1) * sizeof *runs);
  uint32_t *thru_list = malloc(n * sizeof *thru_list);
  if (!observed || !conf || !hits || !labels || !hit_sum || !pub_labels || !pub_conf || !thru || !dirty || !qidx ||
      !dirty_idx || !qxyz || !qdens || !qmargin || !qlabel || !runs || !thru_list ||
      vlff_hold_grow(p->hold, od, sh, nd)) {
    VLFF_FREE_ALL(observed, conf, hits, labels, hit_sum, pub_labels, pub_conf, thru, dirty, qidx, dirty_idx, qxyz,
                  qdens, qmargin, qlabel, runs, thru_list);
    return snprintf(err, errlen, "map: out of memory for %ux%ux%u voxels", nd[0], nd[1], nd[2]), -1;
  }
  /* Between keyframes no view's list is open (thru_commit emptied it). */
  /* A slide (publisher_slide) drops voxels from them: those beyond the new grid. */
  size_t nt = 0, ndirty = 0;
  for (size_t k = 0; k < p->nthru; k++) {
    long i = vlff_lattice_index(p->thru_list[k], od, sh, nd);
    if (i >= 0) thru_list[nt++] = (uint32_t)i;
  }
  for (size_t k = 0; k < p->ndirty; k++) {
    long i = vlff_lattice_index(p->dirty_idx[k], od, sh, nd);
    if (i >= 0) dirty_idx[ndirty++] = (size_t)i;
  }
  p->nthru = nt, p->ndirty = ndirty;
  VLFF_FREE_ALL(p->observed, p->conf, p->hits, p->labels, p->hit_sum, p->pub_labels, p->pub_conf, p->thru, p->dirty,
                p->qidx, p->dirty_idx, p->qxyz, p->qdens, p->qmargin, p->qlabel, p->runs, p->thru_list);
  p->observed = observed, p->conf = conf, p->hits = hits, p->labels = labels, p->hit_sum = hit_sum;
  p->pub_labels = pub_labels, p->pub_conf = pub_conf, p->thru = thru, p->dirty = dirty;
  p->qidx = qidx, p->dirty_idx = dirty_idx, p->qxyz = qxyz, p->qdens = qdens, p->qmargin = qmargin;
  p->qlabel = qlabel, p->runs = runs, p->thru_list = thru_list;
  for (int a = 0; a < 3; a++) {
    p->k0[a] -= (long)sh[a];
    p->origin[a] = p->origin0[a] + (double)p->k0[a] * p->voxel;
    p->dims[a] = nd[a];
  }
  p->nvox = n;
  /* The far map's voxels the grid covers now come back (a slide's return,
   * or a growth or refit that reaches them). */
  if (p->far && vlff_far_blocks(p->far)) vlff_far_restore(p->far, od, sh, nd, p->k0, far_restore_voxel, p);
  /* Readers see the new geometry with the next publish, which writes the
   * whole grid as it is: relabelling it all (need_full) would hold the
   * keyframes behind it for a second on a building. */
  p->regridded = true;
  p->refresh_at = 0;
  p->grown++;
  return 0;
}

static void count_state(struct vlff_publisher *p, size_t i, int d);

/* A voxel the far map gives back to the window: what was published there,
 * as observed (a class: a measured surface at the voxel's centre, seen
 * twice; FREE: space seen through), so that the next relabel keeps it
 * mapped. */
static void far_restore_voxel(void *ctx, size_t i, uint16_t label, uint8_t conf) {
  struct vlff_publisher *p = ctx;
  p->labels[i] = p->pub_labels[i] = label;
  p->conf[i] = p->pub_conf[i] = conf;
  p->observed[i] = 1;
  count_state(p, i, 1); /* a new voxel of the grid: UNKNOWN, counted nowhere, before */
  if (label > VLFF_LABEL_MAX) return;
  long c[3];
  vlff_lattice_xyz(i, p->dims, c);
  p->hits[i] = 2;
  for (int a = 0; a < 3; a++) p->hit_sum[3 * i + a] = (float)(2 * (p->origin[a] + (c[a] + 0.5) * p->voxel));
}

/* The grid at its cap moves on by sh into nd (vlff_lattice_window): the
 * voxels it leaves go to the far map, then the far map's voxels the new
 * grid covers come back; the next publish carries the far map. */
static int publisher_slide(struct vlff_publisher *p, const int32_t sh[3], const uint32_t nd[3], char *err,
                           size_t errlen) {
  const long long dropped = vlff_far_dropped(p->far);
  if (vlff_far_store(p->far, p->dims, p->k0, sh, nd, p->labels, p->conf))
    return snprintf(err, errlen, "map: out of memory for the far map"), -1;
  if (publisher_regrid(p, sh, nd, err, errlen)) return -1;
  vlff_far_trim(p->far, p->k0, p->dims); /* only now: a failed slide drops nothing */
  p->n_labelled = p->n_free = 0; /* the voxels it left are counted out */
  for (size_t i = 0; i < p->nvox; i++) count_state(p, i, 1);
  p->far_owed = true;
  p->slides++;
  const double now = vlff_seconds();
  if (vlff_far_dropped(p->far) > dropped && now - p->far_warned_s >= 10) {
    p->far_warned_s = now;
    VLFF_WARN(TAG, "far map: blocks farthest from the robot dropped for shm.map_far_max_mb (%d MiB; %lld so far); "
                   "they read unknown",
              (int)(p->far_limit >> 20), vlff_far_dropped(p->far));
  }
  return 0;
}

int vlff_publisher_grow(struct vlff_publisher *p, const double want_lo[3], const double want_hi[3],
                        const double lo[3], const double hi[3], char *err, size_t errlen) {
  double ulo[3], uhi[3]; /* the wanted box holds the needed one */
  vlff_box_union(want_lo, want_hi, lo, hi, ulo, uhi);
  const double *blo[2] = {ulo, lo}, *bhi[2] = {uhi, hi};
  int32_t sh[3];
  uint32_t nd[3];
  const double limit = p->field.grow ? p->field.world_limit_m : INFINITY;
  int rc = vlff_lattice_cover(p->origin, VLFF_LATTICE_CUBE(p->voxel), p->dims, lo, hi, limit, sh, nd);
  if (rc >= 0) rc = vlff_lattice_cover(p->origin, VLFF_LATTICE_CUBE(p->voxel), p->dims, ulo, uhi, limit, sh, nd);
  if (rc < 0) return snprintf(err, errlen, "map: growth to an empty or non-finite box"), -1;
  char e[256] = "";
  /* The evidence first: its grid is its own (publish.evidence_voxel_m). */
  int erc = 0;
  if (p->ev && p->field.grow) erc = vlff_evidence_grow(p->ev, ulo, uhi, lo, hi, limit, e, sizeof e);
  if (rc == 0 && erc >= 0) return erc;
  if (!p->field.grow) return snprintf(err, errlen, "map: the box is fixed (field.grow is off)"), -1;
  if (erc < 0) return snprintf(err, errlen, "map: %s", e), -1;
  /* The wanted box, or when a cap or memory refuses it, the one needed;
   * past the capacity the grid is refitted, the voxels scanned once. */
  long klo[3] = {LONG_MAX, LONG_MAX, LONG_MAX}, khi[3] = {LONG_MIN, LONG_MIN, LONG_MIN};
  bool scanned = false;
  for (int t = 0; t < 2; t++) {
    if (t == 1 && vlff_lattice_cover(p->origin, VLFF_LATTICE_CUBE(p->voxel), p->dims, lo, hi, limit, sh, nd) == 0)
      return erc; /* the wanted box refused, the grid holds the needed one */
    size_t n = vlff_lattice_cells(nd);
    const bool refit = n > p->max_voxels;
    if (refit) {
      /* Past the capacity: refit the grid to the voxels that hold something
       * and the box. The margins earlier growths added ahead of the camera,
       * and the first box's beyond the world seen, go where nothing was seen;
       * every voxel that holds something stays where it is. */
      if (!scanned)
        for (size_t v = 0; v < p->nvox; v++)
          if (voxel_held(p, v)) vlff_lattice_extend(klo, khi, v, p->dims);
      scanned = true;
      const uint32_t cover[3] = {nd[0], nd[1], nd[2]};
      if (vlff_lattice_fit(p->origin, VLFF_LATTICE_CUBE(p->voxel), p->dims, klo, khi, blo[t], bhi[t], limit, sh, nd) <
              0 ||
          (n = vlff_lattice_cells(nd)) > p->max_voxels) {
        snprintf(err, errlen,
                 "map: growing to %.1f x %.1f x %.1f m needs %zu voxels of %.3f m, more than shm.map_max_voxels "
                 "(%zu), even without the voxels that hold nothing",
                 cover[0] * p->voxel, cover[1] * p->voxel, cover[2] * p->voxel, vlff_lattice_cells(cover), p->voxel,
                 p->max_voxels);
        continue;
      }
    }
    if (publisher_regrid(p, sh, nd, err, errlen) == 0) return refit ? 2 : 1;
  }
  /* Even refitted neither box fits the capacity: the grid slides with the
   * robot, to the wanted box or else the needed one, what it leaves kept in
   * the far map (far.h). A refit, which keeps everything where it is, goes
   * first. */
  for (int t = 0; p->far && t < 2; t++) {
    char serr[320];
    if (vlff_lattice_window(p->origin, VLFF_LATTICE_CUBE(p->voxel), p->dims, blo[t], bhi[t], limit, p->max_voxels,
                            sh, nd) <= 0)
      continue;
    if (publisher_slide(p, sh, nd, serr, sizeof serr) == 0) return 3;
    snprintf(err, errlen, "%s", serr); /* the slide's reason, not the refit's */
  }
  return -1; /* err: the needed box's refusal */
}

void vlff_publisher_box(const struct vlff_publisher *p, double lo[3], double hi[3], long long *grown) {
  for (int a = 0; a < 3; a++) lo[a] = p->origin[a], hi[a] = p->origin[a] + p->dims[a] * p->voxel;
  if (grown) *grown = p->grown;
}

void vlff_publisher_far(const struct vlff_publisher *p, long long *slides, size_t *blocks, size_t *bytes,
                        size_t *limit, long long *dropped) {
  *slides = p->slides;
  *blocks = p->far ? vlff_far_blocks(p->far) : 0;
  *bytes = p->far ? vlff_far_bytes(p->far) : 0;
  *limit = p->far_limit;
  *dropped = p->far ? vlff_far_dropped(p->far) : 0;
}

void vlff_publisher_reset(struct vlff_publisher *p) {
  if (p->far) vlff_far_reset(p->far), p->far_owed = true;
  if (p->ev) vlff_evidence_reset(p->ev);
  p->ev_full_said = p->ev_overflow_said = p->ev_paged_said = p->ev_page_error_said = false;
  p->lost_mask = 0;
  vlff_hold_reset(p->hold);
  memset(p->thru, 0, p->nvox);
  memset(p->observed, 0, p->nvox);
  memset(p->hits, 0, p->nvox * sizeof *p->hits);
  memset(p->hit_sum, 0, p->nvox * 3 * sizeof *p->hit_sum);
  for (size_t j = 0; j < p->ndirty; j++) p->dirty[p->dirty_idx[j]] = 0;
  p->ndirty = 0;
  p->need_full = true;
}

static long voxel_of(const struct vlff_publisher *p, const double x[3]) {
  return vlff_grid_voxel(p->origin, p->voxel, p->dims, x);
}

bool vlff_publisher_surface_known(const struct vlff_publisher *p, const double x[3]) {
  long vi = voxel_of(p, x);
  return vi >= 0 && p->hits[vi] >= 2;
}

int vlff_publisher_check_view(struct vlff_publisher *p, const struct vlff_view *v, char *err, size_t errlen) {
  char why[200];
  if (vlff_intrinsics_plausible(v->width, v->height, v->fx, v->fy, v->cx, v->cy, why, sizeof why) ||
      vlff_field_pose_plausible(&p->field, v->c2w, why, sizeof why)) {
    snprintf(err, errlen, "view refused: %s", why);
    return -1;
  }
  return 0;
}

/* The part of the segment o + t w, t in [t0, t1], inside the map's box
 * (slab clipping). False when the segment misses the box. */
static bool clip_to_map(const struct vlff_publisher *p, const double o[3], const double w[3], double *t0,
                        double *t1) {
  for (int i = 0; i < 3; i++) {
    double lo = p->origin[i], hi = p->origin[i] + p->dims[i] * p->voxel;
    if (fabs(w[i]) < 1e-300) {
      if (o[i] < lo || o[i] >= hi) return false;
      continue;
    }
    double a = (lo - o[i]) / w[i], b = (hi - o[i]) / w[i];
    *t0 = fmax(*t0, fmin(a, b));
    *t1 = fmin(*t1, fmax(a, b));
  }
  return *t0 <= *t1;
}

/* A state of the evidence budget (count > 0 since it began), said once per
 * map at level. */
static void say_budget(struct vlff_publisher *p, bool *said, long long count, enum vlff_log_level level,
                       const char *what) {
  if (*said || !count) return;
  *said = true;
  vlff_log(level, TAG, "evidence: publish.evidence_max_mb (%zu MB, %zu voxels) %s", p->ev_budget >> 20,
           vlff_evidence_capacity(p->ev), what);
}

/* Voxel vi's observations changed, or a ray passed through what the map
 * labels occupied: it is relabelled and published with the keyframe
 * (vlff_publisher_publish_changed). */
static void touch(struct vlff_publisher *p, size_t vi) {
  if (p->dirty[vi]) return;
  p->dirty[vi] = 1;
  p->dirty_idx[p->ndirty++] = vi;
}

/* A voxel whose measured surface this many rays had ended in before it was
 * seen through held a thing (THRU_GONE), not the depth's stray points in
 * front of a far surface, which newer views rightly see through too. */
enum { GONE_HITS = 8 };

/* Voxel vi gets flag f from the view being observed. */
static void thru_mark(struct vlff_publisher *p, size_t vi, uint8_t f) {
  if (!(p->thru[vi] & THRU_LISTED)) p->thru[vi] |= THRU_LISTED, p->thru_list[p->nthru++] = (uint32_t)vi;
  p->thru[vi] |= f;
}

/* The view is observed: a voxel its rays passed through, well in front of
 * where they ended, and that none of them ended in, is seen through once
 * more; seen through by two views in a row, its measured surface is gone
 * (the thing moved or was taken away). A view that ends a ray in it starts
 * the run over. Two views, not one: a single view's holes and noise must
 * not erase a surface. */
static void thru_commit(struct vlff_publisher *p) {
  for (size_t k = 0; k < p->nthru; k++) {
    size_t vi = p->thru_list[k];
    uint8_t t = p->thru[vi], run = t & THRU_RUN, gone = t & THRU_GONE;
    if (t & THRU_HIT) run = 0, gone = 0;
    else if ((t & THRU_PASSED) && run < THRU_RUN) run++;
    if (run >= 2 && p->hits[vi]) {
      if (p->hits[vi] >= GONE_HITS) gone = THRU_GONE, p->cleared++;
      p->hits[vi] = 0;
      memset(p->hit_sum + vi * 3, 0, 3 * sizeof *p->hit_sum);
    }
    p->thru[vi] = run | gone | (t & THRU_NEW);
  }
  p->nthru = 0;
}

/* A surface where rays had only passed before (a thing moved or put
 * there, THRU_NEW) is read from the evidence alone until this many rays
 * ended in it: the field's trust there (its exposure, vlff_field_exposure)
 * counts the rays that ended on what stood there before (the floor under
 * the chair), and its feature is that one's until training catches up. */
enum { NEW_HITS = 64 };

static bool new_surface(const struct vlff_publisher *p, long vi) {
  return vi >= 0 && (p->thru[vi] & THRU_NEW) && p->hits[vi] < NEW_HITS;
}

/* A ray (o + t w, |w| = len) through voxel vi with a measured surface
 * passes through that surface, not beside it: within 0.3 voxel of its
 * measured points' mean. A voxel an object's edge or a leg fills in part is
 * crossed beside the surface by views that see past the edge; those
 * rays say nothing about the surface. */
static bool through_surface(const struct vlff_publisher *p, size_t vi, const double o[3], const double w[3],
                            double len) {
  double m[3], c[3];
  for (int i = 0; i < 3; i++) m[i] = p->hit_sum[vi * 3 + i] / p->hits[vi] - o[i];
  c[0] = m[1] * w[2] - m[2] * w[1], c[1] = m[2] * w[0] - m[0] * w[2], c[2] = m[0] * w[1] - m[1] * w[0];
  return sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]) < 0.3 * p->voxel * len;
}

/* Seen through by the last two views or more that reached it, and no
 * surface measured in it since: free, whatever the field's density says
 * (the field still holds what was there until training forgets it). */
static bool seen_through(const struct vlff_publisher *p, size_t vi) { return (p->thru[vi] & THRU_RUN) >= 2; }

/* A measured surface point hp in voxel vi (< 0: outside the map). */
static void add_hit(struct vlff_publisher *p, long vi, const double hp[3]) {
  if (vi < 0) return;
  /* Free space before this view (observed, no surface): a new surface. */
  if (p->observed[vi] && !p->hits[vi] && !(p->thru[vi] & THRU_LISTED)) p->thru[vi] |= THRU_NEW;
  thru_mark(p, (size_t)vi, THRU_HIT);
  p->observed[vi] = 1;
  vlff_hold_observed(p->hold, (size_t)vi);
  touch(p, (size_t)vi);
  if (p->hits[vi] < UINT16_MAX) {
    p->hits[vi]++;
    for (int i = 0; i < 3; i++) p->hit_sum[vi * 3 + i] += (float)hp[i];
  }
}

/* Depth at pixel (x, y) of v: 0 outside the view or where it has none. */
static double depth_at(const struct vlff_view *v, int x, int y) {
  if (x < 0 || y < 0 || x >= v->width || y >= v->height) return 0;
  float d = v->depth[(size_t)y * v->width + x];
  return d > 0 && isfinite(d) ? d : 0;
}

/* The widest gap between neighbouring pixels' points that fill_gap closes. */
enum { GAP_VOXELS = 4 };

/* A surface seen at a grazing angle or from afar: neighbouring pixels'
 * points lie more than a voxel apart on it, and the voxels between them,
 * which hold the same surface, get no measured point; they stayed unknown
 * (or free, passed by rays) for good, and the surface's labelled points in
 * them with them. The voxels between pixel (x, y)'s point hp and the point
 * of its neighbour (x + dx, y + dy) take hits on the segment between the two
 * when both lie on one surface: on a plane, inverse depth is affine in the
 * pixel coordinates, so the step between them continues the step before
 * them or the one after them (within a quarter of it, or a tenth of a voxel
 * of depth: the sensor's noise); an object's edge breaks both. Gaps of up to
 * GAP_VOXELS voxels only: beyond, the surface is too oblique to trust. */
static void fill_gap(struct vlff_publisher *p, const struct vlff_view *v, int x, int y, int dx, int dy,
                     const double hp[3]) {
  const double d1 = depth_at(v, x, y), d2 = depth_at(v, x + dx, y + dy);
  if (!(d1 > 0) || !(d2 > 0)) return;
  double hq[3];
  vlff_unproject(v->c2w, v->fx, v->fy, v->cx, v->cy, x + dx + 0.5, y + dy + 0.5, d2, hq);
  const double g = sqrt(pow(hq[0] - hp[0], 2) + pow(hq[1] - hp[1], 2) + pow(hq[2] - hp[2], 2));
  if (!(g > 0.5 * p->voxel) || g > GAP_VOXELS * p->voxel) return;
  const double d0 = depth_at(v, x - dx, y - dy), d3 = depth_at(v, x + 2 * dx, y + 2 * dy);
  const double step = 1 / d2 - 1 / d1, tol = 0.25 * fabs(step) + 0.1 * p->voxel / (d1 * d2);
  const bool before = d0 > 0 && fabs(step - (1 / d1 - 1 / d0)) <= tol;
  const bool after = d3 > 0 && fabs(step - (1 / d3 - 1 / d2)) <= tol;
  if (!before && !after) return;
  const long v1 = voxel_of(p, hp), v2 = voxel_of(p, hq);
  const int n = (int)ceil(g / (0.5 * p->voxel));
  long last = v1;
  for (int i = 1; i < n; i++) {
    double t = (double)i / n, q[3];
    for (int a = 0; a < 3; a++) q[a] = hp[a] + (hq[a] - hp[a]) * t;
    long vi = voxel_of(p, q);
    if (vi != last && vi != v1 && vi != v2) add_hit(p, vi, q);
    last = vi;
  }
}

long long vlff_publisher_cleared(const struct vlff_publisher *p) { return p->cleared; }

bool vlff_publisher_contradicted(const struct vlff_publisher *p, const struct vlff_view *v) {
  if (!v->depth) return false;
  size_t n = 0, through = 0;
  /* Every fourth pixel each way: a moved object covers thousands of them. */
  for (int y = 1; y < v->height; y += 4)
    for (int x = 1; x < v->width; x += 4) {
      float d = v->depth[(size_t)y * v->width + x];
      if (!(d > 0) || !isfinite(d)) continue;
      double hp[3];
      vlff_unproject(v->c2w, v->fx, v->fy, v->cx, v->cy, x + 0.5, y + 0.5, d, hp);
      long vi = voxel_of(p, hp);
      if (vi < 0) continue;
      n++;
      through += !p->hits[vi] && (p->thru[vi] & THRU_GONE);
    }
  return through >= 16 && through * 20 >= n;
}

int vlff_publisher_observe(struct vlff_publisher *p, const struct vlff_view *v, char *err, size_t errlen) {
  if (vlff_publisher_check_view(p, v, err, errlen)) return -1;
  if (!v->depth) return 0;
  vlff_hold_keyframe(p->hold);
  const double *m = v->c2w;
  double o[3] = {m[3], m[7], m[11]};
  const double h = p->voxel * 0.5;
  /* No ray crosses more of the map than its diagonal: this bounds every
   * ray's march whatever the depth or pose claim. */
  double diag = 0;
  for (int i = 0; i < 3; i++) diag += pow(p->dims[i] * p->voxel, 2);
  const double max_steps = sqrt(diag) / h + 2;
  /* Free space is marched from every other pixel of a large view (a ray's
   * march is the cost); every pixel's measured point counts, or a wall
   * seen at a grazing angle keeps unobserved holes between the sampled
   * pixels' points, and its labelled points there stay unknown. */
  int stride = v->width >= 160 ? 2 : 1;
  for (int y = 0; y < v->height; y++)
    for (int x = 0; x < v->width; x++) {
      float d = v->depth[(size_t)y * v->width + x];
      if (!(d > 0) || !isfinite(d)) continue;
      double hp[3], w[3];
      vlff_unproject(m, v->fx, v->fy, v->cx, v->cy, x + 0.5, y + 0.5, d, hp);
      for (int i = 0; i < 3; i++) w[i] = hp[i] - o[i];
      double len = sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
      if (!isfinite(len) || len <= 0) continue;
      /* March at steps of half a voxel to just before the surface (the
       * surface voxel is a hit, not free), only where the ray is inside
       * the map: samples outside it would mark nothing. */
      double steps = floor((len - h) / h), t0 = 0, t1 = 1;
      /* Only the part of the ray the depth's noise cannot reach clears
       * (thru_commit): up to two voxels or a tenth of its length, whichever
       * is more, before its end. */
      const double clear_to = (len - fmax(2 * p->voxel, 0.1 * len)) / h;
      if (x % stride == 0 && y % stride == 0 && steps > 0 && clip_to_map(p, o, w, &t0, &t1)) {
        double s0 = fmax(0, ceil(t0 * len / h)), s1 = fmin(steps, floor(t1 * len / h) + 1);
        if (s1 - s0 > max_steps) s1 = s0 + max_steps;
        for (double s = s0; s < s1; s++) {
          double t = s / (len / h);
          double q[3] = {o[0] + w[0] * t, o[1] + w[1] * t, o[2] + w[2] * t};
          long vi = voxel_of(p, q);
          if (vi < 0) continue;
          /* Free space seen again where the map already says free changes
           * nothing a keyframe publish would show (most of a view's rays
           * cross such voxels); what the field's density does there, the
           * round-robin refresh brings. */
          if (!p->observed[vi] || p->labels[vi] != VLFF_LABEL_FREE) touch(p, (size_t)vi);
          p->observed[vi] = 1, vlff_hold_observed(p->hold, (size_t)vi);
          if (s <= clear_to && (!p->hits[vi] || through_surface(p, (size_t)vi, o, w, len)))
            thru_mark(p, (size_t)vi, THRU_PASSED);
        }
      }
      long vi = voxel_of(p, hp);
      add_hit(p, vi, hp);
      /* A surface near a voxel face is measured on either side of it (noise,
       * where the pixel's ray lands): the voxel half a voxel behind the
       * measured point holds the same surface, and nothing else would ever
       * observe it. It takes the same hit, so the surface's points there are
       * labelled instead of staying unknown for good. */
      double b[3];
      for (int i = 0; i < 3; i++) b[i] = hp[i] + w[i] / len * h;
      long vb = voxel_of(p, b);
      if (vb != vi) add_hit(p, vb, hp);
      fill_gap(p, v, x, y, 1, 0, hp);
      fill_gap(p, v, x, y, 0, 1, hp);
    }
  thru_commit(p);
  if (!p->ev) return 0;
  if (vlff_evidence_add(p->ev, v, err, errlen)) return -1;
  say_budget(p, &p->ev_paged_said, vlff_evidence_paged_out(p->ev), VLFF_LOG_INFO,
             "is full; from now on the least-observed voxels page theirs out to the state directory's "
             "evidence.pages (publish.evidence_page_mb), and get it back when the camera sees them again");
  say_budget(p, &p->ev_full_said, vlff_evidence_evicted(p->ev), VLFF_LOG_INFO,
             p->page_path[0] ? "and its page file (publish.evidence_page_mb) are full; from now on the least-observed "
                               "voxels give theirs up to newly seen ones"
                             : "is full; from now on the least-observed voxels give theirs up to newly seen ones");
  if (!p->ev_page_error_said && vlff_evidence_page_errors(p->ev)) {
    p->ev_page_error_said = true;
    VLFF_WARN(TAG, "evidence: page file %s: what could not be written is given up, what could not be read back "
                   "starts anew (%lld failed so far)",
              vlff_evidence_page_error(p->ev), vlff_evidence_page_errors(p->ev));
  }
  say_budget(p, &p->ev_overflow_said, vlff_evidence_overflow(p->ev), VLFF_LOG_WARN,
             "had no room for some newly seen voxels (those the last 8 views saw are kept, and one view frees at most "
             "an eighth); they read the field alone (raise publish.evidence_max_mb)");
  return 0;
}

/* Labels (and score, margin: either may be NULL) of n points: the field's,
 * or with evidence the field's cosines combined with the voxels' evidence
 * (evidence.h; and with it, each point's sums into vec[n][K], or NULL).
 * stamp: a hash of the prompt embeddings. */
static int label_points(struct vlff_publisher *p, struct vlff_field *f, const float *xyz, size_t n, uint64_t stamp,
                        int *lab, float *score, float *margin, float *vec) {
  if (!p->ev) return vlff_field_query(f, xyz, n, NULL, NULL, lab, score, margin);
  int K;
  const float *E = vlff_field_prompt_embeddings(f, &K);
  for (size_t a = 0; a < n; a += QBLOCK) {
    size_t m = n - a < QBLOCK ? n - a : QBLOCK;
    if (vlff_field_query_cosines(f, xyz + 3 * a, m, p->qcos)) return -1;
    vlff_field_exposure(f, xyz + 3 * a, m, p->qrays);
    for (size_t j = 0; j < m; j++) {
      const float *x = xyz + 3 * (a + j);
      if (new_surface(p, voxel_of(p, (const double[3]){x[0], x[1], x[2]}))) p->qrays[j] = 0;
    }
    vlff_evidence_label_scores(p->ev, xyz + 3 * a, m, p->qcos, p->qrays, p->trust_rays, E, K, stamp, p->ev_weight,
                               lab + a, score ? score + a : NULL, margin ? margin + a : NULL,
                               vec ? vec + a * (size_t)K : NULL);
  }
  return 0;
}

/* Tells when the set of lost classes changes: which class, and the census
 * that says so. */
static void report_lost(struct vlff_publisher *p, const char *const *prompts, int k, uint64_t stamp, int nlost) {
  if (stamp != p->lost_mask_stamp) p->lost_mask = 0, p->lost_mask_stamp = stamp; /* other prompts: none reported */
  uint64_t mask = 0;
  for (int c = 0; c < k && c < 64 && nlost; c++)
    if (vlff_evidence_lost(p->ev, c, NULL, NULL)) mask |= 1ull << c;
  for (int c = 0; c < k && c < 64; c++) {
    if (!((mask ^ p->lost_mask) >> c & 1)) continue;
    unsigned long long nf, ne;
    vlff_evidence_lost(p->ev, c, &nf, &ne);
    if (mask >> c & 1)
      VLFF_INFO("publish",
                "the field labels '%s' at %llu map points, the evidence at %llu: a class it has given away, read "
                "from the evidence there",
                VLFF_Q(prompts[c]), nf, ne);
    else
      VLFF_INFO("publish", "the field keeps '%s' again (%llu map points, the evidence %llu)", VLFF_Q(prompts[c]), nf,
                ne);
  }
  p->lost_mask = mask;
}

int vlff_publisher_set_camera(struct vlff_publisher *p, const struct vlff_view *v, uint64_t t_ns, long long frame_id,
                              char *err, size_t errlen) {
  if (vlff_publisher_check_view(p, v, err, errlen)) return -1;
  p->cam = *v;
  p->nsel = vlff_label_surface(v->c2w, v->fx, v->fy, v->cx, v->cy, v->width, v->height, p->surface ? v->depth : NULL,
                               p->lw, p->lh, p->sel_xyz, p->sel_pix, p->hole_pix, &p->nhole);
  if (p->regions) vlff_regions_colours(v->rgb, v->width, v->height, p->lw, p->lh, p->sel_pix, p->nsel, p->sel_col);
  p->cam.rgb = NULL;
  p->cam.depth = NULL;
  p->cam.features = NULL;
  p->have_cam = true;
  p->cam_t_ns = t_ns;
  p->cam_frame = frame_id;
  return 0;
}

static uint8_t conf_of(float margin) {
  /* A cosine margin of 0.1 between the best and second prompt is already a
   * clear decision for CLIP-like embeddings. */
  float c = margin / 0.1f * 255.0f;
  return (uint8_t)(c < 0 ? 0 : c > 255 ? 255 : c);
}

/* Voxel i's state counted into (d = 1) or out of (d = -1) the totals. */
static void count_state(struct vlff_publisher *p, size_t i, int d) {
  uint16_t l = p->labels[i];
  size_t *c = l <= VLFF_LABEL_MAX ? &p->n_labelled : l == VLFF_LABEL_FREE ? &p->n_free : NULL;
  if (c) *c = d > 0 ? *c + 1 : *c - 1;
}

/* The one place a relabelled voxel's new state is decided and written:
 * label (or FREE, UNKNOWN) with its confidence; a class or FREE through the
 * label hold (hold.h), margin its lead (ignored for FREE). An unobserved
 * voxel is UNKNOWN whatever was held (only a reset or a load unobserves). */
static void set_label(struct vlff_publisher *p, size_t i, uint16_t label, uint8_t conf, float margin) {
  p->labels[i] = label == VLFF_LABEL_UNKNOWN ? label : vlff_hold_label(p->hold, i, label, margin);
  p->conf[i] = conf;
}

/* A labelled voxel whose map label led the second best by at least
 * SETTLED_MARGIN when it was last relabelled (at least twice the default
 * hysteresis): a field drifting between two rounds does not overturn such a
 * lead, and new evidence for it is relabelled by the keyframe's own publish,
 * so a skipping round leaves it as it is. Those are most of a learned map's
 * occupied voxels, and their query most of a round's cost. */
#define SETTLED_MARGIN 0.1f
static bool settled(const struct vlff_publisher *p, size_t i) {
  return p->skip_settled && p->labels[i] <= VLFF_LABEL_MAX && p->conf[i] >= conf_of(SETTLED_MARGIN);
}

/* Whether a refresh slice queries the field at voxel i (gather's rules): an
 * observed voxel, not settled in a round that skips those, with hits or
 * not seen through. */
static bool slice_queries(const struct vlff_publisher *p, size_t i) {
  return p->observed[i] && !settled(p, i) && (p->hits[i] > 0 || !seen_through(p, i));
}

/* The voxels to relabel: idx[0..n), or first .. first + n - 1 when idx is
 * NULL. Unobserved ones become UNKNOWN; the observed ones' query points go
 * into p->qxyz (their hits' mean, or the voxel's centre) and their indices
 * into p->qidx, those with hits first (*nhit of them): their count. */
static size_t gather(struct vlff_publisher *p, const size_t *idx, size_t first, size_t n, size_t *nhit) {
  size_t nq = 0;
  /* Only a refresh slice (idx NULL) may pass over settled voxels; they keep
   * their label, conf and counts. */
  const bool skip = !idx && p->skip_settled;
  for (int pass = 0; pass < 2; pass++) {
    if (pass) *nhit = nq;
    for (size_t j = 0; j < n; j++) {
      size_t i = idx ? idx[j] : first + j;
      if (!pass) count_state(p, i, -1);
      if (!p->observed[i]) {
        if (!pass) set_label(p, i, VLFF_LABEL_UNKNOWN, 0, 0);
        continue;
      }
      if (skip && settled(p, i)) continue;
      if ((p->hits[i] > 0) != !pass) continue;
      /* Seen through is free whatever the density, so it is not queried:
       * most of a map's observed voxels are, and their query was most of a
       * round. */
      if (pass && seen_through(p, i)) {
        set_label(p, i, VLFF_LABEL_FREE, 255, 0);
        continue;
      }
      float *q = p->qxyz + nq * 3;
      if (p->hits[i]) {
        for (int a = 0; a < 3; a++) q[a] = p->hit_sum[i * 3 + a] / p->hits[i];
      } else {
        size_t ix = i % p->dims[0], iy = (i / p->dims[0]) % p->dims[1], iz = i / ((size_t)p->dims[0] * p->dims[1]);
        q[0] = (float)(p->origin[0] + (ix + 0.5) * p->voxel);
        q[1] = (float)(p->origin[1] + (iy + 0.5) * p->voxel);
        q[2] = (float)(p->origin[2] + (iz + 0.5) * p->voxel);
      }
      p->qidx[nq++] = i;
    }
  }
  return nq;
}

/* Density at the nq gathered voxels but the nhit first, occupied whatever
 * the field says (measured depth ended there): the free ones are labelled
 * FREE, the occupied ones compacted to the front of p->qxyz/p->qidx. Their
 * count, or -1 when the query failed. */
static long mark_free(struct vlff_publisher *p, struct vlff_field *f, size_t nq, size_t nhit, char *err,
                      size_t errlen) {
  /* Two passes: density for every observed voxel without hits (the hash
   * grid and MLP1 only), then labels and margins for the occupied ones.
   * Free voxels, most of a room, never need MLP3, the prompt fold or a
   * feature norm. */
  if (nq > nhit &&
      vlff_field_query(f, p->qxyz + 3 * nhit, nq - nhit, p->qdens + nhit, NULL, NULL, NULL, NULL)) {
    snprintf(err, errlen, "field query of %zu voxels failed", nq - nhit);
    return -1;
  }
  size_t nocc = nhit;
  for (size_t j = nhit; j < nq; j++) {
    size_t i = p->qidx[j];
    if (p->qdens[j] >= p->free_density) { /* seen-through voxels were labelled free in gather */
      /* Compacted in place: nocc <= j. */
      memmove(p->qxyz + nocc * 3, p->qxyz + j * 3, 3 * sizeof(float));
      p->qidx[nocc++] = i;
    } else {
      set_label(p, i, VLFF_LABEL_FREE, 255, 0);
    }
  }
  return (long)nocc;
}

/* A hash of the prompt embeddings the evidence's label calls key on (0
 * without evidence). */
static uint64_t prompt_stamp(const struct vlff_publisher *p, struct vlff_field *f) {
  if (!p->ev) return 0;
  int K;
  const float *E = vlff_field_prompt_embeddings(f, &K);
  return vlff_fnv1a64(VLFF_FNV1A64_INIT, E, (size_t)K * p->D * sizeof *E);
}

/* Labels and confidences of the nocc occupied voxels. 0, or -1 when the
 * query failed. */
static int label_occupied(struct vlff_publisher *p, struct vlff_field *f, size_t nocc, uint64_t stamp, char *err,
                          size_t errlen) {
  if (nocc && label_points(p, f, p->qxyz, nocc, stamp, p->qlabel, NULL, p->qmargin, NULL)) {
    snprintf(err, errlen, "field query of %zu occupied voxels failed", nocc);
    return -1;
  }
  for (size_t j = 0; j < nocc; j++) {
    size_t i = p->qidx[j];
    if (p->qlabel[j] >= 0)
      set_label(p, i, (uint16_t)p->qlabel[j], conf_of(p->qmargin[j]), p->qmargin[j]);
    else
      set_label(p, i, VLFF_LABEL_FREE, 255, 0);
  }
  return 0;
}

/* Relabels voxels idx[0..n) (each once), or first .. first + n - 1 when
 * idx is NULL, through the field: only those are queried. 0, or -1 when a
 * query failed (the totals are then recounted by the next whole publish). */
static int relabel_voxels(struct vlff_publisher *p, struct vlff_field *f, const size_t *idx, size_t first, size_t n,
                          uint64_t stamp, char *err, size_t errlen) {
  size_t nhit = 0, nq = gather(p, idx, first, n, &nhit);
  long nocc = mark_free(p, f, nq, nhit, err, errlen);
  if (nocc < 0 || label_occupied(p, f, (size_t)nocc, stamp, err, errlen)) {
    p->need_full = true;
    return -1;
  }
  for (size_t j = 0; j < n; j++) count_state(p, idx ? idx[j] : first + j, 1);
  return 0;
}

enum { TAIL_NONE, TAIL_IMAGE, TAIL_SCORE };
/* A piece of the label image takes about this long: what a keyframe
 * admitted meanwhile waits at most (a piece is at least IMAGE_PIECE_MIN
 * pixels, or a slow machine would render one per call). */
#define IMAGE_PIECE_S 0.02
#define IMAGE_PIECE_MIN 1024
/* A refresh slice queries at most about this long (publish_slice), at
 * least SLICE_PIECE_MIN voxels. */
#define SLICE_PIECE_S 0.04
#define SLICE_PIECE_MIN 256

/* A label image of the last camera (p->cam) at the map's label image size
 * begins: its camera and pixels are copied (set_camera may replace them
 * before it is done). */
static void label_image_begin(struct vlff_publisher *p, const struct vlff_field *f) {
  struct vlff_view cam = p->cam;
  double sx = (double)p->lw / cam.width, sy = (double)p->lh / cam.height;
  cam.width = p->lw;
  cam.height = p->lh;
  cam.fx *= sx, cam.cx *= sx, cam.fy *= sy, cam.cy *= sy;
  p->icam = cam;
  p->icam_t_ns = p->cam_t_ns;
  p->icam_frame = p->cam_frame;
  p->insel = p->nsel, p->inhole = p->nhole, p->ipix = 0;
  memcpy(p->isel_pix, p->sel_pix, p->nsel * sizeof *p->isel_pix);
  memcpy(p->ihole_pix, p->hole_pix, p->nhole * sizeof *p->ihole_pix);
  memcpy(p->snap_xyz, p->sel_xyz, p->nsel * 3 * sizeof *p->snap_xyz);
  /* grouped by the measured points, before the pieces move them */
  if (p->regions)
    vlff_regions_build(p->regions, p->sel_col, p->isel_pix, p->snap_xyz, p->insel,
                       (const double[3]){cam.c2w[3], cam.c2w[7], cam.c2w[11]}, (float)vlff_field_depth_noise(f));
}

/* Surface points s0..s1's labels and scores into their pixels of the image. */
static void surface_to_image(struct vlff_publisher *p, size_t s0, size_t s1) {
  for (size_t j = s0; j < s1; j++) {
    p->img_lab[p->isel_pix[j]] = p->sel_lab[j];
    p->img_score[p->isel_pix[j]] = p->sel_score[j];
  }
}

/* Up to n more of its pixels, holes (rendered) first, then surface points:
 * 0, or -1 when the field failed. */
static int label_image_piece(struct vlff_publisher *p, struct vlff_field *f, uint64_t stamp, size_t n) {
  size_t a = p->ipix, b = a + n < p->inhole + p->insel ? a + n : p->inhole + p->insel;
  if (a < p->inhole) {
    size_t e = b < p->inhole ? b : p->inhole;
    if (vlff_field_render_pixels(f, &p->icam, p->ihole_pix + a, e - a, NULL, NULL, NULL, p->img_lab, p->img_score))
      return -1;
  }
  size_t s0 = a > p->inhole ? a - p->inhole : 0, s1 = b > p->inhole ? b - p->inhole : 0;
  if (s1 > s0) {
    /* A stereo sensor's single depth is off by a decimetre at a few
     * metres, where a point query reads free space or the next object;
     * the field has fitted that surface from every view. */
    vlff_field_snap_surface(f, &p->icam, p->isel_pix + s0, s1 - s0, p->snap_xyz + 3 * s0);
    vlff_field_prompt_embeddings(f, &p->ik);
    if (label_points(p, f, p->snap_xyz + 3 * s0, s1 - s0, stamp, p->sel_lab + s0, p->sel_score + s0, NULL,
                     p->regions ? p->sel_vec + s0 * (size_t)p->ik : NULL))
      return -1;
    surface_to_image(p, s0, s1);
  }
  p->ipix = b;
  return 0;
}

/* The finished label image into *img. */
static void label_image_end(struct vlff_publisher *p, struct vlff_map_label_image *img) {
  size_t li = (size_t)p->lw * p->lh;
  /* Each surface pixel voted with its region (out of memory: as labelled). */
  if (p->regions && p->insel &&
      vlff_regions_vote(p->regions, p->sel_vec, p->insel, p->ik, p->region_weight, p->sel_lab, p->sel_score) == 0)
    surface_to_image(p, 0, p->insel);
  for (size_t i = 0; i < li; i++) {
    p->img_labels[i] = p->img_lab[i] >= 0 ? (uint16_t)p->img_lab[i] : VLFF_LABEL_UNKNOWN;
    float s = p->img_score[i] * 255.0f;
    p->img_conf[i] = (uint8_t)(s < 0 ? 0 : s > 255 ? 255 : s);
  }
  const struct vlff_view *cam = &p->icam;
  *img = (struct vlff_map_label_image){.width = (uint32_t)p->lw, .height = (uint32_t)p->lh,
                                      .labels = p->img_labels, .confidence = p->img_conf,
                                      .fx = cam->fx, .fy = cam->fy, .cx = cam->cx, .cy = cam->cy,
                                      .t_ns = p->icam_t_ns};
  memcpy(img->pose, cam->c2w, sizeof img->pose);
}

/* The label image of the last camera, whole: true when it was rendered
 * into *img. */
static bool label_image(struct vlff_publisher *p, struct vlff_field *f, uint64_t stamp,
                        struct vlff_map_label_image *img) {
  label_image_begin(p, f);
  if (label_image_piece(p, f, stamp, p->inhole + p->insel)) return false;
  label_image_end(p, img);
  return true;
}

/* The far map to the segment, for the next publish to carry: the segment
 * moved to a larger one first when it does not hold it (a quarter more,
 * as the grid's growths), and the move said in the log. */
static int publish_far(struct vlff_publisher *p, char *err, size_t errlen) {
  struct vlff_map_far far;
  if (vlff_far_export(p->far, &far)) return snprintf(err, errlen, "out of memory for the far map"), -1;
  const uint64_t want = vlff_map_far_bytes(far.nblocks, far.nruns);
  if (want > vlff_map_far_capacity(p->map)) {
    if (vlff_map_reserve_far(p->map, vlff_map_capacity(p->map), want + want / 4)) {
      vlff_far_export_release(p->far);
      return snprintf(err, errlen, "its segment could not grow for a far map of %.1f MiB: %s",
                      (double)want / (1 << 20), vlff_shm_last_message()),
             -1;
    }
    VLFF_INFO(TAG, "map: its segment now has room for a far map of %.1f MiB", (double)(want + want / 4) / (1 << 20));
  }
  const int rc = vlff_map_set_far(p->map, &far);
  vlff_far_export_release(p->far); /* the segment stages its own copy */
  if (rc) return snprintf(err, errlen, "%s", vlff_shm_last_message()), -1;
  p->far_owed = false;
  return 0;
}

/* Before a publish: the far map is owed when it was never published to
 * this segment (a replaced one holds none) or its labels' prompts changed,
 * and is staged for the publish. One the segment refuses (no room in
 * /dev/shm, ...) does not hold the grid back: the grid is published
 * without it, said (rate-limited), and the far map tried again 5 s on. */
static void far_before_publish(struct vlff_publisher *p, const char *const *prompts, int k) {
  if (!p->far) return;
  if (vlff_far_prompts(p->far, prompts, k)) p->far_owed = true;
  const uint32_t gen = vlff_map_generation(p->map);
  if (gen != p->far_gen && vlff_far_blocks(p->far)) p->far_owed = true;
  const double now = vlff_seconds();
  if (!p->far_owed || now < p->far_retry_s) return;
  char e[400];
  if (publish_far(p, e, sizeof e)) {
    p->far_retry_s = now + 5;
    VLFF_WARN(TAG, "map: published without its far map (readers read the window; tried again in 5 s): %s", e);
    return;
  }
  p->far_gen = vlff_map_generation(p->map); /* the segment it went to (a move makes a new one) */
}

/* Publishes runs[0..nruns) of the grid (runs NULL: the whole grid), the
 * prompts and, when img is not NULL, the label image. */
static int publish_ranges(struct vlff_publisher *p, const struct vlff_map_range *runs, size_t nruns,
                          const char *const *prompts, int k, const struct vlff_map_label_image *img,
                          struct vlff_publish_result *r, char *err, size_t errlen) {
  struct vlff_map_grid grid = {.voxel_size = p->voxel, .labels = p->labels, .confidence = p->conf};
  memcpy(grid.origin, p->origin, sizeof grid.origin);
  memcpy(grid.dims, p->dims, sizeof grid.dims);
  struct vlff_map_update up = {.grid = &grid, .prompts = prompts, .prompt_count = k, .label_image = img,
                               .ranges = runs, .range_count = runs ? nruns : 0};
  far_before_publish(p, prompts, k);
  if (vlff_map_publish(p->map, &up)) {
    p->far_owed = true;
    snprintf(err, errlen, "map publish: %s", vlff_shm_last_message());
    p->need_full = true; /* a replaced segment holds nothing: all of it again */
    return -1;
  }
  for (size_t j = 0; runs && j < nruns; j++) {
    memcpy(p->pub_labels + runs[j].first, p->labels + runs[j].first, runs[j].count * sizeof *p->labels);
    memcpy(p->pub_conf + runs[j].first, p->conf + runs[j].first, runs[j].count);
  }
  if (!runs) {
    memcpy(p->pub_labels, p->labels, p->nvox * sizeof *p->labels);
    memcpy(p->pub_conf, p->conf, p->nvox);
  }
  r->version = vlff_map_version(p->map);
  r->labelled = p->n_labelled;
  r->free_voxels = p->n_free;
  r->unknown = p->nvox - p->n_labelled - p->n_free;
  p->last_publish_s = p->last_heartbeat_s = vlff_seconds();
  return 0;
}

/* Runs of the sorted voxel indices idx[0..n) into p->runs: their count. */
static size_t runs_of(struct vlff_publisher *p, const size_t *idx, size_t n) {
  size_t nr = 0;
  for (size_t j = 0; j < n; j++) {
    if (nr && p->runs[nr - 1].first + p->runs[nr - 1].count == idx[j])
      p->runs[nr - 1].count++;
    else
      p->runs[nr++] = (struct vlff_map_range){(uint32_t)idx[j], 1};
  }
  return nr;
}

static uint64_t prompts_hash(const char *const *prompts, int k) {
  uint64_t h = vlff_fnv1a64(VLFF_FNV1A64_INIT, &k, sizeof k);
  for (int i = 0; i < k; i++) h = vlff_fnv1a64(h, prompts[i], strlen(prompts[i]) + 1);
  return h;
}

/* Quality against the source's ground truth, what the demo shows live: at
 * each whole refresh of the map. */
static void score(struct vlff_publisher *p, const char *const *prompts, int k, bool have_img,
                  struct vlff_publish_result *r) {
  if (!p->hooks || !p->hooks->observe) return;
  struct vlff_map_grid grid = {.voxel_size = p->voxel, .labels = p->labels, .confidence = p->conf};
  memcpy(grid.origin, p->origin, sizeof grid.origin);
  memcpy(grid.dims, p->dims, sizeof grid.dims);
  struct vlff_map_seen seen = {.grid = &grid, .image_labels = have_img ? p->img_lab : NULL, .width = p->lw,
                               .height = p->lh, .frame_id = p->icam_frame, .prompts = prompts, .prompt_count = k};
  p->hooks->observe(p->hooks->ctx, &seen, &r->miou2d, &r->miou3d);
  if (r->miou2d >= 0) r->miou2d_frame = p->icam_frame;
}

static void result_init(struct vlff_publish_result *r) {
  memset(r, 0, sizeof *r);
  r->miou2d = r->miou3d = -1;
  r->miou2d_frame = -1;
}

/* A hash of the prompt count and embeddings (with or without evidence). */
static uint64_t embeddings_hash(const struct vlff_publisher *p, struct vlff_field *f) {
  int hk;
  const float *he = vlff_field_prompt_embeddings(f, &hk);
  return vlff_fnv1a64(vlff_fnv1a64(VLFF_FNV1A64_INIT, &hk, sizeof hk), he, he ? (size_t)hk * p->D * sizeof *he : 0);
}

/* A publish's label decisions begin (hold.h). Labels index the prompts:
 * other prompt embeddings, other labels, none held. */
static void hold_begin(struct vlff_publisher *p, struct vlff_field *f) {
  uint64_t hstamp = embeddings_hash(p, f);
  if (hstamp != p->hold_prompts) vlff_hold_reset(p->hold), p->hold_prompts = hstamp;
  vlff_hold_begin(p->hold);
}

/* The publish's label flips into its result. */
static void hold_end(const struct vlff_publisher *p, struct vlff_publish_result *r) {
  const struct vlff_hold_stats *hs = vlff_hold_stats(p->hold);
  r->flips = hs->changed, r->flips_elsewhere = hs->changed_elsewhere, r->mapped_elsewhere = hs->mapped_elsewhere;
}

/* After a growth: the grid whole, as it is (partial publishes keep to the
 * published geometry). */
static int publish_regridded(struct vlff_publisher *p, const char *const *prompts, int k,
                             struct vlff_publish_result *r, char *err, size_t errlen) {
  if (!p->regridded) return 0;
  if (publish_ranges(p, NULL, 0, prompts, k, NULL, r, err, errlen)) return -1;
  p->regridded = false;
  return 0;
}

int vlff_publisher_publish(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                           struct vlff_publish_result *r, char *err, size_t errlen) {
  result_init(r);
  p->regridded = false; /* this one is whole */
  hold_begin(p, f);
  uint64_t stamp = prompt_stamp(p, f);
  /* A whole publish relabels every voxel: a full round, which the next
   * round may follow by skipping settled ones. */
  p->skip_settled = false;
  p->full_round_stamp = embeddings_hash(p, f);
  /* The 3D map is the census of lost classes: this pass counts, the next
   * publish (and this one's label image) reads what it found. */
  if (p->ev) vlff_evidence_census_begin(p->ev);
  /* The totals are recounted: relabelling takes each voxel's old state out. */
  p->n_labelled = p->n_free = 0;
  for (size_t i = 0; i < p->nvox; i++) count_state(p, i, 1);
  if (relabel_voxels(p, f, NULL, 0, p->nvox, stamp, err, errlen)) return -1;
  if (p->ev) report_lost(p, prompts, k, stamp, vlff_evidence_census_end(p->ev, p->lost_ratio));
  struct vlff_map_label_image img;
  bool have_img = p->have_cam && label_image(p, f, stamp, &img);
  if (publish_ranges(p, NULL, 0, prompts, k, have_img ? &img : NULL, r, err, errlen)) return -1;
  for (size_t j = 0; j < p->ndirty; j++) p->dirty[p->dirty_idx[j]] = 0;
  p->ndirty = 0;
  p->need_full = false;
  p->refresh_at = 0; /* a whole refresh: the next round starts over */
  p->prompts_hash = prompts_hash(prompts, k);
  r->whole = r->cycle_done = true;
  r->changed = p->nvox;
  hold_end(p, r);
  score(p, prompts, k, have_img, r);
  r->scored = true;
  p->tail = TAIL_NONE; /* an image a round owed is this one */
  return 0;
}

static int by_index(const void *a, const void *b) {
  size_t x = *(const size_t *)a, y = *(const size_t *)b;
  return (x > y) - (x < y);
}

int vlff_publisher_publish_changed(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                                   struct vlff_publish_result *r, char *err, size_t errlen) {
  if (p->need_full || prompts_hash(prompts, k) != p->prompts_hash)
    return vlff_publisher_publish(p, f, prompts, k, r, err, errlen);
  result_init(r);
  if (publish_regridded(p, prompts, k, r, err, errlen)) return -1;
  r->version = vlff_map_version(p->map);
  if (!p->ndirty) return 0;
  qsort(p->dirty_idx, p->ndirty, sizeof *p->dirty_idx, by_index);
  hold_begin(p, f);
  if (relabel_voxels(p, f, p->dirty_idx, 0, p->ndirty, prompt_stamp(p, f), err, errlen)) return -1;
  size_t nr = runs_of(p, p->dirty_idx, p->ndirty);
  r->changed = p->ndirty;
  for (size_t j = 0; j < p->ndirty; j++) p->dirty[p->dirty_idx[j]] = 0;
  p->ndirty = 0;
  hold_end(p, r);
  return publish_ranges(p, p->runs, nr, prompts, k, NULL, r, err, errlen);
}

double vlff_publisher_refresh_done(const struct vlff_publisher *p) {
  return p->nvox ? (double)p->refresh_at / (double)p->nvox : 0;
}

int vlff_publisher_publish_slice(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                                 double to, struct vlff_publish_result *r, char *err, size_t errlen) {
  if (p->need_full || prompts_hash(prompts, k) != p->prompts_hash) {
    p->refresh_at = 0;
    return vlff_publisher_publish(p, f, prompts, k, r, err, errlen);
  }
  result_init(r);
  if (publish_regridded(p, prompts, k, r, err, errlen)) return -1;
  /* Up to the voxel at fraction `to` of the grid, at least one voxel. */
  size_t a = p->refresh_at, b = !(to < 1) ? p->nvox : (size_t)ceil(fmax(0, to) * (double)p->nvox);
  if (b <= a) b = a + 1;
  if (b > p->nvox) b = p->nvox;
  uint64_t stamp = prompt_stamp(p, f);
  /* Rounds alternate: one relabels every voxel, the next only those not
   * settled (as long as the prompts' embeddings are those of the last full
   * round). The census of lost classes spans one whole full round, slice by
   * slice: a skipping round sees only part of each class. */
  if (a == 0) {
    uint64_t eh = embeddings_hash(p, f);
    p->skip_settled = !p->skip_settled && eh == p->full_round_stamp;
    if (!p->skip_settled) p->full_round_stamp = eh;
    if (!p->skip_settled && p->ev) vlff_evidence_census_begin(p->ev);
  }
  /* The grid's occupied voxels lie in a few parts of its index range: a
   * slice over one cost many times one elsewhere, and a keyframe admitted
   * meanwhile waited for all of it. It stops after about SLICE_PIECE_S of
   * queries instead, short of `to` (refresh_done says where). */
  size_t cap = p->piece_vox ? p->piece_vox : p->vox_s > 0 ? (size_t)(SLICE_PIECE_S / p->vox_s) : SLICE_PIECE_MIN;
  if (cap < SLICE_PIECE_MIN && !p->piece_vox) cap = SLICE_PIECE_MIN;
  size_t work = 0;
  for (size_t i = a; i < b; i++)
    if (slice_queries(p, i) && ++work == cap) {
      b = i + 1;
      break;
    }
  const bool last = b == p->nvox;
  double t0 = vlff_seconds();
  hold_begin(p, f);
  if (relabel_voxels(p, f, NULL, a, b - a, stamp, err, errlen)) return -1;
  hold_end(p, r);
  if (work >= SLICE_PIECE_MIN) {
    double s = (vlff_seconds() - t0) / (double)work;
    p->vox_s = p->vox_s > 0 ? 0.5 * (p->vox_s + s) : s;
  }
  if (last && p->ev && !p->skip_settled)
    report_lost(p, prompts, k, stamp, vlff_evidence_census_end(p->ev, p->lost_ratio));
  p->refresh_at = last ? 0 : b;
  if (last) p->tail = TAIL_IMAGE, p->ipix = SIZE_MAX; /* begun by the first publish_image */
  /* Only what changed is logged: a refresh that finds the field agreeing
   * with the map costs readers nothing. */
  size_t nr = 0;
  r->changed = 0;
  for (size_t i = a; i < b; i++) {
    if (p->labels[i] == p->pub_labels[i] && p->conf[i] == p->pub_conf[i]) continue;
    r->changed++;
    if (nr && p->runs[nr - 1].first + p->runs[nr - 1].count == i)
      p->runs[nr - 1].count++;
    else
      p->runs[nr++] = (struct vlff_map_range){(uint32_t)i, 1};
  }
  if (publish_ranges(p, p->runs, nr, prompts, k, NULL, r, err, errlen)) return -1;
  r->cycle_done = last;
  return 0;
}

int vlff_publisher_publish_image(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                                 struct vlff_publish_result *r, char *err, size_t errlen) {
  result_init(r);
  r->version = vlff_map_version(p->map);
  if (p->tail == TAIL_NONE) return 0;
  if (p->need_full || prompts_hash(prompts, k) != p->prompts_hash) {
    p->tail = TAIL_NONE; /* the whole publish owed renders its own */
    return 0;
  }
  if (p->tail == TAIL_SCORE) {
    score(p, prompts, k, p->have_cam, r);
    r->scored = true;
    p->tail = TAIL_NONE;
    return 0;
  }
  if (!p->have_cam) { /* no keyframe yet: no image, the map's scores alone */
    p->tail = TAIL_SCORE;
    return 0;
  }
  /* Other embeddings halfway (the same prompt texts): the pixels done so
   * far labelled for the others, so it begins again. */
  uint64_t eh = embeddings_hash(p, f);
  if (p->ipix != SIZE_MAX && eh != p->istamp) p->ipix = SIZE_MAX;
  if (p->ipix == SIZE_MAX) label_image_begin(p, f), p->istamp = eh;
  double t0 = vlff_seconds();
  size_t n = p->px_s > 0 ? (size_t)(IMAGE_PIECE_S / p->px_s) : IMAGE_PIECE_MIN, before = p->ipix;
  if (n < IMAGE_PIECE_MIN) n = IMAGE_PIECE_MIN;
  if (p->piece_px) n = p->piece_px;
  if (label_image_piece(p, f, prompt_stamp(p, f), n)) {
    p->tail = TAIL_NONE;
    snprintf(err, errlen, "field query of the label image failed");
    return -1;
  }
  if (p->ipix > before) p->px_s = (vlff_seconds() - t0) / (double)(p->ipix - before);
  if (p->ipix < p->inhole + p->insel) return 0;
  struct vlff_map_label_image img;
  label_image_end(p, &img);
  p->tail = TAIL_SCORE;
  if (publish_regridded(p, prompts, k, r, err, errlen)) return -1;
  return publish_ranges(p, p->runs, 0, prompts, k, &img, r, err, errlen);
}

bool vlff_publisher_image_owed(const struct vlff_publisher *p) { return p->tail != TAIL_NONE; }

void vlff_publisher_set_image_piece(struct vlff_publisher *p, size_t pixels) { p->piece_px = pixels; }
void vlff_publisher_set_slice_piece(struct vlff_publisher *p, size_t voxels) { p->piece_vox = voxels; }

void vlff_publisher_heartbeat(struct vlff_publisher *p) {
  double now = vlff_seconds();
  if (now - p->last_heartbeat_s < 0.1) return;
  p->last_heartbeat_s = now;
  /* A map truncated under the node is replaced by the library; say so. */
  /* Replaced by the library, or (no space left in /dev/shm) tried again after a
   * growing delay: said at most every few seconds. */
  if (vlff_map_heartbeat(p->map))
    vlff_warn_limited(&p->heartbeat_warned, TAG, "map heartbeat: %s", vlff_shm_last_message());
}

int vlff_publisher_set_status(struct vlff_publisher *p, const struct vlff_map_status *st, char *err, size_t errlen) {
  if (vlff_map_set_status(p->map, st) == 0) return 0;
  snprintf(err, errlen, "%s", vlff_shm_last_message());
  return -1;
}

double vlff_publisher_age_s(const struct vlff_publisher *p) {
  return p->last_publish_s < 0 ? -1 : vlff_seconds() - p->last_publish_s;
}

/* A prompt's colour in the source's ground-truth palette when it names one
 * of its classes, so segmentation and ground truth compare by eye. */
static const uint8_t *prompt_color(const struct vlff_publisher *p, const char *const *prompts, int k, int label) {
  const uint8_t *c = label >= 0 && label < k && p->hooks && p->hooks->color ? p->hooks->color(p->hooks->ctx, prompts[label])
                                                                           : NULL;
  return c ? c : vlff_label_color(label);
}

void vlff_snapshot_free(struct vlff_snapshot *s) {
  VLFF_FREE_ALL(s->strip, s->xyz, s->rgb, s->label);
  memset(s, 0, sizeof *s);
}

int vlff_publisher_snapshot(struct vlff_publisher *p, struct vlff_field *f, const char *const *prompts, int k,
                            struct vlff_snapshot *out, char *err, size_t errlen) {
  memset(out, 0, sizeof *out);
  if (!p->have_cam) return snprintf(err, errlen, "no keyframe yet: nothing to show"), -1;
  struct vlff_view cam = p->cam;
  int w = cam.width, h = cam.height;
  size_t px = (size_t)w * h;
  float *rgbf = malloc(px * 3 * sizeof(float));
  int *lab = malloc(px * sizeof(int));
  uint8_t *image = malloc(px * 3), *truth = malloc(px * 3);
  int rc = -1;
  if (!rgbf || !lab || !image || !truth) {
    snprintf(err, errlen, "out of memory");
    goto out;
  }
  if (vlff_field_render(f, &cam, rgbf, NULL, NULL, lab, NULL)) {
    snprintf(err, errlen, "render failed");
    goto out;
  }
  /* Left: the scene's camera image, or the field's own rendering of it. */
  bool sourced = p->hooks && p->hooks->panels && p->hooks->panels(p->hooks->ctx, p->cam_frame, w, h, image, truth) == 0;
  if (!sourced)
    for (size_t i = 0; i < px * 3; i++) image[i] = (uint8_t)fminf(255.f, fmaxf(0.f, rgbf[i] * 255.f + 0.5f));
  int panels = sourced ? 3 : 2;
  out->width = w * panels;
  out->height = h;
  out->strip = malloc(px * 3 * panels);
  if (!out->strip) {
    snprintf(err, errlen, "out of memory");
    goto out;
  }
  for (int y = 0; y < h; y++) {
    uint8_t *row = out->strip + (size_t)y * out->width * 3;
    memcpy(row, image + (size_t)y * w * 3, (size_t)w * 3);
    for (int x = 0; x < w; x++) memcpy(row + (w + x) * 3, prompt_color(p, prompts, k, lab[(size_t)y * w + x]), 3);
    if (sourced) memcpy(row + 2 * w * 3, truth + (size_t)y * w * 3, (size_t)w * 3);
  }
  size_t n = 0;
  for (size_t i = 0; i < p->nvox; i++) n += p->labels[i] <= VLFF_LABEL_MAX;
  out->n = n;
  out->xyz = malloc((n ? n : 1) * 3 * sizeof(float));
  out->rgb = malloc((n ? n : 1) * 3);
  out->label = malloc(n ? n : 1);
  if (!out->xyz || !out->rgb || !out->label) {
    snprintf(err, errlen, "out of memory");
    goto out;
  }
  size_t j = 0;
  for (size_t i = 0; i < p->nvox; i++) {
    if (p->labels[i] > VLFF_LABEL_MAX) continue;
    size_t ix = i % p->dims[0], iy = (i / p->dims[0]) % p->dims[1], iz = i / ((size_t)p->dims[0] * p->dims[1]);
    out->xyz[j * 3] = (float)(p->origin[0] + (ix + 0.5) * p->voxel);
    out->xyz[j * 3 + 1] = (float)(p->origin[1] + (iy + 0.5) * p->voxel);
    out->xyz[j * 3 + 2] = (float)(p->origin[2] + (iz + 0.5) * p->voxel);
    memcpy(out->rgb + j * 3, prompt_color(p, prompts, k, p->labels[i]), 3);
    out->label[j] = (uint8_t)(p->labels[i] < 255 ? p->labels[i] : 255);
    j++;
  }
  rc = 0;
out:
  if (rc) vlff_snapshot_free(out);
  VLFF_FREE_ALL(rgbf, lab, image, truth);
  return rc;
}

size_t vlff_publisher_pending(const struct vlff_publisher *p) { return p->ndirty; }

int vlff_publisher_page_evidence(struct vlff_publisher *p, const char *dir, char *err, size_t errlen) {
  if (!p->ev || p->page_mb <= 0) return 0;
  snprintf(p->page_path, sizeof p->page_path, "%s/evidence.pages", dir);
  if (vlff_evidence_page_to(p->ev, p->page_path, (size_t)p->page_mb << 20, err, errlen)) return -1;
  return 0;
}

void vlff_publisher_evidence_paging(const struct vlff_publisher *p, size_t *paged, long long *out, long long *in,
                                    long long *dropped) {
  *paged = p->ev ? vlff_evidence_paged(p->ev) : 0;
  *out = p->ev ? vlff_evidence_paged_out(p->ev) : 0;
  *in = p->ev ? vlff_evidence_paged_in(p->ev) : 0;
  *dropped = p->ev ? vlff_evidence_evicted(p->ev) : 0;
}

void vlff_publisher_evidence_memory(const struct vlff_publisher *p, size_t *used, size_t *limit) {
  size_t cap = p->ev ? vlff_evidence_capacity(p->ev) : 0;
  *limit = p->ev ? p->ev_budget : 0;
  *used = cap ? (size_t)((double)vlff_evidence_voxels(p->ev) / (double)cap * (double)p->ev_budget) : 0;
}
