/*
 * The far map (far.h): a sorted array of blocks, each its runs.
 */
#include "far.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdbool.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "files.h"
#include "hash.h"
#include "lattice.h"
#include "vlff/escape.h"

#define E VLFF_MAP_FAR_EDGE
#define BLOCK_VOXELS (E * E * E)

struct fblock {
  int32_t key[3];
  uint32_t nruns;
  struct vlff_map_far_run *runs;
};

struct vlff_far {
  double origin[3], voxel;
  size_t max_bytes;
  struct fblock *b;
  size_t n, cap;
  size_t nruns; /* over all blocks */
  long long dropped;
  uint64_t gen; /* vlff_far_generation */
  /* vlff_far_export's arrays */
  struct vlff_map_far_block *xb;
  struct vlff_map_far_run *xr;
  /* The prompts the labels index (vlff_far_prompts); k -1: not said yet. */
  int k;
  char texts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
};

static long floor_div(long a, long b) { return a >= 0 ? a / b : -((-a + b - 1) / b); }

/* Keys ordered z, then y, then x: the segment's order. */
static int key_cmp(const int32_t a[3], const int32_t b[3]) {
  for (int i = 2; i >= 0; i--)
    if (a[i] != b[i]) return a[i] < b[i] ? -1 : 1;
  return 0;
}

static int key_order(const void *a, const void *b) { return key_cmp(a, b); }

/* The index of key's block, or of where it would go (found false). */
static size_t find(const struct vlff_far *f, const int32_t key[3], bool *found) {
  size_t lo = 0, hi = f->n;
  while (lo < hi) {
    size_t mid = lo + (hi - lo) / 2;
    int c = key_cmp(f->b[mid].key, key);
    if (!c) return *found = true, mid;
    if (c < 0) lo = mid + 1;
    else hi = mid;
  }
  *found = false;
  return lo;
}

struct vlff_far *vlff_far_create(const double origin[3], double voxel, size_t max_bytes) {
  struct vlff_far *f = calloc(1, sizeof *f);
  if (!f) return NULL;
  memcpy(f->origin, origin, sizeof f->origin);
  f->voxel = voxel;
  f->max_bytes = max_bytes;
  f->k = -1;
  return f;
}

void vlff_far_reset(struct vlff_far *f) {
  for (size_t i = 0; i < f->n; i++) free(f->b[i].runs);
  f->n = f->nruns = 0;
  f->dropped = 0;
  f->gen++;
}

void vlff_far_destroy(struct vlff_far *f) {
  if (!f) return;
  vlff_far_reset(f);
  free(f->b), free(f->xb), free(f->xr);
  free(f);
}

size_t vlff_far_blocks(const struct vlff_far *f) { return f->n; }
size_t vlff_far_bytes(const struct vlff_far *f) { return vlff_map_far_bytes((uint32_t)f->n, (uint32_t)f->nruns); }
long long vlff_far_dropped(const struct vlff_far *f) { return f->dropped; }
uint64_t vlff_far_generation(const struct vlff_far *f) { return f->gen; }

static void decode(const struct fblock *b, uint16_t *lab, uint8_t *conf) {
  size_t at = 0;
  for (uint32_t r = 0; r < b->nruns; r++)
    for (uint16_t c = 0; c < b->runs[r].count; c++, at++) lab[at] = b->runs[r].label, conf[at] = b->runs[r].conf;
}

/* The block as runs (into b, replacing its own): 0, or -1 out of memory. */
static int encode(struct vlff_far *f, struct fblock *b, const uint16_t *lab, const uint8_t *conf) {
  uint32_t n = 0;
  for (size_t i = 0; i < BLOCK_VOXELS; i++)
    n += !i || lab[i] != lab[i - 1] || conf[i] != conf[i - 1];
  struct vlff_map_far_run *r = malloc(n * sizeof *r);
  if (!r) return -1;
  uint32_t k = 0;
  for (size_t i = 0; i < BLOCK_VOXELS; i++) {
    if (i && lab[i] == lab[i - 1] && conf[i] == conf[i - 1]) {
      r[k - 1].count++;
      continue;
    }
    r[k++] = (struct vlff_map_far_run){.label = lab[i], .count = 1, .conf = conf[i]};
  }
  f->nruns = f->nruns - b->nruns + n;
  free(b->runs);
  b->runs = r, b->nruns = n;
  return 0;
}

/* The lattice voxel of window voxel i and its block key. */
static void lattice_of(size_t i, const uint32_t dims[3], const long k0[3], long k[3], int32_t key[3]) {
  vlff_lattice_xyz(i, dims, k);
  for (int a = 0; a < 3; a++) k[a] += k0[a], key[a] = (int32_t)floor_div(k[a], E);
}

static size_t local_of(const long k[3], const int32_t key[3]) {
  return (size_t)(k[0] - (long)key[0] * E) + E * ((size_t)(k[1] - (long)key[1] * E) + E * (size_t)(k[2] - (long)key[2] * E));
}

/* Budget: the blocks farthest from centre (block units) go first. */
static void trim(struct vlff_far *f, const double centre[3]);

void vlff_far_trim(struct vlff_far *f, const long k0[3], const uint32_t dims[3]) {
  double centre[3];
  for (int a = 0; a < 3; a++) centre[a] = (double)(k0[a] + (long)dims[a] / 2) / E;
  trim(f, centre);
}

static void trim(struct vlff_far *f, const double centre[3]) {
  while (f->n && vlff_far_bytes(f) > f->max_bytes) {
    size_t worst = 0;
    double wd = -1;
    for (size_t i = 0; i < f->n; i++) {
      double d = 0;
      for (int a = 0; a < 3; a++) d += (f->b[i].key[a] + 0.5 - centre[a]) * (f->b[i].key[a] + 0.5 - centre[a]);
      if (d > wd) wd = d, worst = i;
    }
    f->nruns -= f->b[worst].nruns;
    free(f->b[worst].runs);
    memmove(f->b + worst, f->b + worst + 1, (f->n - worst - 1) * sizeof *f->b);
    f->n--;
    f->dropped++;
    f->gen++;
  }
}

int vlff_far_store(struct vlff_far *f, const uint32_t dims[3], const long k0[3], const int32_t sh[3],
                   const uint32_t nd[3], const uint16_t *labels, const uint8_t *conf) {
  const size_t nv = vlff_lattice_cells(dims);
  /* The blocks to write: those of leaving voxels that hold something, and
   * those that exist already (their window voxels were stale there). */
  int32_t (*keys)[3] = NULL;
  size_t nk = 0, kcap = 0;
  int rc = -1;
  for (size_t i = 0; i < nv; i++) {
    if (vlff_lattice_index(i, dims, sh, nd) >= 0) continue;
    long k[3];
    int32_t key[3];
    lattice_of(i, dims, k0, k, key);
    bool found;
    if (labels[i] == VLFF_LABEL_UNKNOWN) {
      find(f, key, &found);
      if (!found) continue;
    }
    if (nk && !key_cmp(keys[nk - 1], key)) continue; /* runs of x share blocks: most repeats are adjacent */
    if (nk == kcap) {
      size_t c = kcap ? 2 * kcap : 256;
      int32_t(*nkeys)[3] = realloc(keys, c * sizeof *keys);
      if (!nkeys) goto out;
      keys = nkeys, kcap = c;
    }
    memcpy(keys[nk++], key, sizeof key);
  }
  rc = 0;
  if (!nk) goto out; /* nothing leaving holds anything */
  rc = -1;
  /* Each block once, sorted. */
  qsort(keys, nk, sizeof *keys, key_order);
  size_t u = 0;
  for (size_t i = 0; i < nk; i++)
    if (!u || key_cmp(keys[u - 1], keys[i])) memcpy(keys[u++], keys[i], sizeof keys[i]);
  nk = u;
  if (f->n + nk > f->cap) {
    size_t c = f->cap ? f->cap : 64;
    while (c < f->n + nk) c *= 2;
    struct fblock *nb = realloc(f->b, c * sizeof *nb);
    if (!nb) goto out;
    f->b = nb, f->cap = c;
  }
  uint16_t *lab = malloc(BLOCK_VOXELS * sizeof *lab * nk + 1);
  uint8_t *cf = malloc(BLOCK_VOXELS * nk + 1);
  if (!lab || !cf) {
    free(lab), free(cf);
    goto out;
  }
  for (size_t j = 0; j < nk; j++) {
    bool found;
    size_t at = find(f, keys[j], &found);
    if (found) {
      decode(&f->b[at], lab + j * BLOCK_VOXELS, cf + j * BLOCK_VOXELS);
    } else {
      for (size_t v = 0; v < BLOCK_VOXELS; v++) lab[j * BLOCK_VOXELS + v] = VLFF_LABEL_UNKNOWN;
      memset(cf + j * BLOCK_VOXELS, 0, BLOCK_VOXELS);
    }
  }
  for (size_t i = 0; i < nv; i++) {
    if (vlff_lattice_index(i, dims, sh, nd) >= 0) continue;
    long k[3];
    int32_t key[3];
    lattice_of(i, dims, k0, k, key);
    int32_t(*hit)[3] = bsearch(key, keys, nk, sizeof *keys, key_order);
    if (!hit) continue;
    const size_t j = (size_t)(hit - keys), l = local_of(k, key);
    lab[j * BLOCK_VOXELS + l] = labels[i], cf[j * BLOCK_VOXELS + l] = conf[i];
  }
  rc = 0;
  for (size_t j = 0; j < nk && !rc; j++) {
    bool found;
    size_t at = find(f, keys[j], &found);
    if (!found) {
      memmove(f->b + at + 1, f->b + at, (f->n - at) * sizeof *f->b);
      f->b[at] = (struct fblock){.key = {keys[j][0], keys[j][1], keys[j][2]}};
      f->n++;
    }
    rc = encode(f, &f->b[at], lab + j * BLOCK_VOXELS, cf + j * BLOCK_VOXELS);
    if (rc && !f->b[at].nruns) { /* a new block that could not be made: not kept half made */
      memmove(f->b + at, f->b + at + 1, (f->n - at - 1) * sizeof *f->b);
      f->n--;
    }
  }
  free(lab), free(cf);
out:
  f->gen++; /* even a failed store may have changed blocks it made before */
  free(keys);
  return rc;
}

void vlff_far_restore(const struct vlff_far *f, const uint32_t dims[3], const int32_t sh[3], const uint32_t nd[3],
                      const long nk0[3], void (*fn)(void *ctx, size_t i, uint16_t label, uint8_t conf), void *ctx) {
  for (size_t j = 0; j < f->n; j++) {
    const struct fblock *b = &f->b[j];
    long base[3];
    bool meets = true;
    for (int a = 0; a < 3; a++) {
      base[a] = (long)b->key[a] * E - nk0[a]; /* the block's first voxel in the new window */
      meets = meets && base[a] + (long)E > 0 && base[a] < (long)nd[a];
    }
    if (!meets) continue;
    size_t at = 0;
    for (uint32_t r = 0; r < b->nruns; at += b->runs[r].count, r++) {
      const struct vlff_map_far_run *run = &b->runs[r];
      if (run->label == VLFF_LABEL_UNKNOWN) continue;
      for (size_t v = at; v < at + run->count; v++) {
        const long c[3] = {base[0] + (long)(v % E), base[1] + (long)(v / E % E), base[2] + (long)(v / (E * E))};
        bool in_new = true, in_old = true;
        for (int a = 0; a < 3; a++) {
          in_new = in_new && c[a] >= 0 && c[a] < (long)nd[a];
          in_old = in_old && c[a] >= sh[a] && c[a] < sh[a] + (long)dims[a];
        }
        if (in_new && !in_old) fn(ctx, (size_t)(c[0] + (long)nd[0] * (c[1] + (long)nd[1] * c[2])), run->label, run->conf);
      }
    }
  }
}

int vlff_far_prompts(struct vlff_far *f, const char *const *prompts, int k) {
  if (k < 0 || k > VLFF_SHM_MAX_PROMPTS) k = 0;
  bool same = f->k == k || f->k < 0; /* the first list: the labels index it */
  for (int i = 0; same && f->k >= 0 && i < k; i++) same = !strncmp(f->texts[i], prompts[i], VLFF_SHM_PROMPT_LEN);
  if (same) {
    if (f->k < 0) {
      for (int i = 0; i < k; i++) snprintf(f->texts[i], sizeof f->texts[i], "%s", prompts[i]);
      f->k = k;
      f->gen++; /* the texts a checkpoint holds */
    }
    return 0;
  }
  /* Old label i -> the index of its text in the new list, else UNKNOWN. */
  uint16_t to[VLFF_SHM_MAX_PROMPTS];
  for (int i = 0; i < VLFF_SHM_MAX_PROMPTS; i++) {
    to[i] = VLFF_LABEL_UNKNOWN;
    for (int j = 0; i < f->k && j < k; j++)
      if (!strncmp(f->texts[i], prompts[j], VLFF_SHM_PROMPT_LEN)) {
        to[i] = (uint16_t)j;
        break;
      }
  }
  int changed = 0;
  for (size_t b = 0; b < f->n; b++)
    for (uint32_t r = 0; r < f->b[b].nruns; r++) {
      struct vlff_map_far_run *run = &f->b[b].runs[r];
      if (run->label > VLFF_LABEL_MAX) continue;
      const uint16_t l = run->label < VLFF_SHM_MAX_PROMPTS ? to[run->label] : VLFF_LABEL_UNKNOWN;
      if (l == VLFF_LABEL_UNKNOWN) run->conf = 0;
      changed |= l != run->label;
      run->label = l;
    }
  memset(f->texts, 0, sizeof f->texts);
  for (int i = 0; i < k; i++) snprintf(f->texts[i], sizeof f->texts[i], "%s", prompts[i]);
  f->k = k;
  f->gen++;
  return changed;
}

int vlff_far_export(struct vlff_far *f, struct vlff_map_far *out) {
  struct vlff_map_far_block *xb = realloc(f->xb, (f->n + 1) * sizeof *xb);
  if (xb) f->xb = xb;
  struct vlff_map_far_run *xr = realloc(f->xr, (f->nruns + 1) * sizeof *xr);
  if (xr) f->xr = xr;
  if (!xb || !xr) return -1;
  uint32_t r = 0;
  for (size_t j = 0; j < f->n; j++) {
    memcpy(xb[j].key, f->b[j].key, sizeof xb[j].key);
    xb[j].first_run = r;
    memcpy(xr + r, f->b[j].runs, f->b[j].nruns * sizeof *xr);
    r += f->b[j].nruns;
  }
  *out = (struct vlff_map_far){.origin = {f->origin[0], f->origin[1], f->origin[2]}, .voxel_size = f->voxel,
                               .nblocks = (uint32_t)f->n, .nruns = r, .blocks = xb, .runs = xr};
  return 0;
}

void vlff_far_export_release(struct vlff_far *f) {
  free(f->xb), free(f->xr);
  f->xb = NULL, f->xr = NULL;
}

/* ------------------------------------------------------------ checkpoint */

/* File: "VLFFFAR1", origin (3 doubles), voxel (double), nblocks, nruns,
 * the prompt count k (u32 each), k prompts of VLFF_SHM_PROMPT_LEN bytes
 * (the texts the labels index), the blocks and runs as the segment holds
 * them, FNV-1a 64 of everything before it. */
#define FAR_MAGIC "VLFFFAR1"
#define FAR_HEAD (8 + 32 + 12)

int vlff_far_save(struct vlff_far *f, const char *path, char *err, size_t errlen) {
  if (!f->n) {
    if (unlink(path) && errno != ENOENT) return snprintf(err, errlen, "%s: %s", VLFF_Q(path), strerror(errno)), -1;
    return 0;
  }
  struct vlff_map_far m;
  if (vlff_far_export(f, &m)) return snprintf(err, errlen, "%s: out of memory", VLFF_Q(path)), -1;
  const uint32_t k = f->k > 0 ? (uint32_t)f->k : 0;
  const size_t texts = (size_t)k * VLFF_SHM_PROMPT_LEN, body = (size_t)vlff_map_far_bytes(m.nblocks, m.nruns);
  const size_t len = FAR_HEAD + texts + body + 8;
  uint8_t *buf = malloc(len), *q = buf;
  if (!buf) return snprintf(err, errlen, "%s: out of memory", VLFF_Q(path)), -1;
  memcpy(q, FAR_MAGIC, 8), q += 8;
  memcpy(q, m.origin, 24), q += 24;
  memcpy(q, &m.voxel_size, 8), q += 8;
  memcpy(q, &m.nblocks, 4), q += 4;
  memcpy(q, &m.nruns, 4), q += 4;
  memcpy(q, &k, 4), q += 4;
  memcpy(q, f->texts, texts), q += texts;
  memcpy(q, m.blocks, (size_t)m.nblocks * sizeof *m.blocks), q += (size_t)m.nblocks * sizeof *m.blocks;
  memcpy(q, m.runs, (size_t)m.nruns * sizeof *m.runs), q += (size_t)m.nruns * sizeof *m.runs;
  const uint64_t sum = vlff_fnv1a64(VLFF_FNV1A64_INIT, buf, (size_t)(q - buf));
  memcpy(q, &sum, 8);
  int rc = vlff_write_file_atomic(path, buf, len, err, errlen);
  free(buf);
  vlff_far_export_release(f);
  return rc;
}

/* The far map in a file's bytes (len, checked for its length and sum) as
 * blocks of their own: NULL with why when it is not this lattice's or
 * breaks the segment's contract. */
static struct fblock *far_parse(const struct vlff_far *f, const uint8_t *buf, size_t len, uint32_t *nb, uint32_t *nr,
                                uint32_t *k, const char **why) {
  struct vlff_map_far m = {0};
  memcpy(m.origin, buf + 8, 24);
  memcpy(&m.voxel_size, buf + 32, 8);
  memcpy(&m.nblocks, buf + 40, 4);
  memcpy(&m.nruns, buf + 44, 4);
  memcpy(k, buf + 48, 4);
  uint64_t sum;
  memcpy(&sum, buf + len - 8, 8);
  const uint64_t texts = (uint64_t)*k * VLFF_SHM_PROMPT_LEN;
  if (*k > VLFF_SHM_MAX_PROMPTS || len != FAR_HEAD + texts + vlff_map_far_bytes(m.nblocks, m.nruns) + 8)
    return *why = "truncated or too long", NULL;
  if (sum != vlff_fnv1a64(VLFF_FNV1A64_INIT, buf, len - 8)) return *why = "checksum mismatch", NULL;
  if (memcmp(m.origin, f->origin, sizeof m.origin) || m.voxel_size != f->voxel)
    return *why = "of another map's lattice (publish.voxel_size_m or the first box changed since)", NULL;
  if (!m.nblocks) return *why = "no blocks", NULL;
  /* aligned copies: the records follow the texts at any offset */
  struct vlff_map_far_block *blocks = malloc((size_t)m.nblocks * sizeof *blocks);
  struct vlff_map_far_run *runs = malloc((size_t)m.nruns * sizeof *runs + 1);
  struct fblock *b = calloc(m.nblocks, sizeof *b);
  if (!blocks || !runs || !b) {
    free(blocks), free(runs), free(b);
    return *why = "out of memory", NULL;
  }
  const uint8_t *at = buf + FAR_HEAD + texts;
  memcpy(blocks, at, (size_t)m.nblocks * sizeof *blocks);
  memcpy(runs, at + (size_t)m.nblocks * sizeof *blocks, (size_t)m.nruns * sizeof *runs);
  m.blocks = blocks, m.runs = runs;
  *why = vlff_map_far_check(&m);
  for (uint32_t j = 0; !*why && j < m.nblocks; j++) {
    const uint32_t end = j + 1 < m.nblocks ? blocks[j + 1].first_run : m.nruns;
    b[j].nruns = end - blocks[j].first_run;
    memcpy(b[j].key, blocks[j].key, sizeof b[j].key);
    if (!(b[j].runs = malloc(b[j].nruns * sizeof *b[j].runs))) *why = "out of memory";
    else memcpy(b[j].runs, runs + blocks[j].first_run, b[j].nruns * sizeof *b[j].runs);
  }
  free(blocks), free(runs);
  if (*why) {
    for (uint32_t j = 0; j < m.nblocks; j++) free(b[j].runs);
    free(b);
    return NULL;
  }
  *nb = m.nblocks, *nr = m.nruns;
  return b;
}

int vlff_far_load(struct vlff_far *f, const char *path, char *err, size_t errlen) {
  if (access(path, F_OK) && errno == ENOENT) return 1;
  uint8_t *buf;
  size_t len;
  const size_t texts = (size_t)VLFF_SHM_MAX_PROMPTS * VLFF_SHM_PROMPT_LEN;
  if (vlff_read_file(path, f->max_bytes + FAR_HEAD + texts + 8, &buf, &len, err, errlen)) return -1;
  const char *why = "not a far map (VLFFFAR1)";
  uint32_t nb = 0, nr = 0, k = 0;
  struct fblock *b = len >= FAR_HEAD + 8 && !memcmp(buf, FAR_MAGIC, 8) ? far_parse(f, buf, len, &nb, &nr, &k, &why)
                                                                       : NULL;
  if (!b) {
    free(buf);
    return snprintf(err, errlen, "%s: %s", VLFF_Q(path), why), -1;
  }
  vlff_far_reset(f);
  free(f->b);
  f->b = b, f->n = f->cap = nb, f->nruns = nr;
  memset(f->texts, 0, sizeof f->texts);
  for (uint32_t i = 0; i < k; i++)
    memcpy(f->texts[i], buf + FAR_HEAD + (size_t)i * VLFF_SHM_PROMPT_LEN, VLFF_SHM_PROMPT_LEN - 1);
  f->k = (int)k;
  free(buf);
  /* A class label names one of its k prompts: any other names nothing. */
  for (size_t j = 0; j < f->n; j++)
    for (uint32_t r = 0; r < f->b[j].nruns; r++)
      if (f->b[j].runs[r].label <= VLFF_LABEL_MAX && f->b[j].runs[r].label >= k)
        f->b[j].runs[r].label = VLFF_LABEL_UNKNOWN, f->b[j].runs[r].conf = 0;
  f->gen++;
  return 0;
}
