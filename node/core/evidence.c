/*
 * Per-voxel evidence (evidence.h).
 */
#include "evidence.h"

#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <math.h>
#include <stdbool.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "best.h"
#include "files.h"
#include "hash.h"
#include "lattice.h"
#include "log.h"
#include "select.h"
#include "mem.h"
#include "vlff/escape.h"

#define MAX_VIEWS 255
/* A full budget gives up this share of its slots at a time ... */
#define RECLAIM_DIV 8
/* ... never a voxel that one of the last this many views touched: a newly
 * seen surface has few samples yet and would be given up before the views
 * that are looking at it could add theirs. */
#define RECENT_VIEWS 8
/* The running mean weighs a new sample at least 1/RECENT_SAMPLES: a few
 * views' worth (a view adds several feature pixels to a voxel), so what the
 * camera sees again replaces what it saw before rather than being averaged
 * into a lifetime. */
#define RECENT_SAMPLES 64

struct vlff_evidence {
  double origin[3], voxel;
  double origin0[3]; /* the first grid's origin: origin = origin0 + k0 x voxel (growths, refits) */
  long k0[3];
  uint32_t dims[3];
  size_t nvox;
  int D;
  int32_t *slot;    /* [nvox]: -1 none */
  uint16_t *mean;   /* [cap][D] float16 */
  uint8_t *views;   /* [cap] samples averaged, saturating at MAX_VIEWS */
  uint32_t *owner;  /* [cap] the voxel a slot holds */
  uint32_t *seen;   /* [cap] the add (view) that last touched it */
  uint32_t nadd;    /* views added, modulo 2^32 */
  bool reclaimed;   /* this add has already tried to free slots */
  float *cos;       /* [cap][max_k] cosines with the prompts ... */
  uint8_t *dirty;   /* [cap] ... stale since the slot's evidence changed */
  uint64_t stamp;   /* ... or since the prompts did */
  int stamp_k;
  int max_k;        /* prompts a slot caches cosines for */
  size_t used, cap;
  size_t cap_max;   /* the slots the budget holds (cap: no more than the grid has voxels) */
  size_t max_vox;   /* voxels a growth may reach (vlff_evidence_grow; 0: the grid is fixed) */
  long long overflow, evicted;
  float *tmp;       /* [3 D]: a feature, a mean, a slot's cosines' scratch */
  float blend[VLFF_FIELD_MAX_PROMPTS]; /* one point's blended cosines (label) */
  /* The census of lost classes (vlff_evidence_census_begin / _end): per
   * prompt, points of the current pass the fitted field and the evidence
   * each label so, and the classes the last complete pass found lost, valid
   * for prompts of lost_stamp. */
  bool census, census_stamped;
  uint64_t census_stamp, lost_stamp;
  int census_k, lost_k; /* the prompt count of each */
  unsigned long long n_field[VLFF_FIELD_MAX_PROMPTS], n_ev[VLFF_FIELD_MAX_PROMPTS];
  bool lost[VLFF_FIELD_MAX_PROMPTS];
  int nlost;
  /* Paging (vlff_evidence_page_to): voxel v's evidence in record r of the
   * page file when slot[v] == -2 - r. */
  char *page_path;      /* NULL: evidence given up is dropped */
  int page_fd;          /* opened at the first page-out: -1 before */
  char page_err[320];   /* the first write or read that failed */
  size_t page_cap;      /* records the file may hold */
  size_t page_top;      /* records written so far (the file's length / record) */
  size_t page_alloc;    /* records the arrays below hold */
  size_t paged;         /* live records */
  uint32_t *powner;     /* [page_alloc] the voxel a record holds, NO_VOXEL: free */
  int8_t *pcos;         /* [page_alloc][max_k] its cosines with the prompts E x 127 */
  int pk;               /* the prompts in E */
  bool pvalid;          /* false: E and the cosines not made yet (for the prompts of stamp) */
  uint32_t *pfree;      /* [page_alloc] free records below page_top */
  size_t nfree;
  float *E;             /* [pk][D] the prompts of the last label call: a record's cosines when paged */
  uint8_t *pbuf;        /* [record] one record's bytes */
  float pc[VLFF_FIELD_MAX_PROMPTS]; /* one record's cosines (label) */
  long long paged_out, paged_in, page_errors;
  /* Paged records of voxels a slide left beyond the grid (evidence_slide),
   * by lattice voxel (origin0 + k x voxel): they come back when the grid
   * covers them again. */
  struct far_rec {
    long k[3];
    uint32_t r;
  } *far;
  size_t nfar, far_cap;
  uint64_t far_gen; /* vlff_evidence_far_generation */
  long long slides;
};

#define NO_VOXEL UINT32_MAX
#define FAR_VOXEL (UINT32_MAX - 1) /* powner of a record beyond the grid (e->far) */
/* slot[] values: >= 0 a slot, -1 no evidence, <= -2 a page record. */
static bool is_paged(int32_t s) { return s <= -2; }
static size_t record_of(int32_t s) { return (size_t)(-2 - (long)s); }

double vlff_map_grid_plan(const double lo[3], const double hi[3], double voxel, size_t max_voxels, uint32_t dims[3]) {
  for (;;) {
    size_t n = 1;
    for (int i = 0; i < 3; i++) {
      double c = ceil((hi[i] - lo[i]) / voxel - 1e-9);
      dims[i] = c < 1 ? 1 : c > UINT32_MAX ? UINT32_MAX : (uint32_t)c;
      n = n > SIZE_MAX / dims[i] ? SIZE_MAX : n * dims[i];
    }
    if (n <= max_voxels) return voxel;
    voxel *= 1.1;
  }
}

void vlff_evidence_destroy(struct vlff_evidence *e) {
  if (!e) return;
  if (e->page_fd >= 0) {
    close(e->page_fd);
    unlink(e->page_path); /* its records index this run's table only */
  }
  free(e->far);
  VLFF_FREE_ALL(e->page_path, e->slot, e->mean, e->views, e->owner, e->seen, e->cos, e->dirty, e->tmp, e->powner, e->pcos, e->pfree,
                e->E, e->pbuf, e);
}

struct vlff_evidence *vlff_evidence_create(const double origin[3], const uint32_t dims[3], double voxel, int D,
                                           int max_k, size_t max_bytes, char *err, size_t errlen) {
  if (D < 1 || max_k < 1 || max_k > VLFF_FIELD_MAX_PROMPTS || !(voxel > 0) || !isfinite(voxel) || !dims[0] ||
      !dims[1] || !dims[2]) {
    vlff_errf(err, errlen, "evidence: bad grid, feature size or prompt count");
    return NULL;
  }
  struct vlff_evidence *e = calloc(1, sizeof *e);
  if (!e) {
    vlff_errf(err, errlen, "evidence: out of memory");
    return NULL;
  }
  memcpy(e->origin, origin, sizeof e->origin);
  memcpy(e->origin0, origin, sizeof e->origin0);
  memcpy(e->dims, dims, sizeof e->dims);
  e->voxel = voxel;
  e->D = D;
  e->nvox = (size_t)dims[0] * dims[1] * dims[2];
  if (e->nvox > UINT32_MAX) {
    vlff_errf(err, errlen, "evidence: a grid of %zu voxels is over 2^32", e->nvox);
    free(e);
    return NULL;
  }
  e->max_k = max_k;
  e->page_fd = -1;
  size_t per = (size_t)D * sizeof(uint16_t) + (size_t)max_k * sizeof(float) + 2 + 2 * sizeof(uint32_t);
  e->cap = max_bytes / per;
  if (e->cap < 1) e->cap = 1;
  if (e->cap > INT32_MAX) e->cap = INT32_MAX;
  e->cap_max = e->cap;
  if (e->cap > e->nvox) e->cap = e->nvox;
  e->slot = malloc(e->nvox * sizeof *e->slot);
  e->mean = malloc(e->cap * (size_t)D * sizeof *e->mean);
  e->views = calloc(e->cap, 1);
  e->owner = malloc(e->cap * sizeof *e->owner);
  e->seen = malloc(e->cap * sizeof *e->seen);
  e->cos = malloc(e->cap * (size_t)max_k * sizeof *e->cos);
  e->dirty = calloc(e->cap, 1);
  e->tmp = malloc(3 * (size_t)D * sizeof *e->tmp);
  if (!e->slot || !e->mean || !e->views || !e->owner || !e->seen || !e->cos || !e->dirty || !e->tmp) {
    vlff_errf(err, errlen, "evidence: out of memory for %zu voxels of %d features", e->cap, D);
    vlff_evidence_destroy(e);
    return NULL;
  }
  vlff_evidence_reset(e);
  return e;
}

struct vlff_evidence *vlff_evidence_for(const struct vlff_cfg_publish *pub, const struct vlff_cfg_field *field,
                                        int max_k, char *err, size_t errlen) {
  size_t budget = (size_t)pub->evidence_max_mb << 20;
  uint32_t dims[3];
  double voxel = vlff_map_grid_plan(field->scene_min, field->scene_max, pub->evidence_voxel_m,
                                    budget / 4 / sizeof(int32_t), dims);
  struct vlff_evidence *e = vlff_evidence_create(field->scene_min, dims, voxel, field->feature_dim, max_k,
                              budget - (size_t)dims[0] * dims[1] * dims[2] * sizeof(int32_t), err, errlen);
  /* A growing box's evidence keeps its voxel; its index may grow to that
   * quarter of the budget. */
  if (e && field->grow) e->max_vox = budget / 4 / sizeof(int32_t);
  return e;
}

/* More slots, up to cap_max, for a grid that grew (views and dirty flags
 * of the new slots zero, as at create). */
static int more_slots(struct vlff_evidence *e, size_t cap) {
  const size_t D = (size_t)e->D, K = (size_t)e->max_k;
  uint16_t *mean = realloc(e->mean, cap * D * sizeof *mean);
  if (mean) e->mean = mean;
  uint8_t *views = realloc(e->views, cap);
  if (views) e->views = views;
  uint32_t *owner = realloc(e->owner, cap * sizeof *owner);
  if (owner) e->owner = owner;
  uint32_t *seen = realloc(e->seen, cap * sizeof *seen);
  if (seen) e->seen = seen;
  float *cs = realloc(e->cos, cap * K * sizeof *cs);
  if (cs) e->cos = cs;
  uint8_t *dirty = realloc(e->dirty, cap);
  if (dirty) e->dirty = dirty;
  /* On failure the old cap stands, its arrays at least as large. */
  if (!mean || !views || !owner || !seen || !cs || !dirty) return -1;
  memset(e->views + e->cap, 0, cap - e->cap);
  memset(e->dirty + e->cap, 0, cap - e->cap);
  e->cap = cap;
  return 0;
}

static void far_return(struct vlff_evidence *e);
static void page_release(struct vlff_evidence *e, size_t r);

/* The grid shifted by sh voxels into nd (on the same lattice): every slot
 * and page record follows its voxel. */
static int relayout(struct vlff_evidence *e, const int32_t sh[3], const uint32_t nd[3], char *err, size_t errlen) {
  const size_t n = vlff_lattice_cells(nd);
  if (n > e->max_vox || n > UINT32_MAX)
    return vlff_errf(err, errlen,
                     "evidence: growing to %.1f x %.1f x %.1f m needs %zu voxels, more than a quarter of "
                     "publish.evidence_max_mb indexes (%zu)",
                     nd[0] * e->voxel, nd[1] * e->voxel, nd[2] * e->voxel, n, e->max_vox),
           -1;
  /* A refitted grid drops only voxels that hold nothing. */
  for (size_t v = 0; v < e->nvox; v++)
    if (e->slot[v] != -1 && vlff_lattice_index(v, e->dims, sh, nd) < 0)
      return vlff_errf(err, errlen, "evidence: the new grid would drop voxel %zu's evidence", v), -1;
  int32_t *slot = malloc(n * sizeof *slot);
  size_t cap = e->cap_max < n ? e->cap_max : n;
  if (!slot || (cap > e->cap && more_slots(e, cap))) {
    free(slot);
    return vlff_errf(err, errlen, "evidence: out of memory growing to %zu voxels", n), -1;
  }
  memset(slot, 0xff, n * sizeof *slot);
  for (size_t v = 0; v < e->nvox; v++) {
    int32_t s = e->slot[v];
    if (s == -1) continue;
    size_t nv = (size_t)vlff_lattice_index(v, e->dims, sh, nd);
    slot[nv] = s;
    if (s >= 0)
      e->owner[s] = (uint32_t)nv;
    else
      e->powner[record_of(s)] = (uint32_t)nv;
  }
  free(e->slot);
  e->slot = slot;
  for (int a = 0; a < 3; a++) {
    e->k0[a] -= (long)sh[a];
    e->origin[a] = e->origin0[a] + (double)e->k0[a] * e->voxel; /* the same k0, the same bits */
    e->dims[a] = nd[a];
  }
  e->nvox = n;
  far_return(e);
  return 0;
}

static int page_write(struct vlff_evidence *e, uint32_t vi, uint8_t count, const uint16_t *mean, const float *cos);
static const float *slot_cosines(struct vlff_evidence *e, int32_t s, const float *E, int K);
static void pack_slots(struct vlff_evidence *e);

/* The grid at its index's cap moves on by sh into nd (vlff_lattice_window):
 * each voxel it leaves pages its evidence out (kept by lattice voxel in
 * e->far; without a page file, or with a full one, it is given up:
 * evicted), then the far records the new grid covers come back to their
 * voxels. */
static int evidence_slide(struct vlff_evidence *e, const int32_t sh[3], const uint32_t nd[3], char *err,
                          size_t errlen) {
  /* Room for every record first: nothing changes unless all of it can. */
  size_t leaving = 0;
  for (size_t v = 0; v < e->nvox; v++) leaving += e->slot[v] != -1 && vlff_lattice_index(v, e->dims, sh, nd) < 0;
  if (e->nfar + leaving > e->far_cap) {
    size_t c = e->nfar + leaving + 1024;
    struct far_rec *nf = realloc(e->far, c * sizeof *nf);
    if (!nf) return vlff_errf(err, errlen, "evidence: out of memory sliding the grid"), -1;
    e->far = nf, e->far_cap = c;
  }
  for (size_t v = 0; v < e->nvox; v++) {
    const int32_t s = e->slot[v];
    if (s == -1 || vlff_lattice_index(v, e->dims, sh, nd) >= 0) continue;
    long r;
    if (s >= 0) {
      const float *cs = e->page_path && e->pvalid ? slot_cosines(e, s, e->E, e->pk) : NULL;
      r = e->page_path ? page_write(e, FAR_VOXEL, e->views[s], e->mean + (size_t)s * e->D, cs) : -1;
      e->evicted += r < 0;
      e->views[s] = 0; /* freed: packed below */
    } else {
      r = (long)record_of(s);
    }
    e->slot[v] = -1;
    if (r < 0) continue;
    e->powner[r] = FAR_VOXEL;
    struct far_rec *f = &e->far[e->nfar++];
    long c[3];
    vlff_lattice_xyz(v, e->dims, c);
    for (int a = 0; a < 3; a++) f->k[a] = e->k0[a] + c[a];
    f->r = (uint32_t)r;
  }
  pack_slots(e);
  e->far_gen++;
  if (relayout(e, sh, nd, err, errlen)) {
    far_return(e); /* the grid as it was: its voxels' records back */
    return -1;
  }
  e->slides++;
  return 0;
}

/* The far records the grid covers now back to their voxels (after any
 * relayout: a growth or refit may reach them too). */
static void far_return(struct vlff_evidence *e) {
  for (size_t j = 0; j < e->nfar;) {
    long i = 0, mul = 1;
    bool in = true;
    for (int a = 0; a < 3; a++) {
      const long c = e->far[j].k[a] - e->k0[a];
      in = in && c >= 0 && c < (long)e->dims[a];
      i += c * mul, mul *= (long)e->dims[a];
    }
    if (!in) {
      j++;
      continue;
    }
    if (e->slot[i] == -1) {
      e->slot[i] = -2 - (int32_t)e->far[j].r;
      e->powner[e->far[j].r] = (uint32_t)i;
    } else {
      page_release(e, e->far[j].r); /* the voxel has evidence of its own again: the newer stays */
    }
    e->far[j] = e->far[--e->nfar];
    e->far_gen++;
  }
}

int vlff_evidence_grow(struct vlff_evidence *e, const double want_lo[3], const double want_hi[3], const double lo[3],
                       const double hi[3], double limit, char *err, size_t errlen) {
  double ulo[3], uhi[3]; /* the wanted box holds the needed one */
  vlff_box_union(want_lo, want_hi, lo, hi, ulo, uhi);
  const double *blo[2] = {ulo, lo}, *bhi[2] = {uhi, hi};
  int32_t sh[3];
  uint32_t nd[3];
  long klo[3] = {LONG_MAX, LONG_MAX, LONG_MAX}, khi[3] = {LONG_MIN, LONG_MIN, LONG_MIN};
  bool scanned = false;
  for (int t = 0; t < 2; t++) {
    int rc = vlff_lattice_cover(e->origin, VLFF_LATTICE_CUBE(e->voxel), e->dims, blo[t], bhi[t], limit, sh, nd);
    if (rc < 0) return vlff_errf(err, errlen, "evidence: growth to an empty or non-finite box"), -1;
    if (rc == 0) return 0;
    if (!e->max_vox) return vlff_errf(err, errlen, "evidence: the grid is fixed (field.grow is off)"), -1;
    if (vlff_lattice_cells(nd) > e->max_vox) {
      /* Past the index's budget: refit the grid to the voxels that hold
       * evidence (in memory or paged) and the box, dropping the empty
       * margins earlier growths left (vlff_lattice_fit). */
      if (!scanned)
        for (size_t v = 0; v < e->nvox; v++)
          if (e->slot[v] != -1) vlff_lattice_extend(klo, khi, v, e->dims);
      scanned = true;
      int fit = vlff_lattice_fit(e->origin, VLFF_LATTICE_CUBE(e->voxel), e->dims, klo, khi, blo[t], bhi[t], limit, sh, nd);
      if (fit == 0) return 0;
      if (fit < 0) {
        vlff_errf(err, errlen, "evidence: refitting to a %s box: more than 2^31 voxels on an axis", t ? "needed" : "wanted");
        continue;
      }
    }
    if (!relayout(e, sh, nd, err, errlen)) return 1;
  }
  /* Even refitted neither box fits the index: the grid slides with the
   * robot, to the wanted box or else the needed one (a refit, which keeps
   * everything, went first). */
  for (int t = 0; t < 2; t++) {
    char serr[256];
    if (vlff_lattice_window(e->origin, VLFF_LATTICE_CUBE(e->voxel), e->dims, blo[t], bhi[t], limit, e->max_vox, sh,
                            nd) > 0 &&
        !evidence_slide(e, sh, nd, serr, sizeof serr))
      return 1;
  }
  return -1; /* err: the smaller box's refusal */
}

void vlff_evidence_reset(struct vlff_evidence *e) {
  memset(e->slot, 0xff, e->nvox * sizeof *e->slot);
  e->used = 0;
  e->overflow = e->evicted = 0;
  e->nadd = 0;
  e->census = false;
  memset(e->lost, 0, sizeof e->lost);
  memset(e->n_field, 0, sizeof e->n_field);
  memset(e->n_ev, 0, sizeof e->n_ev);
  e->nlost = 0;
  e->paged = e->page_top = e->nfree = 0;
  e->nfar = 0;
  e->far_gen++;
  e->paged_out = e->paged_in = e->page_errors = 0;
  e->pvalid = false;
  if (e->page_fd >= 0 && ftruncate(e->page_fd, 0)) e->page_errors++;
}

long vlff_grid_voxel(const double origin[3], double voxel, const uint32_t dims[3], const double x[3]) {
  long idx[3];
  for (int i = 0; i < 3; i++) {
    double f = (x[i] - origin[i]) / voxel;
    if (!(f >= 0) || f >= dims[i]) return -1;
    idx[i] = (long)f;
  }
  return idx[0] + (long)dims[0] * (idx[1] + (long)dims[1] * idx[2]);
}

long vlff_evidence_voxel(const struct vlff_evidence *e, const double x[3]) {
  return vlff_grid_voxel(e->origin, e->voxel, e->dims, x);
}

/* Slot from takes slot to's place (its voxel's index follows). */
static void move_slot(struct vlff_evidence *e, size_t from, size_t to) {
  memcpy(e->mean + to * e->D, e->mean + from * e->D, (size_t)e->D * sizeof *e->mean);
  memcpy(e->cos + to * e->max_k, e->cos + from * e->max_k, (size_t)e->max_k * sizeof *e->cos);
  e->views[to] = e->views[from];
  e->owner[to] = e->owner[from];
  e->seen[to] = e->seen[from];
  e->dirty[to] = e->dirty[from];
  e->slot[e->owner[to]] = (int32_t)to;
}

/* Slot s was touched by one of the last RECENT_VIEWS views. */
static bool recent(const struct vlff_evidence *e, size_t s) { return e->nadd - e->seen[s] < RECENT_VIEWS; }

/* A full budget: gives up the evidence of the cap / RECLAIM_DIV voxels with
 * the fewest samples among those no recent view touched (at a count, the
 * first slots), and packs the rest. The least-observed voxels are the depth
 * noise's strays in front of and behind surfaces and surfaces seen once from
 * afar; a voxel seen again starts over. Returns the slots freed. */
static size_t reclaim(struct vlff_evidence *e) {
  size_t hist[MAX_VIEWS + 1] = {0}, want = e->cap / RECLAIM_DIV ? e->cap / RECLAIM_DIV : 1;
  for (size_t s = 0; s < e->used; s++)
    if (!recent(e, s)) hist[e->views[s]]++;
  size_t below = 0;
  int c = 1;
  for (; c < MAX_VIEWS && below + hist[c] < want; c++) below += hist[c];
  size_t atc = want > below ? want - below : 0, freed = 0; /* slots to take at count c */
  for (size_t s = 0; s < e->used; s++) {
    if (recent(e, s) || e->views[s] > c || (e->views[s] == c && !atc)) continue;
    if (e->views[s] == c) atc--;
    /* To the page file when there is one (with its cosines, so that the
     * map still reads it), else dropped. */
    const float *cs = e->page_path && e->pvalid ? slot_cosines(e, (int32_t)s, e->E, e->pk) : NULL;
    int r = e->page_path ? page_write(e, e->owner[s], e->views[s], e->mean + s * (size_t)e->D, cs) : -1;
    e->slot[e->owner[s]] = r >= 0 ? -2 - r : -1;
    e->evicted += r < 0;
    e->views[s] = 0; /* a live slot holds at least one sample */
    freed++;
  }
  pack_slots(e);
  return freed;
}

/* The slots whose views were set to 0 (given up) packed away. */
static void pack_slots(struct vlff_evidence *e) {
  size_t hi = e->used;
  for (size_t s = 0; s < hi; s++) {
    if (e->views[s]) continue;
    while (hi > s + 1 && !e->views[hi - 1]) hi--;
    if (hi == s + 1) {
      hi = s;
      break;
    }
    move_slot(e, --hi, s);
  }
  e->used = hi;
}

/* ------------------------------------------------------------ paging */

/* Per record in the page file: its count (u8), a pad byte, its mean (D float16). */
static size_t page_record(int D) { return 2 + (size_t)D * 2; }

static int8_t quantize_cos(float c) {
  float q = c * 127.0f;
  return (int8_t)(q >= 127 ? 127 : q <= -127 ? -127 : lrintf(q));
}

/* A free record (reused, or the next after page_top), the arrays grown to
 * hold it: its index, or -1 when the file is full or memory is out. */
static long page_alloc(struct vlff_evidence *e) {
  if (e->nfree) return (long)e->pfree[--e->nfree];
  if (e->page_top >= e->page_cap) return -1;
  if (e->page_top == e->page_alloc) {
    size_t n = e->page_alloc ? e->page_alloc * 2 : 4096;
    if (n > e->page_cap) n = e->page_cap;
    uint32_t *o = realloc(e->powner, n * sizeof *o);
    if (o) e->powner = o;
    int8_t *c = realloc(e->pcos, n * (size_t)e->max_k);
    if (c) e->pcos = c;
    uint32_t *f = realloc(e->pfree, n * sizeof *f);
    if (f) e->pfree = f;
    if (!o || !c || !f) return -1;
    e->page_alloc = n;
  }
  return (long)e->page_top++;
}

static void page_release(struct vlff_evidence *e, size_t r) {
  e->powner[r] = NO_VOXEL;
  e->pfree[e->nfree++] = (uint32_t)r;
  e->paged--;
}

/* Writes voxel vi's evidence to a record: its index, or -1 (counted in
 * page_errors when the write failed; the file full is not an error). cos:
 * its cosines with the current prompts, NULL when there are none yet. */
static int page_write(struct vlff_evidence *e, uint32_t vi, uint8_t count, const uint16_t *mean, const float *cos) {
  if (e->page_fd < 0) {
    /* Made when first needed: a node whose budget never fills writes none.
     * O_TRUNC: records index this run's table only. One that cannot be made
     * ends paging (said once; what is given up is dropped, as without). */
    e->page_fd = open(e->page_path, O_RDWR | O_CREAT | O_TRUNC | O_CLOEXEC | O_NOFOLLOW, 0600);
    if (e->page_fd < 0) {
      snprintf(e->page_err, sizeof e->page_err, "%s: %s", VLFF_Q(e->page_path), strerror(errno));
      e->page_errors++;
      free(e->page_path);
      e->page_path = NULL;
      return -1;
    }
  }
  long r = page_alloc(e);
  if (r < 0) return -1;
  const size_t rs = page_record(e->D);
  e->pbuf[0] = count, e->pbuf[1] = 0;
  memcpy(e->pbuf + 2, mean, (size_t)e->D * 2);
  if (vlff_write_at(e->page_fd, (uint64_t)r * rs, e->pbuf, rs)) {
    e->pfree[e->nfree++] = (uint32_t)r;
    if (!e->page_errors++)
      snprintf(e->page_err, sizeof e->page_err, "%s: writing: %s", VLFF_Q(e->page_path), strerror(errno));
    return -1;
  }
  e->powner[r] = vi;
  int8_t *q = e->pcos + (size_t)r * e->max_k;
  for (int k = 0; k < e->max_k; k++) q[k] = cos && k < e->pk ? quantize_cos(cos[k]) : 0;
  e->paged++;
  e->paged_out++;
  return (int)r;
}

/* Record r's count and mean (into mean[D]): 0, or -1 when it cannot be read
 * back whole or is not what was written (counted). */
static int page_read(struct vlff_evidence *e, size_t r, uint8_t *count, uint16_t *mean) {
  const size_t rs = page_record(e->D);
  bool ok = vlff_read_at(e->page_fd, (uint64_t)r * rs, e->pbuf, rs) == 0 && e->pbuf[0] > 0;
  for (int j = 0; ok && j < e->D; j++) {
    uint16_t h;
    memcpy(&h, e->pbuf + 2 + 2 * (size_t)j, 2);
    ok = (h & 0x7c00) != 0x7c00; /* float16 inf and NaN */
  }
  if (!ok) {
    if (!e->page_errors++)
      snprintf(e->page_err, sizeof e->page_err, "%s: record %zu does not read back as written", VLFF_Q(e->page_path),
               r);
    return -1;
  }
  *count = e->pbuf[0];
  memcpy(mean, e->pbuf + 2, (size_t)e->D * 2);
  return 0;
}

int vlff_evidence_page_to(struct vlff_evidence *e, const char *path, size_t max_bytes, char *err, size_t errlen) {
  if (e->page_fd >= 0) close(e->page_fd), unlink(e->page_path);
  e->page_fd = -1;
  free(e->page_path);
  e->page_path = NULL;
  /* What was paged before is gone with the file. */
  for (size_t v = 0; v < e->nvox; v++)
    if (is_paged(e->slot[v])) e->slot[v] = -1;
  e->paged = e->page_top = e->nfree = 0;
  e->nfar = 0;
  e->far_gen++;
  e->page_cap = max_bytes / page_record(e->D);
  if (e->page_cap > (size_t)INT32_MAX - 2) e->page_cap = (size_t)INT32_MAX - 2;
  if (!e->page_cap) return 0;
  free(e->pbuf);
  e->pbuf = malloc(page_record(e->D));
  e->page_path = e->pbuf ? strdup(path) : NULL;
  if (!e->page_path) return vlff_errf(err, errlen, "evidence: out of memory for paging"), -1;
  /* A run killed before it could remove its file left one (up to the
   * budget): nothing in it holds for this run. */
  (void)unlink(path);
  return 0;
}

const char *vlff_evidence_page_error(const struct vlff_evidence *e) { return e->page_err; }

static void mean_cosines(struct vlff_evidence *e, const uint16_t *mean, float *x, const float *E, int K, float *out);

/* Every live record's cosines again, read back from the file, for new
 * prompts E[K][D] (a change of prompts: rare). */
static void repage_cosines(struct vlff_evidence *e, const float *E, int K) {
  uint16_t *mean = (uint16_t *)e->tmp; /* 2 D floats: room for D float16 */
  float *x = e->tmp + e->D;
  uint8_t count;
  for (size_t r = 0; r < e->page_top; r++) {
    if (e->powner[r] == NO_VOXEL) continue;
    int8_t *q = e->pcos + r * (size_t)e->max_k;
    if (page_read(e, r, &count, mean)) {
      memset(q, 0, (size_t)e->max_k);
      continue;
    }
    float c[VLFF_FIELD_MAX_PROMPTS];
    mean_cosines(e, mean, x, E, K, c);
    for (int k = 0; k < e->max_k; k++) q[k] = k < K ? quantize_cos(c[k]) : 0;
  }
}

size_t vlff_evidence_paged(const struct vlff_evidence *e) { return e->paged; }
long long vlff_evidence_paged_out(const struct vlff_evidence *e) { return e->paged_out; }
long long vlff_evidence_paged_in(const struct vlff_evidence *e) { return e->paged_in; }
long long vlff_evidence_page_errors(const struct vlff_evidence *e) { return e->page_errors; }
size_t vlff_evidence_page_memory(const struct vlff_evidence *e) {
  return e->page_alloc * (sizeof *e->powner + (size_t)e->max_k + sizeof *e->pfree);
}

static float dot16(const float *a, const float *b, int n);

/* The running mean of one voxel takes feature f (D finite floats of unit
 * length). */
static void accumulate(struct vlff_evidence *e, long vi, const float *f) {
  int32_t s = e->slot[vi];
  if (s < 0) {
    if (e->used >= e->cap && (e->reclaimed || (e->reclaimed = true, reclaim(e) == 0))) {
      e->overflow++;
      return;
    }
    const int32_t was = s; /* reclaim frees slots only: a paged voxel stays in its record */
    s = (int32_t)e->used++;
    e->slot[vi] = s;
    e->views[s] = 0;
    e->owner[s] = (uint32_t)vi;
    if (is_paged(was)) {
      /* Seen again: its evidence comes back from the page file, and the new
       * sample joins its mean instead of starting one over. */
      uint8_t count;
      if (page_read(e, record_of(was), &count, e->mean + (size_t)s * e->D) == 0) e->views[s] = count;
      page_release(e, record_of(was));
      e->paged_in++;
    }
  }
  e->seen[s] = e->nadd;
  e->dirty[s] = 1;
  uint16_t *m = e->mean + (size_t)s * e->D;
  int n = e->views[s] < MAX_VIEWS ? ++e->views[s] : MAX_VIEWS;
  if (n == 1) {
    vlff_f32_to_f16_n(f, m, (size_t)e->D);
    return;
  }
  /* whole rows through the vector conversions: a keyframe adds a few
   * thousand features of D values, on the trainer's thread */
  float *mean = e->tmp + e->D, a = 1.0f / (float)(n < RECENT_SAMPLES ? n : RECENT_SAMPLES);
  vlff_f16_to_f32_n(m, mean, (size_t)e->D);
  /* A mean of unit vectors is at most 1 long; a longer one was saved before
   * features were averaged as directions (a checkpoint or far file of an
   * older node) and, kept at its length, would outweigh the new samples
   * for as long as it was longer. Brought to unit length, it weighs as the
   * samples it holds. */
  const float nn = dot16(mean, mean, e->D);
  if (nn > 1.0201f) {
    const float inv = 1.0f / sqrtf(nn);
    for (int j = 0; j < e->D; j++) mean[j] *= inv;
  }
  for (int j = 0; j < e->D; j++) mean[j] += (f[j] - mean[j]) * a;
  vlff_f32_to_f16_n(mean, m, (size_t)e->D);
}

int vlff_evidence_add(struct vlff_evidence *e, const struct vlff_view *v, char *err, size_t errlen) {
  if (!v->depth || !v->features) return 0;
  if (v->feature_dim != e->D)
    return vlff_errf(err, errlen, "evidence: view features have another D than the map's"), -1;
  if (v->width < 1 || v->height < 1 || v->feat_width < 1 || v->feat_height < 1)
    return vlff_errf(err, errlen, "evidence: view has no pixels"), -1;
  const int D = e->D;
  float *f = e->tmp;
  /* A feature pixel describes its whole footprint, not only the point under
   * its centre: the depth under its four quarter points (each depth pixel
   * once when depth has twice the features' resolution, as the node's
   * keyframes have) places it, and it is averaged once into every voxel
   * those points reach. With the centre alone, a surface voxel that no
   * centre happened to land in had no evidence, and its pixels of the label
   * image read the field alone, which in a newly seen view has not been
   * trained there yet. */
  static const double quarter[4][2] = {{0.25, 0.25}, {0.75, 0.25}, {0.25, 0.75}, {0.75, 0.75}};
  e->nadd++;
  e->reclaimed = false;
  for (int fj = 0; fj < v->feat_height; fj++)
    for (int fi = 0; fi < v->feat_width; fi++) {
      long vox[4];
      int nv = 0;
      for (int q = 0; q < 4; q++) {
        double u = (fi + quarter[q][0]) * v->width / v->feat_width, w = (fj + quarter[q][1]) * v->height / v->feat_height;
        int iu = (int)u, iv = (int)w;
        if (iu >= v->width) iu = v->width - 1;
        if (iv >= v->height) iv = v->height - 1;
        float d = v->depth[(size_t)iv * v->width + iu];
        if (!(d > 0) || !isfinite(d)) continue;
        double x[3];
        vlff_unproject(v->c2w, v->fx, v->fy, v->cx, v->cy, u, w, d, x);
        long vi = vlff_evidence_voxel(e, x);
        bool seen = vi < 0;
        for (int t = 0; t < nv; t++) seen |= vox[t] == vi;
        if (!seen) vox[nv++] = vi;
      }
      if (!nv) continue;
      const uint16_t *src = v->features + ((size_t)fj * v->feat_width + fi) * D;
      vlff_f16_to_f32_n(src, f, (size_t)D);
      /* Averaged as a direction: the map reads cosines, which ignore a
       * feature's length, so a long feature must not outweigh a short one
       * in the mean (a zero one has no direction and adds nothing). */
      const float nn = dot16(f, f, D);
      if (!(nn > 0) || !isfinite(nn)) continue;
      const float inv = 1.0f / sqrtf(nn);
      for (int j = 0; j < D; j++) f[j] *= inv;
      for (int t = 0; t < nv; t++) accumulate(e, vox[t], f);
    }
  return 0;
}

int vlff_evidence_get(const struct vlff_evidence *e, long vi, float *out) {
  if (vi < 0 || (size_t)vi >= e->nvox || e->slot[vi] < 0) return 0;
  const uint16_t *m = e->mean + (size_t)e->slot[vi] * e->D;
  vlff_f16_to_f32_n(m, out, (size_t)e->D);
  return e->views[e->slot[vi]];
}

/* a . b over n floats in 16 independent sums, which the compiler keeps in
 * vector registers (a sum in one double is a serial chain: with D = 512
 * and 20 prompts it was most of publishing's time). */
static float dot16(const float *a, const float *b, int n) {
  float acc[16] = {0};
  int j = 0;
  for (; j + 16 <= n; j += 16)
    for (int t = 0; t < 16; t++) acc[t] += a[j + t] * b[j + t];
  float s = 0;
  for (; j < n; j++) s += a[j] * b[j];
  for (int t = 0; t < 16; t++) s += acc[t];
  return s;
}

/* The cosines of a float16 mean (through x, D floats of scratch) with
 * E[K][D] into out[K]; 0 for a zero mean. */
static void mean_cosines(struct vlff_evidence *e, const uint16_t *mean, float *x, const float *E, int K, float *out) {
  const int D = e->D;
  vlff_f16_to_f32_n(mean, x, (size_t)D);
  float nn = dot16(x, x, D);
  float inv = nn > 0 ? 1.0f / sqrtf(nn) : 0;
  for (int k = 0; k < K; k++) out[k] = dot16(x, E + (size_t)k * D, D) * inv;
}

/* Slot s's cosines with E, recomputed when its evidence changed. */
static const float *slot_cosines(struct vlff_evidence *e, int32_t s, const float *E, int K) {
  float *c = e->cos + (size_t)s * e->max_k;
  if (!e->dirty[s]) return c;
  /* not tmp's first 2 D: a reclaim in the middle of an add pages slots out */
  mean_cosines(e, e->mean + (size_t)s * e->D, e->tmp + 2 * e->D, E, K, c);
  e->dirty[s] = 0;
  return c;
}

/* The evidence's cosines at world point x, read as a grid is read between
 * its samples: the trilinear blend of those of the (up to) eight voxels
 * whose centres surround x, over the voxels with evidence, into out[K];
 * false where none has any. Why: a surface point near a voxel's face is as
 * much its neighbour's, and the nearest voxel alone quantised every point
 * to 10 cm and averaged only that voxel's samples (docs/field.md, "Evidence
 * read between voxel centres"). The point's own voxel always weighs at
 * least 1/8, so a point whose voxel has evidence always reads some. */
static bool blend_cosines(struct vlff_evidence *e, const double x[3], const float *E, int K, float *out) {
  long i0[3];
  float fr[3];
  for (int d = 0; d < 3; d++) {
    double g = (x[d] - e->origin[d]) / e->voxel - 0.5;
    if (!(g > -2 && g < (double)e->dims[d] + 1)) return false; /* outside the grid (or not finite) */
    i0[d] = (long)floor(g);
    fr[d] = (float)(g - (double)i0[d]);
  }
  float wsum = 0;
  for (int c = 0; c < 8; c++) {
    long ix = i0[0] + (c & 1), iy = i0[1] + (c >> 1 & 1), iz = i0[2] + (c >> 2 & 1);
    if (ix < 0 || iy < 0 || iz < 0 || ix >= (long)e->dims[0] || iy >= (long)e->dims[1] || iz >= (long)e->dims[2])
      continue;
    int32_t s = e->slot[ix + (long)e->dims[0] * (iy + (long)e->dims[1] * iz)];
    float wt = (c & 1 ? fr[0] : 1 - fr[0]) * (c >> 1 & 1 ? fr[1] : 1 - fr[1]) * (c >> 2 & 1 ? fr[2] : 1 - fr[2]);
    if (s == -1 || !(wt > 0) || (is_paged(s) && !e->pvalid)) continue;
    const float *cs;
    if (is_paged(s)) {
      const int8_t *q = e->pcos + record_of(s) * (size_t)e->max_k;
      for (int k = 0; k < K; k++) e->pc[k] = q[k] * (1.0f / 127.0f);
      cs = e->pc;
    } else {
      cs = slot_cosines(e, s, E, K);
    }
    for (int k = 0; k < K; k++) out[k] = (wsum > 0 ? out[k] : 0.0f) + wt * cs[k];
    wsum += wt;
  }
  if (!(wsum > 0)) return false;
  for (int k = 0; k < K; k++) out[k] /= wsum;
  return true;
}

/* A class the evidence finds at fewer points is one view's noise (a few
 * feature pixels leaning the wrong way), not an object the field lost: in the
 * node's first seconds such classes came and went at every publish. */
enum { LOST_MIN_POINTS = 10 };

void vlff_evidence_census_begin(struct vlff_evidence *e) {
  e->census = true;
  e->census_stamped = false;
  memset(e->n_field, 0, sizeof e->n_field);
  memset(e->n_ev, 0, sizeof e->n_ev);
}

int vlff_evidence_census_end(struct vlff_evidence *e, double ratio) {
  if (!e->census) return e->nlost;
  e->census = false;
  /* A class already lost (for the same prompts) is kept again only at twice
   * the ratio: one near the bar would otherwise flip its map labels at
   * every publish. */
  const bool same = e->census_stamped && e->nlost && e->lost_stamp == e->census_stamp && e->lost_k == e->census_k;
  int n = 0;
  for (int k = 0; k < e->max_k; k++) {
    const double bar = (same && e->lost[k] ? 2 : 1) * ratio;
    e->lost[k] = ratio > 0 && e->n_ev[k] >= LOST_MIN_POINTS && (double)e->n_field[k] < bar * (double)e->n_ev[k];
    n += e->lost[k];
  }
  e->nlost = n;
  e->lost_stamp = e->census_stamp, e->lost_k = e->census_k;
  return n;
}

void vlff_evidence_lost_save(const struct vlff_evidence *e, uint8_t out[VLFF_EVIDENCE_LOST_BYTES]) {
  memset(out, 0, VLFF_EVIDENCE_LOST_BYTES);
  if (!e || !e->nlost) return;
  const int32_t k = e->lost_k;
  const uint32_t n = (uint32_t)e->nlost;
  memcpy(out, &e->lost_stamp, 8);
  memcpy(out + 8, &k, 4);
  memcpy(out + 12, &n, 4);
  for (int i = 0; i < k; i++) out[16 + i] = e->lost[i];
}

int vlff_evidence_lost_check(const uint8_t in[VLFF_EVIDENCE_LOST_BYTES], int max_k, char *err, size_t errlen) {
  int32_t k;
  uint32_t n, count = 0;
  memcpy(&k, in + 8, 4);
  memcpy(&n, in + 12, 4);
  if (k < 0 || k > max_k || k > VLFF_FIELD_MAX_PROMPTS) {
    snprintf(err, errlen, "lost classes: %d prompts, expected 0 to %d", (int)k, max_k);
    return -1;
  }
  for (int i = 0; i < VLFF_FIELD_MAX_PROMPTS; i++) {
    if (in[16 + i] > 1 || (i >= k && in[16 + i])) {
      snprintf(err, errlen, "lost classes: prompt %d marked %u (of %d prompts)", i, in[16 + i], (int)k);
      return -1;
    }
    count += in[16 + i];
  }
  if (count != n) {
    snprintf(err, errlen, "lost classes: %u marked, the block says %u", count, n);
    return -1;
  }
  return 0;
}

void vlff_evidence_lost_set(struct vlff_evidence *e, const uint8_t in[VLFF_EVIDENCE_LOST_BYTES]) {
  int32_t k;
  uint32_t n;
  memcpy(&e->lost_stamp, in, 8);
  memcpy(&k, in + 8, 4);
  memcpy(&n, in + 12, 4);
  memset(e->lost, 0, sizeof e->lost);
  for (int i = 0; i < k; i++) e->lost[i] = in[16 + i];
  e->lost_k = k;
  e->nlost = (int)n;
}

bool vlff_evidence_lost(const struct vlff_evidence *e, int k, unsigned long long *n_field, unsigned long long *n_ev) {
  if (k < 0 || k >= e->max_k) return false;
  if (n_field) *n_field = e->n_field[k];
  if (n_ev) *n_ev = e->n_ev[k];
  return e->lost[k];
}

void vlff_evidence_label(struct vlff_evidence *e, const float *xyz, size_t n, const float *fcos,
                         const uint16_t *rays, int trust_rays, const float *E, int K, uint64_t stamp, float w,
                         int *label, float *score, float *margin) {
  vlff_evidence_label_scores(e, xyz, n, fcos, rays, trust_rays, E, K, stamp, w, label, score, margin, NULL);
}

void vlff_evidence_label_scores(struct vlff_evidence *e, const float *xyz, size_t n, const float *fcos,
                                const uint16_t *rays, int trust_rays, const float *E, int K, uint64_t stamp, float w,
                                int *label, float *score, float *margin, float *scores) {
  const size_t stride = (size_t)K; /* scores' rows, as the caller has them */
  if (K > e->max_k) K = e->max_k;
  if (stamp != e->stamp || K != e->stamp_k || (e->page_path && !e->pvalid)) {
    memset(e->dirty, 1, e->used);
    e->stamp = stamp, e->stamp_k = K;
    if (e->page_path) {
      /* The prompts, kept for the cosines of what is paged out later; what
       * is paged now is read back once for them. */
      float *c = realloc(e->E, (size_t)K * e->D * sizeof *c);
      e->pvalid = c != NULL;
      if (c) {
        e->E = c;
        memcpy(e->E, E, (size_t)K * e->D * sizeof *c);
        e->pk = K;
        repage_cosines(e, E, K);
      }
    }
  }
  if (e->census && !e->census_stamped) e->census_stamp = stamp, e->census_k = K, e->census_stamped = true;
  const bool count = e->census && e->census_stamp == stamp && e->census_k == K;
  const bool restore = e->nlost && e->lost_stamp == stamp && e->lost_k == K;
  for (size_t i = 0; i < n; i++) {
    const float *fc = fcos + i * (size_t)K, *ec = NULL;
    double x[3] = {xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]};
    float a = 1.0f; /* the field's trust */
    if (blend_cosines(e, x, E, K, e->blend)) {
      ec = e->blend;
      if (rays && trust_rays > 0 && rays[i] < trust_rays) a = (float)rays[i] / (float)trust_rays;
    }
    int best = -1, any = 0;
    float b1 = -INFINITY, b2 = -INFINITY;
    for (int k = 0; k < K; k++) {
      any |= fc[k] != 0;
      float v = a * fc[k] + (ec ? w * ec[k] : 0.0f);
      if (v > b1) b2 = b1, b1 = v, best = k;
      else if (v > b2) b2 = v;
    }
    float scale = ec && a + w > 0 ? 1.0f / (a + w) : 1.0f;
    if (ec && any && (count || restore)) {
      float gap;
      const int ke = vlff_best_of(ec, K, &gap);
      /* Only a fitted field's label says what it keeps of a class. */
      if (count && a >= 1.0f) e->n_field[vlff_best_of(fc, K, NULL)]++, e->n_ev[ke]++;
      if (restore && e->lost[ke] && ke != best) {
        /* A class the field has lost is read from the evidence wherever it
         * finds it: that class's sum, and the evidence's own margin. */
        best = ke;
        b1 = a * fc[ke] + w * ec[ke];
        b2 = b1 - w * gap;
      }
    }
    if (scores) {
      /* the sums as scaled; a lost class read from the evidence wins by
       * the evidence's margin, as score and margin say */
      float *o = scores + i * stride, other = -INFINITY;
      for (size_t k = (size_t)K; k < stride; k++) o[k] = 0.0f;
      for (int k = 0; k < K; k++) {
        o[k] = any ? (a * fc[k] + (ec ? w * ec[k] : 0.0f)) * scale : 0.0f;
        if (k != best && o[k] > other) other = o[k];
      }
      if (any && K > 1) o[best] = other + (b1 - b2) * scale;
    }
    label[i] = any ? best : -1;
    if (score) score[i] = any ? b1 * scale : 0.0f;
    if (margin) margin[i] = any && K > 1 ? (b1 - b2) * scale : 0.0f;
  }
}

struct ev_header {
  uint32_t dims[3];
  int32_t D;
  double voxel, origin[3];
  uint64_t used;
};

/* Per voxel: its index (u32), its count (u8), its mean (D float16). */
static size_t record_size(int D) { return 4 + 1 + (size_t)D * 2; }

size_t vlff_evidence_save_size(const struct vlff_evidence *e) {
  return sizeof(struct ev_header) + (e->used + e->paged - e->nfar) * record_size(e->D);
}

size_t vlff_evidence_save_part(const struct vlff_evidence *e, uint64_t *cursor, uint8_t *out, size_t cap) {
  /* Reading a paged voxel back uses the page buffer and may count an error:
   * scratch and counters, not the evidence's learned state. */
  struct vlff_evidence *pg = (struct vlff_evidence *)e;
  const size_t rs = record_size(e->D);
  uint8_t *o = out;
  if (*cursor == 0) {
    struct ev_header h = {.D = e->D, .voxel = e->voxel, .used = e->used + e->paged - e->nfar};
    memcpy(h.dims, e->dims, sizeof h.dims);
    memcpy(h.origin, e->origin, sizeof h.origin);
    if (cap < sizeof h) return 0;
    memcpy(o, &h, sizeof h);
    o += sizeof h;
    *cursor = 1;
  }
  size_t vi = (size_t)*cursor - 1; /* the next voxel to look at */
  for (; vi < e->nvox && (size_t)(o - out) + rs <= cap; vi++) {
    int32_t s = e->slot[vi];
    if (s == -1) continue;
    uint32_t idx = (uint32_t)vi;
    memcpy(o, &idx, 4);
    if (is_paged(s)) {
      if (page_read(pg, record_of(s), &o[4], (uint16_t *)pg->tmp) == 0) {
        memcpy(o + 5, pg->tmp, (size_t)e->D * 2);
      } else {
        /* unreadable (counted): a sample of nothing, which no prompt wins */
        o[4] = 1;
        memset(o + 5, 0, (size_t)e->D * 2);
      }
    } else {
      o[4] = e->views[s];
      memcpy(o + 5, e->mean + (size_t)s * e->D, (size_t)e->D * 2);
    }
    o += rs;
  }
  *cursor = vi + 1;
  return (size_t)(o - out);
}

void vlff_evidence_save(const struct vlff_evidence *e, uint8_t *out) {
  uint64_t cursor = 0;
  vlff_evidence_save_part(e, &cursor, out, vlff_evidence_save_size(e));
}

/* Record i read and checked: its voxel in the grid and after the last one
 * (none twice), at least one sample, a finite mean (into mean[D]). */
static int read_record(const struct vlff_evidence *e, vlff_evidence_read_fn rd, void *ctx, uint64_t i, uint32_t prev,
                       uint32_t *idx, uint8_t *count, uint16_t *mean, char *err, size_t errlen) {
  const uint64_t at = sizeof(struct ev_header) + i * record_size(e->D);
  uint8_t head[5];
  if (rd(ctx, at, head, sizeof head, err, errlen) || rd(ctx, at + 5, mean, (size_t)e->D * 2, err, errlen)) return -1;
  memcpy(idx, head, 4);
  *count = head[4];
  bool finite = true;
  for (int j = 0; j < e->D; j++) finite &= (mean[j] & 0x7c00) != 0x7c00; /* float16 inf and NaN: all exponent bits */
  if (*idx >= e->nvox || (i > 0 && *idx <= prev) || *count == 0 || !finite)
    return vlff_errf(err, errlen, "evidence: saved evidence has a bad voxel record (record %llu)",
                     (unsigned long long)i),
           -1;
  return 0;
}

/* A growing grid takes a saved grid on its lattice (what it had grown or
 * been refitted to when saved), which must hold every voxel that holds
 * evidence now: -1 only when that fails. */
static int grow_to_saved(struct vlff_evidence *e, const struct ev_header *h, char *err, size_t errlen) {
  int32_t sh[3];
  if (!e->max_vox || h->D != e->D || h->voxel != e->voxel ||
      !vlff_lattice_saved(e->origin0, e->voxel, e->k0, e->dims, h->origin, h->dims, sh))
    return 0;
  return relayout(e, sh, h->dims, err, errlen);
}

int vlff_evidence_load_from(struct vlff_evidence *e, vlff_evidence_read_fn rd, void *ctx, uint64_t len,
                            char *err, size_t errlen) {
  struct ev_header h;
  if (len < sizeof h) return vlff_errf(err, errlen, "evidence: saved evidence truncated"), -1;
  if (rd(ctx, 0, &h, sizeof h, err, errlen)) return -1;
  if (grow_to_saved(e, &h, err, errlen)) return -1;
  if (memcmp(h.dims, e->dims, sizeof h.dims) || h.D != e->D || h.voxel != e->voxel ||
      memcmp(h.origin, e->origin, sizeof h.origin))
    return vlff_errf(err, errlen,
                     "evidence: saved evidence is of another grid or feature size (publish.evidence_voxel_m, "
                     "publish.evidence_max_mb or field.feature_dim changed since)"),
           1;
  const size_t rs = record_size(e->D);
  if (h.used > e->nvox || len != sizeof h + h.used * rs)
    return vlff_errf(err, errlen, "evidence: saved evidence has the wrong length"), -1;
  /* Every record checked before anything changes, and the counts'
   * histogram: more voxels than the budget holds keep the most-observed. */
  size_t hist[MAX_VIEWS + 1] = {0};
  uint32_t idx, prev = 0;
  uint8_t count;
  uint16_t *scratch = (uint16_t *)e->tmp; /* 2 D floats: room for D float16 */
  for (uint64_t i = 0; i < h.used; i++, prev = idx) {
    if (read_record(e, rd, ctx, i, prev, &idx, &count, scratch, err, errlen)) return -1;
    hist[count]++;
  }
  int c = 1;   /* the fewest samples a kept voxel has */
  size_t atc = SIZE_MAX; /* voxels kept at exactly c (the first in the file) */
  if (h.used > e->cap) {
    size_t above = 0;
    for (c = MAX_VIEWS; c > 1 && above + hist[c] < e->cap; c--) above += hist[c];
    atc = e->cap - above;
  }
  vlff_evidence_reset(e);
  for (uint64_t i = 0; i < h.used; i++, prev = idx) {
    /* Read again: a file changed under the reader leaves no evidence
     * rather than a mix of two. */
    if (read_record(e, rd, ctx, i, prev, &idx, &count, scratch, err, errlen)) goto changed;
    if (count < c || (count == c && !atc)) {
      /* Beyond the budget: to the page file when there is one. */
      int r = e->page_path ? page_write(e, idx, count, scratch, NULL) : -1;
      if (r >= 0) e->slot[idx] = -2 - r;
      continue;
    }
    if (count == c) atc--;
    int32_t s = (int32_t)e->used++;
    memcpy(e->mean + (size_t)s * e->D, scratch, (size_t)e->D * 2);
    e->slot[idx] = s;
    e->views[s] = count;
    e->owner[s] = idx;
    e->seen[s] = e->nadd - RECENT_VIEWS; /* no view since the load touched it: a full budget may give it up */
    e->dirty[s] = 1;
  }
  e->evicted = (long long)(h.used - e->used - e->paged);
  e->paged_out = 0; /* what a load pages is not given up for room */
  return 0;
changed:
  vlff_evidence_reset(e);
  return -1;
}

struct buffer_reader {
  const uint8_t *in;
  size_t len;
};

static int buffer_read(void *ctx, uint64_t off, void *dst, size_t n, char *err, size_t errlen) {
  const struct buffer_reader *b = ctx;
  if (off > b->len || n > b->len - off) return vlff_errf(err, errlen, "evidence: saved evidence truncated"), -1;
  memcpy(dst, b->in + off, n);
  return 0;
}

int vlff_evidence_load(struct vlff_evidence *e, const uint8_t *in, size_t len, char *err, size_t errlen) {
  struct buffer_reader b = {in, len};
  return vlff_evidence_load_from(e, buffer_read, &b, len, err, errlen);
}

size_t vlff_evidence_voxels(const struct vlff_evidence *e) { return e->used; }
size_t vlff_evidence_capacity(const struct vlff_evidence *e) { return e->cap; }

long long vlff_evidence_evicted(const struct vlff_evidence *e) { return e->evicted; }
long long vlff_evidence_overflow(const struct vlff_evidence *e) { return e->overflow; }

/* ------------------------------------------------------- far records saved */

/* File: "VLFFEVF1", D (i32), 4 pad bytes, voxel and the first grid's origin
 * (4 doubles), n (u64), n records of the lattice voxel (3 i64), the count
 * (u8) and the mean (D float16), FNV-1a 64 of everything before it. */
#define EVF_MAGIC "VLFFEVF1"
#define EVF_HEAD (8 + 8 + 32 + 8)
static size_t evf_record(int D) { return 24 + 1 + (size_t)D * 2; }

size_t vlff_evidence_far_records(const struct vlff_evidence *e) { return e->nfar; }
uint64_t vlff_evidence_far_generation(const struct vlff_evidence *e) { return e->far_gen; }

/* A VLFFEVF1 file's header (its first EVF_HEAD bytes, of a file of size
 * bytes) checked against this evidence: NULL and *n its records, or why
 * not. The checksum is the caller's, which has read the records. */
static const char *evf_head(const struct vlff_evidence *e, const uint8_t *head, uint64_t size, uint64_t *n) {
  int32_t D = 0;
  double voxel = 0, origin0[3] = {0, 0, 0};
  if (size < EVF_HEAD + 8 || memcmp(head, EVF_MAGIC, 8)) return "not far evidence (VLFFEVF1)";
  memcpy(&D, head + 8, 4);
  memcpy(&voxel, head + 16, 8);
  memcpy(origin0, head + 24, 24);
  memcpy(n, head + 48, 8);
  if (D != e->D || voxel != e->voxel || memcmp(origin0, e->origin0, sizeof origin0))
    return "of another grid or feature size (publish.evidence_voxel_m, the first box or field.feature_dim changed "
           "since)";
  const size_t rs = evf_record(e->D);
  if (*n > (size - EVF_HEAD - 8) / rs || size != EVF_HEAD + *n * rs + 8) return "truncated or too long";
  return NULL;
}

int vlff_evidence_save_far(const struct vlff_evidence *e, const char *path, char *err, size_t errlen) {
  if (!e->nfar) {
    if (unlink(path) && errno != ENOENT) return vlff_errf(err, errlen, "%s: %s", VLFF_Q(path), strerror(errno)), -1;
    return 0;
  }
  /* Reading a record back uses the page buffer: scratch, as in save_part. */
  struct vlff_evidence *pg = (struct vlff_evidence *)e;
  const size_t rs = evf_record(e->D);
  uint8_t head[EVF_HEAD], *rec = malloc(rs);
  if (!rec) return vlff_errf(err, errlen, "%s: out of memory", VLFF_Q(path)), -1;
  const int32_t D = e->D;
  const uint64_t n = e->nfar;
  memset(head, 0, sizeof head);
  memcpy(head, EVF_MAGIC, 8);
  memcpy(head + 8, &D, 4);
  memcpy(head + 16, &e->voxel, 8);
  memcpy(head + 24, e->origin0, 24);
  memcpy(head + 48, &n, 8);
  struct vlff_atomic a;
  if (vlff_atomic_begin(&a, path, 0644, err, errlen) < 0) return free(rec), -1;
  uint64_t sum = vlff_fnv1a64(VLFF_FNV1A64_INIT, head, sizeof head);
  bool ok = vlff_write_all(a.fd, head, sizeof head) == 0;
  for (size_t j = 0; ok && j < e->nfar; j++) {
    const int64_t k[3] = {e->far[j].k[0], e->far[j].k[1], e->far[j].k[2]};
    memcpy(rec, k, 24);
    if (page_read(pg, e->far[j].r, &rec[24], (uint16_t *)pg->tmp)) {
      rec[24] = 1; /* unreadable (counted): a sample of nothing, as save_part writes it */
      memset(rec + 25, 0, (size_t)e->D * 2);
    } else {
      memcpy(rec + 25, pg->tmp, (size_t)e->D * 2);
    }
    sum = vlff_fnv1a64(sum, rec, rs);
    ok = vlff_write_all(a.fd, rec, rs) == 0;
  }
  free(rec);
  ok = ok && vlff_write_all(a.fd, &sum, 8) == 0;
  if (!ok) {
    vlff_errf(err, errlen, "%s: write failed: %s", VLFF_Q(a.tmp), strerror(errno));
    vlff_atomic_abort(&a);
    return -1;
  }
  return vlff_atomic_commit(&a, err, errlen);
}

/* Without a page file every record is given up: only the header is read,
 * for the count (held to the file's length). */
static int evf_drop_all(struct vlff_evidence *e, const char *path, long long *dropped, char *err, size_t errlen) {
  int fd = vlff_open_regular(path, err, errlen);
  if (fd < 0) return -1;
  uint8_t head[EVF_HEAD];
  struct stat st;
  uint64_t n = 0;
  const char *why = fstat(fd, &st) || vlff_read_at(fd, 0, head, sizeof head) ? "unreadable"
                                                                              : evf_head(e, head, (uint64_t)st.st_size, &n);
  close(fd);
  if (why) return vlff_errf(err, errlen, "%s: %s", VLFF_Q(path), why), -1;
  *dropped = (long long)n;
  e->evicted += (long long)n;
  return 0;
}

int vlff_evidence_load_far(struct vlff_evidence *e, const char *path, long long *dropped, char *err, size_t errlen) {
  *dropped = 0;
  if (access(path, F_OK) && errno == ENOENT) return 1;
  if (!e->page_path) return evf_drop_all(e, path, dropped, err, errlen);
  const size_t rs = evf_record(e->D);
  uint8_t *buf;
  size_t len;
  /* at most what the page file holds, and a header */
  if (vlff_read_file(path, EVF_HEAD + e->page_cap * rs + 8, &buf, &len, err, errlen)) return -1;
  uint64_t n = 0, sum = 0;
  const char *why = evf_head(e, buf, len, &n);
  if (!why) {
    memcpy(&sum, buf + len - 8, 8);
    if (sum != vlff_fnv1a64(VLFF_FNV1A64_INIT, buf, len - 8)) why = "checksum mismatch";
  }
  /* Every record checked before any is taken. */
  for (uint64_t j = 0; !why && j < n; j++) {
    const uint8_t *r = buf + EVF_HEAD + j * rs;
    int64_t k[3];
    memcpy(k, r, 24);
    for (int a = 0; a < 3 && !why; a++)
      if (k[a] < -(int64_t)INT32_MAX || k[a] > (int64_t)INT32_MAX) why = "a record beyond the lattice";
    if (!why && !r[24]) why = "a record of no samples";
    for (int d = 0; !why && d < e->D; d++) {
      uint16_t h;
      memcpy(&h, r + 25 + 2 * (size_t)d, 2);
      if ((h & 0x7c00) == 0x7c00) why = "a record whose mean is not finite";
    }
  }
  size_t need = e->nfar + (size_t)n;
  if (!why && need > e->far_cap) {
    struct far_rec *nf = realloc(e->far, need * sizeof *nf);
    if (!nf) why = "out of memory";
    else e->far = nf, e->far_cap = need;
  }
  if (why) {
    free(buf);
    return vlff_errf(err, errlen, "%s: %s", VLFF_Q(path), why), -1;
  }
  for (uint64_t j = 0; j < n; j++) {
    const uint8_t *r = buf + EVF_HEAD + j * rs;
    int64_t k[3];
    memcpy(k, r, 24);
    memcpy(e->tmp, r + 25, (size_t)e->D * 2); /* aligned for page_write's mean */
    const int rec = e->page_path ? page_write(e, FAR_VOXEL, r[24], (const uint16_t *)e->tmp, NULL) : -1;
    if (rec < 0) {
      ++*dropped; /* no page file, or a full one: given up, as a full budget's */
      e->evicted++;
      continue;
    }
    struct far_rec *f = &e->far[e->nfar++];
    for (int a = 0; a < 3; a++) f->k[a] = (long)k[a];
    f->r = (uint32_t)rec;
  }
  free(buf);
  e->paged_out -= (long long)n - *dropped; /* what a load pages is not given up for room */
  e->far_gen++;
  far_return(e); /* any the grid covers now */
  return 0;
}
