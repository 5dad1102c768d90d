/* Embeddings file: round trip, lookups, and every validation rule. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cmocka.h>

#include "embeddings.h"
#include "unit.h"

static void test_round_trip(void **state) {
  char path[128], err[256];
  snprintf(path, sizeof path, "/tmp/vlff-test-emb-%d.txt", (int)getpid());
  const char *prompts[] = {"chair", "shower curtain", "caf\xc3\xa9"};
  float v[3 * 8];
  for (int i = 0; i < 24; i++) v[i] = (float)(i - 11) / 7.0f + 1e-7f * (float)i;
  assert_int_equal(vlff_embeddings_save(path, 8, 3, prompts, v, err, sizeof err), 0);
  struct vlff_embeddings *e = vlff_embeddings_load(path, 8, err, sizeof err);
  if (!e) fail_msg("%s", err);
  assert_int_equal(vlff_embeddings_dim(e), 8);
  assert_int_equal(vlff_embeddings_count(e), 3);
  assert_string_equal(vlff_embeddings_prompt(e, 1), "shower curtain");
  assert_memory_equal(vlff_embeddings_vector(e, 0), v, sizeof v); /* %.9g round-trips exactly */
  assert_memory_equal(vlff_embeddings_lookup(e, "caf\xc3\xa9"), v + 16, 8 * sizeof(float));
  assert_null(vlff_embeddings_lookup(e, "Chair"));
  vlff_embeddings_free(e);
  /* The field's D differs: refused with both numbers. */
  assert_null(vlff_embeddings_load(path, 512, err, sizeof err));
  assert_non_null(strstr(err, "dim 8, but field.feature_dim is 512"));
  unlink(path);
  assert_null(vlff_embeddings_load(path, 8, err, sizeof err));
  assert_non_null(strstr(err, "cannot open"));
  /* A FIFO at the file's name: refused at once, not waited on. */
  assert_int_equal(mkfifo(path, 0600), 0);
  assert_null(vlff_embeddings_load(path, 8, err, sizeof err));
  assert_non_null(strstr(err, "is a FIFO, expected a regular file"));
  unlink(path);
  /* Saving refuses what loading would refuse. */
  v[3] = 1.0f / 0.0f;
  assert_int_equal(vlff_embeddings_save(path, 8, 3, prompts, v, err, sizeof err), -1);
  const char *bad[] = {"tab\there", "b", "c"};
  v[3] = 0;
  assert_int_equal(vlff_embeddings_save(path, 8, 3, bad, v, err, sizeof err), -1);
  for (int i = 8; i < 16; i++) v[i] = 1e30f; /* "shower curtain": finite, length 2.8e30 */
  assert_int_equal(vlff_embeddings_save(path, 8, 3, prompts, v, err, sizeof err), -1);
  if (!strstr(err, "the vector of 'shower curtain' has length 2.83e+30")) fail_msg("%s", err);
  assert_int_equal(access(path, F_OK), -1);
}

static void refused(const char *text, const char *what) {
  char err[256] = "";
  struct vlff_embeddings *e = vlff_embeddings_parse(text, strlen(text), "t.emb", 0, err, sizeof err);
  if (e) fail_msg("accepted: %s", text);
  if (!strstr(err, what)) fail_msg("error '%s' lacks '%s'", err, what);
}

static void test_validation(void **state) {
  const char *ok = "vlff-embeddings 1\ndim 2\n# comment\n\nchair\t1 0\ntable\t0 -2.5e-1\n";
  char err[256];
  struct vlff_embeddings *e = vlff_embeddings_parse(ok, strlen(ok), "t.emb", 2, err, sizeof err);
  if (!e) fail_msg("%s", err);
  assert_int_equal(vlff_embeddings_count(e), 2);
  assert_true(vlff_embeddings_lookup(e, "table")[1] == -0.25f);
  vlff_embeddings_free(e);

  refused("", "missing 'vlff-embeddings 1'");
  refused("vlff-embeddings 2\n", "t.emb:1: expected 'vlff-embeddings 1'");
  refused("vlff-embeddings 1\n", "missing 'dim N'");
  refused("vlff-embeddings 1\ndim 0\n", ":2: expected 'dim N'");
  refused("vlff-embeddings 1\ndim 5000\n", ":2: expected 'dim N'");
  refused("vlff-embeddings 1\ndim 2\n", "no prompts");
  refused("vlff-embeddings 1\ndim 2\nchair 1 0\n", ":3: expected 'prompt<TAB>numbers'");
  refused("vlff-embeddings 1\ndim 2\nchair\t1\n", ":3: expected 2 numbers");
  refused("vlff-embeddings 1\ndim 2\nchair\t1 0 3\n", ":3: more than 2 numbers");
  refused("vlff-embeddings 1\ndim 2\nchair\t1  0\n", ":3: expected 2 numbers");
  refused("vlff-embeddings 1\ndim 2\nchair\t1 nan\n", ":3: number 2 is not a finite float");
  refused("vlff-embeddings 1\ndim 2\nchair\t1 1e99\n", "not a finite float");
  refused("vlff-embeddings 1\ndim 2\nchair\t1 x\n", "not a finite float");
  refused("vlff-embeddings 1\r\ndim 2\r\nchair\t1 0\r\n", "t.emb:1: CRLF line end");
  refused("vlff-embeddings 1\ndim 2\nchair\t1 0\r\n", "t.emb:3: CRLF line end");
  /* Underflow is a tiny finite number, not an error. */
  const char *tiny = "vlff-embeddings 1\ndim 2\nchair\t1 1e-45\ntable\t1 -1e-50\n";
  e = vlff_embeddings_parse(tiny, strlen(tiny), "t.emb", 2, err, sizeof err);
  if (!e) fail_msg("%s", err);
  assert_true(vlff_embeddings_lookup(e, "chair")[1] > 0);
  assert_true(vlff_embeddings_lookup(e, "table")[1] == 0);
  vlff_embeddings_free(e);
  refused("vlff-embeddings 1\ndim 2\nchair\t0 0\n", "zero vector");
  /* Lengths no encoder gives: products of such values overflow (a
   * dataset's 1e38 vector made its class unscorable) or flush to zero. */
  refused("vlff-embeddings 1\ndim 2\nchair\t1e38 1e38\n", ":3: vector for 'chair' has length 1.41e+38, expected 1e-06 to 1e+06");
  refused("vlff-embeddings 1\ndim 2\nchair\t1e-45 1e-45\n", ":3: vector for 'chair' has length");
  refused("vlff-embeddings 1\ndim 2\nchair\t2e6 0\n", "has length");
  const char *edges = "vlff-embeddings 1\ndim 2\nchair\t1.1e-6 0\ntable\t0 9.9e5\n";
  e = vlff_embeddings_parse(edges, strlen(edges), "t.emb", 2, err, sizeof err);
  if (!e) fail_msg("%s", err);
  vlff_embeddings_free(e);
  refused("vlff-embeddings 1\ndim 2\nchair\t1 0\nchair\t0 1\n", ":4: duplicate prompt 'chair'");
  refused("vlff-embeddings 1\ndim 2\n\t1 0\n", ":3: prompt must be");
  refused("vlff-embeddings 1\ndim 2\nch\xff" "air\t1 0\n", ":3: prompt must be");
  refused("vlff-embeddings 1\ndim 2\n0123456789012345678901234567890123456789012345678901234567890123\t1 0\n",
          "prompt must be");
  const char nul[] = "vlff-embeddings 1\ndim 2\nch\0ir\t1 0\n";
  assert_null(vlff_embeddings_parse(nul, sizeof nul - 1, "t.emb", 0, err, sizeof err));
  assert_non_null(strstr(err, ":3: NUL byte"));
}

/* A prompt_embeddings.txt whose first line is an OSC title and a CSI clear:
 * the error quotes it escaped (vlff/escape.h), as config errors do, and the
 * file's own name too (ESC and newline in it). */
static void expect_escaped(const char *err, const char *want) {
  for (const unsigned char *c = (const unsigned char *)err; *c; c++)
    if (*c < 0x20 || *c == 0x7f) fail_msg("raw byte 0x%02x in error '%s'", *c, err);
  if (!strstr(err, want)) fail_msg("error '%s' lacks '%s'", err, want);
}

static void test_outside_bytes_escaped(void **state) {
  (void)state;
  char dir[128], path[256], err[512];
  snprintf(dir, sizeof dir, "/tmp/vlff-test-emb-esc-%d", (int)getpid());
  assert_int_equal(mkdir(dir, 0700), 0);
  snprintf(path, sizeof path, "%s/prompt_embeddings.txt", dir);
  FILE *f = fopen(path, "w");
  assert_non_null(f);
  fputs("\x1b]0;owned\x07\x1b[2J\x1b[31m'\\\xff\nvlff-embeddings 1\ndim 2\nwall\t1 0\n", f);
  fclose(f);
  assert_null(vlff_embeddings_load(path, 2, err, sizeof err));
  print_message("  error: %s\n", err);
  expect_escaped(err, "prompt_embeddings.txt:1: expected 'vlff-embeddings 1', got "
                      "'\\x1b]0;owned\\x07\\x1b[2J\\x1b[31m\\'\\\\\\xff'");
  /* the dim line, cut at 40 bytes with an ellipsis */
  f = fopen(path, "w");
  assert_non_null(f);
  fputs("vlff-embeddings 1\ndim \x1b[2J\x1b[2J\x1b[2J\x1b[2J\x1b[2J\x1b[2J\x1b[2J\x1b[2J\x1b[2J\x1b[2J\nwall\t1 0\n", f);
  fclose(f);
  assert_null(vlff_embeddings_load(path, 2, err, sizeof err));
  print_message("  error: %s\n", err);
  expect_escaped(err, "got 'dim \\x1b[2J\\x1b[2J");
  expect_escaped(err, "...'");
  /* a file name with ESC and a newline in it */
  char odd[300];
  snprintf(odd, sizeof odd, "%s/e\x1b[2J\nx.txt", dir);
  assert_int_equal(rename(path, odd), 0);
  assert_null(vlff_embeddings_load(odd, 2, err, sizeof err));
  print_message("  error: %s\n", err);
  expect_escaped(err, "/e\\x1b[2J\\x0ax.txt:2: expected 'dim N'");
  assert_int_equal(unlink(odd), 0);
  assert_null(vlff_embeddings_load(odd, 2, err, sizeof err));
  print_message("  error: %s\n", err);
  expect_escaped(err, "/e\\x1b[2J\\x0ax.txt");
  assert_int_equal(rmdir(dir), 0);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_round_trip), cmocka_unit_test(test_validation),
    cmocka_unit_test(test_outside_bytes_escaped))
