/*
 * TUM trajectory lines to pose records (see tum.h). The checks are the
 * ones a pose ring needs to stay searchable: the node brackets a frame's
 * stamp between two consecutive records, so records must be strictly
 * increasing in time and each one a rigid transform.
 */
#include "tum.h"
#include "vlff/escape.h" /* VLFF_QN: bytes of a line quoted in the reason */

#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>

static const char *const result_names[VLFF_TUM_RESULTS] = {
    [VLFF_TUM_OK] = "ok",
    [VLFF_TUM_SKIP] = "skipped",
    [VLFF_TUM_MALFORMED] = "malformed",
    [VLFF_TUM_NOT_FINITE] = "not finite",
    [VLFF_TUM_BAD_QUATERNION] = "non-unit quaternion",
    [VLFF_TUM_DUPLICATE] = "duplicate stamp",
    [VLFF_TUM_OUT_OF_ORDER] = "out of order",
    [VLFF_TUM_BAD_STAMP] = "stamp out of range",
    [VLFF_TUM_CLOCK] = "clock error",
    [VLFF_TUM_NUL] = "NUL byte",
    [VLFF_TUM_TOO_LONG] = "too long",
    [VLFF_TUM_FOREIGN] = "foreign sender",
    [VLFF_TUM_FAR] = "position out of range",
};

const char *vlff_tum_result_name(int result) {
  return result >= 0 && result < VLFF_TUM_RESULTS ? result_names[result] : "unknown";
}

/* A plain decimal stamp "123.456789012" to nanoseconds without going
 * through a double: at a monotonic clock's uptime a double's nanoseconds
 * are off by a few, and the node matches a frame's stamp exactly when
 * there is no second pose near it to interpolate with. 0, or -1 when the
 * text is not a plain non-negative decimal (exponents, signs, hex). */
static int decimal_ns(const char *s, const char *end, int64_t *out) {
  int64_t sec = 0, frac = 0;
  int digits = 0, fd = 0;
  const char *p = s;
  for (; p < end && *p >= '0' && *p <= '9'; p++, digits++) {
    if (sec > (INT64_MAX / 1000000000 - 9) / 10) return -1;
    sec = sec * 10 + (*p - '0');
  }
  if (p < end && *p == '.') {
    for (p++; p < end && *p >= '0' && *p <= '9'; p++, digits++)
      if (fd < 9) frac = frac * 10 + (*p - '0'), fd++;
  }
  if (p != end || digits == 0) return -1;
  for (; fd < 9; fd++) frac *= 10;
  *out = sec * 1000000000 + frac;
  return 0;
}

/* Length of the plain decimal number s starts with: [+-] digits [. digits]
 * [e|E [+-] digits], a digit in the mantissa; 0 when it starts with none. No
 * hexadecimal, no "inf"/"nan": strtod(3) reads "0x10" as 16. */
static size_t decimal_len(const char *s) {
  size_t i = 0, digits = 0;
  if (s[i] == '+' || s[i] == '-') i++;
  for (; s[i] >= '0' && s[i] <= '9'; i++) digits++;
  if (s[i] == '.')
    for (i++; s[i] >= '0' && s[i] <= '9'; i++) digits++;
  if (!digits) return 0;
  if (s[i] == 'e' || s[i] == 'E') {
    size_t j = i + 1, e = 0;
    if (s[j] == '+' || s[j] == '-') j++;
    for (; s[j] >= '0' && s[j] <= '9'; j++) e++;
    if (e) i = j;
  }
  return i;
}

/* The words a tracker prints for non-finite values ("nan", "-nan", "inf",
 * "-Infinity"): 2 for NaN, 1 for +infinity, -1 for -infinity, 0 for
 * anything else. They are refused as not finite, not as malformed. */
static int non_finite_word(const char *s, size_t w) {
  int neg = 0;
  if (w && (*s == '+' || *s == '-')) neg = *s == '-', s++, w--;
  if (w == 3 && !strncasecmp(s, "nan", 3)) return 2;
  if ((w == 3 && !strncasecmp(s, "inf", 3)) || (w == 8 && !strncasecmp(s, "infinity", 8))) return neg ? -1 : 1;
  return 0;
}

int vlff_tum_parse(const char *line, int extra_fields, struct vlff_tum_sample *out, char *why, size_t whylen) {
  const char *s = line;
  while (isspace((unsigned char)*s)) s++;
  if (!*s || *s == '#') return VLFF_TUM_SKIP;
  double v[9];
  int64_t t_ns = 0;
  int exact = 0, n = 0;
  while (*s) {
    if (n == 8 && !extra_fields) {
      snprintf(why, whylen, "more than 8 fields (expected t tx ty tz qx qy qz qw; --extra-fields ignores the rest)");
      return VLFF_TUM_MALFORMED;
    }
    size_t w = 0;
    while (s[w] && !isspace((unsigned char)s[w])) w++;
    const char *end = s + w;
    int nf = non_finite_word(s, w);
    if (nf) {
      v[n] = nf > 0 ? (nf == 2 ? NAN : INFINITY) : -INFINITY;
    } else if (decimal_len(s) == w) {
      char *e;
      v[n] = strtod(s, &e); /* on a plain decimal, only its size can go wrong: overflow is infinite */
      if (e != end) {
        snprintf(why, whylen, "field %d '%s' is not a number (expected t tx ty tz qx qy qz qw)", n + 1,
                 VLFF_QN(s, w < 24 ? w : 24));
        return VLFF_TUM_MALFORMED;
      }
    } else {
      snprintf(why, whylen, "field %d '%s' is not a decimal number (expected t tx ty tz qx qy qz qw)", n + 1,
               VLFF_QN(s, w < 24 ? w : 24));
      return VLFF_TUM_MALFORMED;
    }
    if (n == 0) exact = decimal_ns(s, end, &t_ns) == 0;
    if (n < 8) n++; /* extra fields land in v[8] and are dropped */
    s = end;
    while (isspace((unsigned char)*s)) s++;
  }
  if (n != 8) {
    snprintf(why, whylen, "%d fields, expected 8 (t tx ty tz qx qy qz qw)", n);
    return VLFF_TUM_MALFORMED;
  }
  static const char *const names[8] = {"t", "tx", "ty", "tz", "qx", "qy", "qz", "qw"};
  for (int i = 0; i < 8; i++)
    if (!isfinite(v[i])) {
      snprintf(why, whylen, "%s is %g", names[i], v[i]);
      return VLFF_TUM_NOT_FINITE;
    }
  for (int i = 1; i < 4; i++)
    if (!(fabs(v[i]) <= VLFF_TUM_MAX_POSITION_M)) {
      snprintf(why, whylen, "%s is %g m, beyond %g m", names[i], v[i], VLFF_TUM_MAX_POSITION_M);
      return VLFF_TUM_FAR;
    }
  if (!exact) {
    if (!(fabs(v[0]) < 9.2e9)) {
      snprintf(why, whylen, "stamp %g s is beyond the clock's range", v[0]);
      return VLFF_TUM_MALFORMED;
    }
    t_ns = llround(v[0] * 1e9);
  }
  out->t = v[0];
  out->t_ns = t_ns;
  memcpy(out->p, v + 1, sizeof out->p);
  memcpy(out->q, v + 4, sizeof out->q);
  return VLFF_TUM_OK;
}

void vlff_tum_matrix(const double p[3], const double q[4], double m[16]) {
  double x = q[0], y = q[1], z = q[2], w = q[3];
  double r[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - z * w),     2 * (x * z + y * w),
                 2 * (x * y + z * w),     1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                 2 * (x * z - y * w),     2 * (y * z + x * w),     1 - 2 * (x * x + y * y)};
  for (int i = 0; i < 3; i++) {
    for (int j = 0; j < 3; j++) m[i * 4 + j] = r[i * 3 + j];
    m[i * 4 + 3] = p[i];
  }
  m[12] = m[13] = m[14] = 0;
  m[15] = 1;
}

static void mul44(const double a[16], const double b[16], double out[16]) {
  for (int i = 0; i < 4; i++)
    for (int j = 0; j < 4; j++) {
      double acc = 0;
      for (int k = 0; k < 4; k++) acc += a[i * 4 + k] * b[k * 4 + j];
      out[i * 4 + j] = acc;
    }
}

/* Rotation block orthonormal with determinant +1, last row 0 0 0 1. */
static int rigid(const double m[16]) {
  for (int i = 0; i < 16; i++)
    if (!isfinite(m[i])) return 0;
  if (m[12] != 0 || m[13] != 0 || m[14] != 0 || m[15] != 1) return 0;
  for (int i = 0; i < 3; i++)
    for (int j = 0; j < 3; j++) {
      double d = 0;
      for (int k = 0; k < 3; k++) d += m[i * 4 + k] * m[j * 4 + k];
      if (fabs(d - (i == j)) > 1e-6) return 0;
    }
  double det = m[0] * (m[5] * m[10] - m[6] * m[9]) - m[1] * (m[4] * m[10] - m[6] * m[8]) +
               m[2] * (m[4] * m[9] - m[5] * m[8]);
  return det > 0;
}

int vlff_tum_feed_init(struct vlff_tum_feed *f, const struct vlff_tum_feed_params *params, char *why,
                       size_t whylen) {
  memset(f, 0, sizeof *f);
  if (!rigid(params->body_to_camera)) {
    snprintf(why, whylen, "the body-to-camera extrinsic is not a rigid transform");
    return -1;
  }
  if (!(params->quat_tolerance >= 0 && params->quat_tolerance < 1)) {
    snprintf(why, whylen, "quaternion tolerance %g outside [0, 1)", params->quat_tolerance);
    return -1;
  }
  f->p = *params;
  return 0;
}

static int refuse(struct vlff_tum_feed *f, int result) {
  f->refused[result]++;
  return result;
}

void vlff_tum_feed_count(struct vlff_tum_feed *f, int result) {
  if (result >= VLFF_TUM_MALFORMED && result < VLFF_TUM_RESULTS) f->refused[result]++;
}

int vlff_tum_feed_buf(struct vlff_tum_feed *f, const char *line, size_t len, uint64_t now_ns,
                      struct vlff_pose_rec *out, char *why, size_t whylen) {
  if (len >= VLFF_TUM_LINE_MAX) {
    snprintf(why, whylen, "a line of %d bytes or more (not a TUM line)", VLFF_TUM_LINE_MAX);
    return refuse(f, VLFF_TUM_TOO_LONG);
  }
  const char *nul = memchr(line, 0, len);
  if (nul) {
    /* strtod and every reader after it would stop there: what follows
     * would be lost without a word. */
    snprintf(why, whylen, "a NUL byte at column %zu (not a text line)", (size_t)(nul - line) + 1);
    return refuse(f, VLFF_TUM_NUL);
  }
  struct vlff_tum_sample s;
  int r = vlff_tum_parse(line, f->p.extra_fields, &s, why, whylen);
  if (r == VLFF_TUM_SKIP) return r;
  if (r != VLFF_TUM_OK) return refuse(f, r);
  double norm = sqrt(s.q[0] * s.q[0] + s.q[1] * s.q[1] + s.q[2] * s.q[2] + s.q[3] * s.q[3]);
  if (!(fabs(norm - 1) <= f->p.quat_tolerance)) {
    snprintf(why, whylen, "quaternion (%g %g %g %g) has norm %.6f, off 1 by more than %g", s.q[0], s.q[1], s.q[2],
             s.q[3], norm, f->p.quat_tolerance);
    return refuse(f, VLFF_TUM_BAD_QUATERNION);
  }
  if (f->have_last && s.t_ns == f->last_t_ns) {
    snprintf(why, whylen, "stamp %.9f repeats the previous line's", s.t);
    return refuse(f, VLFF_TUM_DUPLICATE);
  }
  int restart = 0;
  if (f->have_last && s.t_ns < f->last_t_ns) {
    /* One line ahead of the stream (forged, or a clock glitch) must not
     * lock the tracker out: a run of older lines is a stream that restarted. */
    if (f->p.out_of_order_reset && f->out_of_order_run + 1 >= f->p.out_of_order_reset) {
      restart = 1;
    } else {
      f->out_of_order_run++;
      snprintf(why, whylen, "stamp %.9f is %.9f s before the previous line's %.9f", s.t,
               (double)(f->last_t_ns - s.t_ns) * 1e-9, (double)f->last_t_ns * 1e-9);
      return refuse(f, VLFF_TUM_OUT_OF_ORDER);
    }
  }
  uint64_t t_ns;
  if (f->p.stamp == VLFF_TUM_STAMP_HOST) {
    int64_t t = (int64_t)now_ns - f->p.latency_ns;
    if (t <= 0) {
      snprintf(why, whylen, "host time minus the latency is not positive");
      return refuse(f, VLFF_TUM_BAD_STAMP);
    }
    t_ns = (uint64_t)t;
    /* Two lines in the same tick still need increasing records. */
    if (f->have_last && t_ns <= f->last_ns) t_ns = f->last_ns + 1;
  } else {
    int64_t t;
    if (__builtin_add_overflow(s.t_ns, f->p.clock_offset_ns, &t) || t <= 0) {
      snprintf(why, whylen, "stamp %.9f s with the clock offset %.9f s is outside the monotonic clock's range", s.t,
               (double)f->p.clock_offset_ns * 1e-9);
      return refuse(f, VLFF_TUM_BAD_STAMP);
    }
    /* A pose is computed after its frame: a stamp ahead of the clock is
     * the clocks' disagreement, and far ahead a wrong clock or a forgery,
     * which would hold every later line out of order. */
    if (f->p.future_tolerance_ns > 0 && (uint64_t)t > now_ns &&
        (uint64_t)t - now_ns > (uint64_t)f->p.future_tolerance_ns) {
      snprintf(why, whylen,
               "stamp %.9f s is %.3f s ahead of the clock (CLOCK_MONOTONIC %.9f s; tolerance %.3f s): a wrong "
               "clock or clock offset, or a forged line",
               (double)t * 1e-9, (double)((uint64_t)t - now_ns) * 1e-9, (double)now_ns * 1e-9,
               (double)f->p.future_tolerance_ns * 1e-9);
      return refuse(f, VLFF_TUM_CLOCK);
    }
    t_ns = (uint64_t)t;
  }
  double q[4];
  for (int i = 0; i < 4; i++) q[i] = s.q[i] / norm;
  double body[16];
  vlff_tum_matrix(s.p, q, body);
  memset(out, 0, sizeof *out);
  out->t_ns = t_ns;
  out->source_id = f->p.source_id;
  mul44(body, f->p.body_to_camera, out->pose);
  if (restart) {
    f->resets++;
    f->reset_from_t_ns = f->last_t_ns;
  }
  f->out_of_order_run = 0;
  f->have_last = 1;
  f->last_t_ns = s.t_ns;
  f->last_ns = t_ns;
  f->accepted++;
  return VLFF_TUM_OK;
}

int vlff_tum_feed_line(struct vlff_tum_feed *f, const char *line, uint64_t now_ns, struct vlff_pose_rec *out,
                       char *why, size_t whylen) {
  return vlff_tum_feed_buf(f, line, strlen(line), now_ns, out, why, whylen);
}

uint64_t vlff_tum_feed_refused(const struct vlff_tum_feed *f) {
  uint64_t n = 0;
  for (int i = VLFF_TUM_MALFORMED; i < VLFF_TUM_RESULTS; i++) n += f->refused[i];
  return n;
}
