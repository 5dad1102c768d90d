/* The published map: learner -> controllers.
 *
 * Two complete buffers. The writer always fills the one readers are not pointed at,
 * under that buffer's sequence word (odd while writing), then flips `current`. A
 * reader copies the current buffer between two reads of its sequence word and retries
 * if it moved, so it never takes a lock and the writer never waits: a reader only
 * loses a race when it is slower than a whole publish period. Partial updates copy
 * the untouched parts from the current buffer, which only the writer ever writes.
 *
 * The writer's status lives in the first page, between the control words and the
 * buffers, in one block under its own sequence word: it is small and replaced whole,
 * so a reader that finds the word odd or moved simply copies it again.
 *
 * The change log follows the two buffers: a ring of (version, first, count) entries,
 * appended by every publish that changes grid elements before its buffer is flipped
 * in, so a reader that sees version V finds every entry up to V. Entries are
 * numbered; the writer announces the numbers it is about to overwrite (log_reserved)
 * before writing them and publishes them (log_head) after, so a reader knows which
 * of the entries it copied can have been torn, exactly as with a seqlock. The same
 * log lets the writer bring the buffer it is about to fill up to date by copying
 * only the runs of the previous publish, not the whole grid. */
#include "shm_internal.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <dirent.h>
#include <stdint.h>
#include <sys/mman.h>
#include <unistd.h>

#define MAP_BUF_OFFSET 4096u
#define READ_RETRIES 10000
/* Change log entries: a power of two, scaled with the grid (a sixteenth of its
 * capacity, within these bounds), so that a small map has a small segment. */
#define LOG_MIN 256u
#define LOG_MAX 16384u

struct map_meta {
  uint64_t version, publish_ns;
  double origin[3], voxel_size;
  uint32_t dims[3];
  int32_t prompt_count;
  uint32_t has_limg, lw, lh, pad;
  double lfx, lfy, lcx, lcy, lpose[16];
  uint64_t lt_ns;
  char prompts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
  uint64_t limg_version; /* the version that set the label image */
  /* The far map (vlff/shm.h): its geometry and counts, its bytes at
   * off_far in the buffer, and the version that set it. */
  double far_origin[3], far_voxel;
  uint32_t far_nblocks, far_nruns;
  uint64_t far_version;
};

struct map_buf {
  _Atomic uint64_t seq;
  uint8_t pad[56];
  struct map_meta meta;
};
#define BUF_HDR align64(sizeof(struct map_buf))

struct map_ctl {
  _Atomic uint32_t current;
  uint32_t pad;
  _Atomic uint64_t version;
  _Atomic uint64_t log_head;     /* entries written and published so far */
  _Atomic uint64_t log_reserved; /* entries whose slots the writer may be writing */
};

struct log_entry {
  uint64_t version;
  uint32_t first, count;
};

#define STATUS_OFFSET 1024u

struct status_block {
  _Atomic uint64_t seq;
  uint8_t pad[56];
  struct vlff_map_status st;
};
_Static_assert(sizeof(struct vlff_map_status) == 928, "struct vlff_map_status is the segment's layout");
_Static_assert(STATUS_OFFSET >= sizeof(struct seg_hdr) + sizeof(struct map_ctl) &&
                   STATUS_OFFSET + sizeof(struct status_block) <= MAP_BUF_OFFSET,
               "the status block lies between the control words and the buffers");

struct vlff_map {
  struct seg seg;
  struct map_ctl *ctl;
  uint64_t max_voxels, lw_max, lh_max, stride, log_cap, far_cap;
  bool writer;
  bool broken;           /* writer: the segment could not be replaced */
  uint64_t last_version; /* writer: carried over into a replacing segment */
  /* Writer: the runs of its last publish (prev_all: the whole grid) and of which
   * version, to bring the other buffer up to date; prev_ok false = unknown. */
  bool prev_ok, prev_all;
  uint64_t prev_version;
  size_t prev_n;
  struct vlff_map_range *prev;    /* log_cap / 4 */
  struct vlff_map_range *scratch; /* the update's runs being merged */
  uint32_t *gaps;
  size_t scratch_cap;
  /* Writer: the far map the next publish carries (vlff_map_set_far). */
  bool far_staged;
  struct vlff_map_far far_next;
  uint8_t *far_stage;
};

struct vlff_map_snapshot {
  uint64_t max_voxels, lw_max, lh_max, log_cap;
  uint32_t generation;
  struct map_meta meta;
  uint16_t *labels;
  uint8_t *conf;
  uint16_t *llabels;
  uint8_t *lconf;
  uint64_t far_cap;
  uint8_t *far;
  /* What the last take or follow changed: changes[0..nchanges), all = whole. */
  struct vlff_map_range *changes; /* log_cap */
  size_t nchanges;
  int all;
};

/* Voxel count of a grid if it fits cap (three uint32 factors can overflow 64 bits). */
static bool dims_fit(const uint32_t d[3], uint64_t cap, uint64_t *n) {
  uint64_t a, b;
  if (__builtin_mul_overflow((uint64_t)d[0], (uint64_t)d[1], &a) || __builtin_mul_overflow(a, (uint64_t)d[2], &b) ||
      b > cap)
    return false;
  if (n)
    *n = b;
  return true;
}

/* Offsets inside one buffer. */
static uint64_t off_labels(void) { return BUF_HDR; }
static uint64_t off_conf(uint64_t mv) { return off_labels() + align64(2 * mv); }
static uint64_t off_llabels(uint64_t mv) { return off_conf(mv) + align64(mv); }
static uint64_t off_lconf(uint64_t mv, uint64_t lpx) { return off_llabels(mv) + align64(2 * lpx); }
static uint64_t off_far(uint64_t mv, uint64_t lpx) { return align64(off_lconf(mv, lpx) + lpx); }
/* A buffer holds the grid, the label image and far_cap bytes of far map. */
static uint64_t buf_stride(uint64_t mv, uint64_t lpx, uint64_t far_cap) { return off_far(mv, lpx) + align64(far_cap); }
#define FAR_CAP_MAX (1ull << 36)

API uint64_t vlff_map_far_bytes(uint32_t nblocks, uint32_t nruns) {
  return (uint64_t)nblocks * sizeof(struct vlff_map_far_block) + (uint64_t)nruns * sizeof(struct vlff_map_far_run);
}
_Static_assert(sizeof(struct vlff_map_far_block) == 16 && sizeof(struct vlff_map_far_run) == 6,
               "the far map's records are the segment's layout");

static uint64_t log_cap_for(uint64_t mv) {
  uint64_t c = LOG_MIN;
  while (c < LOG_MAX && c * 16 < mv)
    c *= 2;
  return c;
}

static uint64_t map_total(const uint64_t g[6]) {
  uint64_t mv = g[0], lw = g[1], lh = g[2];
  if (!mv || mv > (1ull << 32) || lw > 65536 || lh > 65536 || (!lw) != (!lh))
    return 0;
  const uint64_t grid = buf_stride(mv, lw * lh, 0);
  if (g[3] < grid || (g[3] - grid) % 64 || g[3] - grid > FAR_CAP_MAX || g[4] != MAP_BUF_OFFSET ||
      g[5] != log_cap_for(mv))
    return 0;
  return MAP_BUF_OFFSET + 2 * g[3] + g[5] * sizeof(struct log_entry);
}

static struct map_buf *buf(const struct vlff_map *m, uint32_t i) {
  return (struct map_buf *)(m->seg.base + MAP_BUF_OFFSET + (uint64_t)(i & 1) * m->stride);
}
static uint8_t *bufp(const struct vlff_map *m, uint32_t i, uint64_t off) { return (uint8_t *)buf(m, i) + off; }
static struct log_entry *log_slot(const struct vlff_map *m, uint64_t i) {
  return (struct log_entry *)(m->seg.base + MAP_BUF_OFFSET + 2 * m->stride) + (i & (m->log_cap - 1));
}

static void map_stat(const struct seg *s, struct vlff_shm_info *info) {
  const struct map_ctl *c = (const struct map_ctl *)(s->base + sizeof(struct seg_hdr));
  info->head = atomic_load((_Atomic uint64_t *)&c->version);
  info->slot_size = s->h->geom[0]; /* voxel capacity */
}

const struct seg_spec shm_map_spec = {.kind = VLFF_SHM_KIND_MAP, .compute_total = map_total, .stat = map_stat};

static void bind(struct vlff_map *m) {
  m->ctl = (struct map_ctl *)(m->seg.base + sizeof(struct seg_hdr));
  m->max_voxels = m->seg.h->geom[0];
  m->lw_max = m->seg.h->geom[1];
  m->lh_max = m->seg.h->geom[2];
  m->stride = m->seg.h->geom[3];
  m->log_cap = m->seg.h->geom[5];
  m->far_cap = m->stride - buf_stride(m->max_voxels, m->lw_max * m->lh_max, 0);
}

/* Writer: the temporaries "<name>.grow<pid>" that a writer killed in the middle of
 * a vlff_map_reserve left in /dev/shm (the pid in the name no longer runs) are
 * removed, so that a crash during a move does not leak a map's worth of memory. */
static void sweep_moves(const char *name) {
  char prefix[300];
  int plen = snprintf(prefix, sizeof prefix, "%s.grow", name + 1);
  DIR *d = opendir("/dev/shm");
  if (!d || plen <= 0 || plen >= (int)sizeof prefix) {
    if (d)
      closedir(d);
    return;
  }
  struct dirent *e;
  while ((e = readdir(d)) != NULL) {
    if (strncmp(e->d_name, prefix, (size_t)plen) != 0)
      continue;
    char *end;
    long pid = strtol(e->d_name + plen, &end, 10);
    if (*end || pid <= 0 || pid > INT32_MAX || pid == getpid() || shm_pid_alive((int32_t)pid))
      continue;
    char sn[300];
    snprintf(sn, sizeof sn, "/%s", e->d_name);
    shm_unlink(sn);
  }
  closedir(d);
}

static void status_withdraw(struct vlff_map *m);

API struct vlff_map *vlff_map_create(const char *name, const struct vlff_map_params *p) {
  return vlff_map_create_far(name, p, 0);
}

API struct vlff_map *vlff_map_create_far(const char *name, const struct vlff_map_params *p, uint64_t far_bytes) {
  if (far_bytes > FAR_CAP_MAX) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: a far map of more than 64 GiB", VLFF_Q(name ? name : "(null)"));
    return NULL;
  }
  if (!p || !p->max_voxels || (!p->label_max_width) != (!p->label_max_height)) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: map needs a voxel capacity and both or neither label image sizes",
            VLFF_Q(name ? name : "(null)"));
    return NULL;
  }
  struct vlff_map *m = calloc(1, sizeof *m);
  if (!m) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return NULL;
  }
  uint64_t lpx = (uint64_t)p->label_max_width * p->label_max_height;
  uint64_t geom[6] = {p->max_voxels, p->label_max_width, p->label_max_height,
                      buf_stride(p->max_voxels, lpx, far_bytes), MAP_BUF_OFFSET, log_cap_for(p->max_voxels)};
  m->prev = malloc(geom[5] / 4 * sizeof *m->prev);
  if (!m->prev) {
    free(m);
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return NULL;
  }
  if (name && name[0] == '/' && !strchr(name + 1, '/'))
    sweep_moves(name);
  int fresh = shm_seg_create(&m->seg, name, &shm_map_spec, geom, &p->perm);
  if (fresh < 0) {
    free(m->prev);
    free(m);
    return NULL;
  }
  bind(m);
  m->writer = true;
  if (fresh)
    shm_seg_ready(&m->seg);
  else
    status_withdraw(m);
  m->last_version = atomic_load(&m->ctl->version);
  atomic_store(&m->seg.h->last_ns, shm_now());
  return m;
}

/* Writer: the file shrank under us (another process with write access truncated it).
 * The map is replaced by a new segment whose version goes on from the last one
 * published, so that readers re-attaching never see the version go back; the publish
 * that found it is refused with the reason. */
static void writer_rebind(struct vlff_map *m, int fresh) {
  bind(m);
  if (!fresh)
    status_withdraw(m); /* a dead writer's segment at the name now: not our status */
  m->prev_ok = false; /* the new segment's buffers hold nothing of ours */
  if (atomic_load(&m->ctl->version) < m->last_version)
    atomic_store(&m->ctl->version, m->last_version);
  shm_seg_ready(&m->seg);
  atomic_store(&m->seg.h->last_ns, shm_now());
  m->broken = false;
}

static int writer_replace(struct vlff_map *m, const char *what) {
  char msg[320];
  snprintf(msg, sizeof msg, "%s", vlff_shm_last_message());
  int fresh = shm_seg_replace(&m->seg);
  if (fresh < 0) {
    m->broken = true;
    return -1;
  }
  writer_rebind(m, fresh);
  shm_err(VLFF_SHM_ERR_TRUNCATED, EPIPE, "%s%s", msg, what);
  return -1;
}

/* Writer whose replacement failed (no space left in /dev/shm): tried again after
 * a growing delay; -1 (EPIPE) until it works. */
static int writer_retry(struct vlff_map *m) {
  if (!m->broken)
    return 0;
  int fresh = shm_seg_retry(&m->seg);
  if (fresh < 0)
    return -1;
  writer_rebind(m, fresh);
  return 0;
}

/* Attaches the segment the name leads to now: one opened just before its writer
 * moved the map (vlff_map_reserve renames the new one over it, then marks the old
 * one moved) is refused as moved, and the name then leads to the new one. */
static int attach_current(struct seg *s, const char *name) {
  for (int i = 0;; i++) {
    if (shm_seg_attach(s, name, &shm_map_spec, false, NULL) == 0)
      return 0;
    if (vlff_shm_last_error() != VLFF_SHM_ERR_ABANDONED || i == 7)
      return -1;
  }
}

API struct vlff_map *vlff_map_attach(const char *name) {
  struct vlff_map *m = calloc(1, sizeof *m);
  if (!m) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return NULL;
  }
  if (attach_current(&m->seg, name) < 0) {
    free(m);
    return NULL;
  }
  bind(m);
  return m;
}

API void vlff_map_detach(struct vlff_map *m) {
  if (!m)
    return;
  shm_seg_close(&m->seg);
  free(m->prev);
  free(m->scratch);
  free(m->gaps);
  free(m->far_stage);
  free(m);
}

static bool meta_sane(const struct vlff_map *m, const struct map_meta *mm);

static int bad_update(const struct vlff_map *m, int code, int e, const char *why) {
  shm_err(code, e, "%s: publish refused: %s", VLFF_Q(m->seg.name), why);
  return -1;
}

static bool same_geometry(const struct map_meta *a, const double origin[3], double voxel, const uint32_t dims[3]) {
  return !memcmp(a->dims, dims, sizeof a->dims) && a->voxel_size == voxel && a->origin[0] == origin[0] &&
         a->origin[1] == origin[1] && a->origin[2] == origin[2];
}

/* A grid's voxel size and extent within physical bounds
 * (VLFF_MAP_VOXEL_MIN_M..VLFF_MAP_VOXEL_MAX_M, every corner within
 * VLFF_MAP_COORD_MAX_M of the world's origin): NaN, infinite, zero or
 * absurd geometry is no map, and a reader indexing by it would compute
 * infinite voxel centres. */
static bool geometry_physical(const double origin[3], double voxel, const uint32_t dims[3]) {
  if (!(voxel >= VLFF_MAP_VOXEL_MIN_M && voxel <= VLFF_MAP_VOXEL_MAX_M)) return false;
  for (int a = 0; a < 3; a++) {
    const double hi = origin[a] + (double)dims[a] * voxel;
    if (!(fabs(origin[a]) <= VLFF_MAP_COORD_MAX_M && fabs(hi) <= VLFF_MAP_COORD_MAX_M)) return false;
  }
  return true;
}

/* The far lattice's corner and voxel within the grid's physical bounds. */
static bool far_geometry_physical(const double origin[3], double voxel) {
  const uint32_t one[3] = {1, 1, 1};
  return geometry_physical(origin, voxel, one);
}

static int check_update(const struct vlff_map *m, const struct vlff_map_update *u) {
  if (u->grid) {
    const struct vlff_map_grid *g = u->grid;
    if (!g->labels || !g->dims[0] || !g->dims[1] || !g->dims[2])
      return bad_update(m, VLFF_SHM_ERR_INVAL, EINVAL, "grid without labels or with 0 dims");
    if (!geometry_physical(g->origin, g->voxel_size, g->dims))
      return bad_update(m, VLFF_SHM_ERR_INVAL, EINVAL,
                        "grid geometry outside physical bounds (voxel size 1e-4..1e3 m, within 1e8 m of the origin)");
    uint64_t n;
    if (!dims_fit(g->dims, m->max_voxels, &n))
      return bad_update(m, VLFF_SHM_ERR_SIZE, EMSGSIZE, "grid larger than the map capacity");
    if (u->range_count && !u->ranges)
      return bad_update(m, VLFF_SHM_ERR_INVAL, EINVAL, "range_count without ranges");
    if (u->ranges)
      for (size_t i = 0; i < u->range_count; i++)
        if ((uint64_t)u->ranges[i].first + u->ranges[i].count > n)
          return bad_update(m, VLFF_SHM_ERR_INVAL, EINVAL, "a changed range runs past the grid");
  } else if (u->ranges || u->range_count) {
    return bad_update(m, VLFF_SHM_ERR_INVAL, EINVAL, "changed ranges without a grid");
  }
  if (u->prompts) {
    if (u->prompt_count < 0 || u->prompt_count > VLFF_SHM_MAX_PROMPTS)
      return bad_update(m, VLFF_SHM_ERR_SIZE, EMSGSIZE, "prompt count out of range");
    for (int i = 0; i < u->prompt_count; i++)
      if (!u->prompts[i] || strlen(u->prompts[i]) >= VLFF_SHM_PROMPT_LEN)
        return bad_update(m, VLFF_SHM_ERR_SIZE, EMSGSIZE, "prompt missing or too long");
  }
  if (u->label_image) {
    const struct vlff_map_label_image *li = u->label_image;
    if (!li->labels || !li->width || !li->height)
      return bad_update(m, VLFF_SHM_ERR_INVAL, EINVAL, "label image without pixels");
    if (li->width > m->lw_max || li->height > m->lh_max)
      return bad_update(m, VLFF_SHM_ERR_SIZE, EMSGSIZE, "label image larger than the segment's");
  }
  return 0;
}

static int by_first(const void *a, const void *b) {
  uint32_t x = ((const struct vlff_map_range *)a)->first, y = ((const struct vlff_map_range *)b)->first;
  return (x > y) - (x < y);
}
static int by_value(const void *a, const void *b) {
  uint32_t x = *(const uint32_t *)a, y = *(const uint32_t *)b;
  return (x > y) - (x < y);
}

/* Sorts r[0..n) and merges overlapping and touching runs in place; the new count. */
static size_t merge_runs(struct vlff_map_range *r, size_t n) {
  if (n > 1)
    qsort(r, n, sizeof *r, by_first);
  size_t o = 0;
  for (size_t i = 0; i < n; i++) {
    if (!r[i].count)
      continue;
    if (o && (uint64_t)r[o - 1].first + r[o - 1].count >= r[i].first) {
      uint64_t end = (uint64_t)r[i].first + r[i].count, cur = (uint64_t)r[o - 1].first + r[o - 1].count;
      if (end > cur)
        r[o - 1].count = (uint32_t)(end - r[o - 1].first);
    } else {
      r[o++] = r[i];
    }
  }
  return o;
}

/* Merged runs r[0..n) coarsened to at most max by closing the smallest gaps
 * between them: the covered elements grow, none is dropped. gaps: n - 1 words. */
static size_t coarsen_runs(struct vlff_map_range *r, size_t n, size_t max, uint32_t *gaps) {
  if (n <= max)
    return n;
  size_t need = n - max; /* gaps to close */
  for (size_t i = 0; i + 1 < n; i++)
    gaps[i] = r[i + 1].first - (r[i].first + r[i].count);
  qsort(gaps, n - 1, sizeof *gaps, by_value);
  uint32_t t = gaps[need - 1];
  size_t below = 0;
  for (size_t i = 0; i < need; i++)
    below += gaps[i] < t;
  size_t ties = need - below, o = 0;
  for (size_t i = 0; i < n; i++) {
    if (o) {
      uint32_t gap = r[i].first - (r[o - 1].first + r[o - 1].count);
      if (gap < t || (gap == t && ties)) {
        if (gap == t)
          ties--;
        r[o - 1].count = r[i].first + r[i].count - r[o - 1].first;
        continue;
      }
    }
    r[o++] = r[i];
  }
  return o;
}

/* The update's runs merged and coarsened into m->scratch: their count, or -1
 * (ENOMEM). */
static long writer_runs(struct vlff_map *m, const struct vlff_map_update *u) {
  size_t n = u->range_count;
  if (n > m->scratch_cap) {
    struct vlff_map_range *r = realloc(m->scratch, n * sizeof *r);
    if (r)
      m->scratch = r;
    uint32_t *g = realloc(m->gaps, n * sizeof *g);
    if (g)
      m->gaps = g;
    if (!r || !g) {
      shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "%s: publish refused: out of memory for %zu ranges", VLFF_Q(m->seg.name), n);
      return -1;
    }
    m->scratch_cap = n;
  }
  if (n)
    memcpy(m->scratch, u->ranges, n * sizeof *m->scratch);
  n = merge_runs(m->scratch, n);
  return (long)coarsen_runs(m->scratch, n, m->log_cap / 4, m->gaps);
}

/* Copies runs r[0..n) of the labels and confidences from buffer `from` to `to`. */
static void copy_runs(const struct vlff_map *m, uint32_t to, uint32_t from, const struct vlff_map_range *r, size_t n) {
  uint64_t mv = m->max_voxels;
  for (size_t i = 0; i < n; i++) {
    shm_racy_copy(bufp(m, to, off_labels() + 2 * (uint64_t)r[i].first),
                  bufp(m, from, off_labels() + 2 * (uint64_t)r[i].first), 2 * (size_t)r[i].count);
    shm_racy_copy(bufp(m, to, off_conf(mv) + r[i].first), bufp(m, from, off_conf(mv) + r[i].first), r[i].count);
  }
}

/* Appends runs r[0..n) of version v to the change log. */
static void log_append(struct vlff_map *m, uint64_t v, const struct vlff_map_range *r, size_t n) {
  if (!n)
    return;
  uint64_t h = atomic_load_explicit(&m->ctl->log_head, memory_order_relaxed);
  atomic_store_explicit(&m->ctl->log_reserved, h + n, memory_order_relaxed);
  shm_fence_release();
  for (size_t i = 0; i < n; i++) {
    struct log_entry e = {.version = v, .first = r[i].first, .count = r[i].count};
    shm_racy_copy(log_slot(m, h + i), &e, sizeof e);
  }
  atomic_store_explicit(&m->ctl->log_head, h + n, memory_order_release);
}

API int vlff_map_publish(struct vlff_map *m, const struct vlff_map_update *u) {
  if (!m || !m->writer || !u) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_publish: not a writer handle or no update");
    return -1;
  }
  if (writer_retry(m) < 0)
    return -1;
  if (check_update(m, u) < 0)
    return -1;
  if (shm_seg_check(&m->seg, true) < 0)
    return writer_replace(m, "; this update was not published");
  uint32_t cur = atomic_load_explicit(&m->ctl->current, memory_order_relaxed) & 1, nb = cur ^ 1;
  struct map_buf *b = buf(m, nb);
  struct map_meta meta, nbm;
  shm_racy_copy(&meta, &buf(m, cur)->meta, sizeof meta);
  shm_racy_copy(&nbm, &b->meta, sizeof nbm);
  /* A taken-over segment is only as good as what the dead writer (or anyone else
   * with write access) left: start from nothing rather than from garbage. */
  if (!meta_sane(m, &meta))
    memset(&meta, 0, sizeof meta);
  const struct vlff_map_grid *g = u->grid;
  bool partial = g && u->ranges;
  bool has_grid = meta.version && meta.dims[0] && meta.dims[1] && meta.dims[2];
  if (partial && !(has_grid && same_geometry(&meta, g->origin, g->voxel_size, g->dims)))
    return bad_update(m, VLFF_SHM_ERR_INVAL, EINVAL,
                      "changed ranges given for a grid of another geometry than the published one, or before it");
  long nruns = partial ? writer_runs(m, u) : 0;
  if (nruns < 0)
    return -1;
  /* A writer killed between flipping `current` and storing the version left a
   * published buffer one version ahead of ctl->version: number on from the higher,
   * so that no version number ever names two different maps. */
  uint64_t base = atomic_load_explicit(&m->ctl->version, memory_order_relaxed);
  uint64_t version = (meta.version > base ? meta.version : base) + 1;
  /* A writer that died mid-publish left this buffer odd; continue from there
   * (its far area may be half written whatever its meta says). */
  const uint64_t was = atomic_load_explicit(&b->seq, memory_order_relaxed);
  const bool torn = was & 1;
  uint64_t odd = was | 1;
  atomic_store_explicit(&b->seq, odd, memory_order_relaxed);
  shm_fence_release();

  uint64_t mv = m->max_voxels, lpx = m->lw_max * m->lh_max;
  struct vlff_map_range whole = {0, 0};
  const struct vlff_map_range *logged = NULL;
  size_t nlogged = 0;
  bool logged_all = false;
  if (g && !partial) {
    uint64_t n = (uint64_t)g->dims[0] * g->dims[1] * g->dims[2];
    memcpy(meta.origin, g->origin, sizeof meta.origin);
    meta.voxel_size = g->voxel_size;
    memcpy(meta.dims, g->dims, sizeof meta.dims);
    shm_racy_copy(bufp(m, nb, off_labels()), g->labels, 2 * n);
    if (g->confidence)
      shm_racy_copy(bufp(m, nb, off_conf(mv)), g->confidence, n);
    else
      shm_racy_fill(bufp(m, nb, off_conf(mv)), 255, n);
    whole.count = (uint32_t)n;
    logged = &whole, nlogged = 1, logged_all = true;
  } else if (has_grid) {
    uint64_t n = (uint64_t)meta.dims[0] * meta.dims[1] * meta.dims[2];
    /* This buffer holds the version before the current one when this writer
     * published both: the runs of its last publish bring it up to date. */
    if (m->prev_ok && !m->prev_all && m->prev_version == meta.version && nbm.version + 1 == meta.version &&
        same_geometry(&nbm, meta.origin, meta.voxel_size, meta.dims)) {
      copy_runs(m, nb, cur, m->prev, m->prev_n);
    } else {
      shm_racy_copy(bufp(m, nb, off_labels()), bufp(m, cur, off_labels()), 2 * n);
      shm_racy_copy(bufp(m, nb, off_conf(mv)), bufp(m, cur, off_conf(mv)), n);
    }
    for (long i = 0; partial && i < nruns; i++) {
      const struct vlff_map_range *r = &m->scratch[i];
      shm_racy_copy(bufp(m, nb, off_labels() + 2 * (uint64_t)r->first), g->labels + r->first, 2 * (size_t)r->count);
      if (g->confidence)
        shm_racy_copy(bufp(m, nb, off_conf(mv) + r->first), g->confidence + r->first, r->count);
      else
        shm_racy_fill(bufp(m, nb, off_conf(mv) + r->first), 255, r->count);
    }
    if (partial)
      logged = m->scratch, nlogged = (size_t)nruns;
  }
  if (u->prompts) {
    memset(meta.prompts, 0, sizeof meta.prompts);
    for (int i = 0; i < u->prompt_count; i++)
      memcpy(meta.prompts[i], u->prompts[i], strlen(u->prompts[i]));
    meta.prompt_count = u->prompt_count;
  }
  if (u->label_image) {
    const struct vlff_map_label_image *li = u->label_image;
    uint64_t n = (uint64_t)li->width * li->height;
    meta.has_limg = 1;
    meta.lw = li->width;
    meta.lh = li->height;
    meta.lfx = li->fx;
    meta.lfy = li->fy;
    meta.lcx = li->cx;
    meta.lcy = li->cy;
    memcpy(meta.lpose, li->pose, sizeof meta.lpose);
    meta.lt_ns = li->t_ns;
    meta.limg_version = version;
    shm_racy_copy(bufp(m, nb, off_llabels(mv)), li->labels, 2 * n);
    if (li->confidence)
      shm_racy_copy(bufp(m, nb, off_lconf(mv, lpx)), li->confidence, n);
    else
      shm_racy_fill(bufp(m, nb, off_lconf(mv, lpx)), 255, n);
  } else if (meta.has_limg) {
    uint64_t n = (uint64_t)meta.lw * meta.lh;
    shm_racy_copy(bufp(m, nb, off_llabels(mv)), bufp(m, cur, off_llabels(mv)), 2 * n);
    shm_racy_copy(bufp(m, nb, off_lconf(mv, lpx)), bufp(m, cur, off_lconf(mv, lpx)), n);
  }
  const uint64_t foff = off_far(mv, lpx);
  if (m->far_staged) {
    const struct vlff_map_far *f = &m->far_next;
    if (f->nblocks) /* none: no bytes (and no staged copy to read them from) */
      shm_racy_copy(bufp(m, nb, foff), m->far_stage, vlff_map_far_bytes(f->nblocks, f->nruns));
    memcpy(meta.far_origin, f->origin, sizeof meta.far_origin);
    meta.far_voxel = f->voxel_size;
    meta.far_nblocks = f->nblocks, meta.far_nruns = f->nruns;
    meta.far_version = version;
    m->far_staged = false;
    free(m->far_stage); /* published: the buffers hold it now */
    m->far_stage = NULL;
  } else if (meta.far_nblocks && (torn || nbm.far_version != meta.far_version)) {
    shm_racy_copy(bufp(m, nb, foff), bufp(m, cur, foff), vlff_map_far_bytes(meta.far_nblocks, meta.far_nruns));
  }
  /* Logged before the flip: a reader that sees this version finds its runs. */
  log_append(m, version, logged, nlogged);
  uint64_t now = shm_now();
  meta.version = version;
  meta.publish_ns = now;
  shm_racy_copy(&b->meta, &meta, sizeof meta);
  atomic_store_explicit(&b->seq, odd + 1, memory_order_release);
  atomic_store_explicit(&m->ctl->current, nb, memory_order_release);
  atomic_store_explicit(&m->ctl->version, meta.version, memory_order_release);
  atomic_store_explicit(&m->seg.h->last_ns, now, memory_order_release);
  /* Shrunk while we wrote (the guard fired): that version reached nobody. */
  if (shm_seg_check(&m->seg, false) < 0)
    return writer_replace(m, "; this update was not published");
  m->last_version = meta.version;
  m->prev_ok = true;
  m->prev_all = logged_all;
  m->prev_version = version;
  m->prev_n = logged_all ? 0 : nlogged;
  if (m->prev_n)
    memcpy(m->prev, logged, m->prev_n * sizeof *m->prev);
  return 0;
}

API int vlff_map_heartbeat(struct vlff_map *m) {
  if (!m || !m->writer) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_heartbeat: not a writer handle");
    return -1;
  }
  if (writer_retry(m) < 0)
    return -1;
  if (shm_seg_check(&m->seg, true) < 0)
    return writer_replace(m, "");
  atomic_store_explicit(&m->seg.h->last_ns, shm_now(), memory_order_release);
  return 0;
}

API uint64_t vlff_map_capacity(const struct vlff_map *m) { return m ? m->max_voxels : 0; }

/* a's order against b's (z, then y, then x): -1, 0 or 1. */
static int key_order(const int32_t a[3], const int32_t b[3]) {
  for (int i = 2; i >= 0; i--)
    if (a[i] != b[i])
      return a[i] < b[i] ? -1 : 1;
  return 0;
}

API const char *vlff_map_far_check(const struct vlff_map_far *f) {
  if (!f)
    return "no far map";
  if (!far_geometry_physical(f->origin, f->voxel_size))
    return "far map geometry outside physical bounds (voxel size 1e-4..1e3 m, within 1e8 m of the origin)";
  if (!f->blocks || !f->runs || f->nruns < f->nblocks)
    return "far map without blocks or runs";
  const double reach = VLFF_MAP_COORD_MAX_M / (f->voxel_size * VLFF_MAP_FAR_EDGE);
  for (uint32_t b = 0; b < f->nblocks; b++) {
    const struct vlff_map_far_block *k = &f->blocks[b];
    for (int a = 0; a < 3; a++)
      if (fabs((double)k->key[a]) + 1 > reach || k->key[a] == INT32_MIN || k->key[a] == INT32_MAX)
        return "a far block beyond 1e8 m of the origin";
    const int order = b ? key_order(f->blocks[b - 1].key, k->key) : -1;
    if (!order)
      return "a far block key given twice";
    if (order > 0)
      return "far blocks not sorted by key (z, y, x)";
    const uint32_t end = b + 1 < f->nblocks ? f->blocks[b + 1].first_run : f->nruns;
    if (k->first_run != (b ? k->first_run : 0) || end <= k->first_run || end > f->nruns)
      return "far block runs out of order or out of range";
    uint64_t sum = 0;
    for (uint32_t r = k->first_run; r < end; r++) {
      if (!f->runs[r].count)
        return "a far run of 0 voxels";
      sum += f->runs[r].count;
    }
    if (sum != (uint64_t)VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE)
      return "a far block whose runs do not cover its voxels";
  }
  return NULL;
}

API int vlff_map_set_far(struct vlff_map *m, const struct vlff_map_far *f) {
  if (!m || !m->writer) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_set_far: not a writer handle");
    return -1;
  }
  static const struct vlff_map_far none = {.voxel_size = 1};
  if (!f || !f->nblocks)
    f = &none;
  const char *why = f->nblocks ? vlff_map_far_check(f) : NULL;
  if (why)
    return bad_update(m, VLFF_SHM_ERR_INVAL, EINVAL, why);
  const uint64_t n = vlff_map_far_bytes(f->nblocks, f->nruns);
  if (n > m->far_cap) {
    shm_err(VLFF_SHM_ERR_SIZE, EMSGSIZE, "%s: far map of %llu bytes, the segment holds %llu (vlff_map_reserve_far)",
            VLFF_Q(m->seg.name), (unsigned long long)n, (unsigned long long)m->far_cap);
    return -1;
  }
  uint8_t *stage = n ? malloc(n) : NULL;
  if (n && !stage) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return -1;
  }
  if (n) {
    const size_t nb = (size_t)f->nblocks * sizeof *f->blocks;
    memcpy(stage, f->blocks, nb);
    memcpy(stage + nb, f->runs, (size_t)f->nruns * sizeof *f->runs);
  }
  free(m->far_stage);
  m->far_stage = stage;
  m->far_next = *f;
  m->far_next.blocks = NULL, m->far_next.runs = NULL;
  m->far_staged = true;
  return 0;
}

/* Writer: the map as published now (buffer c, whose meta mm was copied out and
 * checked: its grid and label image, the status block, the version) into the
 * fresh segment ns of capacity geom, its buffer 0 made current. */
static void copy_into(const struct vlff_map *m, uint32_t c, const struct map_meta *mm, struct seg *ns,
                      const uint64_t geom[6]) {
  struct map_ctl *nctl = (struct map_ctl *)(ns->base + sizeof(struct seg_hdr));
  struct map_buf *nb = (struct map_buf *)(ns->base + MAP_BUF_OFFSET);
  const uint64_t mv = m->max_voxels, nmv = geom[0], lpx = m->lw_max * m->lh_max;
  memcpy(ns->base + STATUS_OFFSET, m->seg.base + STATUS_OFFSET, sizeof(struct status_block));
  nb->meta = *mm;
  if (mm->far_nblocks)
    memcpy((uint8_t *)nb + off_far(nmv, lpx), bufp(m, c, off_far(mv, lpx)),
           vlff_map_far_bytes(mm->far_nblocks, mm->far_nruns));
  if (mm->version) {
    uint64_t n = (uint64_t)mm->dims[0] * mm->dims[1] * mm->dims[2];
    memcpy((uint8_t *)nb + off_labels(), bufp(m, c, off_labels()), 2 * n);
    memcpy((uint8_t *)nb + off_conf(nmv), bufp(m, c, off_conf(mv)), n);
  }
  if (mm->has_limg) {
    uint64_t n = (uint64_t)mm->lw * mm->lh;
    memcpy((uint8_t *)nb + off_llabels(nmv), bufp(m, c, off_llabels(mv)), 2 * n);
    memcpy((uint8_t *)nb + off_lconf(nmv, lpx), bufp(m, c, off_lconf(mv, lpx)), n);
  }
  atomic_store(&nb->seq, 2);
  atomic_store(&nctl->current, 0);
  atomic_store(&nctl->version, m->last_version > mm->version ? m->last_version : mm->version);
}

/* The handle reads and writes the segment ns (allocated, mapped) from now on; its
 * old one is unmapped. */
static void adopt(struct vlff_map *m, struct seg *ns) {
  shm_seg_close(&m->seg);
  shm_seg_move(&m->seg, ns);
  free(ns);
  bind(m);
}

API int vlff_map_reserve(struct vlff_map *m, uint64_t max_voxels) {
  return vlff_map_reserve_far(m, max_voxels, m ? m->far_cap : 0);
}

API uint64_t vlff_map_far_capacity(const struct vlff_map *m) { return m ? m->far_cap : 0; }

API int vlff_map_reserve_far(struct vlff_map *m, uint64_t max_voxels, uint64_t far_bytes) {
  if (!m || !m->writer || max_voxels > UINT32_MAX || far_bytes > FAR_CAP_MAX) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_reserve: %s",
            !m || !m->writer            ? "not a writer handle"
            : max_voxels > UINT32_MAX ? "more than 2^32 - 1 voxels"
                                        : "a far map of more than 64 GiB");
    return -1;
  }
  if (writer_retry(m) < 0)
    return -1;
  if (max_voxels <= m->max_voxels && far_bytes <= m->far_cap)
    return 0;
  if (max_voxels < m->max_voxels)
    max_voxels = m->max_voxels;
  if (far_bytes < m->far_cap)
    far_bytes = m->far_cap;
  /* What is copied must be what was published: not a segment truncated under
   * us (its pages read as zeros), nor a meta that would copy past a buffer. */
  if (shm_seg_check(&m->seg, true) < 0)
    return writer_replace(m, "; the map did not grow");
  const uint32_t c = atomic_load_explicit(&m->ctl->current, memory_order_relaxed) & 1;
  struct map_meta mm;
  memcpy(&mm, &buf(m, c)->meta, sizeof mm);
  if (!meta_sane(m, &mm)) {
    shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "%s: published map metadata is inconsistent; the map did not grow",
            VLFF_Q(m->seg.name));
    return -1;
  }
  const uint64_t lpx = m->lw_max * m->lh_max;
  uint64_t geom[6] = {max_voxels, m->lw_max, m->lh_max, buf_stride(max_voxels, lpx, far_bytes), MAP_BUF_OFFSET,
                      log_cap_for(max_voxels)};
  struct vlff_map_range *prev = malloc(geom[5] / 4 * sizeof *prev);
  struct seg *ns = calloc(1, sizeof *ns);
  char tmp[sizeof m->seg.name + 32];
  int n = snprintf(tmp, sizeof tmp, "%s.grow%d", m->seg.name, (int)getpid()); /* the create checks its length */
  if (!prev || !ns || n >= (int)sizeof tmp) {
    free(prev), free(ns);
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return -1;
  }
  /* Made and filled under a name of its own, then renamed over the map's: a reader
   * attaching the name at any moment gets a whole map, the old one or the new. */
  struct vlff_shm_perm perm = {.mode = m->seg.mode, .group = m->seg.group[0] ? m->seg.group : NULL};
  if (shm_seg_create(ns, tmp, &shm_map_spec, geom, &perm) < 0) {
    free(prev), free(ns);
    return -1;
  }
  copy_into(m, c, &mm, ns, geom);
  const bool ours = atomic_load(&m->seg.fault) != 0;
  if (ours || atomic_load(&ns->fault)) {
    if (!ours)
      shm_err(VLFF_SHM_ERR_TRUNCATED, EPIPE, "%s: the new segment shrank while being filled; the map did not grow",
              VLFF_Q(tmp));
    goto drop;
  }
  shm_seg_ready(ns);
  atomic_store(&ns->h->last_ns, shm_now());
  if (shm_seg_rename(ns, m->seg.name) < 0)
    goto drop;
  /* Readers still on the old segment attach the new one at their next call. */
  atomic_store_explicit(&m->seg.h->state, SEG_MOVED, memory_order_release);
  adopt(m, ns);
  free(m->prev);
  m->prev = prev;
  m->prev_ok = false; /* buffer 1 holds nothing yet */
  return 0;
drop: /* the new segment, not the map: the old one stays as it was */
  shm_seg_close(ns);
  shm_unlink(tmp);
  free(prev), free(ns);
  return ours ? writer_replace(m, "; the map did not grow") : -1;
}

/* Reader: the segment its writer moved to (vlff_map_reserve), attached under the
 * same name in place of the old one. 0, or -1 (the old one kept, to try again). */
static int follow(struct vlff_map *m) {
  struct seg *ns = calloc(1, sizeof *ns);
  if (!ns) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return -1;
  }
  char name[sizeof m->seg.name];
  snprintf(name, sizeof name, "%s", m->seg.name);
  if (attach_current(ns, name) < 0) {
    free(ns);
    return -1;
  }
  adopt(m, ns);
  return 0;
}

/* 0: the segment is usable; 1: it is not (EPIPE and the reason set); 2: a reader
 * followed its writer to a new segment (what it was reading is gone: start over). */
static int abandoned(struct vlff_map *m) {
  if (m->broken || shm_seg_check(&m->seg, false) < 0)
    return 1;
  uint32_t st = atomic_load_explicit(&m->seg.h->state, memory_order_acquire);
  if (st == SEG_MOVED && !m->writer) {
    if (follow(m) == 0)
      return 2;
    return 1;
  }
  if (st == SEG_ABANDONED || st == SEG_MOVED) {
    shm_err(VLFF_SHM_ERR_ABANDONED, EPIPE, "%s: abandoned by its writer; attach again", VLFF_Q(m->seg.name));
    return 1;
  }
  return 0;
}

/* A meta block read from shared memory is checked before any of it is used to index. */
static bool meta_sane(const struct vlff_map *m, const struct map_meta *mm) {
  bool has_grid = mm->dims[0] && mm->dims[1] && mm->dims[2];
  if (has_grid && !geometry_physical(mm->origin, mm->voxel_size, mm->dims))
    return false;
  if (!dims_fit(mm->dims, m->max_voxels, NULL))
    return false;
  if (mm->prompt_count < 0 || mm->prompt_count > VLFF_SHM_MAX_PROMPTS)
    return false;
  if (mm->has_limg && (mm->lw > m->lw_max || mm->lh > m->lh_max))
    return false;
  if (mm->far_nblocks && (vlff_map_far_bytes(mm->far_nblocks, mm->far_nruns) > m->far_cap ||
                          mm->far_nruns < mm->far_nblocks || !far_geometry_physical(mm->far_origin, mm->far_voxel)))
    return false;
  return true;
}

/* Reads `fn` consistently from the current buffer: the seqlock retry loop.
 * fn returns READ_OK, READ_BAD (what it read is inconsistent, unless torn)
 * or READ_FAILED (its own failure, already said with shm_err: a snapshot
 * out of memory is not a corrupt map). */
enum { READ_FAILED = -1, READ_BAD = 0, READ_OK = 1 };
typedef int (*reader_fn)(const struct vlff_map *m, uint32_t b, const struct map_meta *mm, void *ctx);

static int read_consistent(struct vlff_map *m, struct map_meta *mm, reader_fn fn, void *ctx) {
  for (int i = 0; i < READ_RETRIES; i++) {
    int a = abandoned(m);
    if (a == 1)
      return -1;
    uint32_t c = atomic_load_explicit(&m->ctl->current, memory_order_acquire) & 1;
    struct map_buf *b = buf(m, c);
    uint64_t s1 = atomic_load_explicit(&b->seq, memory_order_acquire);
    if (s1 & 1)
      continue;
    shm_racy_copy(mm, &b->meta, sizeof *mm);
    int r = !meta_sane(m, mm) ? READ_BAD : fn ? fn(m, c, mm, ctx) : READ_OK;
    if (r == READ_FAILED)
      return -1;
    bool ok = r == READ_OK;
    shm_fence_acquire();
    if ((a = abandoned(m)) == 1)
      return -1;
    if (a == 2)
      continue; /* read from the segment the writer left: read the new one */
    if (atomic_load_explicit(&b->seq, memory_order_relaxed) != s1)
      continue;
    if (!ok) {
      shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "%s: published map metadata is inconsistent", VLFF_Q(m->seg.name));
      return -1;
    }
    return 0;
  }
  shm_err(VLFF_SHM_OK, EAGAIN, "%s: writer kept overwriting the map for %d reads", VLFF_Q(m->seg.name), READ_RETRIES);
  return -1;
}

static bool voxel_index(const struct map_meta *mm, double x, double y, double z, uint64_t *idx) {
  if (!mm->version || !(mm->voxel_size > 0))
    return false;
  double p[3] = {x, y, z};
  uint64_t ijk[3];
  for (int a = 0; a < 3; a++) {
    double f = floor((p[a] - mm->origin[a]) / mm->voxel_size);
    if (!(f >= 0 && f < (double)mm->dims[a]))
      return false;
    ijk[a] = (uint64_t)f;
  }
  *idx = ijk[0] + (uint64_t)mm->dims[0] * (ijk[1] + (uint64_t)mm->dims[1] * ijk[2]);
  return true;
}

/* The far map's answer at p, from the far bytes at base (a buffer's or a
 * snapshot's) that mm describes (checked by meta_sane): READ_OK with the
 * label (VLFF_LABEL_UNKNOWN where no block holds p), READ_BAD when the runs
 * break the contract (torn, or written by something else than this library). */
static int far_lookup(const uint8_t *base, const struct map_meta *mm, const double p[3], uint16_t *label,
                      uint8_t *conf) {
  *label = VLFF_LABEL_UNKNOWN, *conf = 0;
  if (!mm->far_nblocks)
    return READ_OK;
  const double E = VLFF_MAP_FAR_EDGE;
  int32_t key[3];
  uint32_t l = 0, mul = 1;
  for (int a = 0; a < 3; a++, mul *= VLFF_MAP_FAR_EDGE) {
    const double v = floor((p[a] - mm->far_origin[a]) / mm->far_voxel), k = floor(v / E);
    if (!(fabs(k) < 2147483647.0))
      return READ_OK;
    key[a] = (int32_t)k;
    const double in = v - k * E;
    l += mul * (uint32_t)(in >= 0 && in < E ? in : 0);
  }
  const struct vlff_map_far_block *blocks = (const struct vlff_map_far_block *)base;
  const struct vlff_map_far_run *runs = (const struct vlff_map_far_run *)(base + (size_t)mm->far_nblocks * 16);
  size_t lo = 0, hi = mm->far_nblocks;
  struct vlff_map_far_block blk;
  while (lo < hi) {
    size_t mid = lo + (hi - lo) / 2;
    shm_racy_copy(&blk, &blocks[mid], sizeof blk);
    const int c = key_order(blk.key, key);
    if (!c) {
      /* The block read is checked whole: its runs from where the block
       * before it ends to where the next begins, covering its voxels, and
       * its neighbours' keys on either side of it. */
      uint32_t end = mm->far_nruns;
      struct vlff_map_far_block nb;
      if (mid + 1 < mm->far_nblocks) {
        shm_racy_copy(&nb, &blocks[mid + 1], sizeof nb);
        end = nb.first_run;
        if (key_order(key, nb.key) >= 0)
          return READ_BAD;
      }
      if (mid) {
        shm_racy_copy(&nb, &blocks[mid - 1], sizeof nb);
        if (key_order(nb.key, key) >= 0)
          return READ_BAD;
      }
      if ((!mid && blk.first_run) || blk.first_run >= end || end > mm->far_nruns)
        return READ_BAD;
      uint64_t acc = 0;
      for (uint32_t r = blk.first_run; r < end; r++) {
        struct vlff_map_far_run run;
        shm_racy_copy(&run, &runs[r], sizeof run);
        if (!run.count)
          return READ_BAD;
        if (l >= acc && l < acc + run.count)
          *label = run.label, *conf = run.conf;
        acc += run.count;
      }
      return acc == (uint64_t)VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE * VLFF_MAP_FAR_EDGE ? READ_OK : READ_BAD;
    }
    if (c < 0)
      lo = mid + 1;
    else
      hi = mid;
  }
  return READ_OK;
}

struct at_ctx {
  double x, y, z;
  uint16_t label;
  uint8_t conf;
};

static int read_voxel(const struct vlff_map *m, uint32_t b, const struct map_meta *mm, void *vctx) {
  struct at_ctx *c = vctx;
  uint64_t i;
  c->label = VLFF_LABEL_UNKNOWN;
  c->conf = 0;
  if (voxel_index(mm, c->x, c->y, c->z, &i)) {
    shm_racy_copy(&c->label, bufp(m, b, off_labels() + 2 * i), 2);
    shm_racy_copy(&c->conf, bufp(m, b, off_conf(m->max_voxels) + i), 1);
    return READ_OK;
  }
  const double p[3] = {c->x, c->y, c->z};
  return far_lookup(bufp(m, b, off_far(m->max_voxels, m->lw_max * m->lh_max)), mm, p, &c->label, &c->conf);
}

API int vlff_map_label_at(struct vlff_map *m, double x, double y, double z, uint16_t *label, uint8_t *conf) {
  if (!m || !label) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_label_at: NULL argument");
    return -1;
  }
  /* A NaN or infinite coordinate names no point of the world: answering "unknown"
   * would hide a caller's broken arithmetic behind a valid-looking label. */
  if (!isfinite(x) || !isfinite(y) || !isfinite(z)) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: point (%g, %g, %g) is not finite", VLFF_Q(m->seg.name), x, y, z);
    return -1;
  }
  struct map_meta mm;
  struct at_ctx c = {.x = x, .y = y, .z = z};
  if (read_consistent(m, &mm, read_voxel, &c) < 0)
    return -1;
  *label = c.label;
  if (conf)
    *conf = c.conf;
  return 0;
}

API int vlff_map_prompt(struct vlff_map *m, uint16_t label, char *out, size_t len) {
  struct map_meta mm;
  if (!m || !out || !len) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_prompt: NULL argument");
    return -1;
  }
  if (read_consistent(m, &mm, NULL, NULL) < 0)
    return -1;
  if (label >= mm.prompt_count) {
    shm_err(VLFF_SHM_OK, ENOENT, "%s: label %u has no prompt (%d prompts)", VLFF_Q(m->seg.name), label,
            mm.prompt_count);
    return -1;
  }
  mm.prompts[label][VLFF_SHM_PROMPT_LEN - 1] = 0;
  snprintf(out, len, "%s", mm.prompts[label]);
  return 0;
}

API uint64_t vlff_map_version(struct vlff_map *m) {
  if (m->writer)
    return m->last_version;
  (void)abandoned(m); /* a moved map's version goes on in the new segment */
  return atomic_load_explicit(&m->ctl->version, memory_order_acquire);
}

API uint64_t vlff_map_age_ns(struct vlff_map *m) {
  struct map_meta mm;
  if (read_consistent(m, &mm, NULL, NULL) < 0 || !mm.version)
    return UINT64_MAX;
  uint64_t now = shm_now();
  return now > mm.publish_ns ? now - mm.publish_ns : 0;
}

API int vlff_map_writer_alive(struct vlff_map *m, uint64_t max_silence_ns) {
  if (abandoned(m) == 1)
    return 0;
  uint64_t hb = atomic_load_explicit(&m->seg.h->last_ns, memory_order_acquire), now = shm_now();
  if (now > hb && now - hb > max_silence_ns)
    return 0;
  return shm_hdr_creator_alive(m->seg.h);
}

API uint32_t vlff_map_generation(struct vlff_map *m) {
  if (!m->writer)
    (void)abandoned(m);
  return m->broken ? 0 : atomic_load(&m->seg.h->generation);
}

API struct vlff_map_snapshot *vlff_map_snapshot_new(struct vlff_map *m) {
  if (!m) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_snapshot_new: NULL map");
    return NULL;
  }
  struct vlff_map_snapshot *s = calloc(1, sizeof *s);
  uint64_t lpx = m->lw_max * m->lh_max;
  if (s) {
    s->max_voxels = m->max_voxels;
    s->lw_max = m->lw_max;
    s->lh_max = m->lh_max;
    s->labels = malloc(2 * m->max_voxels);
    s->conf = malloc(m->max_voxels);
    s->llabels = malloc(2 * lpx + 2);
    s->lconf = malloc(lpx + 1);
    s->log_cap = m->log_cap;
    s->changes = malloc(m->log_cap * sizeof *s->changes);
    s->far_cap = m->far_cap;
    s->far = malloc(m->far_cap + 1);
  }
  if (!s || !s->labels || !s->conf || !s->llabels || !s->lconf || !s->changes || !s->far) {
    vlff_map_snapshot_free(s);
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "snapshot: out of memory");
    return NULL;
  }
  return s;
}

API void vlff_map_snapshot_free(struct vlff_map_snapshot *s) {
  if (!s)
    return;
  free(s->labels);
  free(s->conf);
  free(s->llabels);
  free(s->lconf);
  free(s->changes);
  free(s->far);
  free(s);
}

static bool snap_fits(const struct vlff_map *m, const struct vlff_map_snapshot *s) {
  return s->max_voxels == m->max_voxels && s->lw_max == m->lw_max && s->lh_max == m->lh_max &&
         s->log_cap == m->log_cap && s->far_cap == m->far_cap;
}

/* A snapshot sized for the segment the handle reads now: a reader that followed
 * its writer to a larger segment (vlff_map_reserve) reallocates it (what it held
 * is gone: the caller copies whole). False when out of memory (the snapshot is
 * then as it was). */
static bool snap_resize(const struct vlff_map *m, struct vlff_map_snapshot *s) {
  if (snap_fits(m, s))
    return true;
  uint64_t lpx = m->lw_max * m->lh_max;
  uint16_t *labels = malloc(2 * m->max_voxels), *llabels = malloc(2 * lpx + 2);
  uint8_t *conf = malloc(m->max_voxels), *lconf = malloc(lpx + 1);
  struct vlff_map_range *changes = malloc(m->log_cap * sizeof *changes);
  uint8_t *far = malloc(m->far_cap + 1);
  if (!labels || !llabels || !conf || !lconf || !changes || !far) {
    free(labels), free(llabels), free(conf), free(lconf), free(changes), free(far);
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "snapshot: out of memory for a map of %llu voxels",
            (unsigned long long)m->max_voxels);
    return false;
  }
  free(s->labels), free(s->llabels), free(s->conf), free(s->lconf), free(s->changes), free(s->far);
  s->labels = labels, s->llabels = llabels, s->conf = conf, s->lconf = lconf, s->changes = changes, s->far = far;
  s->max_voxels = m->max_voxels, s->lw_max = m->lw_max, s->lh_max = m->lh_max, s->log_cap = m->log_cap;
  s->far_cap = m->far_cap;
  s->nchanges = 0; /* s->meta is left alone: it may be the read's own meta (take) */
  return true;
}

static struct vlff_map_far far_of(const struct map_meta *mm, const uint8_t *base) {
  struct vlff_map_far f = {.voxel_size = mm->far_voxel, .nblocks = mm->far_nblocks, .nruns = mm->far_nruns,
                           .blocks = (const struct vlff_map_far_block *)base,
                           .runs = (const struct vlff_map_far_run *)(base + (size_t)mm->far_nblocks * 16)};
  memcpy(f.origin, mm->far_origin, sizeof f.origin);
  return f;
}

/* The far map copied into the snapshot and checked there (the copy is the
 * reader's own: what callers of vlff_map_snapshot_far index by): READ_OK,
 * or READ_BAD when it breaks the contract (torn: the read is retried). */
static int copy_far(const struct vlff_map *m, uint32_t b, const struct map_meta *mm, struct vlff_map_snapshot *s) {
  if (!mm->far_nblocks)
    return READ_OK;
  shm_racy_copy(s->far, bufp(m, b, off_far(m->max_voxels, m->lw_max * m->lh_max)),
                vlff_map_far_bytes(mm->far_nblocks, mm->far_nruns));
  const struct vlff_map_far f = far_of(mm, s->far);
  return vlff_map_far_check(&f) ? READ_BAD : READ_OK;
}

static int copy_all(const struct vlff_map *m, uint32_t b, const struct map_meta *mm, void *ctx) {
  struct vlff_map_snapshot *s = ctx;
  if (!snap_resize(m, s))
    return READ_FAILED;
  uint64_t mv = m->max_voxels;
  if (mm->version) {
    uint64_t n = (uint64_t)mm->dims[0] * mm->dims[1] * mm->dims[2];
    shm_racy_copy(s->labels, bufp(m, b, off_labels()), 2 * n);
    shm_racy_copy(s->conf, bufp(m, b, off_conf(mv)), n);
  }
  if (mm->has_limg) {
    uint64_t n = (uint64_t)mm->lw * mm->lh;
    shm_racy_copy(s->llabels, bufp(m, b, off_llabels(mv)), 2 * n);
    shm_racy_copy(s->lconf, bufp(m, b, off_lconf(mv, m->lw_max * m->lh_max)), n);
  }
  return copy_far(m, b, mm, s);
}

/* The snapshot's change list after a whole copy of a map with meta mm. */
static void changes_all(struct vlff_map_snapshot *s, const struct map_meta *mm) {
  uint64_t n = (uint64_t)mm->dims[0] * mm->dims[1] * mm->dims[2];
  s->all = 1;
  s->nchanges = 0;
  if (mm->version && n)
    s->changes[s->nchanges++] = (struct vlff_map_range){0, (uint32_t)n};
}

static void snap_done(struct vlff_map *m, struct vlff_map_snapshot *s, const struct map_meta *mm) {
  if (&s->meta != mm)
    s->meta = *mm;
  for (int i = 0; i < VLFF_SHM_MAX_PROMPTS; i++)
    s->meta.prompts[i][VLFF_SHM_PROMPT_LEN - 1] = 0;
  s->generation = atomic_load(&m->seg.h->generation);
}

API int vlff_map_snapshot_take(struct vlff_map *m, struct vlff_map_snapshot *s) {
  if (!m || !s) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_snapshot_take: NULL argument");
    return -1;
  }
  if (read_consistent(m, &s->meta, copy_all, s) < 0) {
    s->meta.version = 0; /* torn: the next follow copies everything */
    s->nchanges = 0;
    s->all = 0;
    return -1;
  }
  changes_all(s, &s->meta);
  snap_done(m, s, &s->meta);
  return 0;
}

struct follow_ctx {
  struct vlff_map_snapshot *s;
  bool whole; /* out: copied everything */
};

/* The runs logged for versions in (from, to] into s->changes, merged: true, or
 * false when the log cannot prove it holds all of them (it wrapped past `from`,
 * entries were overwritten while read, or an entry is out of the grid of n
 * elements). */
static bool logged_since(const struct vlff_map *m, struct vlff_map_snapshot *s, uint64_t from, uint64_t to,
                         uint64_t n) {
  uint64_t head = atomic_load_explicit(&m->ctl->log_head, memory_order_acquire);
  uint64_t lo = head > m->log_cap ? head - m->log_cap : 0, i = head;
  bool found = false, sane = true;
  size_t k = 0;
  while (i > lo) {
    struct log_entry e;
    shm_racy_copy(&e, log_slot(m, --i), sizeof e);
    if (e.version <= from) {
      found = true;
      break;
    }
    if (e.version > to)
      continue; /* a publish after the buffer being read: not in it yet */
    if (!e.count || (uint64_t)e.first + e.count > n) {
      sane = false;
      break;
    }
    s->changes[k++] = (struct vlff_map_range){e.first, e.count};
  }
  shm_fence_acquire();
  uint64_t reserved = atomic_load_explicit(&m->ctl->log_reserved, memory_order_relaxed);
  /* Slots from reserved - cap on may have been rewritten while we read them. */
  if (reserved > m->log_cap && i < reserved - m->log_cap)
    return false;
  if (!found || !sane)
    return false;
  s->nchanges = merge_runs(s->changes, k);
  return true;
}

static int copy_changed(const struct vlff_map *m, uint32_t b, const struct map_meta *mm, void *vctx) {
  struct follow_ctx *c = vctx;
  struct vlff_map_snapshot *s = c->s;
  const bool resized = !snap_fits(m, s); /* what it held is gone: copy everything */
  if (!snap_resize(m, s))
    return READ_FAILED;
  const struct map_meta *old = &s->meta;
  uint64_t n = (uint64_t)mm->dims[0] * mm->dims[1] * mm->dims[2], mv = m->max_voxels;
  /* Once an attempt copied everything (torn, since it is retried), so do the rest. */
  c->whole = c->whole || resized || !old->version || !mm->version || mm->version < old->version ||
             s->generation != atomic_load(&m->seg.h->generation) ||
             !same_geometry(old, mm->origin, mm->voxel_size, mm->dims) ||
             !logged_since(m, s, old->version, mm->version, n);
  if (c->whole) {
    changes_all(s, mm);
    return copy_all(m, b, mm, s);
  }
  s->all = 0;
  for (size_t i = 0; i < s->nchanges; i++) {
    const struct vlff_map_range *r = &s->changes[i];
    shm_racy_copy(s->labels + r->first, bufp(m, b, off_labels() + 2 * (uint64_t)r->first), 2 * (size_t)r->count);
    shm_racy_copy(s->conf + r->first, bufp(m, b, off_conf(mv) + r->first), r->count);
  }
  if (mm->has_limg && mm->limg_version != old->limg_version) {
    uint64_t ln = (uint64_t)mm->lw * mm->lh;
    shm_racy_copy(s->llabels, bufp(m, b, off_llabels(mv)), 2 * ln);
    shm_racy_copy(s->lconf, bufp(m, b, off_lconf(mv, m->lw_max * m->lh_max)), ln);
  }
  /* A new far map, or counts or geometry that are not the copy's (forged:
   * a copy is only ever handed out checked). */
  if (mm->far_version != old->far_version || mm->far_nblocks != old->far_nblocks || mm->far_nruns != old->far_nruns ||
      mm->far_voxel != old->far_voxel || memcmp(mm->far_origin, old->far_origin, sizeof mm->far_origin))
    return copy_far(m, b, mm, s);
  return READ_OK;
}

API int vlff_map_snapshot_follow(struct vlff_map *m, struct vlff_map_snapshot *s) {
  if (!m || !s) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_snapshot_follow: NULL argument");
    return -1;
  }
  struct map_meta mm;
  struct follow_ctx c = {.s = s};
  /* A retry copies the runs of a later version, a superset of those a torn
   * attempt wrote into the snapshot, or everything: nothing torn survives. */
  if (read_consistent(m, &mm, copy_changed, &c) < 0) {
    s->meta.version = 0;
    s->nchanges = 0;
    s->all = 0;
    return -1;
  }
  snap_done(m, s, &mm);
  return c.whole ? 1 : 0;
}

API size_t vlff_map_snapshot_changes(const struct vlff_map_snapshot *s, const struct vlff_map_range **ranges,
                                     int *all) {
  if (all)
    *all = s ? s->all : 0;
  if (ranges)
    *ranges = s ? s->changes : NULL;
  return s ? s->nchanges : 0;
}

API int vlff_map_snapshot_info(const struct vlff_map_snapshot *s, struct vlff_map_info *info) {
  if (!s || !info) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_snapshot_info: NULL argument");
    return -1;
  }
  const struct map_meta *mm = &s->meta;
  memset(info, 0, sizeof *info);
  info->version = mm->version;
  info->publish_ns = mm->publish_ns;
  info->generation = s->generation;
  info->prompt_count = mm->prompt_count;
  memcpy(info->grid.origin, mm->origin, sizeof mm->origin);
  info->grid.voxel_size = mm->voxel_size;
  memcpy(info->grid.dims, mm->dims, sizeof mm->dims);
  info->grid.labels = s->labels;
  info->grid.confidence = s->conf;
  info->has_label_image = (int)mm->has_limg;
  if (mm->has_limg) {
    struct vlff_map_label_image *li = &info->label_image;
    li->width = mm->lw;
    li->height = mm->lh;
    li->labels = s->llabels;
    li->confidence = s->lconf;
    li->fx = mm->lfx;
    li->fy = mm->lfy;
    li->cx = mm->lcx;
    li->cy = mm->lcy;
    memcpy(li->pose, mm->lpose, sizeof li->pose);
    li->t_ns = mm->lt_ns;
  }
  return 0;
}

API uint16_t vlff_map_snapshot_label_at(const struct vlff_map_snapshot *s, double x, double y, double z,
                                        uint8_t *conf) {
  uint64_t i;
  if (conf)
    *conf = 0;
  if (!s || !isfinite(x) || !isfinite(y) || !isfinite(z) || !s->meta.version)
    return VLFF_LABEL_UNKNOWN;
  if (!voxel_index(&s->meta, x, y, z, &i)) {
    const double p[3] = {x, y, z};
    uint16_t label;
    uint8_t c;
    if (far_lookup(s->far, &s->meta, p, &label, &c) != READ_OK)
      return VLFF_LABEL_UNKNOWN;
    if (conf)
      *conf = c;
    return label;
  }
  if (conf)
    *conf = s->conf[i];
  return s->labels[i];
}

API int vlff_map_snapshot_far(const struct vlff_map_snapshot *s, struct vlff_map_far *f) {
  if (!s || !f) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_snapshot_far: NULL argument");
    return -1;
  }
  const struct map_meta *mm = &s->meta;
  memset(f, 0, sizeof *f);
  if (!mm->version || !mm->far_nblocks)
    return 0;
  *f = far_of(mm, s->far);
  return 0;
}

API uint64_t vlff_map_snapshot_far_version(const struct vlff_map_snapshot *s) {
  return s && s->meta.version ? s->meta.far_version : 0;
}

API const char *vlff_map_snapshot_prompt(const struct vlff_map_snapshot *s, uint16_t label) {
  if (!s || label >= s->meta.prompt_count)
    return NULL;
  return s->meta.prompts[label];
}

/* ------------------------------------------------------- the writer's status */

static struct status_block *status_block(const struct vlff_map *m) {
  return (struct status_block *)(m->seg.base + STATUS_OFFSET);
}

static bool text_fits(const char *s, size_t cap) { return memchr(s, 0, cap) != NULL; }

static void status_write(struct status_block *b, const struct vlff_map_status *st) {
  /* A writer that died mid-write left the word odd; continue from there. */
  uint64_t odd = atomic_load_explicit(&b->seq, memory_order_relaxed) | 1;
  atomic_store_explicit(&b->seq, odd, memory_order_relaxed);
  shm_fence_release();
  shm_racy_copy(&b->st, st, sizeof *st);
  atomic_store_explicit(&b->seq, odd + 1, memory_order_release);
}

/* A taken-over segment still holds its dead writer's last status: readers would
 * take it for the new writer's (a restarted node "at iteration 5000" before it
 * has trained once). It reads as no status until the new writer sets one; the
 * update count goes on. */
static void status_withdraw(struct vlff_map *m) {
  struct status_block *b = status_block(m);
  struct vlff_map_status none = {0};
  shm_racy_copy(&none.updates, &b->st.updates, sizeof none.updates);
  status_write(b, &none);
}

API int vlff_map_set_status(struct vlff_map *m, const struct vlff_map_status *st) {
  if (!m || !m->writer || !st) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_set_status: not a writer handle or no status");
    return -1;
  }
  if (writer_retry(m) < 0)
    return -1;
  if (st->reason_count > VLFF_SHM_MAX_REASONS) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: status refused: %u reasons, at most %d", VLFF_Q(m->seg.name),
            st->reason_count,
            VLFF_SHM_MAX_REASONS);
    return -1;
  }
  if (!text_fits(st->state_name, sizeof st->state_name)) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: status refused: state name longer than %d bytes", VLFF_Q(m->seg.name),
            VLFF_SHM_STATE_LEN - 1);
    return -1;
  }
  for (uint32_t i = 0; i < st->reason_count; i++)
    if (!text_fits(st->reason[i].name, sizeof st->reason[i].name) || !st->reason[i].name[0]) {
      shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: status refused: reason %u is unnamed or its name is longer than %d bytes",
              VLFF_Q(m->seg.name), i, VLFF_SHM_REASON_LEN - 1);
      return -1;
    }
  if (shm_seg_check(&m->seg, true) < 0)
    return writer_replace(m, "; this status was not set");
  struct status_block *b = status_block(m);
  struct vlff_map_status out;
  memcpy(&out, st, sizeof out);
  /* Unused entries and string tails are zeroed: readers see nothing stale. */
  memset(&out.reason[out.reason_count], 0, (VLFF_SHM_MAX_REASONS - out.reason_count) * sizeof out.reason[0]);
  out.pad = 0;
  uint64_t prev;
  shm_racy_copy(&prev, &b->st.updates, sizeof prev);
  out.updates = prev + 1;
  out.t_ns = shm_now();
  status_write(b, &out);
  if (shm_seg_check(&m->seg, false) < 0)
    return writer_replace(m, "; this status was not set");
  return 0;
}

API int vlff_map_get_status(struct vlff_map *m, struct vlff_map_status *out) {
  if (!m || !out) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_map_get_status: NULL argument");
    return -1;
  }
  for (int i = 0; i < READ_RETRIES; i++) {
    if (abandoned(m) == 1)
      return -1;
    struct status_block *b = status_block(m);
    uint64_t s1 = atomic_load_explicit(&b->seq, memory_order_acquire);
    if (s1 & 1)
      continue;
    shm_racy_copy(out, &b->st, sizeof *out);
    shm_fence_acquire();
    int a = abandoned(m);
    if (a == 1)
      return -1;
    if (a == 2)
      continue;
    if (atomic_load_explicit(&b->seq, memory_order_relaxed) != s1)
      continue;
    if (s1 == 0 || out->t_ns == 0) {
      memset(out, 0, sizeof *out);
      shm_err(VLFF_SHM_OK, ENOENT, "%s: the writer has set no status yet", VLFF_Q(m->seg.name));
      return -1;
    }
    if (out->reason_count > VLFF_SHM_MAX_REASONS) {
      shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "%s: status block holds %u reasons, at most %d", VLFF_Q(m->seg.name),
              out->reason_count, VLFF_SHM_MAX_REASONS);
      return -1;
    }
    out->state_name[VLFF_SHM_STATE_LEN - 1] = 0;
    for (uint32_t r = 0; r < VLFF_SHM_MAX_REASONS; r++)
      out->reason[r].name[VLFF_SHM_REASON_LEN - 1] = 0;
    return 0;
  }
  shm_err(VLFF_SHM_OK, EAGAIN, "%s: writer kept overwriting its status for %d reads", VLFF_Q(m->seg.name),
          READ_RETRIES);
  return -1;
}
