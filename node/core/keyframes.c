/*
 * Why redundancy-based eviction: the reference evicts at random, which on a
 * robot that lingers in one room slowly forgets the rooms it left. Dropping
 * the view nearest to another view loses the least coverage per byte.
 */
#include "keyframes.h"

#include "files.h"
#include "mem.h"
#include "select.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

struct kf {
  long long id, t_ns;
  size_t bytes;          /* what it costs the budget (vlff_kfstore_cost) */
  size_t fdepth, ffeat, len; /* mem: depth, features, rgb; len in all */
  struct vlff_view view;
  void *mem; /* one block holding depth, features, rgb */
};

/* A keyframe in the page file: its block (as struct kf's mem) at off. */
struct paged {
  long long id, t_ns;
  size_t bytes, fdepth, ffeat, len;
  off_t off;
  struct vlff_view view; /* its pointers NULL: the block is in the file */
};

/* Two views nearer than this (vlff_pose_distance: 5 cm, or 0.1 rad) see the
 * same: an evicted view this near one kept is not paged, and a paged view
 * this near a newly evicted one is overwritten by it. */
#define KF_SAME_PLACE 0.05

/* A free stretch of the page file. */
struct hole {
  off_t off;
  size_t len;
};

struct vlff_kfstore {
  size_t budget, bytes;
  int max_count, protect, count;
  long long evicted, retired;
  struct kf *kfs;              /* oldest first */
  struct vlff_view *views;     /* rebuilt by views() */
  float *weights;
  /* paging */
  int fd;
  char *path;
  size_t page_max, page_top, page_used;
  struct paged *pg;
  int npg, pgcap;
  struct hole *holes;
  int nholes, holecap;
  long long paged_out, paged_in, dropped;
  char page_err[192];
};

/* The block's three parts: depth and features first keeps them 4- and
 * 2-byte aligned. */
static void block_sizes(const struct vlff_view *v, int feature_dim, size_t *fdepth, size_t *ffeat, size_t *frgb) {
  size_t px = (size_t)v->width * v->height;
  *frgb = px * 3;
  *fdepth = v->depth ? px * sizeof(float) : 0;
  *ffeat = v->features ? (size_t)v->feat_width * v->feat_height * feature_dim * sizeof(uint16_t) : 0;
}

/* The view's pointers into mem, laid out as block_sizes says. */
static void point_into(struct vlff_view *v, char *mem, size_t fdepth, size_t ffeat) {
  v->depth = fdepth ? (const float *)mem : NULL;
  v->features = ffeat ? (const uint16_t *)(mem + fdepth) : NULL;
  v->rgb = (const uint8_t *)(mem + fdepth + ffeat);
}

size_t vlff_kfstore_cost(int w, int h, int fw, int fh, int d, int has_depth) {
  size_t px = (size_t)w * h;
  return sizeof(struct kf) + px * 3 + (has_depth ? px * sizeof(float) : 0) +
         (size_t)fw * fh * d * sizeof(uint16_t);
}

struct vlff_kfstore *vlff_kfstore_create(size_t budget_bytes, int max_count, int protect) {
  if (max_count < 1 || protect < 0) {
    errno = EINVAL;
    return NULL;
  }
  struct vlff_kfstore *s = calloc(1, sizeof *s);
  if (!s) return NULL;
  s->budget = budget_bytes;
  s->fd = -1;
  s->max_count = max_count;
  s->protect = protect;
  s->kfs = calloc((size_t)max_count + 1, sizeof *s->kfs);
  s->views = calloc((size_t)max_count + 1, sizeof *s->views);
  s->weights = calloc((size_t)max_count + 1, sizeof *s->weights);
  if (!s->kfs || !s->views || !s->weights) {
    vlff_kfstore_destroy(s);
    return NULL;
  }
  return s;
}

void vlff_kfstore_destroy(struct vlff_kfstore *s) {
  if (!s) return;
  for (int i = 0; i < s->count; i++) free(s->kfs[i].mem);
  if (s->fd >= 0) {
    /* The file goes with the store, unless a newer store's file has its
     * name by now (a mapping reset makes the new store first). */
    struct stat a, b;
    if (fstat(s->fd, &a) == 0 && stat(s->path, &b) == 0 && a.st_dev == b.st_dev && a.st_ino == b.st_ino)
      unlink(s->path);
    close(s->fd);
  }
  VLFF_FREE_ALL(s->kfs, s->views, s->weights, s->path, s->pg, s->holes, s);
}

double vlff_pose_distance(const double a[16], const double b[16]) {
  double dt = 0;
  for (int i = 0; i < 3; i++) {
    double d = a[i * 4 + 3] - b[i * 4 + 3];
    dt += d * d;
  }
  return sqrt(dt) + 0.5 * vlff_pose_angle(a, b);
}

/* Room for len bytes in the page file: a hole (first fit, the rest kept)
 * or the end; -1 when full. */
static off_t page_place(struct vlff_kfstore *s, size_t len) {
  for (int i = 0; i < s->nholes; i++)
    if (s->holes[i].len >= len) {
      off_t off = s->holes[i].off;
      s->holes[i].off += (off_t)len;
      s->holes[i].len -= len;
      if (!s->holes[i].len) s->holes[i] = s->holes[--s->nholes];
      return off;
    }
  if (s->page_top + len > s->page_max) return -1;
  off_t off = (off_t)s->page_top;
  s->page_top += len;
  return off;
}

static void page_free(struct vlff_kfstore *s, off_t off, size_t len) {
  if (s->nholes == s->holecap) {
    int cap = s->holecap ? 2 * s->holecap : 16;
    struct hole *h = realloc(s->holes, (size_t)cap * sizeof *h);
    if (!h) return; /* the stretch stays unused: only space is lost */
    s->holes = h, s->holecap = cap;
  }
  s->holes[s->nholes++] = (struct hole){off, len};
}

/* Keyframe k to the page file; false (k dropped) without one, when full,
 * or when the write fails. A paged view of the same place (within
 * KF_SAME_PLACE) is overwritten by it: a robot that patrols a loop would
 * otherwise fill the file with copies of the same views. */
static bool page_out(struct vlff_kfstore *s, const struct kf *k) {
  if (s->fd < 0) return false;
  const size_t len = k->len;
  int same = -1;
  for (int i = 0; i < s->npg && same < 0; i++)
    if (s->pg[i].len == len && vlff_pose_distance(s->pg[i].view.c2w, k->view.c2w) < KF_SAME_PLACE) same = i;
  if (s->npg == s->pgcap) {
    int cap = s->pgcap ? 2 * s->pgcap : 64;
    struct paged *p = realloc(s->pg, (size_t)cap * sizeof *p);
    if (!p) {
      snprintf(s->page_err, sizeof s->page_err, "%s: no memory for its index", s->path);
      return false;
    }
    s->pg = p, s->pgcap = cap;
  }
  off_t off = same >= 0 ? s->pg[same].off : page_place(s, len);
  if (off < 0) {
    snprintf(s->page_err, sizeof s->page_err, "%s is full (%zu MiB)", s->path, s->page_max >> 20);
    return false;
  }
  if (vlff_write_at(s->fd, (uint64_t)off, k->mem, len)) {
    snprintf(s->page_err, sizeof s->page_err, "%s: %s", s->path, strerror(errno));
    if (same >= 0) { /* the record it was overwriting is lost too */
      s->page_used -= len;
      s->pg[same] = s->pg[--s->npg];
      s->dropped++;
    }
    page_free(s, off, len);
    return false;
  }
  if (same < 0) s->page_used += len;
  struct paged *p = &s->pg[same >= 0 ? same : s->npg++];
  p->id = k->id, p->t_ns = k->t_ns, p->bytes = k->bytes, p->off = off;
  p->fdepth = k->fdepth, p->ffeat = k->ffeat, p->len = len;
  p->view = k->view;
  p->view.rgb = NULL, p->view.depth = NULL, p->view.features = NULL;
  s->paged_out++;
  return true;
}

/* The keyframe that would be evicted next and its distance to its nearest
 * other keyframe (the oldest, at INFINITY, when every one is protected).
 * As if keyframe skip (-1: none) were gone and a view at extra (NULL: none)
 * were there: what page_in asks of a swap. */
static int victim_of(const struct vlff_kfstore *s, int skip, const double *extra, double *nn_out) {
  int candidates = s->count - s->protect;
  int victim = 0;
  double best = INFINITY;
  for (int i = 0; i < candidates; i++) {
    if (i == skip) continue;
    double nn = extra ? vlff_pose_distance(s->kfs[i].view.c2w, extra) : INFINITY;
    for (int j = 0; j < s->count; j++)
      if (j != i && j != skip) nn = fmin(nn, vlff_pose_distance(s->kfs[i].view.c2w, s->kfs[j].view.c2w));
    if (nn < best) { /* strict: on ties the older view goes */
      best = nn;
      victim = i;
    }
  }
  if (nn_out) *nn_out = best;
  return victim;
}

/* Evicts the most redundant keyframe for one coming at incoming (NULL: a
 * paged one coming back). */
static void evict_one(struct vlff_kfstore *s, const double *incoming) {
  double nn;
  int victim = victim_of(s, -1, NULL, &nn);
  if (incoming) nn = fmin(nn, vlff_pose_distance(s->kfs[victim].view.c2w, incoming));
  /* A view of the same place as one kept carries nothing the store lacks. */
  if (!(nn < KF_SAME_PLACE) && !page_out(s, &s->kfs[victim])) s->dropped++;
  s->bytes -= s->kfs[victim].bytes;
  free(s->kfs[victim].mem);
  memmove(&s->kfs[victim], &s->kfs[victim + 1], (size_t)(s->count - victim - 1) * sizeof *s->kfs);
  s->count--;
  s->evicted++;
}

int vlff_kfstore_page_to(struct vlff_kfstore *s, const char *path, size_t max_bytes, char *err, size_t errlen) {
  /* A new file, never another's (a killed run's, or a store still open). */
  (void)unlink(path);
  int fd = open(path, O_RDWR | O_CREAT | O_EXCL | O_CLOEXEC | O_NOFOLLOW, 0600);
  if (fd < 0) {
    if (err && errlen) snprintf(err, errlen, "keyframe page file %s: %s", path, strerror(errno));
    return -1;
  }
  char *p = strdup(path);
  if (!p) {
    close(fd);
    if (err && errlen) snprintf(err, errlen, "keyframe page file %s: no memory", path);
    return -1;
  }
  if (s->fd >= 0) close(s->fd);
  free(s->path);
  s->fd = fd, s->path = p, s->page_max = max_bytes;
  s->page_top = s->page_used = 0;
  s->npg = s->nholes = 0;
  return 0;
}

int vlff_kfstore_page_in(struct vlff_kfstore *s, const double c2w[16], double radius) {
  int best = -1;
  double bd = radius;
  for (int i = 0; i < s->npg; i++) {
    double d = vlff_pose_distance(s->pg[i].view.c2w, c2w);
    if (d <= bd) bd = d, best = i;
  }
  if (best < 0) return 0;
  struct paged p = s->pg[best];
  /* It comes back only when, the victim gone for it, it would not be the
   * next to go: its nearest view then is farther than every other
   * candidate's (strictly: as the oldest it would lose a tie). */
  if (s->count >= s->max_count || s->bytes + p.bytes > s->budget) {
    const int victim = victim_of(s, -1, NULL, NULL);
    double nn = INFINITY, next;
    for (int j = 0; j < s->count; j++)
      if (j != victim) nn = fmin(nn, vlff_pose_distance(p.view.c2w, s->kfs[j].view.c2w));
    victim_of(s, victim, p.view.c2w, &next);
    if (!(nn > next)) return 0;
  }
  char *mem = malloc(p.len);
  if (!mem) return 0; /* it stays paged */
  s->pg[best] = s->pg[--s->npg];
  s->page_used -= p.len;
  const bool read = vlff_read_at(s->fd, (uint64_t)p.off, mem, p.len) == 0;
  if (!read) /* vlff_read_at says EIO where the file ends first */
    snprintf(s->page_err, sizeof s->page_err, "%s: %s", s->path,
             errno == EIO ? "short read, or an I/O error" : strerror(errno));
  page_free(s, p.off, p.len);
  if (!read) {
    free(mem);
    s->dropped++;
    return -1;
  }
  while (s->count > 0 && (s->count >= s->max_count || s->bytes + p.bytes > s->budget)) evict_one(s, NULL);
  memmove(&s->kfs[1], &s->kfs[0], (size_t)s->count * sizeof *s->kfs);
  struct kf *k = &s->kfs[0];
  s->count++;
  k->id = p.id, k->t_ns = p.t_ns, k->bytes = p.bytes, k->mem = mem;
  k->fdepth = p.fdepth, k->ffeat = p.ffeat, k->len = p.len;
  k->view = p.view;
  point_into(&k->view, mem, p.fdepth, p.ffeat);
  s->bytes += p.bytes;
  s->paged_in++;
  return 1;
}

long long vlff_kfstore_paged(const struct vlff_kfstore *s) { return s->npg; }
long long vlff_kfstore_paged_out(const struct vlff_kfstore *s) { return s->paged_out; }
long long vlff_kfstore_paged_in(const struct vlff_kfstore *s) { return s->paged_in; }
long long vlff_kfstore_dropped(const struct vlff_kfstore *s) { return s->dropped; }
size_t vlff_kfstore_page_bytes(const struct vlff_kfstore *s) { return s->page_used; }
size_t vlff_kfstore_page_limit(const struct vlff_kfstore *s) { return s->page_max; }
const char *vlff_kfstore_page_error(const struct vlff_kfstore *s) { return s->page_err; }

int vlff_kfstore_add(struct vlff_kfstore *s, const struct vlff_keyframe_in *in) {
  const struct vlff_view *v = &in->view;
  int fw = v->features ? v->feat_width : 0, fh = v->features ? v->feat_height : 0;
  size_t cost = vlff_kfstore_cost(v->width, v->height, fw, fh, in->feature_dim, v->depth != NULL);
  if (cost > s->budget || v->width <= 0 || v->height <= 0 || !v->rgb) {
    errno = EINVAL;
    return -1;
  }
  size_t fdepth, ffeat, frgb;
  block_sizes(v, in->feature_dim, &fdepth, &ffeat, &frgb);
  char *mem = malloc(fdepth + ffeat + frgb);
  if (!mem) return -1;
  while (s->count > 0 && (s->count >= s->max_count || s->bytes + cost > s->budget)) evict_one(s, v->c2w);
  struct kf *k = &s->kfs[s->count++];
  k->id = in->id;
  k->t_ns = in->t_ns;
  k->bytes = cost;
  k->mem = mem;
  k->fdepth = fdepth, k->ffeat = ffeat, k->len = fdepth + ffeat + frgb;
  k->view = *v;
  if (fdepth) memcpy(mem, v->depth, fdepth);
  if (ffeat) memcpy(mem + fdepth, v->features, ffeat);
  memcpy(mem + fdepth + ffeat, v->rgb, frgb);
  point_into(&k->view, mem, fdepth, ffeat);
  s->bytes += cost;
  return 0;
}

int vlff_kfstore_retire(struct vlff_kfstore *s, bool (*contradicted)(void *ctx, const struct vlff_view *v), void *ctx) {
  int kept = 0, dropped = 0;
  for (int i = 0; i < s->count; i++) {
    if (i < s->count - 1 && contradicted(ctx, &s->kfs[i].view)) {
      s->bytes -= s->kfs[i].bytes;
      free(s->kfs[i].mem);
      dropped++;
      continue;
    }
    s->kfs[kept++] = s->kfs[i];
  }
  s->count = kept;
  s->retired += dropped;
  return dropped;
}

long long vlff_kfstore_retired(const struct vlff_kfstore *s) { return s->retired; }

int vlff_kfstore_count(const struct vlff_kfstore *s) { return s->count; }
size_t vlff_kfstore_bytes(const struct vlff_kfstore *s) { return s->bytes; }
long long vlff_kfstore_evicted(const struct vlff_kfstore *s) { return s->evicted; }
long long vlff_kfstore_id(const struct vlff_kfstore *s, int i) { return s->kfs[i].id; }

int vlff_kfstore_views(struct vlff_kfstore *s, int recent, const struct vlff_view **views, const float **weights) {
  int n = s->count;
  if (recent > n) recent = n;
  if (recent < 1) recent = 1;
  int old = n - recent;
  for (int i = 0; i < n; i++) {
    s->views[i] = s->kfs[i].view;
    /* Half the rays to the newest views, half spread over the older ones. */
    if (old == 0)
      s->weights[i] = 1.0f / (float)n;
    else
      s->weights[i] = i >= old ? 0.5f / (float)recent : 0.5f / (float)old;
  }
  *views = s->views;
  *weights = s->weights;
  return n;
}
