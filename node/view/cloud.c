/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * cloud.c - the viewer's protobuf channels: the map as foxglove.PointCloud
 * (/map/points), its top-down projection as foxglove.Grid (/map/grid) and the
 * camera's depth as foxglove.RawImage (/camera/depth).
 *
 * Protobuf is written here by hand: a message is a few tagged fields, and the
 * payload travels as one bytes field, so a library would add a dependency for some
 * twenty lines. Each channel's schema is the FileDescriptorSet of its message and
 * the messages it uses, with the files, packages, imports, field names, numbers and
 * types of the official definitions, which node/view/proto/ holds as .proto files
 * (test_view_proto decodes the channels with those files, test_view_foxglove
 * compares the descriptors with what the npm package @foxglove/schemas generates).
 */
#include "view.h"

#include <libwebsockets.h>
#include <stdlib.h>
#include <string.h>

/* An append-only byte buffer with a bound; overflowing it marks it failed. */
struct pb {
  uint8_t *d;
  size_t n, cap;
  int failed;
};

static void pb_put(struct pb *b, const void *s, size_t n) {
  if (b->failed || b->n + n > b->cap) {
    b->failed = 1;
    return;
  }
  memcpy(b->d + b->n, s, n);
  b->n += n;
}

static void pb_varint(struct pb *b, uint64_t v) {
  uint8_t t[10];
  size_t n = 0;
  do {
    t[n++] = (uint8_t)((v & 0x7f) | (v > 0x7f ? 0x80 : 0));
    v >>= 7;
  } while (v);
  pb_put(b, t, n);
}

enum { WT_VARINT = 0, WT_I64 = 1, WT_LEN = 2, WT_I32 = 5 };

static void pb_tag(struct pb *b, unsigned field, unsigned wt) { pb_varint(b, (uint64_t)field << 3 | wt); }

static void pb_bytes(struct pb *b, unsigned field, const void *s, size_t n) {
  pb_tag(b, field, WT_LEN);
  pb_varint(b, n);
  pb_put(b, s, n);
}

static void pb_str(struct pb *b, unsigned field, const char *s) { pb_bytes(b, field, s, strlen(s)); }

static void pb_uint(struct pb *b, unsigned field, uint64_t v) {
  pb_tag(b, field, WT_VARINT);
  pb_varint(b, v);
}

static void pb_fixed32(struct pb *b, unsigned field, uint32_t v) {
  uint8_t t[4] = {(uint8_t)v, (uint8_t)(v >> 8), (uint8_t)(v >> 16), (uint8_t)(v >> 24)};
  pb_tag(b, field, WT_I32);
  pb_put(b, t, 4);
}

static void pb_double(struct pb *b, unsigned field, double v) {
  uint64_t u;
  memcpy(&u, &v, 8);
  uint8_t t[8];
  for (int i = 0; i < 8; i++) t[i] = (uint8_t)(u >> (8 * i));
  pb_tag(b, field, WT_I64);
  pb_put(b, t, 8);
}

/* A nested message: inner (written into a buffer of its own) as field. */
static void pb_msg(struct pb *b, unsigned field, const struct pb *inner) {
  if (inner->failed) b->failed = 1;
  pb_bytes(b, field, inner->d, inner->n);
}

/* ------------------------------------------------------------- the schema */

/* google/protobuf/descriptor.proto's numbers */
enum { T_DOUBLE = 1, T_INT64 = 3, T_INT32 = 5, T_FIXED32 = 7, T_STRING = 9, T_MESSAGE = 11, T_BYTES = 12, T_ENUM = 14 };
enum { L_OPTIONAL = 1, L_REPEATED = 3 };

struct field_def {
  const char *name;
  int number, type, label;
  const char *type_name;
};

#define FILE_DEPS 4
#define FILE_FIELDS 9
struct file_def {
  const char *file, *package, *message;
  const char *deps[FILE_DEPS];
  struct field_def fields[FILE_FIELDS];
  int numeric_type_enum; /* PackedElementField's nested enum NumericType */
};

/* In dependency order: a file comes after every file it imports. */
static const struct file_def files[] = {
    {"google/protobuf/timestamp.proto", "google.protobuf", "Timestamp", {NULL},
     {{"seconds", 1, T_INT64, L_OPTIONAL, NULL}, {"nanos", 2, T_INT32, L_OPTIONAL, NULL}}, 0},
    {"foxglove/Vector2.proto", "foxglove", "Vector2", {NULL},
     {{"x", 1, T_DOUBLE, L_OPTIONAL, NULL}, {"y", 2, T_DOUBLE, L_OPTIONAL, NULL}}, 0},
    {"foxglove/Vector3.proto", "foxglove", "Vector3", {NULL},
     {{"x", 1, T_DOUBLE, L_OPTIONAL, NULL}, {"y", 2, T_DOUBLE, L_OPTIONAL, NULL}, {"z", 3, T_DOUBLE, L_OPTIONAL, NULL}},
     0},
    {"foxglove/Quaternion.proto", "foxglove", "Quaternion", {NULL},
     {{"x", 1, T_DOUBLE, L_OPTIONAL, NULL},
      {"y", 2, T_DOUBLE, L_OPTIONAL, NULL},
      {"z", 3, T_DOUBLE, L_OPTIONAL, NULL},
      {"w", 4, T_DOUBLE, L_OPTIONAL, NULL}},
     0},
    {"foxglove/Pose.proto", "foxglove", "Pose", {"foxglove/Quaternion.proto", "foxglove/Vector3.proto", NULL},
     {{"position", 1, T_MESSAGE, L_OPTIONAL, ".foxglove.Vector3"},
      {"orientation", 2, T_MESSAGE, L_OPTIONAL, ".foxglove.Quaternion"}},
     0},
    {"foxglove/PackedElementField.proto", "foxglove", "PackedElementField", {NULL},
     {{"name", 1, T_STRING, L_OPTIONAL, NULL},
      {"offset", 2, T_FIXED32, L_OPTIONAL, NULL},
      {"type", 3, T_ENUM, L_OPTIONAL, ".foxglove.PackedElementField.NumericType"}},
     1},
    {"foxglove/PointCloud.proto", "foxglove", "PointCloud",
     {"foxglove/PackedElementField.proto", "foxglove/Pose.proto", "google/protobuf/timestamp.proto"},
     {{"timestamp", 1, T_MESSAGE, L_OPTIONAL, ".google.protobuf.Timestamp"},
      {"frame_id", 2, T_STRING, L_OPTIONAL, NULL},
      {"pose", 3, T_MESSAGE, L_OPTIONAL, ".foxglove.Pose"},
      {"point_stride", 4, T_FIXED32, L_OPTIONAL, NULL},
      {"fields", 5, T_MESSAGE, L_REPEATED, ".foxglove.PackedElementField"},
      {"data", 6, T_BYTES, L_OPTIONAL, NULL}},
     0},
    {"foxglove/Grid.proto", "foxglove", "Grid",
     {"foxglove/PackedElementField.proto", "foxglove/Pose.proto", "foxglove/Vector2.proto",
      "google/protobuf/timestamp.proto"},
     {{"timestamp", 1, T_MESSAGE, L_OPTIONAL, ".google.protobuf.Timestamp"},
      {"frame_id", 2, T_STRING, L_OPTIONAL, NULL},
      {"pose", 3, T_MESSAGE, L_OPTIONAL, ".foxglove.Pose"},
      {"column_count", 4, T_FIXED32, L_OPTIONAL, NULL},
      {"cell_size", 5, T_MESSAGE, L_OPTIONAL, ".foxglove.Vector2"},
      {"row_stride", 6, T_FIXED32, L_OPTIONAL, NULL},
      {"cell_stride", 7, T_FIXED32, L_OPTIONAL, NULL},
      {"fields", 8, T_MESSAGE, L_REPEATED, ".foxglove.PackedElementField"},
      {"data", 9, T_BYTES, L_OPTIONAL, NULL}},
     0},
    {"foxglove/RawImage.proto", "foxglove", "RawImage", {"google/protobuf/timestamp.proto"},
     {{"timestamp", 1, T_MESSAGE, L_OPTIONAL, ".google.protobuf.Timestamp"},
      {"frame_id", 7, T_STRING, L_OPTIONAL, NULL},
      {"width", 2, T_FIXED32, L_OPTIONAL, NULL},
      {"height", 3, T_FIXED32, L_OPTIONAL, NULL},
      {"encoding", 4, T_STRING, L_OPTIONAL, NULL},
      {"step", 5, T_FIXED32, L_OPTIONAL, NULL},
      {"data", 6, T_BYTES, L_OPTIONAL, NULL}},
     0},
};
enum { NFILES = sizeof files / sizeof *files };

static const char *const numeric_types[] = {"UNKNOWN", "UINT8",  "INT8",    "UINT16", "INT16",
                                            "UINT32",  "INT32",  "FLOAT32", "FLOAT64"};

#define DESC_MAX 4096
/* a channel's FileDescriptorSet, built at its first use */
struct descriptor {
  const char *message; /* the root message's file, e.g. "foxglove/PointCloud.proto" */
  uint8_t d[DESC_MAX];
  size_t len;
  char b64[DESC_MAX / 3 * 4 + 8];
};
static struct descriptor descs[] = {
    {"foxglove/PointCloud.proto", {0}, 0, {0}},
    {"foxglove/Grid.proto", {0}, 0, {0}},
    {"foxglove/RawImage.proto", {0}, 0, {0}},
};

/* FileDescriptorProto of f into out. */
static void file_proto(struct pb *out, const struct file_def *f) {
  uint8_t mb[1024], fb[256], eb[512], vb[64];
  struct pb msg = {mb, 0, sizeof mb, 0};
  pb_str(&msg, 1, f->message); /* DescriptorProto.name */
  for (int i = 0; i < FILE_FIELDS && f->fields[i].name; i++) {
    const struct field_def *d = &f->fields[i];
    struct pb fd = {fb, 0, sizeof fb, 0};
    pb_str(&fd, 1, d->name);
    pb_uint(&fd, 3, (uint64_t)d->number);
    pb_uint(&fd, 4, (uint64_t)d->label);
    pb_uint(&fd, 5, (uint64_t)d->type);
    if (d->type_name) pb_str(&fd, 6, d->type_name);
    pb_msg(&msg, 2, &fd);
  }
  if (f->numeric_type_enum) {
    struct pb en = {eb, 0, sizeof eb, 0};
    pb_str(&en, 1, "NumericType");
    for (unsigned v = 0; v < sizeof numeric_types / sizeof *numeric_types; v++) {
      struct pb val = {vb, 0, sizeof vb, 0};
      pb_str(&val, 1, numeric_types[v]);
      pb_uint(&val, 2, v);
      pb_msg(&en, 2, &val);
    }
    pb_msg(&msg, 4, &en); /* DescriptorProto.enum_type */
  }
  pb_str(out, 1, f->file);
  pb_str(out, 2, f->package);
  for (int i = 0; i < FILE_DEPS && f->deps[i]; i++) pb_str(out, 3, f->deps[i]);
  pb_msg(out, 4, &msg);
  pb_str(out, 12, "proto3");
}

static int file_index(const char *file) {
  for (int i = 0; i < NFILES; i++)
    if (!strcmp(files[i].file, file)) return i;
  abort(); /* an import the table does not hold: a bug in it */
}

/* Marks file i and every file it imports, transitively. */
static void mark_needed(int i, uint8_t *need) {
  need[i] = 1;
  for (int d = 0; d < FILE_DEPS && files[i].deps[d]; d++) mark_needed(file_index(files[i].deps[d]), need);
}

static void build_descriptor(struct descriptor *ds) {
  if (ds->len) return;
  uint8_t need[NFILES] = {0};
  mark_needed(file_index(ds->message), need);
  struct pb set = {ds->d, 0, sizeof ds->d, 0};
  for (int i = 0; i < NFILES; i++) {
    if (!need[i]) continue;
    uint8_t fb[1536];
    struct pb file = {fb, 0, sizeof fb, 0};
    file_proto(&file, &files[i]);
    pb_msg(&set, 1, &file); /* FileDescriptorSet.file */
  }
  /* the tables above fit the bounds; a failure here is a bug in them */
  if (set.failed) abort();
  ds->len = set.n;
  lws_b64_encode_string((const char *)ds->d, (int)ds->len, ds->b64, (int)sizeof ds->b64);
}

static struct descriptor *channel_descriptor(int ch) {
  int i = ch == VLFF_VIEW_CH_CLOUD ? 0 : ch == VLFF_VIEW_CH_GRID ? 1 : ch == VLFF_VIEW_CH_DEPTH ? 2 : -1;
  if (i < 0) return NULL;
  build_descriptor(&descs[i]);
  return &descs[i];
}

const uint8_t *vlff_view_descriptor(int ch, size_t *len) {
  struct descriptor *d = channel_descriptor(ch);
  *len = d ? d->len : 0;
  return d ? d->d : NULL;
}

const char *vlff_view_descriptor_b64(int ch) {
  struct descriptor *d = channel_descriptor(ch);
  return d ? d->b64 : NULL;
}

/* ---------------------------------------------------------- the messages */

/* PackedElementField.NumericType */
enum { NT_UINT8 = 1, NT_UINT16 = 3, NT_FLOAT32 = 7 };

struct packed_field {
  const char *name;
  uint32_t offset, type;
};

/* Each of fields[0..n) as a PackedElementField, message field `no` of b. */
static void pb_packed_fields(struct pb *b, int no, const struct packed_field *fields, size_t n) {
  for (size_t i = 0; i < n; i++) {
    uint8_t fb[64];
    struct pb f = {fb, 0, sizeof fb, 0};
    pb_str(&f, 1, fields[i].name);
    pb_fixed32(&f, 2, fields[i].offset);
    pb_uint(&f, 3, fields[i].type);
    pb_msg(b, no, &f);
  }
}

static const struct packed_field point_fields[] = {
    {"x", 0, NT_FLOAT32},  {"y", 4, NT_FLOAT32},     {"z", 8, NT_FLOAT32},   {"red", 12, NT_UINT8},
    {"green", 13, NT_UINT8}, {"blue", 14, NT_UINT8}, {"alpha", 15, NT_UINT8}, {"label", 16, NT_UINT16},
    {"confidence", 18, NT_UINT8},
};

/* Everything of a PointCloud before its data's bytes; the data field's tag and
 * length end it. */
static size_t cloud_head(uint8_t *out, size_t cap, const char *frame, uint64_t t_ns, size_t data_len) {
  struct pb b = {out, 0, cap, 0};
  uint8_t tb[32], vb[8], qb[16], pb_[64];
  struct pb ts = {tb, 0, sizeof tb, 0};
  pb_uint(&ts, 1, t_ns / 1000000000u);
  pb_uint(&ts, 2, t_ns % 1000000000u);
  pb_msg(&b, 1, &ts);
  pb_str(&b, 2, frame);
  struct pb pos = {vb, 0, sizeof vb, 0}, rot = {qb, 0, sizeof qb, 0}, pose = {pb_, 0, sizeof pb_, 0};
  pb_double(&rot, 4, 1.0); /* identity: the points are in world coordinates */
  pb_msg(&pose, 1, &pos);
  pb_msg(&pose, 2, &rot);
  pb_msg(&b, 3, &pose);
  pb_fixed32(&b, 4, VLFF_VIEW_CLOUD_STRIDE);
  pb_packed_fields(&b, 5, point_fields, sizeof point_fields / sizeof *point_fields);
  pb_tag(&b, 6, WT_LEN);
  pb_varint(&b, data_len);
  return b.failed ? 0 : b.n;
}

struct vlff_view_msg *vlff_view_cloud_msgs(int channel, const char *frame, const uint8_t *points, size_t n,
                                           uint64_t t_ns, size_t piece_bytes, int *pieces) {
  /* the head holds the frame and fixed fields: 512 bytes with a frame of the
   * config's bound */
  size_t head_cap = 512 + strlen(frame);
  size_t per = piece_bytes > 1024 + strlen(frame) ? (piece_bytes - 512 - strlen(frame)) / VLFF_VIEW_CLOUD_STRIDE : 25;
  struct vlff_view_msg *head = NULL, **link = &head;
  *pieces = 0;
  size_t at = 0;
  do {
    size_t k = n - at < per ? n - at : per, data = k * VLFF_VIEW_CLOUD_STRIDE;
    struct vlff_view_msg *m = vlff_view_msg_new(channel, head_cap + data);
    if (!m) {
      vlff_view_msg_unref(head);
      return NULL;
    }
    uint8_t *p = vlff_view_msg_payload(m);
    size_t h = cloud_head(p, head_cap, frame, t_ns, data);
    if (!h) abort(); /* the head's fields are fixed: it always fits */
    memcpy(p + h, points + at * VLFF_VIEW_CLOUD_STRIDE, data);
    m->len = h + data;
    m->t_ns = t_ns;
    *link = m;
    link = &m->next;
    ++*pieces;
    at += k;
  } while (at < n);
  return head;
}

/* The head shared by Grid and RawImage: timestamp (field 1) and frame_id (field
 * frame_field). */
static void stamp_frame(struct pb *b, uint64_t t_ns, const char *frame, unsigned frame_field) {
  uint8_t tb[32];
  struct pb ts = {tb, 0, sizeof tb, 0};
  pb_uint(&ts, 1, t_ns / 1000000000u);
  pb_uint(&ts, 2, t_ns % 1000000000u);
  pb_msg(b, 1, &ts);
  pb_str(b, frame_field, frame);
}

static const struct packed_field grid_fields[] = {
    {"red", 0, NT_UINT8},   {"green", 1, NT_UINT8},       {"blue", 2, NT_UINT8},          {"alpha", 3, NT_UINT8},
    {"label", 4, NT_UINT16}, {"confidence", 6, NT_UINT8}, {"elevation", 8, NT_FLOAT32},
};

struct vlff_view_msg *vlff_view_grid_msg(int channel, const char *frame, uint64_t t_ns, const double corner[3],
                                         double cell, uint32_t cols, uint32_t rows, const uint8_t *cells) {
  size_t data = (size_t)cols * rows * VLFF_VIEW_GRID_STRIDE, head_cap = 512 + strlen(frame);
  struct vlff_view_msg *m = vlff_view_msg_new(channel, head_cap + data);
  if (!m) return NULL;
  uint8_t *p = vlff_view_msg_payload(m);
  struct pb b = {p, 0, head_cap, 0};
  stamp_frame(&b, t_ns, frame, 2);
  uint8_t vb[32], qb[16], pb_[80], cb[24];
  struct pb pos = {vb, 0, sizeof vb, 0}, rot = {qb, 0, sizeof qb, 0}, pose = {pb_, 0, sizeof pb_, 0};
  for (unsigned a = 0; a < 3; a++) pb_double(&pos, a + 1, corner[a]);
  pb_double(&rot, 4, 1.0); /* the map's axes: the grid lies in its x-y plane */
  pb_msg(&pose, 1, &pos);
  pb_msg(&pose, 2, &rot);
  pb_msg(&b, 3, &pose);
  pb_fixed32(&b, 4, cols);
  struct pb cs = {cb, 0, sizeof cb, 0};
  pb_double(&cs, 1, cell);
  pb_double(&cs, 2, cell);
  pb_msg(&b, 5, &cs);
  pb_fixed32(&b, 6, cols * VLFF_VIEW_GRID_STRIDE);
  pb_fixed32(&b, 7, VLFF_VIEW_GRID_STRIDE);
  pb_packed_fields(&b, 8, grid_fields, sizeof grid_fields / sizeof *grid_fields);
  pb_tag(&b, 9, WT_LEN);
  pb_varint(&b, data);
  if (b.failed) abort(); /* the head's fields are fixed: it always fits */
  memcpy(p + b.n, cells, data);
  m->len = b.n + data;
  m->t_ns = t_ns;
  return m;
}

struct vlff_view_msg *vlff_view_depth_msg(int channel, const char *frame, uint64_t t_ns, uint32_t w, uint32_t h,
                                          const uint8_t *mm) {
  size_t data = (size_t)w * h * 2, head_cap = 128 + strlen(frame);
  struct vlff_view_msg *m = vlff_view_msg_new(channel, head_cap + data);
  if (!m) return NULL;
  uint8_t *p = vlff_view_msg_payload(m);
  struct pb b = {p, 0, head_cap, 0};
  stamp_frame(&b, t_ns, frame, 7);
  pb_fixed32(&b, 2, w);
  pb_fixed32(&b, 3, h);
  pb_str(&b, 4, "16UC1");
  pb_fixed32(&b, 5, w * 2);
  pb_tag(&b, 6, WT_LEN);
  pb_varint(&b, data);
  if (b.failed) abort();
  memcpy(p + b.n, mm, data);
  m->len = b.n + data;
  m->t_ns = t_ns;
  return m;
}
