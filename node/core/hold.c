/*
 * Label hold (hold.h).
 */
#include "hold.h"

#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "lattice.h"
#include "mem.h"
#include "vlff/shm.h"

struct vlff_hold {
  size_t nvox;
  float h;
  uint32_t kf;        /* keyframes begun, from 1 (0: none yet) */
  uint16_t *label;    /* [nvox] held label, VLFF_LABEL_UNKNOWN: none */
  uint32_t *seen;     /* [nvox] the keyframe that last observed it (0: none) */
  uint32_t *decided;  /* [nvox] kf when its label was last decided */
  struct vlff_hold_stats st;
};

struct vlff_hold *vlff_hold_create(size_t nvox, double hysteresis) {
  struct vlff_hold *h = calloc(1, sizeof *h);
  if (!h) return NULL;
  h->nvox = nvox;
  h->h = (float)hysteresis;
  h->label = malloc((nvox ? nvox : 1) * sizeof *h->label);
  h->seen = malloc((nvox ? nvox : 1) * sizeof *h->seen);
  h->decided = malloc((nvox ? nvox : 1) * sizeof *h->decided);
  if (!h->label || !h->seen || !h->decided) {
    vlff_hold_destroy(h);
    return NULL;
  }
  vlff_hold_reset(h);
  return h;
}

void vlff_hold_destroy(struct vlff_hold *h) {
  if (!h) return;
  VLFF_FREE_ALL(h->label, h->seen, h->decided, h);
}

int vlff_hold_grow(struct vlff_hold *h, const uint32_t dims[3], const int32_t sh[3], const uint32_t nd[3]) {
  uint16_t *label = vlff_lattice_regrid(h->label, sizeof *label, 0xff, dims, sh, nd); /* VLFF_LABEL_UNKNOWN */
  uint32_t *seen = vlff_lattice_regrid(h->seen, sizeof *seen, 0, dims, sh, nd);
  uint32_t *decided = vlff_lattice_regrid(h->decided, sizeof *decided, 0, dims, sh, nd);
  if (!label || !seen || !decided) {
    VLFF_FREE_ALL(label, seen, decided);
    return -1;
  }
  VLFF_FREE_ALL(h->label, h->seen, h->decided);
  h->label = label, h->seen = seen, h->decided = decided;
  h->nvox = vlff_lattice_cells(nd);
  return 0;
}

void vlff_hold_reset(struct vlff_hold *h) {
  memset(h->label, 0xff, h->nvox * sizeof *h->label); /* VLFF_LABEL_UNKNOWN */
  memset(h->seen, 0, h->nvox * sizeof *h->seen);
  memset(h->decided, 0, h->nvox * sizeof *h->decided);
  h->kf = 0;
  memset(&h->st, 0, sizeof h->st);
}

void vlff_hold_keyframe(struct vlff_hold *h) {
  /* After 2^32 keyframes the stamps would wrap and old evidence read as
   * new; starting over then only re-decides every label once. */
  if (h->kf == UINT32_MAX) {
    memset(h->seen, 0, h->nvox * sizeof *h->seen);
    memset(h->decided, 0, h->nvox * sizeof *h->decided);
    h->kf = 0;
  }
  h->kf++;
}

void vlff_hold_observed(struct vlff_hold *h, size_t vi) { h->seen[vi] = h->kf; }

void vlff_hold_begin(struct vlff_hold *h) { memset(&h->st, 0, sizeof h->st); }

static bool is_class(uint16_t l) { return l <= VLFF_LABEL_MAX; }

uint16_t vlff_hold_label(struct vlff_hold *h, size_t vi, uint16_t label, float margin) {
  const uint16_t old = h->label[vi];
  /* The evidence stamp: a keyframe observed the voxel after the label was
   * last decided (at the same keyframe count, the observations came first:
   * vlff_hold_keyframe precedes them). */
  const bool fresh = h->seen[vi] > h->decided[vi] || (h->seen[vi] && old == VLFF_LABEL_UNKNOWN);
  uint16_t out = label;
  if (old != VLFF_LABEL_UNKNOWN && !fresh && old != label && is_class(old) && is_class(label) && !(margin > h->h))
    out = old;
  h->st.decided++;
  /* A voxel labelled for the first time is new to the map, not a flip: a
   * reader's copy had nothing there to change. */
  h->st.changed += out != old && old != VLFF_LABEL_UNKNOWN;
  if (old != VLFF_LABEL_UNKNOWN && !fresh) {
    h->st.mapped_elsewhere++;
    h->st.changed_elsewhere += out != old;
  }
  h->label[vi] = out;
  h->decided[vi] = h->kf;
  return out;
}

void vlff_hold_forget(struct vlff_hold *h, size_t vi) { h->label[vi] = VLFF_LABEL_UNKNOWN; }

const struct vlff_hold_stats *vlff_hold_stats(const struct vlff_hold *h) { return &h->st; }

/* Saved per voxel: the label (u16, little-endian as the host's other saved
 * grids: the file is this machine's own) and flags. */
enum { HOLD_SEEN = 1, HOLD_FRESH = 2, HOLD_BYTES = 3 };

size_t vlff_hold_save_size(const struct vlff_hold *h) { return h->nvox * HOLD_BYTES; }

void vlff_hold_save(const struct vlff_hold *h, uint8_t *out) {
  for (size_t i = 0; i < h->nvox; i++, out += HOLD_BYTES) {
    memcpy(out, &h->label[i], 2);
    out[2] = (uint8_t)((h->seen[i] ? HOLD_SEEN : 0) | (h->seen[i] > h->decided[i] ? HOLD_FRESH : 0));
  }
}

int vlff_hold_load(struct vlff_hold *h, const uint8_t *in, size_t len, char *err, size_t errlen) {
  if (len != h->nvox * HOLD_BYTES) {
    snprintf(err, errlen, "label hold: %zu bytes, expected %zu for %zu voxels", len, h->nvox * HOLD_BYTES, h->nvox);
    return -1;
  }
  for (size_t i = 0; i < h->nvox; i++) {
    const uint8_t *q = in + i * HOLD_BYTES;
    uint16_t l;
    memcpy(&l, q, 2);
    if (l >= VLFF_SHM_MAX_PROMPTS && l != VLFF_LABEL_FREE && l != VLFF_LABEL_UNKNOWN) {
      snprintf(err, errlen, "label hold: voxel %zu holds label %u, not one of %d prompts, free or unknown", i, l,
               VLFF_SHM_MAX_PROMPTS);
      return -1;
    }
    if (q[2] & ~(HOLD_SEEN | HOLD_FRESH) || (q[2] & HOLD_FRESH && !(q[2] & HOLD_SEEN))) {
      snprintf(err, errlen, "label hold: voxel %zu has flags 0x%02x (known: seen 0x1, fresh 0x3)", i, q[2]);
      return -1;
    }
  }
  /* Stamps 1 (decided, or seen and not since) and 2 (seen since its label
   * was decided) keep every voxel's order; new keyframes count from 3. */
  memset(&h->st, 0, sizeof h->st);
  h->kf = 2;
  for (size_t i = 0; i < h->nvox; i++) {
    const uint8_t *q = in + i * HOLD_BYTES;
    memcpy(&h->label[i], q, 2);
    h->decided[i] = 1;
    h->seen[i] = q[2] & HOLD_FRESH ? 2 : q[2] & HOLD_SEEN ? 1 : 0;
  }
  return 0;
}
