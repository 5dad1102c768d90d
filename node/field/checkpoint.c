/*
 * Checkpoints: the whole learned state in one versioned binary file.
 *
 * Layout (host byte order, checked by a byte-order mark):
 *   header  : magic "VLFFCKPT", version, byte-order mark, config field hash,
 *             array sizes, step, rng, occupancy cursor, the encoding's
 *             cells (from version 5; before, per axis); from version 6 the
 *             occupancy grid's place on its lattice (first cell, cells per
 *             axis: the box, which a growing field's checkpoint restores);
 *             from version 7 the occupancy cells' size per axis (float64)
 *   arrays  : params, Adam m, Adam v (float32), occupancy density (float32),
 *             occupancy bits (uint8), per-cell exposure (uint16; from
 *             version 2), the averaged MLP weights queries read (float32,
 *             the MLP's share of params; from version 3), each cell's
 *             running feature loss and the candidates' mean (float32 per
 *             cell, one float64; train.error_sampling; from version 4)
 *   trailer : 64-bit checksum of everything before it
 * Save writes "<path>.tmp.<pid>", fsyncs, renames over path and fsyncs the
 * directory, and refuses to write a state that vlff_field_check refuses.
 * Load reads into fresh buffers and swaps them in only after the header,
 * sizes and checksum all match and every value is within the bounds of
 * field.h (the checksum guards against corruption, not forgery: anyone who
 * can write the file can recompute it), so a bad file leaves f untouched.
 */
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "field_internal.h"
#include "files.h"
#include "mem.h"

#define CKPT_MAGIC "VLFFCKPT"
#define CKPT_VERSION 7u
/* Version 1 lacks the exposure; it still loads, the field counting as fitted
 * everywhere, so a robot's learned map survives the upgrade. Its later
 * checkpoints carry that on until a mapping reset: nothing tells where an
 * old field was fitted. */
#define CKPT_VERSION_NO_EXPOSURE 1u
/* Versions 1 and 2 lack the averaged weights: the average restarts from
 * the trained weights, which it follows within a few hundred steps. */
#define CKPT_VERSION_NO_AVERAGE 2u
/* Versions 1-3 lack the cells' running losses: error sampling measures them
 * anew (every cell is drawn as not yet trained until a ray ends there). */
#define CKPT_VERSION_NO_ERRORS 3u
/* Versions 1-4 were learned in cells scaled to the box per axis: their
 * field loads in those cells, and says so in its later checkpoints
 * (header's cells: 0) until a mapping reset makes them cubic. */
#define CKPT_VERSION_AXIS_CELLS 4u
/* Versions 1-5 hold no box: their grid is the fixed box's (growing fields
 * came with version 6). */
#define CKPT_VERSION_NO_BOX 5u
/* Version 6 does not say its occupancy cells' size: a growing field's
 * cells were then cubes of its first box's longest side over
 * train.occupancy_resolution, so it loads only where the cells still are
 * (train.occupancy_cell_m 0 and a cubic first box). */
#define CKPT_VERSION_NO_CELL_SIZE 6u
#define CKPT_BOM 0x01020304u

struct ckpt_header {
  char magic[8];
  uint32_t version, bom;
  uint64_t config_hash;
  uint64_t nparams, ntable, ncells;
  int64_t step;
  uint64_t rng;
  int64_t occ_cursor;
  int32_t feature_dim, cells; /* cells (from version 5): 1 cubic, 0 scaled per axis (encoding.c) */
};
struct ckpt_box { /* from version 6, after the header */
  int32_t k0[3], dims[3];
};
struct ckpt_cell { /* from version 7, after the box: the occupancy cells' size (m) per axis */
  double m[3];
};

/* Word-wise FNV-style mix: fast enough for hundreds of MB. */
struct sum {
  uint64_t h;
  unsigned char tail[8];
  int ntail;
};
static void sum_init(struct sum *s) {
  s->h = 0xcbf29ce484222325ull;
  s->ntail = 0;
}
static void sum_word(struct sum *s, uint64_t w) {
  s->h ^= w;
  s->h *= 0x100000001b3ull;
  s->h ^= s->h >> 29;
}
static void sum_add(struct sum *s, const void *p, size_t n) {
  const unsigned char *b = p;
  while (n && s->ntail) {
    s->tail[s->ntail++] = *b++;
    n--;
    if (s->ntail == 8) {
      uint64_t w;
      memcpy(&w, s->tail, 8);
      sum_word(s, w);
      s->ntail = 0;
    }
  }
  for (; n >= 8; n -= 8, b += 8) {
    uint64_t w;
    memcpy(&w, b, 8);
    sum_word(s, w);
  }
  while (n--) s->tail[s->ntail++] = *b++;
}
static uint64_t sum_final(struct sum *s) {
  uint64_t w = 0;
  memcpy(&w, s->tail, (size_t)s->ntail);
  sum_word(s, w ^ ((uint64_t)s->ntail << 56));
  return s->h;
}

/* The first of x[0, n) outside [lo, hi] (or NaN): its index, n when none.
 * Blocks of 1024 without a branch per value, then the block that has one. */
static size_t first_outside(const float *x, size_t n, float lo, float hi) {
  for (size_t b = 0; b < n; b += 1024) {
    size_t e = n - b < 1024 ? n : b + 1024;
    int bad = 0;
    for (size_t i = b; i < e; i++) bad |= !(x[i] >= lo && x[i] <= hi);
    if (bad)
      for (size_t i = b; i < e; i++)
        if (!(x[i] >= lo && x[i] <= hi)) return i;
  }
  return n;
}

/* Checks one tensor against [lo, hi]; on the first value outside, writes
 * "name[i] (part) = value, not finite | outside [lo, hi]" to why and
 * returns -1. split: where the MLP part of a params-shaped array begins
 * (SIZE_MAX: the tensor has no parts). */
static int check_tensor(const char *name, const float *x, size_t n, size_t split, float lo, float hi, char *why,
                        size_t len) {
  size_t i = first_outside(x, n, lo, hi);
  if (i == n) return 0;
  const char *part = split == SIZE_MAX ? "" : i < split ? " (hash table)" : " (MLP weights)";
  if (isfinite(x[i]))
    snprintf(why, len, "%s[%zu]%s = %g, outside [%g, %g]", name, i, part, (double)x[i], (double)lo, (double)hi);
  else
    snprintf(why, len, "%s[%zu]%s = %g, not finite", name, i, part, (double)x[i]);
  return -1;
}

/* The learned state's bounds (field.h), tensor by tensor; the first value
 * outside is named in why. */
static int check_state(size_t ntable, size_t nparams, size_t nmlp, size_t ncells, const float *p, const float *m,
                       const float *v, const float *avg, const float *dens, char *why, size_t len) {
  const float P = VLFF_FIELD_MAX_PARAM, M = VLFF_FIELD_MAX_MOMENT1, V = VLFF_FIELD_MAX_MOMENT2;
  return check_tensor("params", p, nparams, ntable, -P, P, why, len) ||
         check_tensor("adam_m", m, nparams, ntable, -M, M, why, len) ||
         check_tensor("adam_v", v, nparams, ntable, 0.0f, V, why, len) ||
         check_tensor("avg", avg, nmlp, 0, -P, P, why, len) ||
         check_tensor("occupancy density", dens, ncells, SIZE_MAX, 0.0f, VLFF_FIELD_MAX_DENSITY, why, len);
}

int vlff_field_check(const struct vlff_field *f, char *err, size_t errlen) {
  char why[160];
  if (!check_state(f->ntable, f->nparams, f->nmlp, vlff_occ_cells(&f->occ), f->params, f->adam_m, f->adam_v, f->avg,
                   f->occ.density, why, sizeof why))
    return 0;
  if (err && errlen) snprintf(err, errlen, "field at step %lld: %s", f->step, why);
  return -1;
}

static int write_all(int fd, const void *p, size_t n, struct sum *s) {
  if (s) sum_add(s, p, n);
  return vlff_write_all(fd, p, n);
}

static int read_all(int fd, void *p, size_t n, struct sum *s) {
  char *c = p;
  size_t want = n;
  while (n) {
    ssize_t k = read(fd, c, n > (1u << 24) ? (1u << 24) : n);
    if (k < 0) {
      if (errno == EINTR) continue;
      return -1;
    }
    if (k == 0) return 1;  /* truncated */
    c += k;
    n -= (size_t)k;
  }
  if (s) sum_add(s, p, want);
  return 0;
}

int vlff_field_save(const struct vlff_field *f, const char *path, char *err, size_t errlen) {
  if (!f || !path) {
    if (err && errlen) snprintf(err, errlen, "checkpoint: no field or path");
    return -1;
  }
  char cerr[384];
  /* A diverged field is never written: it would replace the last good
   * checkpoint, the one a rollback goes back to. */
  if (vlff_field_check(f, cerr, sizeof cerr)) {
    if (err && errlen) snprintf(err, errlen, "checkpoint %s: not written: %s", path, cerr);
    return -1;
  }
  struct vlff_atomic a;
  if (vlff_atomic_begin(&a, path, 0644, cerr, sizeof cerr) < 0) {
    if (err && errlen) snprintf(err, errlen, "checkpoint %s", cerr);
    return -1;
  }
  const int fd = a.fd;
  struct ckpt_header h;
  memset(&h, 0, sizeof(h));
  memcpy(h.magic, CKPT_MAGIC, 8);
  h.version = CKPT_VERSION;
  h.bom = CKPT_BOM;
  h.config_hash = vlff_config_field_hash(&f->cfg.field);
  h.nparams = f->nparams;
  h.ntable = f->ntable;
  h.ncells = vlff_occ_cells(&f->occ);
  h.step = f->step;
  h.rng = f->rng;
  h.occ_cursor = f->occ_cursor;
  h.feature_dim = f->D;
  h.cells = f->enc.cubic;
  struct ckpt_box b;
  for (int i = 0; i < 3; i++) b.k0[i] = f->occ_k0[i], b.dims[i] = f->occ.dims[i];
  struct ckpt_cell cell;
  for (int i = 0; i < 3; i++) cell.m[i] = f->occ.cell[i];
  struct sum s;
  sum_init(&s);
  size_t np = f->nparams * sizeof(float), nc = vlff_occ_cells(&f->occ);
  int rc = write_all(fd, &h, sizeof(h), &s) || write_all(fd, &b, sizeof b, &s) ||
           write_all(fd, &cell, sizeof cell, &s) || write_all(fd, f->params, np, &s) ||
           write_all(fd, f->adam_m, np, &s) || write_all(fd, f->adam_v, np, &s) ||
           write_all(fd, f->occ.density, nc * sizeof(float), &s) || write_all(fd, f->occ.occ, nc, &s) ||
           write_all(fd, f->exposure, nc * sizeof(uint16_t), &s) || write_all(fd, f->avg, f->nmlp * sizeof(float), &s) ||
           write_all(fd, f->cell_err, nc * sizeof(float), &s) || write_all(fd, &f->err_mean, sizeof f->err_mean, &s);
  if (!rc) {
    uint64_t cs = sum_final(&s);
    rc = write_all(fd, &cs, sizeof(cs), NULL);
  }
  if (rc) {
    if (err && errlen) snprintf(err, errlen, "checkpoint %s: write failed: %s", path, strerror(errno));
    vlff_atomic_abort(&a);
    return -1;
  }
  if (vlff_atomic_commit(&a, cerr, sizeof cerr) < 0) {
    if (err && errlen) snprintf(err, errlen, "checkpoint %s", cerr);
    return -1;
  }
  return 0;
}

/* A checkpoint's box: the fixed box's grid when fixed; when growing, cells
 * of the lattice within the world and within train.occupancy_max_mb. */
static int box_check(const struct vlff_field *f, const struct ckpt_box *b, char *why, size_t len) {
  const struct vlff_field_cfg *c = &f->cfg;
  double cells = 1;
  for (int a = 0; a < 3; a++) {
    if (!c->field.grow) {
      if (b->k0[a] != 0 || b->dims[a] != c->train.occupancy_resolution) {
        snprintf(why, len, "box: grid axis %d is cells [%d, +%d), the fixed box's is [0, +%d)", a, (int)b->k0[a],
                 (int)b->dims[a], c->train.occupancy_resolution);
        return -1;
      }
      continue;
    }
    double lo = f->first_lo[a] + (double)b->k0[a] * f->occ.cell[a], hi = lo + (double)b->dims[a] * f->occ.cell[a];
    double w = c->field.world_limit_m + f->occ.cell[a];
    if (b->dims[a] < 1 || !(lo >= -w && hi <= w)) {
      snprintf(why, len, "box: axis %d spans [%g, %g] m, not within field.world_limit_m (%g)", a, lo, hi,
               c->field.world_limit_m);
      return -1;
    }
    cells *= b->dims[a];
  }
  if (!vlff_occ_fits(&c->train, cells)) {
    snprintf(why, len, "box: %.0f occupancy cells, more than train.occupancy_max_mb (%g) holds", cells,
             c->train.occupancy_max_mb);
    return -1;
  }
  return 0;
}

/* A checkpoint's occupancy cells: the densities, exposures and losses it
 * holds are per cell, so cells of another size (train.occupancy_cell_m or
 * occupancy_resolution changed) would put them in the wrong places. */
static int cell_check(const struct vlff_field *f, const struct ckpt_cell *c, char *why, size_t len) {
  for (int a = 0; a < 3; a++)
    if (!(fabs(c->m[a] - f->occ.cell[a]) <= 1e-6 * f->occ.cell[a])) {
      const bool cube = c->m[0] == c->m[1] && c->m[0] == c->m[2];
      /* A growing field's cubes from before the cells followed the first
       * box's sides: the key that resumes it. */
      char hint[96] = "";
      if (cube && f->cfg.field.grow) snprintf(hint, sizeof hint, "; train.occupancy_cell_m: %.7g resumes it", c->m[0]);
      snprintf(why, len,
               "occupancy cells of %g m on axis %d, this node's are %g m (train.occupancy_cell_m or "
               "occupancy_resolution changed)%s",
               c->m[a], a, (double)f->occ.cell[a], hint);
      return -1;
    }
  return 0;
}

/* Whether a checkpoint's hash is this field section's with field.grow set
 * to grow: growth became the default, and a node upgraded over a fixed
 * box's checkpoint should be told the one key that refuses it. */
static bool written_growing(const struct vlff_cfg_field *c, uint64_t hash, bool grow) {
  struct vlff_cfg_field other = *c;
  other.grow = grow;
  return vlff_config_field_hash(&other) == hash;
}

int vlff_field_load(struct vlff_field *f, const char *path, char *err, size_t errlen) {
  if (!f || !path) {
    if (err && errlen) snprintf(err, errlen, "checkpoint: no field or path");
    return -1;
  }
  char oerr[384];
  int fd = vlff_open_regular(path, oerr, sizeof oerr);
  if (fd < 0) {
    if (err && errlen) snprintf(err, errlen, "checkpoint %s", oerr);
    return -1;
  }
  struct ckpt_header h;
  struct sum s;
  sum_init(&s);
  const char *why = NULL;
  char whybuf[320];
  float *p = NULL, *m = NULL, *v = NULL, *dens = NULL, *avg = NULL, *cerr = NULL;
  double err_mean = 0;
  uint8_t *occ = NULL;
  uint16_t *expo = NULL;
  size_t np = f->nparams, nc = vlff_occ_cells(&f->occ);
  struct ckpt_box b;
  for (int i = 0; i < 3; i++) b.k0[i] = f->occ_k0[i], b.dims[i] = f->occ.dims[i];
  int r = read_all(fd, &h, sizeof(h), &s);
  if (!r && !memcmp(h.magic, CKPT_MAGIC, 8) && h.version > CKPT_VERSION_NO_BOX && h.version <= CKPT_VERSION) {
    r = read_all(fd, &b, sizeof b, &s);
    /* the cells first: the box is counted in them */
    if (!r && h.version > CKPT_VERSION_NO_CELL_SIZE) {
      struct ckpt_cell cell;
      r = read_all(fd, &cell, sizeof cell, &s);
      if (!r && cell_check(f, &cell, whybuf, sizeof whybuf)) why = whybuf;
    } else if (!r && f->cfg.field.grow &&
               (f->cfg.train.occupancy_cell_m > 0 || f->occ.cell[0] != f->occ.cell[1] || f->occ.cell[0] != f->occ.cell[2])) {
      why = "a growing field's checkpoint before version 7 does not say its occupancy cells' size: it loads only "
            "with train.occupancy_cell_m 0 and a cubic first box (its cells were the first box's longest side / "
            "occupancy_resolution)";
    }
    if (!r && !why && box_check(f, &b, whybuf, sizeof whybuf)) why = whybuf;
    nc = (size_t)b.dims[0] * b.dims[1] * b.dims[2]; /* within the cap when box_check passed */
  } else if (!r && f->cfg.field.grow) {
    nc = 0, why = "a growing field's checkpoint holds its box (version 6 on), this one none";
  }
  if (why) {
    /* the box's verdict */
  } else if (r)
    why = "truncated header";
  else if (memcmp(h.magic, CKPT_MAGIC, 8))
    why = "not a vlff checkpoint (bad magic)";
  else if (h.version < CKPT_VERSION_NO_EXPOSURE || h.version > CKPT_VERSION)
    why = "unsupported version";
  else if (h.bom != CKPT_BOM)
    why = "written on a machine of other byte order";
  else if (h.config_hash != vlff_config_field_hash(&f->cfg.field))
    why = written_growing(&f->cfg.field, h.config_hash, !f->cfg.field.grow)
              ? (f->cfg.field.grow ? "model configuration (field.*) differs from this node's: it was written with "
                                     "field.grow false (a fixed box, once the default); set that to resume it"
                                   : "model configuration (field.*) differs from this node's: it was written with "
                                     "field.grow true; set that to resume it")
              : "model configuration (field.*) differs from this node's";
  else if (h.nparams != np || h.ntable != f->ntable || h.ncells != nc || h.feature_dim != f->D)
    why = "array sizes differ from this model";
  else if (h.version > CKPT_VERSION_AXIS_CELLS && h.cells != 0 && h.cells != 1)
    why = "cells neither cubic (1) nor per axis (0)";
  else if (f->cfg.field.grow && h.cells != 1)
    why = "a growing field's cells are cubic (1)";
  else if (h.step < 0 || h.step > VLFF_FIELD_MAX_STEP) {
    snprintf(whybuf, sizeof whybuf, "step %lld outside [0, %lld]", (long long)h.step, (long long)VLFF_FIELD_MAX_STEP);
    why = whybuf;
  } else if (h.occ_cursor < 0 || (uint64_t)h.occ_cursor >= nc)
    why = "header values out of range";
  if (!why) {
    if (posix_memalign((void **)&p, 64, np * sizeof(float)) || posix_memalign((void **)&m, 64, np * sizeof(float)) ||
        posix_memalign((void **)&v, 64, np * sizeof(float)) ||
        posix_memalign((void **)&dens, 64, nc * sizeof(float)) || !(occ = malloc(nc)) ||
        !(expo = malloc(nc * sizeof *expo)) || posix_memalign((void **)&avg, 64, f->nmlp * sizeof(float)) ||
        !(cerr = malloc(nc * sizeof *cerr)))
      why = "out of memory";
  }
  if (!why) {
    r = read_all(fd, p, np * sizeof(float), &s);
    if (!r) r = read_all(fd, m, np * sizeof(float), &s);
    if (!r) r = read_all(fd, v, np * sizeof(float), &s);
    if (!r) r = read_all(fd, dens, nc * sizeof(float), &s);
    if (!r) r = read_all(fd, occ, nc, &s);
    if (!r && h.version > CKPT_VERSION_NO_EXPOSURE) r = read_all(fd, expo, nc * sizeof *expo, &s);
    if (!r && h.version > CKPT_VERSION_NO_AVERAGE) r = read_all(fd, avg, f->nmlp * sizeof(float), &s);
    if (!r && h.version > CKPT_VERSION_NO_ERRORS) r = read_all(fd, cerr, nc * sizeof *cerr, &s);
    if (!r && h.version > CKPT_VERSION_NO_ERRORS) r = read_all(fd, &err_mean, sizeof err_mean, &s);
    uint64_t cs = 0;
    if (!r) r = read_all(fd, &cs, sizeof(cs), NULL);
    char extra;
    if (r)
      why = r > 0 ? "truncated" : "read error";
    else if (cs != sum_final(&s))
      why = "checksum mismatch (corrupt file)";
    else if (read(fd, &extra, 1) != 0)
      why = "trailing bytes after the checksum";
  }
  /* A forged file (its checksum recomputed) with NaN parameters, negative
   * second moments or 3e38 values would resume and train on as NaN. Before
   * version 3 the average is not in the file: it restarts from params. */
  if (!why && check_state(f->ntable, np, f->nmlp, nc, p, m, v, h.version > CKPT_VERSION_NO_AVERAGE ? avg : p + f->ntable,
                          dens, whybuf, sizeof whybuf))
    why = whybuf;
  if (!why && h.version > CKPT_VERSION_NO_ERRORS) {
    /* Each cell's loss is -1 (none yet) or a loss: a forged value would
     * steer every ray. */
    if (!(isfinite(err_mean) && err_mean >= 0)) why = "error sampling's mean loss out of range";
    for (size_t i = 0; !why && i < nc; i++)
      if (!(isfinite(cerr[i]) && (cerr[i] >= 0 || cerr[i] == -1.0f))) why = "a cell's running loss out of range";
  }
  close(fd);
  if (why) {
    if (err && errlen) snprintf(err, errlen, "checkpoint %s: refused: %s", path, why);
    VLFF_FREE_ALL(p, m, v, dens, occ, expo, avg, cerr);
    return -1;
  }
  VLFF_FREE_ALL(f->params, f->adam_m, f->adam_v, f->occ.density, f->occ.occ, f->exposure, f->avg, f->cell_err);
  for (int i = 0; i < 3; i++) f->occ_k0[i] = b.k0[i], f->occ.dims[i] = b.dims[i];
  f->params = p;
  f->adam_m = m;
  f->adam_v = v;
  f->occ.density = dens;
  f->occ.occ = occ;
  f->step = h.step;
  f->rng = h.rng;
  f->occ_cursor = (int)h.occ_cursor;
  vlff_encoding_set_cells(&f->enc, h.version > CKPT_VERSION_AXIS_CELLS ? h.cells : 0);
  vlff_field_set_box(f);
  /* Where the field was fitted is learned state too: resumed with less,
   * its cosines would outweigh the evidence where it has hardly trained
   * (the kill -9 test saw the resumed 3D map 5-8 points below the one
   * checkpointed). A version-1 file does not say: the field counts as
   * fitted everywhere, as before exposure was counted. */
  if (h.version == CKPT_VERSION_NO_EXPOSURE)
    for (size_t i = 0; i < nc; i++) expo[i] = UINT16_MAX;
  f->exposure = expo;
  /* Where rays are drawn: resumed without it, the field trains on as if
   * nothing were fitted (and a resumed run would not repeat the original). */
  f->cell_err = cerr;
  f->err_mean = err_mean;
  if (h.version <= CKPT_VERSION_NO_ERRORS) vlff_field_forget_errors(f);
  /* The average is what the map was read from: resumed from the trained
   * weights instead, the map would move by the jitter the average removes. */
  f->avg = avg;
  if (h.version <= CKPT_VERSION_NO_AVERAGE) vlff_field_reset_average(f);
  else vlff_field_refresh(f);
  return 0;
}

int vlff_field_rollback(struct vlff_field *f, const char *const *paths, int npaths, char *err, size_t errlen) {
  if (err && errlen) err[0] = 0;
  size_t used = 0;
  /* Newest first: each round takes the newest file not yet tried. */
  unsigned char tried[64] = {0};
  if (npaths > 64) npaths = 64;
  for (;;) {
    int best = -1;
    struct timespec bt = {0, 0};
    for (int i = 0; i < npaths; i++) {
      struct stat sb;
      if (tried[i] || !paths[i] || stat(paths[i], &sb)) continue;
      if (best < 0 || sb.st_mtim.tv_sec > bt.tv_sec ||
          (sb.st_mtim.tv_sec == bt.tv_sec && sb.st_mtim.tv_nsec > bt.tv_nsec))
        best = i, bt = sb.st_mtim;
    }
    if (best < 0) break;
    tried[best] = 1;
    char lerr[512];
    if (vlff_field_load(f, paths[best], lerr, sizeof lerr) == 0) return best;
    if (err && errlen > used) {
      int k = snprintf(err + used, errlen - used, "%s%s", used ? "; " : "", lerr);
      used = k < 0 ? used : used + (size_t)k < errlen ? used + (size_t)k : errlen - 1;
    }
  }
  vlff_field_reinit(f);
  return -1;
}
