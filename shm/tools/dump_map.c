/* vlff-shm dump-map (dump_map.h). */
#include "dump_map.h"

#include "vlff/escape.h"
#include "vlff/shm.h"

#include "files.h"
#include "palette.h"

#include <errno.h>
#include <inttypes.h>
#include <math.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Both formats are little-endian and written from memory as is. */
#if !defined(__BYTE_ORDER__) || __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "vlff-shm dump-map writes little-endian files from host memory"
#endif

struct out {
  uint8_t *p;
  size_t n, cap;
  int oom;
};

static void put(struct out *o, const void *d, size_t n) {
  if (o->oom) return;
  if (o->n + n > o->cap) {
    size_t cap = o->cap ? o->cap : 1 << 16;
    while (cap < o->n + n) cap *= 2;
    uint8_t *q = realloc(o->p, cap);
    if (!q) {
      o->oom = 1;
      return;
    }
    o->p = q, o->cap = cap;
  }
  memcpy(o->p + o->n, d, n);
  o->n += n;
}

static void putf(struct out *o, const char *fmt, const char *a, int k) {
  char line[160];
  int n = snprintf(line, sizeof line, fmt, k, a);
  put(o, line, (size_t)n < sizeof line ? (size_t)n : sizeof line - 1);
}

static int ends_with(const char *s, const char *tail) {
  size_t a = strlen(s), b = strlen(tail);
  return a >= b && !strcmp(s + a - b, tail);
}

static void write_binary(struct out *o, const struct vlff_map_info *mi, const struct vlff_map_snapshot *s,
                         size_t nvox) {
  put(o, "VLFFMAP1", 8);
  put(o, &mi->version, 8);
  put(o, &mi->publish_ns, 8);
  put(o, mi->grid.origin, 24);
  put(o, &mi->grid.voxel_size, 8);
  put(o, mi->grid.dims, 12);
  uint32_t k = (uint32_t)mi->prompt_count;
  put(o, &k, 4);
  for (int i = 0; i < mi->prompt_count; i++) {
    char text[VLFF_SHM_PROMPT_LEN] = {0};
    const char *t = vlff_map_snapshot_prompt(s, (uint16_t)i);
    snprintf(text, sizeof text, "%s", t ? t : "");
    put(o, text, sizeof text);
  }
  put(o, mi->grid.labels, nvox * 2);
  if (mi->grid.confidence) {
    put(o, mi->grid.confidence, nvox);
  } else {
    uint8_t full[4096];
    memset(full, 255, sizeof full);
    for (size_t i = 0; i < nvox; i += sizeof full) put(o, full, nvox - i < sizeof full ? nvox - i : sizeof full);
  }
}

/* The far map after the grid, when there is one: VLFFFAR1, origin, voxel
 * size, block and run counts, the blocks and the runs as in the segment. */
static void write_far(struct out *o, const struct vlff_map_far *f) {
  if (!f->nblocks) return;
  put(o, "VLFFFAR1", 8);
  put(o, f->origin, 24);
  put(o, &f->voxel_size, 8);
  put(o, &f->nblocks, 4);
  put(o, &f->nruns, 4);
  put(o, f->blocks, (size_t)f->nblocks * sizeof *f->blocks);
  put(o, f->runs, (size_t)f->nruns * sizeof *f->runs);
}

/* The far map's labelled voxels outside the grid (the grid answers inside
 * it, docs/shm.md "The far map"): their count, and each written to o when o
 * is given. */
static size_t far_labelled(struct out *o, const struct vlff_map_far *f, const struct vlff_map_grid *g) {
  const uint32_t E = VLFF_MAP_FAR_EDGE;
  size_t n = 0;
  for (uint32_t b = 0; b < f->nblocks; b++) {
    const uint32_t end = b + 1 < f->nblocks ? f->blocks[b + 1].first_run : f->nruns;
    uint32_t at = 0;
    for (uint32_t r = f->blocks[b].first_run; r < end; at += f->runs[r].count, r++) {
      const struct vlff_map_far_run *run = &f->runs[r];
      if (run->label > VLFF_LABEL_MAX) continue;
      for (uint32_t v = at; v < at + run->count; v++) {
        const uint32_t c[3] = {v % E, v / E % E, v / (E * E)};
        double w[3];
        bool in_grid = true;
        for (int a = 0; a < 3; a++) {
          w[a] = f->origin[a] + ((double)f->blocks[b].key[a] * E + c[a] + 0.5) * f->voxel_size;
          const double gi = floor((w[a] - g->origin[a]) / g->voxel_size);
          in_grid = in_grid && gi >= 0 && gi < g->dims[a];
        }
        if (in_grid) continue;
        n++;
        if (!o) continue;
        float xyz[3] = {(float)w[0], (float)w[1], (float)w[2]};
        put(o, xyz, sizeof xyz);
        put(o, vlff_label_color(run->label), 3);
        put(o, &run->label, 2);
        put(o, &run->conf, 1);
      }
    }
  }
  return n;
}

static void write_ply(struct out *o, const struct vlff_map_info *mi, const struct vlff_map_snapshot *s,
                      const struct vlff_map_far *far, size_t labelled) {
  const struct vlff_map_grid *g = &mi->grid;
  char head[512];
  int n = snprintf(head, sizeof head,
                   "ply\nformat binary_little_endian 1.0\ncomment vlff map version %" PRIu64 " voxel_size %.6g\n",
                   mi->version, g->voxel_size);
  put(o, head, (size_t)n);
  for (int i = 0; i < mi->prompt_count; i++) {
    const char *t = vlff_map_snapshot_prompt(s, (uint16_t)i);
    /* Prompts are checked text without control characters (vlff_prompt_check). */
    putf(o, "comment prompt %d %s\n", t ? t : "", i);
  }
  n = snprintf(head, sizeof head,
               "element vertex %zu\nproperty float x\nproperty float y\nproperty float z\n"
               "property uchar red\nproperty uchar green\nproperty uchar blue\n"
               "property ushort label\nproperty uchar confidence\nend_header\n",
               labelled);
  put(o, head, (size_t)n);
  for (uint32_t k = 0; k < g->dims[2]; k++)
    for (uint32_t j = 0; j < g->dims[1]; j++)
      for (uint32_t i = 0; i < g->dims[0]; i++) {
        size_t at = i + (size_t)g->dims[0] * (j + (size_t)g->dims[1] * k);
        uint16_t lab = g->labels[at];
        if (lab > VLFF_LABEL_MAX) continue;
        float xyz[3] = {(float)(g->origin[0] + (i + 0.5) * g->voxel_size),
                        (float)(g->origin[1] + (j + 0.5) * g->voxel_size),
                        (float)(g->origin[2] + (k + 0.5) * g->voxel_size)};
        uint8_t conf = g->confidence ? g->confidence[at] : 255;
        put(o, xyz, sizeof xyz);
        put(o, vlff_label_color(lab), 3);
        put(o, &lab, 2);
        put(o, &conf, 1);
      }
  far_labelled(o, far, g);
}

int vlff_dump_map(const char *name, const char *path) {
  char err[512];
  if (vlff_check_output(path, err, sizeof err) < 0) {
    fprintf(stderr, "vlff-shm: %s\n", err);
    return 1;
  }
  struct vlff_map *m = vlff_map_attach(name);
  if (!m) return vlff_shm_fail(name);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  struct vlff_map_info mi;
  struct vlff_map_far far;
  int rc = 1;
  struct out o = {0};
  if (!s || vlff_map_snapshot_take(m, s) < 0 || vlff_map_snapshot_info(s, &mi) < 0 ||
      vlff_map_snapshot_far(s, &far) < 0) {
    vlff_shm_fail(name);
    goto done;
  }
  size_t nvox = (size_t)mi.grid.dims[0] * mi.grid.dims[1] * mi.grid.dims[2];
  if (mi.version == 0) {
    fprintf(stderr, "vlff-shm: %s: no map published yet (version 0)\n", VLFF_Q(name));
    goto done;
  }
  if (nvox == 0) {
    fprintf(stderr, "vlff-shm: %s: version %" PRIu64 " holds no grid (prompts or a label image only)\n", VLFF_Q(name),
            mi.version);
    goto done;
  }
  size_t labelled = 0, free_ = 0, unknown = 0;
  for (size_t i = 0; i < nvox; i++) {
    uint16_t l = mi.grid.labels[i];
    labelled += l <= VLFF_LABEL_MAX, free_ += l == VLFF_LABEL_FREE, unknown += l == VLFF_LABEL_UNKNOWN;
  }
  const size_t far_n = far_labelled(NULL, &far, &mi.grid);
  if (ends_with(path, ".ply") || ends_with(path, ".PLY")) {
    write_ply(&o, &mi, s, &far, labelled + far_n);
  } else {
    write_binary(&o, &mi, s, nvox);
    write_far(&o, &far);
  }
  if (o.oom) {
    fprintf(stderr, "vlff-shm: %s: out of memory for %zu voxels\n", VLFF_Q(path), nvox);
  } else if (vlff_write_file_atomic(path, o.p, o.n, err, sizeof err) < 0) {
    fprintf(stderr, "vlff-shm: %s\n", err);
  } else {
    printf("version %" PRIu64 " voxels %zu labelled %zu free %zu unknown %zu", mi.version, nvox, labelled, free_,
           unknown);
    if (far.nblocks) printf(" far_blocks %" PRIu32 " far_labelled %zu", far.nblocks, far_n);
    printf(" -> %s\n", VLFF_Q(path));
    rc = 0;
  }
done:
  free(o.p);
  vlff_map_snapshot_free(s);
  vlff_map_detach(m);
  return rc;
}
