/* libFuzzer target: the MCAP reader vlff-view --play opens recordings with (mcap.c),
 * and the inputs reader vlff-replay validates MCAP recordings with (inputs.c).
 * Promises checked: no crash, no read past the bytes or the chunk it decompressed;
 * an error names the byte offset; every message read is on a channel the file
 * defined before it, with its data inside the file or the chunk; reading again
 * after a rewind gives the same messages and the same end. The inputs reader:
 * every event it hands out is within the bounds inputs.h promises (sizes, D,
 * finite unit-quaternion poses, intrinsics), its data readable; an error is one
 * line; a rewind gives the same events. */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <math.h>

#include "inputs.h"
#include "mcap.h"
#include "vlff/shm.h"

/* The inputs reader's events and how its walk ended: 0 end, -1 error. */
static int walk_inputs(struct vlff_in_reader *r, uint64_t *count, uint64_t *sum) {
  char why[512];
  struct vlff_in_event ev;
  int rc;
  *count = *sum = 0;
  while ((rc = vlff_in_next(r, &ev, why, sizeof why)) == 1) {
    uint64_t h = ev.t_ns ^ (uint64_t)ev.kind;
    if (ev.kind == VLFF_IN_EV_FRAME) {
      if (!ev.width || !ev.height || ev.width > 65536 || ev.height > 65536 || !vlff_pixfmt_bpp(ev.color_format) ||
          !(ev.fx > 0) || !(ev.fy > 0) || !isfinite(ev.cx) || !isfinite(ev.cy))
        __builtin_trap();
      size_t n = (size_t)ev.width * ev.height * vlff_pixfmt_bpp(ev.color_format);
      for (size_t i = 0; i < n; i++) h = h * 31 + ev.color[i];
      if (ev.depth_format) {
        n = (size_t)ev.width * ev.height * vlff_pixfmt_bpp(ev.depth_format);
        for (size_t i = 0; i < n; i++) h = h * 31 + ev.depth[i];
      } else if (ev.depth) {
        __builtin_trap();
      }
    } else if (ev.kind == VLFF_IN_EV_POSE) {
      for (int i = 0; i < 16; i++) {
        if (!isfinite(ev.pose[i])) __builtin_trap();
        h = h * 31 + (uint64_t)(int64_t)(ev.pose[i] * 1e6);
      }
      if (ev.pose[15] != 1) __builtin_trap();
    } else if (ev.kind == VLFF_IN_EV_FEATURES) {
      if (!ev.dim || ev.dim > VLFF_IN_MAX_DIM || !ev.feat_height || !ev.feat_width ||
          (size_t)2 * ev.dim * ev.feat_height * ev.feat_width > VLFF_IN_MAX_FEATURE_BYTES)
        __builtin_trap();
      size_t n = (size_t)ev.dim * ev.feat_height * ev.feat_width;
      for (size_t i = 0; i < n; i++) h = h * 31 + ev.features[i];
    } else {
      __builtin_trap();
    }
    (*count)++;
    *sum += h;
  }
  if (rc < 0) {
    if (!memchr(why, 0, sizeof why) || !why[0] || strchr(why, '\n')) __builtin_trap();
    return -1;
  }
  return 0;
}

/* The messages read and how the walk ended: 0 end, 1 cut short, -1 error. */
static int walk(struct vlff_mcap_reader *r, uint64_t *count, uint64_t *sum) {
  char why[256];
  struct vlff_mcap_message m;
  int rc;
  *count = *sum = 0;
  while ((rc = vlff_mcap_next(r, &m, why, sizeof why)) == 1) {
    int known = 0;
    for (int i = 0; i < vlff_mcap_channel_count(r); i++) known |= vlff_mcap_channel_at(r, i)->id == m.channel;
    if (!known) __builtin_trap();
    uint64_t h = m.log_ns ^ m.publish_ns ^ m.sequence ^ m.len;
    for (size_t i = 0; i < m.len; i++) h = h * 31 + m.data[i]; /* ASan: the data is readable */
    (*count)++;
    *sum += h;
  }
  if (rc < 0) {
    if (!memchr(why, 0, sizeof why) || strncmp(why, "byte ", 5)) __builtin_trap();
    return -1;
  }
  return vlff_mcap_truncated(r, NULL);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  uint8_t *copy = malloc(size ? size : 1); /* exactly the bytes, so that ASan sees a read past them */
  if (!copy) return 0;
  if (size) memcpy(copy, data, size);
  char why[256];
  struct vlff_mcap_reader *r = vlff_mcap_reader_new(copy, size, why, sizeof why);
  if (!r) {
    if (!memchr(why, 0, sizeof why) || !why[0]) __builtin_trap();
  } else {
    uint64_t n1, s1, n2, s2;
    int e1 = walk(r, &n1, &s1);
    vlff_mcap_rewind(r);
    int e2 = walk(r, &n2, &s2);
    if (e1 != e2 || n1 != n2 || s1 != s2) __builtin_trap();
    vlff_mcap_reader_free(r);
    struct vlff_in_reader *in = vlff_in_reader_new(copy, size, why, sizeof why);
    if (!in) __builtin_trap(); /* the same header vlff_mcap_reader_new accepted */
    e1 = walk_inputs(in, &n1, &s1);
    vlff_in_rewind(in);
    e2 = walk_inputs(in, &n2, &s2);
    if (e1 != e2 || n1 != n2 || s1 != s2) __builtin_trap();
    vlff_in_reader_free(in);
  }
  free(copy);
  return 0;
}
