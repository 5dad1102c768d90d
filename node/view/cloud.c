/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * cloud.c - the map as foxglove.PointCloud in protobuf (the /map/points channel).
 *
 * Protobuf is written here by hand: a message is a few tagged fields, and the
 * points travel as one bytes field, so a library would add a dependency for some
 * twenty lines. The channel's schema is the FileDescriptorSet of
 * foxglove.PointCloud and the messages it uses, with the files, packages, imports,
 * field names, numbers and types of the official definitions (test_view_foxglove
 * compares it with the .proto files the npm package @foxglove/schemas generates).
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

struct file_def {
  const char *file, *package, *message;
  const char *deps[3];
  struct field_def fields[6];
  int numeric_type_enum; /* PackedElementField's nested enum NumericType */
};

static const struct file_def files[] = {
    {"google/protobuf/timestamp.proto", "google.protobuf", "Timestamp", {NULL},
     {{"seconds", 1, T_INT64, L_OPTIONAL, NULL}, {"nanos", 2, T_INT32, L_OPTIONAL, NULL}}, 0},
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
};

static const char *const numeric_types[] = {"UNKNOWN", "UINT8",  "INT8",    "UINT16", "INT16",
                                            "UINT32",  "INT32",  "FLOAT32", "FLOAT64"};

#define DESC_MAX 4096
static uint8_t desc[DESC_MAX];
static size_t desc_len;
static char desc_b64[DESC_MAX / 3 * 4 + 8];

/* FileDescriptorProto of f into out. */
static void file_proto(struct pb *out, const struct file_def *f) {
  uint8_t mb[1024], fb[256], eb[512], vb[64];
  struct pb msg = {mb, 0, sizeof mb, 0};
  pb_str(&msg, 1, f->message); /* DescriptorProto.name */
  for (int i = 0; i < 6 && f->fields[i].name; i++) {
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
  for (int i = 0; i < 3 && f->deps[i]; i++) pb_str(out, 3, f->deps[i]);
  pb_msg(out, 4, &msg);
  pb_str(out, 12, "proto3");
}

static void build_descriptor(void) {
  if (desc_len) return;
  struct pb set = {desc, 0, sizeof desc, 0};
  for (size_t i = 0; i < sizeof files / sizeof *files; i++) {
    uint8_t fb[1536];
    struct pb file = {fb, 0, sizeof fb, 0};
    file_proto(&file, &files[i]);
    pb_msg(&set, 1, &file); /* FileDescriptorSet.file */
  }
  /* the tables above fit the bounds; a failure here is a bug in them */
  if (set.failed) abort();
  desc_len = set.n;
  lws_b64_encode_string((const char *)desc, (int)desc_len, desc_b64, (int)sizeof desc_b64);
}

const uint8_t *vlff_view_cloud_descriptor(size_t *len) {
  build_descriptor();
  *len = desc_len;
  return desc;
}

const char *vlff_view_cloud_descriptor_b64(void) {
  build_descriptor();
  return desc_b64;
}

/* ---------------------------------------------------------- the messages */

/* PackedElementField.NumericType */
enum { NT_UINT8 = 1, NT_UINT16 = 3, NT_FLOAT32 = 7 };

static const struct {
  const char *name;
  uint32_t offset, type;
} point_fields[] = {
    {"x", 0, NT_FLOAT32},  {"y", 4, NT_FLOAT32},     {"z", 8, NT_FLOAT32},   {"red", 12, NT_UINT8},
    {"green", 13, NT_UINT8}, {"blue", 14, NT_UINT8}, {"alpha", 15, NT_UINT8}, {"label", 16, NT_UINT16},
    {"confidence", 18, NT_UINT8},
};

/* Everything of a PointCloud before its data's bytes; the data field's tag and
 * length end it. */
static size_t cloud_head(uint8_t *out, size_t cap, const char *frame, uint64_t t_ns, size_t data_len) {
  struct pb b = {out, 0, cap, 0};
  uint8_t tb[32], vb[8], qb[16], pb_[64], fb[64];
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
  for (size_t i = 0; i < sizeof point_fields / sizeof *point_fields; i++) {
    struct pb f = {fb, 0, sizeof fb, 0};
    pb_str(&f, 1, point_fields[i].name);
    pb_fixed32(&f, 2, point_fields[i].offset);
    pb_uint(&f, 3, point_fields[i].type);
    pb_msg(&b, 5, &f);
  }
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
