/*
 * The viewer's MCAP writer and reader (mcap.h), in-process: a recording read back
 * message by message (compressed and not), every prefix of it (what a killed
 * recorder leaves) read up to its last whole chunk without an error, and corrupt
 * files (flipped bytes in a chunk, the data section or the summary; a chunk
 * claiming more than the bound; a record running past the end; no magic) refused with the
 * byte offset and the reason; a recording whose wall clock stepped forward by
 * years between two messages played without waiting out the step (--play); a
 * recording of 50 MiB played (--play) with the file's resident pages bounded.
 * @mcap/core checks the same files from the outside
 * (test_view_mcap_js).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "files.h"
#include "mcap.h"
#include "unit.h"
#include "view.h"

#define N_MSG 600

static char dir[64], path[128];

static int setup(void **state) {
  (void)state;
  snprintf(dir, sizeof dir, "/tmp/vlff-test-mcap-XXXXXX");
  if (!mkdtemp(dir)) return -1;
  snprintf(path, sizeof path, "%s/rec.mcap", dir);
  return 0;
}

static int teardown(void **state) {
  (void)state;
  unlink(path);
  rmdir(dir);
  return 0;
}

/* Message i: its channel (1..3), time and text. */
static uint16_t ch_of(int i) { return (uint16_t)(1 + i % 3); }
static uint64_t t_of(int i) { return 1700000000000000000ull + (uint64_t)i * 1000000u; }
static int text_of(int i, char *out, size_t cap) {
  return snprintf(out, cap, "{\"i\":%d,\"pad\":\"%0*d\"}", i, 1 + (i * 7) % 300, i);
}

static const char *SCHEMA_A = "{\"type\":\"object\",\"title\":\"a\"}";
static const char *SCHEMA_B = "{\"type\":\"object\",\"title\":\"b\"}";

/* Writes the test recording; chunks of chunk_bytes. */
static void write_file(int level, size_t chunk_bytes) {
  char why[256];
  struct vlff_mcap_writer_params p = {.library = "test", .chunk_bytes = chunk_bytes, .zstd_level = level};
  struct vlff_mcap_writer *w = vlff_mcap_writer_open(path, &p, why, sizeof why);
  assert_non_null(w);
  /* channels 1 and 3 share a schema */
  assert_int_equal(vlff_mcap_writer_channel(w, 1, "/a", "json", "t.A", "jsonschema", SCHEMA_A, strlen(SCHEMA_A)), 0);
  assert_int_equal(vlff_mcap_writer_channel(w, 2, "/b", "json", "t.B", "jsonschema", SCHEMA_B, strlen(SCHEMA_B)), 0);
  assert_int_equal(vlff_mcap_writer_channel(w, 3, "/c", "json", "t.A", "jsonschema", SCHEMA_A, strlen(SCHEMA_A)), 0);
  assert_int_equal(vlff_mcap_writer_channel(w, 2, "/b2", "json", "t.B", "jsonschema", "{}", 2), -1);
  assert_non_null(strstr(vlff_mcap_writer_error(w), "declared twice"));
  vlff_mcap_writer_close(w, NULL, 0);

  w = vlff_mcap_writer_open(path, &p, why, sizeof why);
  assert_non_null(w);
  assert_int_equal(vlff_mcap_writer_channel(w, 1, "/a", "json", "t.A", "jsonschema", SCHEMA_A, strlen(SCHEMA_A)), 0);
  assert_int_equal(vlff_mcap_writer_channel(w, 2, "/b", "json", "t.B", "jsonschema", SCHEMA_B, strlen(SCHEMA_B)), 0);
  assert_int_equal(vlff_mcap_writer_channel(w, 3, "/c", "json", "t.A", "jsonschema", SCHEMA_A, strlen(SCHEMA_A)), 0);
  char text[512];
  for (int i = 0; i < N_MSG; i++) {
    int n = text_of(i, text, sizeof text);
    assert_int_equal(vlff_mcap_writer_message(w, ch_of(i), t_of(i), t_of(i) - 5, text, (size_t)n), 0);
  }
  assert_int_equal(vlff_mcap_writer_messages(w), N_MSG);
  assert_int_equal(vlff_mcap_writer_close(w, why, sizeof why), 0);
}

static void load(uint8_t **d, size_t *n) {
  char why[256];
  assert_int_equal(vlff_read_file(path, 1u << 30, d, n, why, sizeof why), 0);
}

/* Reads d[n]: the messages read (each checked against what was written), -1 on an
 * error (its reason in why). */
static int read_all(const uint8_t *d, size_t n, char *why, size_t wl, int *truncated) {
  struct vlff_mcap_reader *r = vlff_mcap_reader_new(d, n, why, wl);
  if (!r) return -1;
  struct vlff_mcap_message m;
  int count = 0, rc;
  char text[512];
  while ((rc = vlff_mcap_next(r, &m, why, wl)) == 1) {
    int len = text_of(count, text, sizeof text);
    assert_int_equal(m.channel, ch_of(count));
    assert_int_equal(m.sequence, (uint32_t)(count / 3));
    assert_true(m.log_ns == t_of(count) && m.publish_ns == t_of(count) - 5);
    assert_int_equal(m.len, (size_t)len);
    assert_memory_equal(m.data, text, (size_t)len);
    count++;
  }
  if (truncated) *truncated = vlff_mcap_truncated(r, NULL);
  if (rc == 0 && count) {
    assert_int_equal(vlff_mcap_channel_count(r), 3);
    const struct vlff_mcap_channel *c = vlff_mcap_channel_at(r, 2);
    assert_string_equal(c->topic, "/c");
    assert_string_equal(c->schema_name, "t.A");
    assert_string_equal(c->schema_encoding, "jsonschema");
    assert_string_equal(c->message_encoding, "json");
    assert_string_equal(c->schema, SCHEMA_A);
  }
  vlff_mcap_reader_free(r);
  return rc < 0 ? -1 : count;
}

static void test_round_trip(void **state) {
  (void)state;
  for (int level = 0; level <= 3; level += 3) {
    write_file(level, 4096);
    uint8_t *d;
    size_t n;
    load(&d, &n);
    char why[256] = "";
    int trunc = -1;
    assert_int_equal(read_all(d, n, why, sizeof why, &trunc), N_MSG);
    assert_int_equal(trunc, 0);
    /* read again after a rewind: the same messages */
    struct vlff_mcap_reader *r = vlff_mcap_reader_new(d, n, why, sizeof why);
    struct vlff_mcap_message m;
    int k = 0;
    while (vlff_mcap_next(r, &m, why, sizeof why) == 1) k++;
    vlff_mcap_rewind(r);
    while (vlff_mcap_next(r, &m, why, sizeof why) == 1) k++;
    assert_int_equal(k, 2 * N_MSG);
    vlff_mcap_reader_free(r);
    free(d);
  }
}

/* Every prefix of a recording reads without an error; the messages read are a
 * prefix of those written, and a file cut in its summary still holds them all. */
static void test_truncated(void **state) {
  (void)state;
  write_file(3, 2048);
  uint8_t *d;
  size_t n;
  load(&d, &n);
  int last = 0, chunks_seen = 0;
  /* from the end of the header on (a file without a whole header is refused) */
  size_t header_end = 8 + 9 + (size_t)d[9];
  char why0[256];
  assert_int_equal(read_all(d, header_end - 1, why0, sizeof why0, NULL), -1);
  assert_non_null(strstr(why0, "not a whole header"));
  for (size_t cut = header_end; cut < n; cut += 1 + cut % 61) {
    char why[256] = "";
    int trunc = 0;
    int k = read_all(d, cut, why, sizeof why, &trunc);
    if (k < 0) fail_msg("a file cut at %zu of %zu bytes: %s", cut, n, why);
    assert_true(k >= last);
    if (k > last) chunks_seen++;
    last = k;
    assert_int_equal(trunc, 1);
  }
  assert_true(chunks_seen > 5);
  char why[256];
  int trunc = 0;
  assert_int_equal(read_all(d, n - 1, why, sizeof why, &trunc), N_MSG); /* only the magic's last byte lost */
  assert_int_equal(trunc, 1);
  free(d);
}

static void expect_error(uint8_t *d, size_t n, const char *what) {
  char why[256] = "";
  int k = read_all(d, n, why, sizeof why, NULL);
  if (k != -1 || !strstr(why, what)) fail_msg("expected an error with '%s', got %d messages and '%s'", what, k, why);
  assert_non_null(strstr(why, "byte "));
}

/* The first offset of a record with opcode op at the top level. */
static size_t find_record(const uint8_t *d, size_t n, int op) {
  size_t pos = 8;
  while (pos + 9 <= n) {
    uint64_t len = 0;
    for (int i = 0; i < 8; i++) len |= (uint64_t)d[pos + 1 + i] << (8 * i);
    if (d[pos] == op) return pos;
    pos += 9 + (size_t)len;
  }
  fail_msg("no record 0x%02x", op);
  return 0;
}

static void test_corrupt(void **state) {
  (void)state;
  write_file(3, 2048);
  uint8_t *d;
  size_t n;
  load(&d, &n);
  uint8_t *c = malloc(n);
  char why[256] = "";

  memcpy(c, d, n);
  c[0] = 'X';
  assert_null(vlff_mcap_reader_new(c, n, why, sizeof why));
  assert_non_null(strstr(why, "magic"));

  /* a byte in the middle of the first chunk's compressed records */
  size_t chunk = find_record(d, n, 0x06);
  memcpy(c, d, n);
  c[chunk + 80] ^= 0x40;
  expect_error(c, n, "chunk");

  /* the same chunk uncompressed: its CRC finds the flip */
  write_file(0, 2048);
  free(d);
  load(&d, &n);
  free(c);
  c = malloc(n);
  chunk = find_record(d, n, 0x06);
  memcpy(c, d, n);
  c[chunk + 120] ^= 0x01;
  expect_error(c, n, "CRC does not match");

  /* a chunk claiming 1 GiB uncompressed */
  memcpy(c, d, n);
  c[chunk + 9 + 16 + 3] = 0x40;
  expect_error(c, n, "more than");

  /* a byte of the header's library name: the Data End's CRC of the data section */
  memcpy(c, d, n);
  c[8 + 9 + 4 + 4] ^= 0x20;
  expect_error(c, n, "data section whose CRC does not match");

  /* a byte of the summary: its CRC in the footer */
  memcpy(c, d, n);
  c[n - 8 - 29 - 5] ^= 0x01;
  expect_error(c, n, "summary whose CRC does not match");

  /* a record whose length runs past a complete file's end */
  memcpy(c, d, n);
  c[chunk + 8] = 0x7f;
  expect_error(c, n, "past the end of the file");
  free(c);
  free(d);
}

/* The writer refuses to write anywhere but into a regular file. */
static void test_refuses(void **state) {
  (void)state;
  char why[256] = "";
  struct vlff_mcap_writer_params p = {.zstd_level = 3};
  assert_null(vlff_mcap_writer_open(dir, &p, why, sizeof why));
  assert_non_null(strstr(why, "not a regular file"));
  char fifo[160];
  snprintf(fifo, sizeof fifo, "%s/fifo", dir);
  assert_int_equal(mkfifo(fifo, 0600), 0);
  assert_null(vlff_mcap_writer_open(fifo, &p, why, sizeof why));
  assert_non_null(strstr(why, "not a regular file"));
  unlink(fifo);
}

/* Messages vlff_view_play_poll gives at now_ns (each unreferenced). */
static int poll_at(struct vlff_view_play *p, uint64_t now_ns) {
  struct vlff_view_msg *out[8];
  int n = vlff_view_play_poll(p, 1, now_ns, out, 8);
  for (int i = 0; i < n; i++) vlff_view_msg_unref(out[i]);
  return n;
}

/* The recorder stamps log times with the wall clock: one set by NTP while it
 * records (a robot's clock that started at 1970) jumps by decades. Playback
 * keeps the recorded spacing on each side of the jump and does not wait it out. */
static void test_play_clock_step(void **state) {
  (void)state;
  char why[256];
  struct vlff_mcap_writer_params wp = {.library = "test", .zstd_level = 3};
  struct vlff_mcap_writer *w = vlff_mcap_writer_open(path, &wp, why, sizeof why);
  assert_non_null(w);
  assert_int_equal(vlff_mcap_writer_channel(w, 1, "/a", "json", "t.A", "jsonschema", SCHEMA_A, strlen(SCHEMA_A)), 0);
  const uint64_t s = 1000000000ull, step = 56ull * 365 * 86400 * s;
  const uint64_t at[4] = {10 * s, 11 * s, 11 * s + step, 12 * s + step};
  for (int i = 0; i < 4; i++) assert_int_equal(vlff_mcap_writer_message(w, 1, at[i], at[i], "{}", 2), 0);
  assert_int_equal(vlff_mcap_writer_close(w, why, sizeof why), 0);
  struct vlff_view_play *p = vlff_view_play_open(path);
  assert_non_null(p);
  const uint64_t t0 = 5000 * s;
  assert_int_equal(poll_at(p, t0), 1);
  assert_int_equal(poll_at(p, t0 + s / 2), 0);
  assert_int_equal(poll_at(p, t0 + s), 2); /* the one before the step and the one after it */
  assert_int_equal(poll_at(p, t0 + s + s / 2), 0);
  assert_int_equal(poll_at(p, t0 + 2 * s), 1); /* a second after the step's, as recorded */
  assert_true(vlff_view_play_done(p));
  assert_int_equal(vlff_view_play_sent(p), 4);
  vlff_view_play_free(p);
}

/* This process's resident pages of mapped files, MiB (RssFile). */
static double rss_file_mb(void) { return vlff_test_status_kb("RssFile") / 1024; }

/* --play maps its recording and gives back what it walked: checking and playing
 * a 50 MiB recording leaves at most a few MiB of it resident at any time (the
 * whole of it without the give-back), so a recording larger than memory plays. */
static void test_play_long_recording_memory(void **state) {
  (void)state;
  char why[256];
  struct vlff_mcap_writer_params wp = {.library = "test", .chunk_bytes = 1u << 20};
  struct vlff_mcap_writer *w = vlff_mcap_writer_open(path, &wp, why, sizeof why);
  assert_non_null(w);
  assert_int_equal(vlff_mcap_writer_channel(w, 1, "/a", "json", "t.A", "jsonschema", SCHEMA_A, strlen(SCHEMA_A)), 0);
  enum { N = 200, LEN = 256 << 10 };
  uint8_t *payload = malloc(LEN);
  assert_non_null(payload);
  uint32_t x = 1;
  for (int i = 0; i < N; i++) {
    for (size_t k = 0; k < LEN; k++) x = x * 1664525u + 1013904223u, payload[k] = (uint8_t)(x >> 24);
    assert_int_equal(vlff_mcap_writer_message(w, 1, t_of(i), t_of(i), payload, LEN), 0);
  }
  free(payload);
  assert_int_equal(vlff_mcap_writer_close(w, why, sizeof why), 0);
  struct stat st;
  assert_int_equal(stat(path, &st), 0);
  assert_true(st.st_size > 50 << 20);
  double before = rss_file_mb();
  assert_true(before >= 0);
  struct vlff_view_play *p = vlff_view_play_open(path);
  assert_non_null(p);
  double peak = rss_file_mb();
  uint64_t now = 0;
  while (!vlff_view_play_done(p)) {
    now += 1000000000ull;
    poll_at(p, now);
    double r = rss_file_mb();
    if (r > peak) peak = r;
  }
  assert_int_equal(vlff_view_play_sent(p), N);
  vlff_view_play_free(p);
  printf("--play of a %.1f MiB recording: the file's resident pages peaked %.1f MiB above the start\n",
         st.st_size / 1048576.0, peak - before);
  assert_true(peak - before < 16);
}

VLFF_UNIT_MAIN(setup, teardown, cmocka_unit_test(test_round_trip), cmocka_unit_test(test_truncated),
               cmocka_unit_test(test_corrupt), cmocka_unit_test(test_refuses), cmocka_unit_test(test_play_clock_step),
               cmocka_unit_test(test_play_long_recording_memory))
