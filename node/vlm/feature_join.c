/*
 * Feature join. Both tables are small (a few keyframes in flight), so they
 * are plain arrays searched linearly; feature maps live in preallocated
 * slots so reading the ring never allocates.
 */
#include "feature_join.h"

#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <vlff/shm.h>
#include "log.h"
#include "transpose.h"
#include "mem.h"

struct waiting {
  bool used;
  uint64_t id, since_ns;
};

struct feat {
  bool used;
  uint64_t id, seq; /* seq orders eviction */
  int h, w;
  uint16_t *hwc;
};

struct vlff_feature_join {
  int cap, dim, max_h, max_w;
  uint64_t timeout_ns, seq, not_before_ns;
  struct waiting *frames;
  struct feat *feats;
  uint8_t *record; /* pump buffer */
  size_t record_cap;
  struct vlff_feature_join_stats st;
  char last_bad[256]; /* the latest bad record's reason */
};

const char *vlff_feature_join_last_bad(const struct vlff_feature_join *j) { return j->last_bad; }


struct vlff_feature_join *vlff_feature_join_create(int capacity, double timeout_s, int dim, int max_h, int max_w,
                                                   char *err, size_t errlen) {
  if (capacity < 1 || capacity > 1024 || !(timeout_s > 0) || dim < 1 || dim > 4096 || max_h < 1 || max_w < 1 ||
      (size_t)max_h * max_w * dim > ((size_t)1 << 28)) {
    vlff_errf(err, errlen, "feature join: bad geometry (capacity %d, timeout %g s, D %d, %dx%d)", capacity, timeout_s,
            dim, max_w, max_h);
    return NULL;
  }
  struct vlff_feature_join *j = calloc(1, sizeof *j);
  if (!j) goto oom;
  j->cap = capacity, j->dim = dim, j->max_h = max_h, j->max_w = max_w;
  j->timeout_ns = (uint64_t)(timeout_s * 1e9);
  j->frames = calloc((size_t)capacity, sizeof *j->frames);
  j->feats = calloc((size_t)capacity, sizeof *j->feats);
  j->record_cap = vlff_feature_slot_size((uint32_t)dim, (uint32_t)max_h, (uint32_t)max_w);
  j->record = malloc(j->record_cap);
  if (!j->frames || !j->feats || !j->record || !j->record_cap) goto oom;
  for (int i = 0; i < capacity; i++)
    if (!(j->feats[i].hwc = malloc((size_t)max_h * max_w * dim * sizeof(uint16_t)))) goto oom;
  return j;
oom:
  vlff_errf(err, errlen, "feature join: out of memory");
  vlff_feature_join_destroy(j);
  return NULL;
}

void vlff_feature_join_destroy(struct vlff_feature_join *j) {
  if (!j) return;
  for (int i = 0; j->feats && i < j->cap; i++) free(j->feats[i].hwc);
  VLFF_FREE_ALL(j->feats, j->frames, j->record, j);
}

int vlff_feature_join_add_frame(struct vlff_feature_join *j, uint64_t frame_id, uint64_t now_ns, char *err,
                                size_t errlen) {
  struct waiting *free_slot = NULL;
  for (int i = 0; i < j->cap; i++) {
    if (j->frames[i].used && j->frames[i].id == frame_id) {
      vlff_errf(err, errlen, "feature join: frame %llu is already waiting", (unsigned long long)frame_id);
      j->st.frames_refused++;
      return -1;
    }
    if (!j->frames[i].used && !free_slot) free_slot = &j->frames[i];
  }
  if (!free_slot) {
    vlff_errf(err, errlen, "feature join: %d keyframes already wait for features", j->cap);
    j->st.frames_refused++;
    return -1;
  }
  free_slot->used = true;
  free_slot->id = frame_id;
  free_slot->since_ns = now_ns;
  return 0;
}

int vlff_feature_join_add_record(struct vlff_feature_join *j, const void *record, size_t len, char *err,
                                 size_t errlen) {
  const struct vlff_feature_hdr *h = record;
  if (!record || vlff_feature_validate(record, len) != 0) {
    vlff_errf(err, errlen, "feature record: malformed (%zu bytes)", len);
    goto bad;
  }
  if (h->data_offset % 2) {
    vlff_errf(err, errlen, "feature record for frame %llu: misaligned data", (unsigned long long)h->frame_id);
    goto bad;
  }
  if (h->dtype != VLFF_FEAT_F16 || (int)h->dim != j->dim || h->height < 1 || h->width < 1 ||
      (int)h->height > j->max_h || (int)h->width > j->max_w) {
    vlff_errf(err, errlen, "feature record for frame %llu: dtype %u, [%u,%u,%u]; expected float16 with D=%d, at most %dx%d",
            (unsigned long long)h->frame_id, h->dtype, h->dim, h->height, h->width, j->dim, j->max_h, j->max_w);
    goto bad;
  }
  if (h->t_host_ns < j->not_before_ns) {
    j->st.stale++;
    return 1;
  }
  size_t hw = (size_t)h->height * h->width;
  const uint16_t *src = (const uint16_t *)((const uint8_t *)record + h->data_offset);
  /* Refuse non-finite data, and values beyond VLFF_FEATURE_MAX_ABS (no
   * vision-language model's: maps of 65504s drove the feature loss from
   * 0.05 to 1800, wrecked colour and geometry and went into the
   * checkpoint), before touching any slot (bounds.h). */
  size_t total = hw * (size_t)j->dim, outside = 0;
  for (size_t i = 0; i < total; i++) outside += (src[i] & 0x7FFFu) > VLFF_FEATURE_MAX_ABS_F16; /* vectorises */
  if (outside) {
    size_t i = 0;
    while ((src[i] & 0x7FFFu) <= VLFF_FEATURE_MAX_ABS_F16) i++;
    vlff_errf(err, errlen, "feature record for frame %llu: %s value at %zu (%zu outside [-%g, %g] in all)",
              (unsigned long long)h->frame_id, (src[i] & 0x7C00u) == 0x7C00u ? "non-finite" : "out-of-range", i,
              outside, VLFF_FEATURE_MAX_ABS, VLFF_FEATURE_MAX_ABS);
    goto bad;
  }
  struct feat *slot = NULL;
  for (int i = 0; i < j->cap && !slot; i++)
    if (j->feats[i].used && j->feats[i].id == h->frame_id) slot = &j->feats[i]; /* a resend replaces */
  for (int i = 0; i < j->cap && !slot; i++)
    if (!j->feats[i].used) slot = &j->feats[i];
  if (!slot) { /* evict the oldest orphan */
    slot = &j->feats[0];
    for (int i = 1; i < j->cap; i++)
      if (j->feats[i].seq < slot->seq) slot = &j->feats[i];
    j->st.orphans_evicted++;
  }
  vlff_transpose_u16(src, (size_t)j->dim, hw, slot->hwc); /* the ring carries [D][h][w], slots [h][w][D] */
  slot->used = true;
  slot->id = h->frame_id;
  slot->seq = ++j->seq;
  slot->h = (int)h->height;
  slot->w = (int)h->width;
  return 0;
bad:
  j->st.bad_records++;
  if (err && errlen) snprintf(j->last_bad, sizeof j->last_bad, "%s", err);
  return -1;
}

int vlff_feature_join_pump(struct vlff_feature_join *j, struct vlff_ring *ring) {
  int accepted = 0;
  for (;;) {
    ssize_t n = vlff_ring_read_copy(ring, j->record, j->record_cap, NULL, 0);
    if (n < 0) {
      if (errno == EMSGSIZE) { /* too large for the configured geometry: skipped by the ring */
        j->st.bad_records++;
        continue;
      }
      if (errno == EPIPE) return -1;
      return accepted;
    }
    char err[256];
    if (vlff_feature_join_add_record(j, j->record, (size_t)n, err, sizeof err) == 0) accepted++;
  }
}

int vlff_feature_join_poll(struct vlff_feature_join *j, uint64_t now_ns, uint64_t *frame_id, uint16_t *out, int *h,
                           int *w) {
  for (int i = 0; i < j->cap; i++) {
    struct waiting *f = &j->frames[i];
    if (!f->used) continue;
    for (int k = 0; k < j->cap; k++) {
      struct feat *ft = &j->feats[k];
      if (!ft->used || ft->id != f->id) continue;
      *frame_id = f->id;
      *h = ft->h;
      *w = ft->w;
      memcpy(out, ft->hwc, (size_t)ft->h * ft->w * j->dim * sizeof *out);
      f->used = false;
      ft->used = false;
      j->st.joined++;
      return VLFF_JOIN_READY;
    }
  }
  for (int i = 0; i < j->cap; i++) {
    struct waiting *f = &j->frames[i];
    if (f->used && now_ns >= f->since_ns && now_ns - f->since_ns > j->timeout_ns) {
      *frame_id = f->id;
      f->used = false;
      j->st.expired++;
      return VLFF_JOIN_EXPIRED;
    }
  }
  return VLFF_JOIN_NONE;
}

void vlff_feature_join_not_before(struct vlff_feature_join *j, uint64_t t_ns) { j->not_before_ns = t_ns; }

void vlff_feature_join_stats(const struct vlff_feature_join *j, struct vlff_feature_join_stats *st) { *st = j->st; }
