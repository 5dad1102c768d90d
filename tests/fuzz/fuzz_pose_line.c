/* libFuzzer target: any bytes a tracker (or anyone who can reach vlff-pose's
 * UDP port) can send go through the pose line parser and the feed's checks
 * (tum.h) without crashing or reading past them, and the feed keeps its
 * promises: a line holding a NUL or of VLFF_TUM_LINE_MAX bytes or more is
 * refused as such; an accepted line's stamp is a plain decimal, its record
 * a rigid transform stamped no further ahead of the clock than the
 * tolerance, and later than the previous record unless the order restarted;
 * every refusal is counted once under its reason with a sentence why. The
 * input is fed whole, then line by line as vlff-pose's readers split it. */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "tum.h"

static const uint64_t now_ns = 1000000000000ull; /* 1000 s of uptime */
static const int64_t tolerance_ns = 5000000000;

static void rigid_or_trap(const double m[16]) {
  for (int i = 0; i < 16; i++)
    if (!isfinite(m[i])) __builtin_trap();
  if (m[12] != 0 || m[13] != 0 || m[14] != 0 || m[15] != 1) __builtin_trap();
  for (int i = 0; i < 3; i++)
    for (int j = 0; j < 3; j++) {
      double d = 0;
      for (int k = 0; k < 3; k++) d += m[i * 4 + k] * m[j * 4 + k];
      if (fabs(d - (i == j)) > 1e-6) __builtin_trap();
    }
}

/* One line of len bytes (buf[len] is the terminator the readers add). */
static void feed_one(struct vlff_tum_feed *f, const char *buf, size_t len, uint64_t *last_rec) {
  char why[256];
  memset(why, 0x55, sizeof why);
  struct vlff_pose_rec rec;
  uint64_t before = vlff_tum_feed_refused(f), resets = f->resets, accepted = f->accepted;
  int r = vlff_tum_feed_buf(f, buf, len, now_ns, &rec, why, sizeof why);
  if (r < 0 || r >= VLFF_TUM_RESULTS || r == VLFF_TUM_FOREIGN) __builtin_trap();
  int has_nul = memchr(buf, 0, len) != NULL;
  if (len >= VLFF_TUM_LINE_MAX) {
    if (r != VLFF_TUM_TOO_LONG) __builtin_trap();
  } else if (has_nul && r != VLFF_TUM_NUL) {
    __builtin_trap();
  }
  if (r == VLFF_TUM_SKIP) {
    if (vlff_tum_feed_refused(f) != before || f->accepted != accepted) __builtin_trap();
    return;
  }
  if (r != VLFF_TUM_OK) {
    if (vlff_tum_feed_refused(f) != before + 1 || f->accepted != accepted) __builtin_trap();
    if (!memchr(why, 0, sizeof why) || !why[0]) __builtin_trap();
    return;
  }
  if (f->accepted != accepted + 1 || vlff_tum_feed_refused(f) != before) __builtin_trap();
  /* the stamp field: digits, one point, an exponent, signs; never "0x" */
  const char *s = buf;
  while (*s == ' ' || (*s >= '\t' && *s <= '\r')) s++;
  for (; *s && *s != ' ' && !(*s >= '\t' && *s <= '\r'); s++)
    if (!strchr("0123456789.eE+-", *s)) __builtin_trap();
  rigid_or_trap(rec.pose);
  if (rec.t_ns == 0 || rec.t_ns > now_ns + (uint64_t)tolerance_ns) __builtin_trap();
  if (f->resets == resets && *last_rec && rec.t_ns <= *last_rec) __builtin_trap();
  *last_rec = rec.t_ns;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  struct vlff_tum_feed_params p = {.stamp = VLFF_TUM_STAMP_SOURCE, .quat_tolerance = 0.01,
                                   .future_tolerance_ns = tolerance_ns, .out_of_order_reset = 3};
  for (int i = 0; i < 16; i++) p.body_to_camera[i] = i % 5 == 0;
  /* a first byte below 4 picks a few of the feed's settings */
  if (size && data[0] < 4) {
    p.extra_fields = data[0] & 1;
    if (data[0] & 2) p.clock_offset_ns = -999000000000ll;
    data++, size--;
  }
  struct vlff_tum_feed f;
  char why[256];
  if (vlff_tum_feed_init(&f, &p, why, sizeof why)) __builtin_trap();
  /* a copy of exactly size bytes and the terminator, so that ASan sees any
   * read past them */
  char *buf = malloc(size + 1);
  if (!buf) return 0;
  memcpy(buf, data, size);
  buf[size] = 0;
  uint64_t last = 0;
  feed_one(&f, buf, size, &last);
  /* line by line, as the stream reader splits (the newline replaced by the
   * terminator) */
  size_t start = 0;
  for (size_t i = 0; i <= size; i++) {
    if (i < size && buf[i] != '\n') continue;
    buf[i] = 0;
    feed_one(&f, buf + start, i - start, &last);
    start = i + 1;
  }
  free(buf);
  return 0;
}
