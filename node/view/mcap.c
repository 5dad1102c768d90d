/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * mcap.c - the MCAP writer and reader (mcap.h), written from the format's
 * specification: little-endian records of an opcode byte, a u64 length and the
 * fields; strings and byte arrays prefixed with a u32 length, maps with a u32 byte
 * length. CRCs are zlib's CRC-32 (the one MCAP names), chunks are compressed by
 * libzstd.
 */
#include "mcap.h"

#include <errno.h>
#include <fcntl.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>
#include <zstd.h>

#include "clock.h"
#include "vlff/escape.h"

static const uint8_t MAGIC[8] = {0x89, 'M', 'C', 'A', 'P', '0', '\r', '\n'};

enum {
  OP_HEADER = 0x01,
  OP_FOOTER = 0x02,
  OP_SCHEMA = 0x03,
  OP_CHANNEL = 0x04,
  OP_MESSAGE = 0x05,
  OP_CHUNK = 0x06,
  OP_MESSAGE_INDEX = 0x07,
  OP_CHUNK_INDEX = 0x08,
  OP_STATISTICS = 0x0B,
  OP_SUMMARY_OFFSET = 0x0E,
  OP_DATA_END = 0x0F,
};

static void say(char *why, size_t len, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
static void say(char *why, size_t len, const char *fmt, ...) {
  if (!why || !len) return;
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(why, len, fmt, ap);
  va_end(ap);
}

static uint32_t crc(uint32_t c, const void *d, size_t n) {
  const uint8_t *p = d;
  while (n) { /* zlib takes at most a uInt at a time */
    uInt k = n > (1u << 30) ? (1u << 30) : (uInt)n;
    c = (uint32_t)crc32(c, p, k);
    p += k;
    n -= k;
  }
  return c;
}

/* ------------------------------------------------------------ byte buffer */

struct buf {
  uint8_t *d;
  size_t n, cap;
  int failed;
};

static int b_reserve(struct buf *b, size_t more) {
  if (b->failed) return -1;
  if (b->n + more <= b->cap) return 0;
  size_t cap = b->cap ? b->cap : 4096;
  while (cap < b->n + more) cap *= 2;
  uint8_t *d = realloc(b->d, cap);
  if (!d) {
    b->failed = 1;
    return -1;
  }
  b->d = d;
  b->cap = cap;
  return 0;
}

static void b_put(struct buf *b, const void *s, size_t n) {
  if (b_reserve(b, n)) return;
  if (n) memcpy(b->d + b->n, s, n);
  b->n += n;
}

static void b_le(struct buf *b, uint64_t v, int bytes) {
  uint8_t t[8];
  for (int i = 0; i < bytes; i++) t[i] = (uint8_t)(v >> (8 * i));
  b_put(b, t, (size_t)bytes);
}
#define b_u8(b, v) b_le(b, v, 1)
#define b_u16(b, v) b_le(b, v, 2)
#define b_u32(b, v) b_le(b, v, 4)
#define b_u64(b, v) b_le(b, v, 8)

static void b_bytes(struct buf *b, const void *s, size_t n) {
  b_u32(b, n);
  b_put(b, s, n);
}
static void b_str(struct buf *b, const char *s) { b_bytes(b, s, strlen(s)); }

/* Starts a record: its opcode and a length patched by b_end. */
static size_t b_begin(struct buf *b, int op) {
  b_u8(b, (uint64_t)op);
  size_t at = b->n;
  b_u64(b, 0);
  return at;
}
static void b_end(struct buf *b, size_t at) {
  if (b->failed) return;
  uint64_t len = b->n - at - 8;
  for (int i = 0; i < 8; i++) b->d[at + i] = (uint8_t)(len >> (8 * i));
}

/* ----------------------------------------------------------------- writer */

struct wchannel {
  uint16_t id, schema;
  uint64_t count;               /* messages in the file */
  struct buf index;             /* this chunk's (log time, offset) pairs */
};

struct vlff_mcap_writer {
  struct vlff_mcap_writer_params p;
  int fd;
  char *path;
  uint64_t pos;   /* bytes in the file */
  uint32_t dcrc;  /* CRC of the data section so far */
  char err[256];
  int failed;
  struct buf schemas, channels; /* their records, repeated in the summary */
  int nschemas;
  struct { uint32_t crc; size_t len; } schema_key[VLFF_MCAP_MAX_CHANNELS];
  struct wchannel ch[VLFF_MCAP_MAX_CHANNELS];
  int nch;
  struct buf chunk;     /* the records of the chunk being filled */
  uint64_t chunk_start, chunk_end, chunk_t0;
  struct buf out;       /* a chunk record and its indexes, written at once */
  struct buf zbuf;
  struct buf chunk_index; /* the summary's chunk index records */
  uint32_t nchunks;
  uint64_t messages, first_ns, last_ns;
};

static int w_fail(struct vlff_mcap_writer *w, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static int w_fail(struct vlff_mcap_writer *w, const char *fmt, ...) {
  if (!w->failed) {
    va_list ap;
    va_start(ap, fmt);
    int n = snprintf(w->err, sizeof w->err, "%s: ", w->path);
    if (n > 0 && (size_t)n < sizeof w->err) vsnprintf(w->err + n, sizeof w->err - (size_t)n, fmt, ap);
    va_end(ap);
    w->failed = 1;
  }
  return -1;
}

/* Bytes to the file; in_data: they belong to the data section's CRC. */
static int w_out(struct vlff_mcap_writer *w, const void *d, size_t n, int in_data) {
  if (w->failed) return -1;
  const uint8_t *p = d;
  size_t left = n;
  while (left) {
    ssize_t k = write(w->fd, p, left);
    if (k < 0 && errno == EINTR) continue;
    if (k <= 0) return w_fail(w, "write failed after %llu bytes: %s", (unsigned long long)w->pos, strerror(errno));
    p += k;
    left -= (size_t)k;
  }
  if (in_data) w->dcrc = crc(w->dcrc, d, n);
  w->pos += n;
  return 0;
}

struct vlff_mcap_writer *vlff_mcap_writer_open(const char *path, const struct vlff_mcap_writer_params *p, char *why,
                                               size_t len) {
  struct stat st;
  if (lstat(path, &st) == 0 && !S_ISREG(st.st_mode)) {
    say(why, len, "%s is not a regular file: a recording is written only to one", VLFF_Q(path));
    return NULL;
  }
  int fd = open(path, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC | O_NOFOLLOW, 0644);
  if (fd < 0) {
    say(why, len, "cannot create %s: %s", VLFF_Q(path), strerror(errno));
    return NULL;
  }
  struct vlff_mcap_writer *w = calloc(1, sizeof *w);
  if (!w || !(w->path = strdup(path))) {
    free(w);
    close(fd);
    say(why, len, "out of memory");
    return NULL;
  }
  w->fd = fd;
  w->p = *p;
  if (!w->p.chunk_bytes) w->p.chunk_bytes = 1u << 20;
  if (w->p.chunk_s <= 0) w->p.chunk_s = 1.0;
  if (w->p.zstd_level < 0 || w->p.zstd_level > 19) w->p.zstd_level = 3;
  struct buf h = {0};
  b_put(&h, MAGIC, sizeof MAGIC);
  size_t at = b_begin(&h, OP_HEADER);
  b_str(&h, ""); /* profile: none of the well-known ones (ros1, ros2) */
  b_str(&h, w->p.library ? w->p.library : "");
  b_end(&h, at);
  if (h.failed) w_fail(w, "out of memory");
  else w_out(w, h.d, h.n, 1);
  free(h.d);
  if (w->failed) {
    say(why, len, "%s", w->err);
    vlff_mcap_writer_close(w, NULL, 0);
    return NULL;
  }
  return w;
}

static struct wchannel *w_channel(struct vlff_mcap_writer *w, uint16_t id) {
  for (int i = 0; i < w->nch; i++)
    if (w->ch[i].id == id) return &w->ch[i];
  return NULL;
}

int vlff_mcap_writer_channel(struct vlff_mcap_writer *w, uint16_t id, const char *topic, const char *message_encoding,
                             const char *schema_name, const char *schema_encoding, const void *schema,
                             size_t schema_len) {
  if (w->failed) return -1;
  if (w_channel(w, id)) return w_fail(w, "channel %u declared twice", id);
  if (w->nch == VLFF_MCAP_MAX_CHANNELS) return w_fail(w, "more than %d channels", VLFF_MCAP_MAX_CHANNELS);
  /* a schema is identified by its record's bytes: channels sharing a message type share it */
  struct buf rec = {0};
  b_str(&rec, schema_name);
  b_str(&rec, schema_encoding);
  b_bytes(&rec, schema, schema_len);
  if (rec.failed) return w_fail(w, "out of memory");
  uint32_t key = crc(0, rec.d, rec.n);
  int sid = 0;
  for (int i = 0; i < w->nschemas && !sid; i++)
    if (w->schema_key[i].crc == key && w->schema_key[i].len == rec.n) sid = i + 1;
  struct buf out = {0};
  if (!sid) {
    sid = ++w->nschemas;
    w->schema_key[sid - 1].crc = key;
    w->schema_key[sid - 1].len = rec.n;
    size_t at = b_begin(&out, OP_SCHEMA);
    b_u16(&out, (uint64_t)sid);
    b_put(&out, rec.d, rec.n);
    b_end(&out, at);
    b_put(&w->schemas, out.d + (out.n - rec.n - 11), rec.n + 11);
  }
  free(rec.d);
  size_t start = out.n;
  size_t at = b_begin(&out, OP_CHANNEL);
  b_u16(&out, id);
  b_u16(&out, (uint64_t)sid);
  b_str(&out, topic);
  b_str(&out, message_encoding);
  b_u32(&out, 0); /* metadata: none */
  b_end(&out, at);
  b_put(&w->channels, out.d + start, out.n - start);
  int rc = 0;
  if (out.failed || w->schemas.failed || w->channels.failed) rc = w_fail(w, "out of memory");
  else rc = w_out(w, out.d, out.n, 1);
  free(out.d);
  if (rc) return -1;
  w->ch[w->nch++] = (struct wchannel){.id = id, .schema = (uint16_t)sid};
  return 0;
}

/* The chunk being filled, compressed, with its message indexes after it, in one
 * write; its chunk index kept for the summary. */
static int flush_chunk(struct vlff_mcap_writer *w) {
  if (w->failed) return -1;
  if (!w->chunk.n) return 0;
  const char *comp = w->p.zstd_level ? "zstd" : "";
  const uint8_t *rec = w->chunk.d;
  size_t rec_n = w->chunk.n;
  if (w->p.zstd_level) {
    size_t bound = ZSTD_compressBound(w->chunk.n);
    w->zbuf.n = 0;
    if (b_reserve(&w->zbuf, bound)) return w_fail(w, "out of memory for a chunk of %zu bytes", w->chunk.n);
    size_t z = ZSTD_compress(w->zbuf.d, bound, w->chunk.d, w->chunk.n, w->p.zstd_level);
    if (ZSTD_isError(z)) return w_fail(w, "zstd: %s", ZSTD_getErrorName(z));
    rec = w->zbuf.d;
    rec_n = z;
  }
  struct buf *o = &w->out;
  o->n = 0;
  uint64_t chunk_at = w->pos;
  size_t at = b_begin(o, OP_CHUNK);
  b_u64(o, w->chunk_start);
  b_u64(o, w->chunk_end);
  b_u64(o, w->chunk.n);
  b_u32(o, crc(0, w->chunk.d, w->chunk.n));
  b_str(o, comp);
  b_u64(o, rec_n);
  b_put(o, rec, rec_n);
  b_end(o, at);
  uint64_t chunk_len = o->n;
  /* the chunk index: where each channel's message index lies */
  struct buf offs = {0};
  for (int i = 0; i < w->nch; i++) {
    struct wchannel *c = &w->ch[i];
    if (!c->index.n) continue;
    b_u16(&offs, c->id);
    b_u64(&offs, chunk_at + o->n);
    size_t mi = b_begin(o, OP_MESSAGE_INDEX);
    b_u16(o, c->id);
    b_bytes(o, c->index.d, c->index.n);
    b_end(o, mi);
    c->index.n = 0;
  }
  struct buf *ci = &w->chunk_index;
  size_t cat = b_begin(ci, OP_CHUNK_INDEX);
  b_u64(ci, w->chunk_start);
  b_u64(ci, w->chunk_end);
  b_u64(ci, chunk_at);
  b_u64(ci, chunk_len);
  b_bytes(ci, offs.d, offs.n);
  b_u64(ci, o->n - chunk_len);
  b_str(ci, comp);
  b_u64(ci, rec_n);
  b_u64(ci, w->chunk.n);
  b_end(ci, cat);
  int failed = offs.failed || o->failed || ci->failed;
  free(offs.d);
  if (failed) return w_fail(w, "out of memory");
  w->chunk.n = 0;
  w->nchunks++;
  return w_out(w, o->d, o->n, 1);
}

int vlff_mcap_writer_message(struct vlff_mcap_writer *w, uint16_t channel, uint64_t log_ns, uint64_t publish_ns,
                             const void *data, size_t len) {
  if (w->failed) return -1;
  struct wchannel *c = w_channel(w, channel);
  if (!c) return w_fail(w, "message on channel %u, which was not declared", channel);
  if (log_ns < w->last_ns) log_ns = w->last_ns;
  if (!w->chunk.n) {
    w->chunk_start = log_ns;
    w->chunk_t0 = vlff_now_ns();
  }
  b_u64(&c->index, log_ns);
  b_u64(&c->index, w->chunk.n);
  size_t at = b_begin(&w->chunk, OP_MESSAGE);
  b_u16(&w->chunk, channel);
  b_u32(&w->chunk, (uint32_t)c->count);
  b_u64(&w->chunk, log_ns);
  b_u64(&w->chunk, publish_ns);
  b_put(&w->chunk, data, len);
  b_end(&w->chunk, at);
  if (w->chunk.failed || c->index.failed) return w_fail(w, "out of memory for a message of %zu bytes", len);
  w->chunk_end = log_ns;
  if (!w->messages) w->first_ns = log_ns;
  w->last_ns = log_ns;
  w->messages++;
  c->count++;
  return w->chunk.n >= w->p.chunk_bytes ? flush_chunk(w) : 0;
}

int vlff_mcap_writer_tick(struct vlff_mcap_writer *w, uint64_t now_ns) {
  if (w->failed) return -1;
  if (w->chunk.n && now_ns - w->chunk_t0 >= (uint64_t)(w->p.chunk_s * 1e9)) return flush_chunk(w);
  return 0;
}

int vlff_mcap_writer_flush(struct vlff_mcap_writer *w) { return flush_chunk(w); }

/* A summary group: its records, and its summary offset record. */
static void group(struct vlff_mcap_writer *w, struct buf *sum, struct buf *offs, int op, const struct buf *g) {
  if (!g->n) return;
  uint64_t start = w->pos + sum->n;
  b_put(sum, g->d, g->n);
  size_t at = b_begin(offs, OP_SUMMARY_OFFSET);
  b_u8(offs, (uint64_t)op);
  b_u64(offs, start);
  b_u64(offs, g->n);
  b_end(offs, at);
}

int vlff_mcap_writer_close(struct vlff_mcap_writer *w, char *why, size_t len) {
  if (!w) return 0;
  flush_chunk(w);
  if (!w->failed) {
    struct buf b = {0};
    size_t at = b_begin(&b, OP_DATA_END);
    b_u32(&b, w->dcrc);
    b_end(&b, at);
    if (!b.failed) w_out(w, b.d, b.n, 0);
    b.n = 0;
    /* the summary: schemas, channels, statistics, chunk indexes, then their offsets */
    struct buf sum = {0}, offs = {0}, stats = {0};
    at = b_begin(&stats, OP_STATISTICS);
    b_u64(&stats, w->messages);
    b_u16(&stats, (uint64_t)w->nschemas);
    b_u32(&stats, (uint64_t)w->nch);
    b_u32(&stats, 0); /* attachments */
    b_u32(&stats, 0); /* metadata */
    b_u32(&stats, w->nchunks);
    b_u64(&stats, w->first_ns);
    b_u64(&stats, w->last_ns);
    b_u32(&stats, (uint64_t)w->nch * 10);
    for (int i = 0; i < w->nch; i++) {
      b_u16(&stats, w->ch[i].id);
      b_u64(&stats, w->ch[i].count);
    }
    b_end(&stats, at);
    uint64_t sum_start = w->pos;
    group(w, &sum, &offs, OP_SCHEMA, &w->schemas);
    group(w, &sum, &offs, OP_CHANNEL, &w->channels);
    group(w, &sum, &offs, OP_STATISTICS, &stats);
    group(w, &sum, &offs, OP_CHUNK_INDEX, &w->chunk_index);
    uint64_t offs_start = sum_start + sum.n;
    b_put(&sum, offs.d, offs.n);
    at = b_begin(&sum, OP_FOOTER);
    b_u64(&sum, sum_start);
    b_u64(&sum, offs_start);
    b_end(&sum, at);
    /* the footer's length says 20: its CRC follows, over the summary up to here */
    if (!sum.failed) sum.d[at] = 20;
    b_u32(&sum, crc(0, sum.d, sum.n));
    b_put(&sum, MAGIC, sizeof MAGIC);
    if (sum.failed || stats.failed || offs.failed || b.failed) w_fail(w, "out of memory for the summary");
    else w_out(w, sum.d, sum.n, 0);
    free(sum.d);
    free(offs.d);
    free(stats.d);
    free(b.d);
  }
  if (w->fd >= 0 && close(w->fd) != 0) w_fail(w, "close: %s", strerror(errno));
  int rc = w->failed ? -1 : 0;
  if (rc) say(why, len, "%s", w->err);
  for (int i = 0; i < w->nch; i++) free(w->ch[i].index.d);
  free(w->schemas.d);
  free(w->channels.d);
  free(w->chunk.d);
  free(w->out.d);
  free(w->zbuf.d);
  free(w->chunk_index.d);
  free(w->path);
  free(w);
  return rc;
}

uint64_t vlff_mcap_writer_bytes(const struct vlff_mcap_writer *w) { return w->pos + w->chunk.n; }
uint64_t vlff_mcap_writer_messages(const struct vlff_mcap_writer *w) { return w->messages; }
const char *vlff_mcap_writer_error(const struct vlff_mcap_writer *w) { return w->failed ? w->err : NULL; }

/* ----------------------------------------------------------------- reader */

struct rschema {
  uint16_t id;
  char *name, *encoding, *data;
  size_t len;
};

struct vlff_mcap_reader {
  const uint8_t *d;
  size_t n;
  int complete;          /* the file ends with the magic */
  size_t pos;            /* next top-level record */
  int ended, truncated;
  uint64_t trunc_at;
  struct rschema schemas[VLFF_MCAP_MAX_CHANNELS];
  int nschemas;
  struct vlff_mcap_channel ch[VLFF_MCAP_MAX_CHANNELS];
  int nch;
  /* the chunk being read: its records and where the next one starts */
  uint8_t *chunk;
  size_t chunk_cap, chunk_n, cpos;
  uint64_t chunk_at;     /* its offset in the file, for messages */
  int in_chunk;
  /* the data section's CRC over d[0, crc_at), taken as the top-level records
   * pass: the check at its end does not read the whole file again */
  uint32_t dcrc;
  size_t crc_at;
  size_t last_at;        /* the top-level record the last message came from */
};

/* A cursor over one record's fields. */
struct cur {
  const uint8_t *p;
  size_t n;
  int bad;
};

static uint64_t c_le(struct cur *c, size_t bytes) {
  if (c->bad || c->n < bytes) {
    c->bad = 1;
    return 0;
  }
  uint64_t v = 0;
  for (size_t i = 0; i < bytes; i++) v |= (uint64_t)c->p[i] << (8 * i);
  c->p += bytes;
  c->n -= bytes;
  return v;
}

/* A u32-prefixed byte string of at most max bytes. */
static const uint8_t *c_bytes(struct cur *c, size_t max, size_t *len) {
  uint64_t n = c_le(c, 4);
  if (c->bad || n > c->n || n > max) {
    c->bad = 1;
    *len = 0;
    return NULL;
  }
  const uint8_t *s = c->p;
  c->p += n;
  c->n -= n;
  *len = (size_t)n;
  return s;
}

/* A name (topic, schema name, encoding): at most VLFF_MCAP_MAX_NAME bytes, no NUL
 * (it is kept as a C string). */
static const uint8_t *c_name(struct cur *c, size_t *len) {
  const uint8_t *s = c_bytes(c, VLFF_MCAP_MAX_NAME, len);
  if (s && memchr(s, 0, *len)) c->bad = 1;
  return c->bad ? NULL : s;
}

static char *dup_n(const uint8_t *s, size_t n) {
  char *d = malloc(n + 1);
  if (!d) return NULL;
  if (n) memcpy(d, s, n);
  d[n] = 0;
  return d;
}

static void free_channel(struct vlff_mcap_channel *c) {
  free(c->topic);
  free(c->message_encoding);
  free(c->schema_name);
  free(c->schema_encoding);
  free(c->schema);
}

struct vlff_mcap_reader *vlff_mcap_reader_new(const uint8_t *d, size_t n, char *why, size_t len) {
  if (n > VLFF_MCAP_MAX_FILE) {
    say(why, len, "%zu bytes, more than the %zu a recording may have", n, VLFF_MCAP_MAX_FILE);
    return NULL;
  }
  if (n < sizeof MAGIC || memcmp(d, MAGIC, sizeof MAGIC)) {
    say(why, len, "not an MCAP file: it does not start with MCAP's magic bytes");
    return NULL;
  }
  struct vlff_mcap_reader *r = calloc(1, sizeof *r);
  if (!r) {
    say(why, len, "out of memory");
    return NULL;
  }
  r->d = d;
  r->n = n;
  r->complete = n >= 2 * sizeof MAGIC + 9 && !memcmp(d + n - sizeof MAGIC, MAGIC, sizeof MAGIC);
  r->pos = sizeof MAGIC;
  struct cur c = {d + r->pos, n - r->pos, 0};
  uint64_t op = c_le(&c, 1), rl = c_le(&c, 8);
  if (c.bad || op != OP_HEADER || rl > c.n) {
    say(why, len, "byte 8: the first record is not a whole header (opcode 0x%02llx)", (unsigned long long)op);
    free(r);
    return NULL;
  }
  return r;
}

void vlff_mcap_reader_free(struct vlff_mcap_reader *r) {
  if (!r) return;
  for (int i = 0; i < r->nschemas; i++) {
    free(r->schemas[i].name);
    free(r->schemas[i].encoding);
    free(r->schemas[i].data);
  }
  for (int i = 0; i < r->nch; i++) free_channel(&r->ch[i]);
  free(r->chunk);
  free(r);
}

void vlff_mcap_rewind(struct vlff_mcap_reader *r) {
  r->pos = sizeof MAGIC;
  r->ended = r->truncated = 0;
  r->in_chunk = 0;
  r->dcrc = 0, r->crc_at = 0, r->last_at = 0;
}

size_t vlff_mcap_consumed(const struct vlff_mcap_reader *r) { return r->last_at; }

int vlff_mcap_truncated(const struct vlff_mcap_reader *r, uint64_t *at) {
  if (r->truncated && at) *at = r->trunc_at;
  return r->truncated;
}

int vlff_mcap_channel_count(const struct vlff_mcap_reader *r) { return r->nch; }
const struct vlff_mcap_channel *vlff_mcap_channel_at(const struct vlff_mcap_reader *r, int i) {
  return i >= 0 && i < r->nch ? &r->ch[i] : NULL;
}

static const struct vlff_mcap_channel *find_channel(const struct vlff_mcap_reader *r, uint16_t id) {
  for (int i = 0; i < r->nch; i++)
    if (r->ch[i].id == id) return &r->ch[i];
  return NULL;
}

static int bad(char *why, size_t len, uint64_t at, const char *what) {
  say(why, len, "byte %llu: %s", (unsigned long long)at, what);
  return -1;
}

static int read_schema(struct vlff_mcap_reader *r, struct cur *c, uint64_t at, char *why, size_t len) {
  uint16_t id = (uint16_t)c_le(c, 2);
  size_t nn, ne, nd;
  const uint8_t *name = c_name(c, &nn), *enc = c_name(c, &ne);
  const uint8_t *data = c_bytes(c, VLFF_MCAP_MAX_SCHEMA, &nd);
  if (c->bad) return bad(why, len, at, "a schema record whose fields do not fit it (or a name too long or holding a NUL, or a schema too long)");
  if (id == 0) return bad(why, len, at, "a schema with id 0 (reserved for none)");
  for (int i = 0; i < r->nschemas; i++)
    if (r->schemas[i].id == id) {
      struct rschema *s = &r->schemas[i];
      if (strlen(s->name) != nn || memcmp(s->name, name, nn) || s->len != nd || memcmp(s->data, data, nd))
        return bad(why, len, at, "a schema id defined twice with different content");
      return 0;
    }
  if (r->nschemas == VLFF_MCAP_MAX_CHANNELS) return bad(why, len, at, "more schemas than vlff-view plays (64)");
  struct rschema *s = &r->schemas[r->nschemas];
  s->id = id;
  s->name = dup_n(name, nn);
  s->encoding = dup_n(enc, ne);
  s->data = dup_n(data, nd);
  s->len = nd;
  r->nschemas++;
  if (!s->name || !s->encoding || !s->data) return bad(why, len, at, "out of memory");
  return 0;
}

static int read_channel(struct vlff_mcap_reader *r, struct cur *c, uint64_t at, char *why, size_t len) {
  uint16_t id = (uint16_t)c_le(c, 2), sid = (uint16_t)c_le(c, 2);
  size_t nt, ne, nm;
  const uint8_t *topic = c_name(c, &nt), *enc = c_name(c, &ne);
  c_bytes(c, c->n, &nm); /* metadata: not used */
  if (c->bad) return bad(why, len, at, "a channel record whose fields do not fit it (or a topic too long or holding a NUL)");
  const struct vlff_mcap_channel *old = find_channel(r, id);
  if (old) {
    if (strlen(old->topic) != nt || memcmp(old->topic, topic, nt))
      return bad(why, len, at, "a channel id defined twice with different topics");
    return 0;
  }
  const struct rschema *s = NULL;
  for (int i = 0; i < r->nschemas; i++)
    if (r->schemas[i].id == sid) s = &r->schemas[i];
  if (sid && !s) return bad(why, len, at, "a channel whose schema was not defined before it");
  if (r->nch == VLFF_MCAP_MAX_CHANNELS) return bad(why, len, at, "more channels than vlff-view plays (64)");
  struct vlff_mcap_channel *ch = &r->ch[r->nch];
  *ch = (struct vlff_mcap_channel){.id = id};
  ch->topic = dup_n(topic, nt);
  ch->message_encoding = dup_n(enc, ne);
  ch->schema_name = dup_n(s ? (const uint8_t *)s->name : NULL, s ? strlen(s->name) : 0);
  ch->schema_encoding = dup_n(s ? (const uint8_t *)s->encoding : NULL, s ? strlen(s->encoding) : 0);
  ch->schema = dup_n(s ? (const uint8_t *)s->data : NULL, s ? s->len : 0);
  ch->schema_len = s ? s->len : 0;
  r->nch++;
  if (!ch->topic || !ch->message_encoding || !ch->schema_name || !ch->schema_encoding || !ch->schema)
    return bad(why, len, at, "out of memory");
  return 0;
}

static int read_message(struct vlff_mcap_reader *r, struct cur *c, uint64_t at, struct vlff_mcap_message *m, char *why,
                        size_t len) {
  m->channel = (uint16_t)c_le(c, 2);
  m->sequence = (uint32_t)c_le(c, 4);
  m->log_ns = c_le(c, 8);
  m->publish_ns = c_le(c, 8);
  if (c->bad) return bad(why, len, at, "a message record shorter than its fields");
  if (!find_channel(r, m->channel)) return bad(why, len, at, "a message on a channel not defined before it");
  m->data = c->p;
  m->len = c->n;
  return 1;
}

/* Opens the chunk record c (at file offset at) for reading its records. */
static int open_chunk(struct vlff_mcap_reader *r, struct cur *c, uint64_t at, char *why, size_t len) {
  c_le(c, 8);
  c_le(c, 8);
  uint64_t usize = c_le(c, 8);
  uint32_t ucrc = (uint32_t)c_le(c, 4);
  size_t nc, nrec;
  const uint8_t *comp = c_bytes(c, 64, &nc);
  uint64_t rlen = c_le(c, 8);
  if (c->bad || rlen != c->n) return bad(why, len, at, "a chunk whose records' length is not what the record holds");
  const uint8_t *rec = c->p;
  nrec = c->n;
  if (usize > VLFF_MCAP_MAX_CHUNK) {
    say(why, len, "byte %llu: a chunk of %llu bytes uncompressed, more than the %zu vlff-view reads",
        (unsigned long long)at, (unsigned long long)usize, VLFF_MCAP_MAX_CHUNK);
    return -1;
  }
  if (nc == 0 && nrec != usize) return bad(why, len, at, "an uncompressed chunk whose size is not its records'");
  if (nc == 4 && !memcmp(comp, "zstd", 4)) {
    /* a frame that states its size (as vlff-view's do) must state the chunk's, before
     * that much memory is taken for it */
    unsigned long long fs = ZSTD_getFrameContentSize(rec, nrec);
    if (fs == ZSTD_CONTENTSIZE_ERROR || (fs != ZSTD_CONTENTSIZE_UNKNOWN && fs != usize))
      return bad(why, len, at, "a zstd chunk whose frame is not the size the chunk declares");
  }
  if ((size_t)usize > r->chunk_cap) {
    uint8_t *b = realloc(r->chunk, usize ? (size_t)usize : 1);
    if (!b) return bad(why, len, at, "out of memory for a chunk");
    r->chunk = b;
    r->chunk_cap = (size_t)usize;
  }
  if (nc == 0) {
    if (nrec) memcpy(r->chunk, rec, nrec);
  } else if (nc == 4 && !memcmp(comp, "zstd", 4)) {
    size_t z = ZSTD_decompress(r->chunk, (size_t)usize, rec, nrec);
    if (ZSTD_isError(z)) {
      say(why, len, "byte %llu: a zstd chunk that does not decompress: %s", (unsigned long long)at,
          ZSTD_getErrorName(z));
      return -1;
    }
    if (z != usize) return bad(why, len, at, "a zstd chunk whose size is not the one it declares");
  } else {
    say(why, len, "byte %llu: a chunk compressed with '%s' (vlff-view reads zstd and uncompressed chunks)",
        (unsigned long long)at, VLFF_QN(comp, nc));
    return -1;
  }
  if (ucrc && crc(0, r->chunk, (size_t)usize) != ucrc) return bad(why, len, at, "a chunk whose CRC does not match");
  r->chunk_n = (size_t)usize;
  r->cpos = 0;
  r->chunk_at = at;
  r->in_chunk = 1;
  return 0;
}

/* The footer, after Data End: its summary CRC when it has one. */
static int check_footer(struct vlff_mcap_reader *r, char *why, size_t len) {
  if (!r->complete) {
    r->truncated = 1;
    r->trunc_at = r->n;
    return 0;
  }
  size_t fat = r->n - sizeof MAGIC - 29;
  struct cur c = {r->d + fat, 29, 0};
  uint64_t op = c_le(&c, 1), fl = c_le(&c, 8), sstart = c_le(&c, 8);
  c_le(&c, 8);
  uint32_t scrc = (uint32_t)c_le(&c, 4);
  if (op != OP_FOOTER || fl != 20) return bad(why, len, fat, "no footer before the closing magic");
  if (sstart > fat) return bad(why, len, fat, "a footer whose summary starts after it");
  if (scrc && sstart && crc(0, r->d + sstart, fat + 25 - (size_t)sstart) != scrc)
    return bad(why, len, fat, "a summary whose CRC does not match");
  return 0;
}

int vlff_mcap_next(struct vlff_mcap_reader *r, struct vlff_mcap_message *m, char *why, size_t len) {
  for (;;) {
    if (r->ended) return 0;
    if (r->in_chunk) {
      if (r->cpos == r->chunk_n) {
        r->in_chunk = 0;
        continue;
      }
      uint64_t at = r->chunk_at; /* offsets inside a chunk are named by the chunk's */
      struct cur c = {r->chunk + r->cpos, r->chunk_n - r->cpos, 0};
      uint64_t op = c_le(&c, 1), rl = c_le(&c, 8);
      if (c.bad || rl > c.n) return bad(why, len, at, "a chunk whose last record is cut short");
      r->cpos += 9 + (size_t)rl;
      struct cur f = {c.p, (size_t)rl, 0};
      switch (op) {
      case OP_SCHEMA:
        if (read_schema(r, &f, at, why, len)) return -1;
        continue;
      case OP_CHANNEL:
        if (read_channel(r, &f, at, why, len)) return -1;
        continue;
      case OP_MESSAGE:
        return read_message(r, &f, at, m, why, len);
      default:
        say(why, len, "byte %llu: a chunk holding a record of opcode 0x%02llx (only schemas, channels and messages "
            "belong there)", (unsigned long long)at, (unsigned long long)op);
        return -1;
      }
    }
    uint64_t at = r->pos;
    r->dcrc = crc(r->dcrc, r->d + r->crc_at, (size_t)at - r->crc_at);
    r->crc_at = (size_t)at;
    r->last_at = (size_t)at;
    if (r->pos == r->n || r->n - r->pos < 9) {
      r->ended = r->truncated = 1;
      r->trunc_at = r->pos;
      return 0;
    }
    struct cur c = {r->d + r->pos, r->n - r->pos, 0};
    uint64_t op = c_le(&c, 1), rl = c_le(&c, 8);
    if (rl > c.n) {
      if (r->complete) {
        say(why, len, "byte %llu: a record of opcode 0x%02llx claims %llu bytes, past the end of the file",
            (unsigned long long)at, (unsigned long long)op, (unsigned long long)rl);
        return -1;
      }
      r->ended = r->truncated = 1; /* cut short while this record was written */
      r->trunc_at = r->pos;
      return 0;
    }
    r->pos += 9 + (size_t)rl;
    struct cur f = {c.p, (size_t)rl, 0};
    switch (op) {
    case OP_HEADER:
      if (at != sizeof MAGIC) return bad(why, len, at, "a second header");
      continue;
    case OP_SCHEMA:
      if (read_schema(r, &f, at, why, len)) return -1;
      continue;
    case OP_CHANNEL:
      if (read_channel(r, &f, at, why, len)) return -1;
      continue;
    case OP_MESSAGE:
      return read_message(r, &f, at, m, why, len);
    case OP_CHUNK:
      if (open_chunk(r, &f, at, why, len)) return -1;
      continue;
    case OP_DATA_END: {
      uint32_t dcrc = (uint32_t)c_le(&f, 4);
      if (f.bad) return bad(why, len, at, "a data end record shorter than its CRC");
      if (dcrc && r->dcrc != dcrc) return bad(why, len, at, "a data section whose CRC does not match");
      r->ended = 1;
      return check_footer(r, why, len);
    }
    case OP_FOOTER:
      r->ended = 1;
      return 0;
    default: /* indexes, attachments, metadata, statistics and opcodes of later versions */
      continue;
    }
  }
}
