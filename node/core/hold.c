/*
 * Label hold (hold.h).
 */
#include "hold.h"

#include <stdbool.h>
#include <stdlib.h>
#include <string.h>

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
  h->st.changed += out != old;
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
