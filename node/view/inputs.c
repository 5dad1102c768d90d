/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * inputs.c - ring records as MCAP messages and back (inputs.h).
 *
 * JSON rather than protobuf: the three foxglove.* messages and vlff.FeatureMap
 * are then read by Foxglove and by @mcap/core scripts with the schemas in the
 * file alone, and decoded here with json-c, which vlff-view links already. The
 * pixel and feature payloads are base64, a third larger than raw bytes, which
 * the recorder's zstd chunks mostly win back.
 */
#include "inputs.h"

#include <errno.h>
#include <json-c/json.h>
#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "bounds.h"
#include "vlff/shm.h"

/* The ring's planes and half floats are copied as bytes into little-endian
 * messages: a big-endian host would have to swap them. */
#if !defined(__BYTE_ORDER__) || __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "inputs.c writes host-order samples as little-endian message data"
#endif

static const char *const topics[VLFF_IN_CHANNELS + 1] = {
    NULL, "/input/color", "/input/depth", "/input/calibration", "/input/pose", "/input/features", "/input/frame_pose"};
static const char *const schema_names[VLFF_IN_CHANNELS + 1] = {
    NULL, "foxglove.RawImage", "foxglove.RawImage", "foxglove.CameraCalibration", "foxglove.FrameTransform",
    "vlff.FeatureMap", "foxglove.FrameTransform"};

const char *vlff_in_topic(int ch) { return ch >= 1 && ch <= VLFF_IN_CHANNELS ? topics[ch] : NULL; }

#define TIME_S                                                                                                        \
  "{\"type\":\"object\",\"properties\":{\"sec\":{\"type\":\"integer\",\"minimum\":0},\"nsec\":{\"type\":\"integer\"," \
  "\"minimum\":0,\"maximum\":999999999}},\"required\":[\"sec\",\"nsec\"]}"
#define NUM_S "{\"type\":\"number\"}"
#define NUMS_S(n) "{\"type\":\"array\",\"items\":{\"type\":\"number\"},\"minItems\":" #n ",\"maxItems\":" #n "}"

static const char raw_schema[] =
    "{\"title\":\"foxglove.RawImage\",\"type\":\"object\",\"properties\":{"
    "\"timestamp\":" TIME_S ",\"frame_id\":{\"type\":\"string\"},\"width\":{\"type\":\"integer\",\"minimum\":0},"
    "\"height\":{\"type\":\"integer\",\"minimum\":0},\"encoding\":{\"type\":\"string\"},"
    "\"step\":{\"type\":\"integer\",\"minimum\":0},\"data\":{\"type\":\"string\",\"contentEncoding\":\"base64\"}},"
    "\"required\":[\"timestamp\",\"frame_id\",\"width\",\"height\",\"encoding\",\"step\",\"data\"]}";
const char vlff_schema_camera_calibration[] =
    "{\"title\":\"foxglove.CameraCalibration\",\"type\":\"object\",\"properties\":{"
    "\"timestamp\":" TIME_S ",\"frame_id\":{\"type\":\"string\"},\"width\":{\"type\":\"integer\",\"minimum\":0},"
    "\"height\":{\"type\":\"integer\",\"minimum\":0},\"distortion_model\":{\"type\":\"string\"},"
    "\"D\":{\"type\":\"array\",\"items\":{\"type\":\"number\"}},\"K\":" NUMS_S(9) ",\"R\":" NUMS_S(9) ","
    "\"P\":" NUMS_S(12) "},"
    "\"required\":[\"timestamp\",\"frame_id\",\"width\",\"height\",\"distortion_model\",\"D\",\"K\",\"R\",\"P\"]}";
const char vlff_schema_frame_transform[] =
    "{\"title\":\"foxglove.FrameTransform\",\"type\":\"object\",\"properties\":{"
    "\"timestamp\":" TIME_S ",\"parent_frame_id\":{\"type\":\"string\"},\"child_frame_id\":{\"type\":\"string\"},"
    "\"translation\":{\"type\":\"object\",\"properties\":{\"x\":" NUM_S ",\"y\":" NUM_S ",\"z\":" NUM_S "},"
    "\"required\":[\"x\",\"y\",\"z\"]},"
    "\"rotation\":{\"type\":\"object\",\"properties\":{\"x\":" NUM_S ",\"y\":" NUM_S ",\"z\":" NUM_S ",\"w\":" NUM_S
    "},\"required\":[\"x\",\"y\",\"z\",\"w\"]}},"
    "\"required\":[\"timestamp\",\"parent_frame_id\",\"child_frame_id\",\"translation\",\"rotation\"]}";
static const char feat_schema[] =
    "{\"title\":\"vlff.FeatureMap\",\"description\":\"A feature ring record: the per-pixel features of one frame, "
    "dim x height x width IEEE half floats, little-endian, laid out [dim][height][width]; timestamp is the frame's "
    "host time and frame_id its number in the frame ring.\",\"type\":\"object\",\"properties\":{"
    "\"timestamp\":" TIME_S ",\"frame_id\":{\"type\":\"integer\",\"minimum\":0},"
    "\"dim\":{\"type\":\"integer\",\"minimum\":1},\"height\":{\"type\":\"integer\",\"minimum\":1},"
    "\"width\":{\"type\":\"integer\",\"minimum\":1},\"encoding\":{\"type\":\"string\",\"enum\":[\"float16\"]},"
    "\"data\":{\"type\":\"string\",\"contentEncoding\":\"base64\"}},"
    "\"required\":[\"timestamp\",\"frame_id\",\"dim\",\"height\",\"width\",\"encoding\",\"data\"]}";
static const char *const schemas[VLFF_IN_CHANNELS + 1] = {
    NULL, raw_schema, raw_schema, vlff_schema_camera_calibration, vlff_schema_frame_transform, feat_schema,
    vlff_schema_frame_transform};

static const struct {
  uint32_t fmt;
  const char *name;
} encodings[] = {
    {VLFF_PIX_RGB8, "rgb8"},          {VLFF_PIX_BGR8, "bgr8"},          {VLFF_PIX_MONO8, "mono8"},
    {VLFF_PIX_MONO16, "mono16"},      {VLFF_PIX_BAYER_RG8, "bayer_rggb8"}, {VLFF_PIX_BAYER_BG8, "bayer_bggr8"},
    {VLFF_PIX_BAYER_GR8, "bayer_grbg8"}, {VLFF_PIX_BAYER_GB8, "bayer_gbrg8"}, {VLFF_PIX_DEPTH_U16_MM, "16UC1"},
    {VLFF_PIX_DEPTH_F32_M, "32FC1"},
};

static const char *encoding_name(uint32_t fmt) {
  for (size_t i = 0; i < sizeof encodings / sizeof *encodings; i++)
    if (encodings[i].fmt == fmt) return encodings[i].name;
  return NULL;
}

static uint32_t encoding_format(const char *name) {
  for (size_t i = 0; i < sizeof encodings / sizeof *encodings; i++)
    if (!strcmp(encodings[i].name, name)) return encodings[i].fmt;
  return VLFF_PIX_NONE;
}

static int is_depth(uint32_t fmt) { return fmt == VLFF_PIX_DEPTH_U16_MM || fmt == VLFF_PIX_DEPTH_F32_M; }

static int fail(char *why, size_t len, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
static int fail(char *why, size_t len, const char *fmt, ...) {
  if (why && len) {
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(why, len, fmt, ap);
    va_end(ap);
  }
  return -1;
}

/* --------------------------------------------------------------- writing */

int vlff_in_declare(struct vlff_mcap_writer *w, char *why, size_t len) {
  for (int ch = 1; ch <= VLFF_IN_CHANNELS; ch++)
    if (vlff_mcap_writer_channel(w, (uint16_t)ch, topics[ch], "json", schema_names[ch], "jsonschema", schemas[ch],
                                 strlen(schemas[ch])) < 0)
      return fail(why, len, "declaring %s: %s", topics[ch], vlff_mcap_writer_error(w));
  return 0;
}

/* A JSON text being written into a caller's growable buffer. */
struct sb {
  char **d;
  size_t *cap, n;
  int failed;
};

static int sb_reserve(struct sb *b, size_t more) {
  if (b->failed) return -1;
  if (more > SIZE_MAX / 2 - b->n) return b->failed = 1, -1;
  if (b->n + more + 1 <= *b->cap) return 0;
  size_t cap = *b->cap ? *b->cap : 4096;
  while (cap < b->n + more + 1) cap *= 2;
  char *d = realloc(*b->d, cap);
  if (!d) return b->failed = 1, -1;
  *b->d = d;
  *b->cap = cap;
  return 0;
}

static void sb_f(struct sb *b, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static void sb_f(struct sb *b, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  int k = vsnprintf(NULL, 0, fmt, ap);
  va_end(ap);
  if (k < 0 || sb_reserve(b, (size_t)k) < 0) {
    b->failed = 1;
    return;
  }
  va_start(ap, fmt);
  vsnprintf(*b->d + b->n, (size_t)k + 1, fmt, ap);
  va_end(ap);
  b->n += (size_t)k;
}

static const char b64[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

static void sb_b64(struct sb *b, const uint8_t *s, size_t n) {
  if (sb_reserve(b, (n + 2) / 3 * 4 + 2) < 0) return;
  char *o = *b->d + b->n;
  *o++ = '"';
  size_t i = 0;
  for (; i + 3 <= n; i += 3) {
    uint32_t v = (uint32_t)s[i] << 16 | (uint32_t)s[i + 1] << 8 | s[i + 2];
    *o++ = b64[v >> 18], *o++ = b64[v >> 12 & 63], *o++ = b64[v >> 6 & 63], *o++ = b64[v & 63];
  }
  if (i < n) {
    uint32_t v = (uint32_t)s[i] << 16 | (i + 1 < n ? (uint32_t)s[i + 1] << 8 : 0);
    *o++ = b64[v >> 18], *o++ = b64[v >> 12 & 63];
    *o++ = i + 1 < n ? b64[v >> 6 & 63] : '=';
    *o++ = '=';
  }
  *o++ = '"';
  b->n = (size_t)(o - *b->d);
}

static void sb_time(struct sb *b, uint64_t t) {
  sb_f(b, "\"timestamp\":{\"sec\":%llu,\"nsec\":%u}", (unsigned long long)(t / 1000000000u),
       (unsigned)(t % 1000000000u));
}

static int emit(struct vlff_mcap_writer *w, int ch, uint64_t t, struct sb *b, char *why, size_t len) {
  if (b->failed) return fail(why, len, "%s: out of memory for a message", topics[ch]);
  if (vlff_mcap_writer_message(w, (uint16_t)ch, t, t, *b->d, b->n) < 0)
    return fail(why, len, "%s: %s", topics[ch], vlff_mcap_writer_error(w));
  return 0;
}

static int write_transform(struct vlff_mcap_writer *w, int ch, uint64_t t_ns, const double P[16], char *why,
                           size_t len);

/* A plane as a RawImage, its rows packed. */
static int write_plane(struct vlff_mcap_writer *w, int ch, uint64_t t, const struct vlff_plane *pl,
                       const uint8_t *px, struct sb *b, uint8_t **rows, char *why, size_t len) {
  size_t step = (size_t)pl->width * vlff_pixfmt_bpp(pl->format), n = step * pl->height;
  const char *enc = encoding_name(pl->format);
  if (!enc || !step) return fail(why, len, "%s: pixel format %u has no RawImage encoding", topics[ch], pl->format);
  const uint8_t *data = px;
  if (pl->stride != step) {
    uint8_t *r = realloc(*rows, n ? n : 1);
    if (!r) return fail(why, len, "%s: out of memory", topics[ch]);
    *rows = r;
    for (uint32_t v = 0; v < pl->height; v++) memcpy(r + v * step, px + (size_t)v * pl->stride, step);
    data = r;
  }
  b->n = 0;
  sb_f(b, "{");
  sb_time(b, t);
  sb_f(b, ",\"frame_id\":\"camera\",\"width\":%u,\"height\":%u,\"encoding\":\"%s\",\"step\":%zu,\"data\":", pl->width,
       pl->height, enc, step);
  sb_b64(b, data, n);
  sb_f(b, "}");
  return emit(w, ch, t, b, why, len);
}

int vlff_in_write_frame(struct vlff_mcap_writer *w, const void *record, size_t rec_len, char **scratch,
                        size_t *scratch_cap, char *why, size_t len) {
  if (vlff_frame_validate(record, rec_len) < 0) return fail(why, len, "a malformed frame record");
  const struct vlff_frame_hdr *h = record;
  if (!(h->flags & VLFF_FRAME_INTRINSICS_VALID)) return fail(why, len, "frame %llu has no intrinsics",
                                                            (unsigned long long)h->frame_id);
  struct sb b = {scratch, scratch_cap, 0, 0};
  uint8_t *rows = NULL;
  uint64_t t = h->t_host_ns;
  int rc = write_plane(w, VLFF_IN_COLOR, t, &h->plane[VLFF_PLANE_COLOR], vlff_frame_plane(record, VLFF_PLANE_COLOR),
                       &b, &rows, why, len);
  const uint8_t *dp = vlff_frame_plane(record, VLFF_PLANE_DEPTH);
  if (!rc && dp) rc = write_plane(w, VLFF_IN_DEPTH, t, &h->plane[VLFF_PLANE_DEPTH], dp, &b, &rows, why, len);
  free(rows);
  if (!rc && (h->flags & VLFF_FRAME_POSE_VALID))
    rc = write_transform(w, VLFF_IN_FRAME_POSE, h->pose_t_ns, h->pose, why, len);
  if (rc) return rc;
  const struct vlff_plane *pl = &h->plane[VLFF_PLANE_COLOR];
  double cx = h->cx - 0.5, cy = h->cy - 0.5; /* OpenCV's principal point */
  b.n = 0;
  sb_f(&b, "{");
  sb_time(&b, t);
  sb_f(&b,
       ",\"frame_id\":\"camera\",\"width\":%u,\"height\":%u,\"distortion_model\":\"plumb_bob\",\"D\":[0,0,0,0,0],"
       "\"K\":[%.17g,0,%.17g,0,%.17g,%.17g,0,0,1],\"R\":[1,0,0,0,1,0,0,0,1],"
       "\"P\":[%.17g,0,%.17g,0,0,%.17g,%.17g,0,0,0,1,0]}",
       pl->width, pl->height, h->fx, cx, h->fy, cy, h->fx, cx, h->fy, cy);
  return emit(w, VLFF_IN_CALIBRATION, t, &b, why, len);
}

static int write_transform(struct vlff_mcap_writer *w, int ch, uint64_t t_ns, const double P[16], char *why,
                           size_t len) {
  for (int i = 0; i < 16; i++)
    if (!isfinite(P[i])) return fail(why, len, "a pose with a non-finite element");
  double q[4]; /* w x y z */
  vlff_pose_quaternion(P, q);
  char buf[512];
  size_t cap = sizeof buf;
  int k = snprintf(buf, cap,
                   "{\"timestamp\":{\"sec\":%llu,\"nsec\":%u},\"parent_frame_id\":\"world\",\"child_frame_id\":\"camera\","
                   "\"translation\":{\"x\":%.17g,\"y\":%.17g,\"z\":%.17g},"
                   "\"rotation\":{\"x\":%.17g,\"y\":%.17g,\"z\":%.17g,\"w\":%.17g}}",
                   (unsigned long long)(t_ns / 1000000000u), (unsigned)(t_ns % 1000000000u), P[3], P[7], P[11], q[1],
                   q[2], q[3], q[0]);
  if (k < 0 || (size_t)k >= cap) return fail(why, len, "%s: message too long", topics[ch]);
  if (vlff_mcap_writer_message(w, (uint16_t)ch, t_ns, t_ns, buf, (size_t)k) < 0)
    return fail(why, len, "%s: %s", topics[ch], vlff_mcap_writer_error(w));
  return 0;
}

int vlff_in_write_pose(struct vlff_mcap_writer *w, uint64_t t_ns, const double P[16], char *why, size_t len) {
  return write_transform(w, VLFF_IN_POSE, t_ns, P, why, len);
}

int vlff_in_write_features(struct vlff_mcap_writer *w, const void *record, size_t rec_len, char **scratch,
                           size_t *scratch_cap, char *why, size_t len) {
  if (vlff_feature_validate(record, rec_len) < 0) return fail(why, len, "a malformed feature record");
  const struct vlff_feature_hdr *f = record;
  struct sb b = {scratch, scratch_cap, 0, 0};
  sb_f(&b, "{");
  sb_time(&b, f->t_host_ns);
  sb_f(&b, ",\"frame_id\":%llu,\"dim\":%u,\"height\":%u,\"width\":%u,\"encoding\":\"float16\",\"data\":",
       (unsigned long long)f->frame_id, f->dim, f->height, f->width);
  sb_b64(&b, (const uint8_t *)record + f->data_offset, (size_t)2 * f->dim * f->height * f->width);
  sb_f(&b, "}");
  return emit(w, VLFF_IN_FEATURES, f->t_host_ns, &b, why, len);
}

/* --------------------------------------------------------------- reading */

struct vlff_in_reader {
  struct vlff_mcap_reader *m;
  json_tokener *tok;
  uint64_t index, other;
  uint64_t last_t[VLFF_IN_CHANNELS + 1];
  int seen[VLFF_IN_CHANNELS + 1];
  /* the frame being assembled: its colour (and depth) read, its calibration due */
  int pending, pending_depth;
  struct vlff_in_event ev;
  uint8_t *color, *depth;
  size_t color_cap, depth_cap;
  uint16_t *feat;
  size_t feat_cap;
  /* the recording's frame geometry and feature shape, from their first record */
  int geom, shape;
  uint32_t width, height, color_format, depth_format, dim, fh, fw;
};

struct vlff_in_reader *vlff_in_reader_new(const uint8_t *d, size_t n, char *why, size_t len) {
  struct vlff_in_reader *r = calloc(1, sizeof *r);
  if (!r) return fail(why, len, "out of memory"), NULL;
  r->m = vlff_mcap_reader_new(d, n, why, len);
  r->tok = json_tokener_new_ex(16);
  if (!r->m || !r->tok) {
    if (r->m && !r->tok) fail(why, len, "out of memory");
    vlff_in_reader_free(r);
    return NULL;
  }
  return r;
}

void vlff_in_reader_free(struct vlff_in_reader *r) {
  if (!r) return;
  vlff_mcap_reader_free(r->m);
  if (r->tok) json_tokener_free(r->tok);
  free(r->color);
  free(r->depth);
  free(r->feat);
  free(r);
}

void vlff_in_rewind(struct vlff_in_reader *r) {
  vlff_mcap_rewind(r->m);
  r->index = r->other = 0;
  memset(r->last_t, 0, sizeof r->last_t);
  memset(r->seen, 0, sizeof r->seen);
  r->pending = r->pending_depth = 0;
  r->geom = r->shape = 0;
}

uint64_t vlff_in_other_messages(const struct vlff_in_reader *r) { return r->other; }
size_t vlff_in_consumed(const struct vlff_in_reader *r) { return vlff_mcap_consumed(r->m); }

/* The input channel of a message's channel id: 1..5, 0 another channel, -1 an
 * /input/ topic with another schema or encoding. */
static int channel_kind(const struct vlff_in_reader *r, uint16_t id, const char **topic) {
  for (int i = 0; i < vlff_mcap_channel_count(r->m); i++) {
    const struct vlff_mcap_channel *c = vlff_mcap_channel_at(r->m, i);
    if (c->id != id) continue;
    *topic = c->topic;
    for (int ch = 1; ch <= VLFF_IN_CHANNELS; ch++)
      if (!strcmp(c->topic, topics[ch]))
        return !strcmp(c->message_encoding, "json") && !strcmp(c->schema_name, schema_names[ch]) ? ch : -1;
    return 0;
  }
  return 0; /* the MCAP reader hands out messages of defined channels only */
}

/* Message context for errors. */
struct ctx {
  const char *topic;
  uint64_t index;
  char *why;
  size_t len;
};

static int bad(const struct ctx *c, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static int bad(const struct ctx *c, const char *fmt, ...) {
  if (c->why && c->len) {
    int k = snprintf(c->why, c->len, "channel %s message %llu: ", c->topic, (unsigned long long)c->index);
    if (k > 0 && (size_t)k < c->len) {
      va_list ap;
      va_start(ap, fmt);
      vsnprintf(c->why + k, c->len - (size_t)k, fmt, ap);
      va_end(ap);
    }
  }
  return -1;
}

static json_object *get(const struct ctx *c, json_object *o, const char *key, json_type t) {
  json_object *v = NULL;
  if (!json_object_object_get_ex(o, key, &v) || !v) {
    bad(c, "no '%s'", key);
    return NULL;
  }
  int ok = json_object_is_type(v, t) || (t == json_type_double && json_object_is_type(v, json_type_int));
  if (!ok) {
    bad(c, "'%s' is not %s", key, t == json_type_int ? "an integer" : t == json_type_double ? "a number"
                                 : t == json_type_string ? "a string" : t == json_type_array ? "an array"
                                                                                             : "an object");
    return NULL;
  }
  return v;
}

static int get_uint(const struct ctx *c, json_object *o, const char *key, uint64_t lo, uint64_t hi, uint64_t *out) {
  json_object *v = get(c, o, key, json_type_int);
  if (!v) return -1;
  errno = 0;
  int64_t x = json_object_get_int64(v);
  if (errno || x < 0 || (uint64_t)x < lo || (uint64_t)x > hi)
    return bad(c, "'%s' %lld is outside [%llu, %llu]", key, (long long)x, (unsigned long long)lo,
               (unsigned long long)hi);
  *out = (uint64_t)x;
  return 0;
}

static int get_num(const struct ctx *c, json_object *o, const char *key, double *out) {
  json_object *v = get(c, o, key, json_type_double);
  if (!v) return -1;
  double x = json_object_get_double(v);
  if (!isfinite(x)) return bad(c, "'%s' is not finite", key);
  *out = x;
  return 0;
}

static int get_time(const struct ctx *c, json_object *o, uint64_t *t) {
  json_object *ts = get(c, o, "timestamp", json_type_object);
  uint64_t s, ns;
  if (!ts || get_uint(c, ts, "sec", 0, UINT64_MAX / 1000000000u - 1, &s) < 0 ||
      get_uint(c, ts, "nsec", 0, 999999999, &ns) < 0)
    return -1;
  *t = s * 1000000000u + ns;
  return 0;
}

/* A base64 digit's value, -1 for any other byte (by ranges rather than a
 * search of the alphabet: every pixel and feature of a recording passes here). */
static int b64v(int ch) {
  if (ch >= 'A' && ch <= 'Z') return ch - 'A';
  if (ch >= 'a' && ch <= 'z') return ch - 'a' + 26;
  if (ch >= '0' && ch <= '9') return ch - '0' + 52;
  return ch == '+' ? 62 : ch == '/' ? 63 : -1;
}

/* Strict base64 of exactly want bytes into *buf (grown). */
static int get_b64(const struct ctx *c, json_object *o, const char *key, size_t want, void **buf, size_t *cap) {
  json_object *v = get(c, o, key, json_type_string);
  if (!v) return -1;
  const char *s = json_object_get_string(v);
  size_t n = (size_t)json_object_get_string_len(v);
  if (n % 4 || n / 4 * 3 < want || n / 4 * 3 - want > 2 || (want == 0 && n))
    return bad(c, "'%s' holds %zu base64 characters, not the %zu bytes its size says", key, n, want);
  if (*cap < want || !*buf) {
    void *d = realloc(*buf, want ? want : 1);
    if (!d) return bad(c, "out of memory for %zu bytes", want);
    *buf = d;
    *cap = want ? want : 1;
  }
  uint8_t *out = *buf;
  size_t k = 0;
  for (size_t i = 0; i < n; i += 4) {
    int a = b64v(s[i]), b = b64v(s[i + 1]), cc = s[i + 2] == '=' ? -2 : b64v(s[i + 2]),
        d = s[i + 3] == '=' ? -2 : b64v(s[i + 3]);
    int last = i + 4 == n;
    if (a < 0 || b < 0 || cc == -1 || d == -1 || (!last && (cc < 0 || d < 0)) || (cc == -2 && d != -2))
      return bad(c, "'%s' is not base64 near character %zu", key, i);
    uint32_t v32 = (uint32_t)a << 18 | (uint32_t)b << 12 | (uint32_t)(cc < 0 ? 0 : cc) << 6 | (uint32_t)(d < 0 ? 0 : d);
    uint8_t t[3] = {(uint8_t)(v32 >> 16), (uint8_t)(v32 >> 8), (uint8_t)v32};
    int m = cc < 0 ? 1 : d < 0 ? 2 : 3;
    for (int j = 0; j < m; j++) {
      if (k >= want) return bad(c, "'%s' holds more than the %zu bytes its size says", key, want);
      out[k++] = t[j];
    }
  }
  if (k != want) return bad(c, "'%s' holds %zu bytes, its size says %zu", key, k, want);
  return 0;
}

/* A RawImage: its size and format (color or depth as wanted) into *w,*h,*fmt, data into buf. */
static int raw_image(const struct ctx *c, json_object *o, int depth, uint32_t *w, uint32_t *h, uint32_t *fmt,
                     uint8_t **buf, size_t *cap) {
  uint64_t W, H, step;
  if (get_uint(c, o, "width", 1, VLFF_MAX_IMAGE_SIDE, &W) < 0 || get_uint(c, o, "height", 1, VLFF_MAX_IMAGE_SIDE, &H) < 0)
    return -1;
  json_object *e = get(c, o, "encoding", json_type_string);
  if (!e) return -1;
  uint32_t f = encoding_format(json_object_get_string(e));
  if (!f || is_depth(f) != depth)
    return bad(c, "encoding '%.32s' is not a %s encoding vlff records", json_object_get_string(e),
               depth ? "depth" : "colour");
  size_t bpp = vlff_pixfmt_bpp(f);
  if (get_uint(c, o, "step", 0, UINT32_MAX, &step) < 0) return -1;
  if (step != W * bpp) return bad(c, "step %llu is not width %llu x %zu bytes", (unsigned long long)step,
                                  (unsigned long long)W, bpp);
  if (step * H > VLFF_MCAP_MAX_CHUNK) return bad(c, "a %llux%llu image is larger than a chunk",
                                                 (unsigned long long)W, (unsigned long long)H);
  if (get_b64(c, o, "data", step * H, (void **)buf, cap) < 0) return -1;
  *w = (uint32_t)W, *h = (uint32_t)H, *fmt = f;
  return 0;
}

static int calibration(struct vlff_in_reader *r, const struct ctx *c, json_object *o) {
  struct vlff_in_event *ev = &r->ev;
  uint64_t W, H;
  if (get_uint(c, o, "width", 1, VLFF_MAX_IMAGE_SIDE, &W) < 0 || get_uint(c, o, "height", 1, VLFF_MAX_IMAGE_SIDE, &H) < 0)
    return -1;
  if (W != ev->width || H != ev->height)
    return bad(c, "%llux%llu, its frame's colour is %ux%u", (unsigned long long)W, (unsigned long long)H, ev->width,
               ev->height);
  json_object *K = get(c, o, "K", json_type_array);
  if (!K) return -1;
  if (json_object_array_length(K) != 9) return bad(c, "K holds %zu numbers, not 9", json_object_array_length(K));
  double k[9];
  for (size_t i = 0; i < 9; i++) {
    json_object *v = json_object_array_get_idx(K, i);
    if (!v || !(json_object_is_type(v, json_type_double) || json_object_is_type(v, json_type_int)) ||
        !isfinite(k[i] = json_object_get_double(v)))
      return bad(c, "K[%zu] is not a finite number", i);
  }
  if (k[1] != 0 || k[3] != 0 || k[6] != 0 || k[7] != 0 || k[8] != 1)
    return bad(c, "K is not a pinhole matrix [fx 0 cx; 0 fy cy; 0 0 1]");
  double fx = k[0], fy = k[4], cx = k[2] + 0.5, cy = k[5] + 0.5;
  char why[256];
  if (vlff_intrinsics_plausible((int)W, (int)H, fx, fy, cx, cy, why, sizeof why) < 0) return bad(c, "%s", why);
  ev->fx = fx, ev->fy = fy, ev->cx = cx, ev->cy = cy;
  return 0;
}

static int pose(struct vlff_in_event *ev, const struct ctx *c, json_object *o) {
  json_object *t = get(c, o, "translation", json_type_object), *q = t ? get(c, o, "rotation", json_type_object) : NULL;
  double x = 0, y = 0, z = 0, qx = 0, qy = 0, qz = 0, qw = 0; /* set by get_num (gcc -O2 cannot tell) */
  if (!q || get_num(c, t, "x", &x) < 0 || get_num(c, t, "y", &y) < 0 || get_num(c, t, "z", &z) < 0 ||
      get_num(c, q, "x", &qx) < 0 || get_num(c, q, "y", &qy) < 0 || get_num(c, q, "z", &qz) < 0 ||
      get_num(c, q, "w", &qw) < 0)
    return -1;
  double n = sqrt(qx * qx + qy * qy + qz * qz + qw * qw);
  if (!(fabs(n - 1) <= 1e-6)) return bad(c, "rotation is not a unit quaternion (norm %.9g)", n);
  qx /= n, qy /= n, qz /= n, qw /= n;
  double *P = ev->pose;
  P[0] = 1 - 2 * (qy * qy + qz * qz), P[1] = 2 * (qx * qy - qz * qw), P[2] = 2 * (qx * qz + qy * qw), P[3] = x;
  P[4] = 2 * (qx * qy + qz * qw), P[5] = 1 - 2 * (qx * qx + qz * qz), P[6] = 2 * (qy * qz - qx * qw), P[7] = y;
  P[8] = 2 * (qx * qz - qy * qw), P[9] = 2 * (qy * qz + qx * qw), P[10] = 1 - 2 * (qx * qx + qy * qy), P[11] = z;
  P[12] = P[13] = P[14] = 0, P[15] = 1;
  char why[256];
  if (vlff_pose_plausible(P, NULL, NULL, why, sizeof why) < 0) return bad(c, "%s", why);
  return 0;
}

static int features(struct vlff_in_reader *r, const struct ctx *c, json_object *o) {
  struct vlff_in_event *ev = &r->ev;
  uint64_t id, D, h, w;
  if (get_uint(c, o, "frame_id", 0, INT64_MAX, &id) < 0 || get_uint(c, o, "dim", 1, VLFF_IN_MAX_DIM, &D) < 0 ||
      get_uint(c, o, "height", 1, VLFF_MAX_IMAGE_SIDE, &h) < 0 || get_uint(c, o, "width", 1, VLFF_MAX_IMAGE_SIDE, &w) < 0)
    return -1;
  json_object *e = get(c, o, "encoding", json_type_string);
  if (!e) return -1;
  if (strcmp(json_object_get_string(e), "float16")) return bad(c, "encoding is not float16");
  if (h * w > VLFF_IN_MAX_FEATURE_BYTES / 2 / D)
    return bad(c, "%llu x %llu x %llu features are more than %zu bytes", (unsigned long long)D,
               (unsigned long long)h, (unsigned long long)w, VLFF_IN_MAX_FEATURE_BYTES);
  if (r->shape && (D != r->dim || h != r->fh || w != r->fw))
    return bad(c, "features %llux%llux%llu, the recording's first map is %ux%ux%u (a ring has one shape)",
               (unsigned long long)D, (unsigned long long)h, (unsigned long long)w, r->dim, r->fh, r->fw);
  size_t cap = r->feat_cap * 2;
  void *buf = r->feat;
  int rc = get_b64(c, o, "data", (size_t)(2 * D * h * w), &buf, &cap);
  r->feat = buf, r->feat_cap = cap / 2;
  if (rc < 0) return -1;
  if (!r->shape) r->shape = 1, r->dim = (uint32_t)D, r->fh = (uint32_t)h, r->fw = (uint32_t)w;
  ev->frame_id = id, ev->dim = (uint32_t)D, ev->feat_height = (uint32_t)h, ev->feat_width = (uint32_t)w;
  ev->features = r->feat;
  return 0;
}

int vlff_in_next(struct vlff_in_reader *r, struct vlff_in_event *out, char *why, size_t len) {
  for (;;) {
    struct vlff_mcap_message m;
    int rc = vlff_mcap_next(r->m, &m, why, len);
    if (rc < 0) return -1;
    if (rc == 0) {
      uint64_t at;
      if (vlff_mcap_truncated(r->m, &at))
        return fail(why, len, "the file ends at byte %llu without its footer: a recording cut short (its recorder "
                              "was killed) is not replayed",
                    (unsigned long long)at);
      if (r->pending) {
        struct ctx c = {topics[VLFF_IN_COLOR], r->ev.index, why, len};
        return bad(&c, "the frame has no calibration message");
      }
      return 0;
    }
    uint64_t index = r->index++;
    const char *topic = "?";
    int ch = channel_kind(r, m.channel, &topic);
    struct ctx c = {topic, index, why, len};
    if (ch < 0) return bad(&c, "an /input/ channel with another schema or encoding than vlff-record writes");
    if (ch == 0) {
      r->other++;
      continue;
    }
    if (m.len > INT_MAX) return bad(&c, "a message of %zu bytes", m.len);
    json_tokener_reset(r->tok);
    json_object *o = json_tokener_parse_ex(r->tok, (const char *)m.data, (int)m.len);
    if (!o || json_tokener_get_error(r->tok) != json_tokener_success ||
        json_tokener_get_parse_end(r->tok) != m.len) {
      if (o) json_object_put(o);
      return bad(&c, "not one JSON text (%s)", json_tokener_error_desc(json_tokener_get_error(r->tok)));
    }
    rc = -1;
    uint64_t t;
    if (!json_object_is_type(o, json_type_object)) {
      bad(&c, "not a JSON object");
      goto out;
    }
    if (get_time(&c, o, &t) < 0) goto out;
    if (r->seen[ch] && (t < r->last_t[ch] || (ch == VLFF_IN_COLOR && t == r->last_t[ch]))) {
      bad(&c, "stamp %llu ns is %s the previous one's on the channel (%llu ns)", (unsigned long long)t,
          t == r->last_t[ch] ? "the same as" : "before", (unsigned long long)r->last_t[ch]);
      goto out;
    }
    r->seen[ch] = 1, r->last_t[ch] = t;
    if (r->pending && (ch == VLFF_IN_COLOR || ch == VLFF_IN_POSE || ch == VLFF_IN_FEATURES)) {
      bad(&c, "the frame of message %llu has no calibration before this message", (unsigned long long)r->ev.index);
      goto out;
    }
    if ((ch == VLFF_IN_DEPTH || ch == VLFF_IN_CALIBRATION) && (!r->pending || t != r->ev.t_ns)) {
      bad(&c, "not just after a colour message of the same stamp");
      goto out;
    }
    if (ch == VLFF_IN_FRAME_POSE && !r->pending) {
      bad(&c, "not just after a frame's colour message");
      goto out;
    }
    switch (ch) {
    case VLFF_IN_COLOR:
      memset(&r->ev, 0, sizeof r->ev);
      r->ev.kind = VLFF_IN_EV_FRAME, r->ev.t_ns = t, r->ev.index = index;
      if (raw_image(&c, o, 0, &r->ev.width, &r->ev.height, &r->ev.color_format, &r->color, &r->color_cap) < 0)
        goto out;
      r->pending = 1, r->pending_depth = 0;
      rc = 2; /* more to come */
      break;
    case VLFF_IN_DEPTH: {
      uint32_t w, h, f;
      if (r->pending_depth) {
        bad(&c, "a second depth image for the frame");
        goto out;
      }
      if (raw_image(&c, o, 1, &w, &h, &f, &r->depth, &r->depth_cap) < 0) goto out;
      if (w != r->ev.width || h != r->ev.height) {
        bad(&c, "%ux%u, its frame's colour is %ux%u", w, h, r->ev.width, r->ev.height);
        goto out;
      }
      if (r->ev.has_pose) {
        bad(&c, "the frame's depth after its pose");
        goto out;
      }
      r->pending_depth = 1, r->ev.depth_format = f;
      rc = 2;
      break;
    }
    case VLFF_IN_FRAME_POSE:
      if (r->ev.has_pose) {
        bad(&c, "a second pose for the frame");
        goto out;
      }
      if (pose(&r->ev, &c, o) < 0) goto out;
      r->ev.has_pose = 1, r->ev.pose_t_ns = t;
      rc = 2;
      break;
    case VLFF_IN_CALIBRATION:
      if (calibration(r, &c, o) < 0) goto out;
      if (r->geom && (r->ev.width != r->width || r->ev.height != r->height || r->ev.color_format != r->color_format ||
                      r->ev.depth_format != r->depth_format)) {
        bad(&c, "the frame is %ux%u %s%s%s, the recording's first is %ux%u %s%s%s (a ring has one slot size)",
            r->ev.width, r->ev.height, encoding_name(r->ev.color_format), r->ev.depth_format ? "+" : "",
            r->ev.depth_format ? encoding_name(r->ev.depth_format) : "", r->width, r->height,
            encoding_name(r->color_format), r->depth_format ? "+" : "",
            r->depth_format ? encoding_name(r->depth_format) : "");
        goto out;
      }
      if (!r->geom)
        r->geom = 1, r->width = r->ev.width, r->height = r->ev.height, r->color_format = r->ev.color_format,
        r->depth_format = r->ev.depth_format;
      r->pending = 0;
      r->ev.color = r->color;
      r->ev.depth = r->ev.depth_format ? r->depth : NULL;
      *out = r->ev;
      rc = 1;
      break;
    case VLFF_IN_POSE:
      memset(out, 0, sizeof *out);
      out->kind = VLFF_IN_EV_POSE, out->t_ns = t, out->index = index;
      rc = pose(out, &c, o) < 0 ? -1 : 1;
      break;
    case VLFF_IN_FEATURES: {
      struct vlff_in_event keep = r->ev;
      memset(&r->ev, 0, sizeof r->ev);
      r->ev.kind = VLFF_IN_EV_FEATURES, r->ev.t_ns = t, r->ev.index = index;
      rc = features(r, &c, o) < 0 ? -1 : 1;
      if (rc == 1) *out = r->ev;
      r->ev = keep;
      break;
    }
    }
  out:
    json_object_put(o);
    if (rc != 2) return rc;
  }
}
