/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * mcap.h - MCAP files (the recording format of Foxglove and ROS 2): a writer for
 * vlff-view --record and vlff-record, and a reader for vlff-view --play and
 * vlff-replay (through inputs.h, which also validates every message it reads).
 * One implementation, the library vlff_mcap, which needs neither libwebsockets
 * nor OpenCV, so that vlff-record and vlff-replay link it without the viewer.
 *
 * The writer makes a chunked, indexed file: the header, then every schema and
 * channel (before any message, so that a file cut short still names them), then
 * chunks of messages (zstd-compressed, each with its CRC) each followed by its
 * message indexes, then Data End (the data section's CRC), the summary (schemas,
 * channels, statistics, chunk indexes), the summary offsets, the footer and the
 * closing magic. A chunk is written whole, with one write(), when it reaches
 * chunk_bytes or is chunk_s old (vlff_mcap_writer_tick): a recorder that is killed
 * leaves a file whose every whole chunk a stream reader reads, and loses the chunk
 * being filled, the indexes and the summary.
 *
 * The reader walks a file held in memory record by record, every length checked
 * against what is left before it is used: a truncated file ends early (with
 * vlff_mcap_truncated saying where; vlff-view plays what is there, vlff-replay
 * refuses it), anything malformed is an error naming the record and the byte
 * offset. It reads untrusted files (recordings copied from robots): the checks
 * are the bounds below, and tests/fuzz/fuzz_mcap.c holds it to them. It reads uncompressed and zstd chunks, checks the
 * CRCs a file carries (chunk, data section, summary), and ignores the summary
 * (it plays messages in file order).
 *
 * CONTRACT
 * Errors: functions returning a pointer return NULL, functions returning int
 *   return -1, each with one line naming what failed in why[len] (when why is not
 *   NULL); the writer also remembers its first error (vlff_mcap_writer_error) and
 *   refuses further writes.
 * Bounds: a file read is at most VLFF_MCAP_MAX_FILE bytes, a chunk at most
 *   VLFF_MCAP_MAX_CHUNK bytes uncompressed, at most VLFF_MCAP_MAX_CHANNELS channels
 *   and as many schemas, names at most VLFF_MCAP_MAX_NAME bytes.
 * Ownership: the reader borrows the file's bytes (the caller keeps them alive and
 *   unchanged until vlff_mcap_reader_free); a message's data points into those
 *   bytes or into the reader's current chunk, valid until the next call.
 * Threads: an object is used by one thread at a time.
 */
#ifndef VLFF_VIEW_MCAP_H
#define VLFF_VIEW_MCAP_H

#include <stddef.h>
#include <stdint.h>

#define VLFF_MCAP_MAX_FILE ((size_t)4 << 30)
#define VLFF_MCAP_MAX_CHUNK ((size_t)256 << 20)
#define VLFF_MCAP_MAX_CHANNELS 64
#define VLFF_MCAP_MAX_NAME 1024
#define VLFF_MCAP_MAX_SCHEMA ((size_t)1 << 20)

/* --------------------------------------------------------------- writer */

struct vlff_mcap_writer_params {
  const char *library;  /* the header's library field, e.g. "vlff-view 0.1.0" */
  size_t chunk_bytes;   /* a chunk is closed once it holds this much (0 = 1 MiB) */
  double chunk_s;       /* or once its first message is this old (0 = 1 s) */
  int zstd_level;       /* 0 = chunks uncompressed; 1..19 */
};

struct vlff_mcap_writer;
/* Creates path (replacing a regular file there; refusing a FIFO, device or
 * directory) and writes the magic and the header. */
struct vlff_mcap_writer *vlff_mcap_writer_open(const char *path, const struct vlff_mcap_writer_params *p, char *why,
                                               size_t len);
/* Declares channel id (0..65535, each once) before the first message; schemas with
 * the same name, encoding and text are written once. */
int vlff_mcap_writer_channel(struct vlff_mcap_writer *w, uint16_t id, const char *topic, const char *message_encoding,
                             const char *schema_name, const char *schema_encoding, const void *schema,
                             size_t schema_len);
/* A message on a declared channel; log_ns orders the file (a time before the
 * previous message's is written as that time). */
int vlff_mcap_writer_message(struct vlff_mcap_writer *w, uint16_t channel, uint64_t log_ns, uint64_t publish_ns,
                             const void *data, size_t len);
/* Writes the chunk being filled when it is chunk_s old at now_ns (CLOCK_MONOTONIC). */
int vlff_mcap_writer_tick(struct vlff_mcap_writer *w, uint64_t now_ns);
/* Writes the chunk being filled now, so that the next message opens a chunk (a
 * reader seeking by the chunk indexes starts there); nothing when it is empty. */
int vlff_mcap_writer_flush(struct vlff_mcap_writer *w);
/* Writes the last chunk, the indexes, the summary and the footer, and closes the
 * file; frees w in every case. 0, or -1 (the file then holds every whole chunk). */
int vlff_mcap_writer_close(struct vlff_mcap_writer *w, char *why, size_t len);
/* Bytes written so far, messages written so far. */
uint64_t vlff_mcap_writer_bytes(const struct vlff_mcap_writer *w);
uint64_t vlff_mcap_writer_messages(const struct vlff_mcap_writer *w);
/* The first error, or NULL while there was none. */
const char *vlff_mcap_writer_error(const struct vlff_mcap_writer *w);

/* --------------------------------------------------------------- reader */

struct vlff_mcap_channel {
  uint16_t id;
  char *topic, *message_encoding, *schema_name, *schema_encoding;
  char *schema;      /* NUL-terminated copy */
  size_t schema_len;
};

struct vlff_mcap_message {
  uint16_t channel;
  uint32_t sequence;
  uint64_t log_ns, publish_ns;
  const uint8_t *data;
  size_t len;
};

struct vlff_mcap_reader;
/* A reader of the file bytes d[n]: checks the leading magic and the header. */
struct vlff_mcap_reader *vlff_mcap_reader_new(const uint8_t *d, size_t n, char *why, size_t len);
void vlff_mcap_reader_free(struct vlff_mcap_reader *r);
/* The next message in file order: 1 with *m set, 0 at the end (of the data
 * section, or where the file is cut short), -1 on a malformed file. */
int vlff_mcap_next(struct vlff_mcap_reader *r, struct vlff_mcap_message *m, char *why, size_t len);
/* Back to the first message. */
void vlff_mcap_rewind(struct vlff_mcap_reader *r);
/* The file offset before which the reader needs no byte again until a
 * rewind (the start of the record the last message came from): a caller
 * reading a mapped file may give those pages back (vlff_unread_mapped). */
size_t vlff_mcap_consumed(const struct vlff_mcap_reader *r);
/* After vlff_mcap_next returned 0: 1 when the file ended without its footer (a
 * recorder that was killed), with the offset of the first byte not read in *at. */
int vlff_mcap_truncated(const struct vlff_mcap_reader *r, uint64_t *at);
/* The channels seen so far, in the order they were defined. */
int vlff_mcap_channel_count(const struct vlff_mcap_reader *r);
const struct vlff_mcap_channel *vlff_mcap_channel_at(const struct vlff_mcap_reader *r, int i);

#endif /* VLFF_VIEW_MCAP_H */
