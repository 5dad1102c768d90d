/* libFuzzer target: the MCAP reader vlff-view --play opens recordings with (mcap.c).
 * Promises checked: no crash, no read past the bytes or the chunk it decompressed;
 * an error names the byte offset; every message read is on a channel the file
 * defined before it, with its data inside the file or the chunk; reading again
 * after a rewind gives the same messages and the same end. */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "mcap.h"

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
  }
  free(copy);
  return 0;
}
