/* CLIP tokenizer: every reference vector, the cleaning rules, bad merges files. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <zlib.h>

#include <cmocka.h>

#include "tokenizer.h"
#include "unit.h"

static char merges_path[512];
static struct vlff_tokenizer *tok;

static int setup(void **state) {
  const char *data = getenv("VLFF_DATA_DIR");
  assert_non_null(data);
  snprintf(merges_path, sizeof merges_path, "%s/bpe_simple_vocab_16e6.txt.gz", data);
  char err[256] = "";
  tok = vlff_tokenizer_open(merges_path, err, sizeof err);
  if (!tok) fprintf(stderr, "%s\n", err);
  return tok ? 0 : -1;
}

static int teardown(void **state) {
  vlff_tokenizer_close(tok);
  return 0;
}

static long enc(const char *s, int32_t *ids, size_t cap) {
  char err[256] = "";
  long n = vlff_tokenizer_encode(tok, s, strlen(s), ids, cap, err, sizeof err);
  if (n < 0) fail_msg("encode '%s': %s", s, err);
  return n;
}

static void test_reference_vectors(void **state) {
  char path[512];
  snprintf(path, sizeof path, "%s/tokenizer-vectors.tsv", getenv("VLFF_DATA_DIR"));
  FILE *f = fopen(path, "r");
  assert_non_null(f);
  char line[4096];
  int rows = 0;
  while (fgets(line, sizeof line, f)) {
    if (line[0] == '#') continue;
    line[strcspn(line, "\n")] = 0;
    char *tab = strchr(line, '\t');
    assert_non_null(tab);
    *tab = 0;
    int32_t want[128], got[128];
    int nw = 0;
    for (char *p = tab + 1, *e; *p; p = e) {
      want[nw++] = (int32_t)strtol(p, &e, 10);
      assert_true(e != p);
    }
    long n = enc(line, got, 128);
    if (n != nw || memcmp(want, got, (size_t)nw * sizeof *got)) {
      fprintf(stderr, "mismatch for '%s': got", line);
      for (long i = 0; i < n && i < 128; i++) fprintf(stderr, " %d", got[i]);
      fprintf(stderr, "\n");
      fail();
    }
    rows++;
  }
  fclose(f);
  assert_true(rows >= 37);
}

static void test_context(void **state) {
  int32_t ctx[VLFF_CLIP_CONTEXT];
  char err[256];
  int eot = vlff_tokenizer_context(tok, "a photo of a chair.", ctx, err, sizeof err);
  assert_int_equal(eot, 7);
  const int32_t want[] = {49406, 320, 1125, 539, 320, 4269, 269, 49407};
  assert_memory_equal(ctx, want, sizeof want);
  for (int i = 8; i < VLFF_CLIP_CONTEXT; i++) assert_int_equal(ctx[i], 0);
  /* 76 digits = 76 tokens: one more than the context holds. */
  char longp[200];
  memset(longp, '7', 76), longp[76] = 0;
  assert_int_equal(vlff_tokenizer_context(tok, longp, ctx, err, sizeof err), -1);
  assert_non_null(strstr(err, "76 tokens"));
  longp[75] = 0;
  assert_int_equal(vlff_tokenizer_context(tok, longp, ctx, err, sizeof err), 76);
  assert_int_equal(ctx[76], 49407);
}

static void same(const char *a, const char *b) {
  int32_t x[64], y[64];
  long na = enc(a, x, 64), nb = enc(b, y, 64);
  if (na != nb || memcmp(x, y, (size_t)na * sizeof *x)) fail_msg("'%s' and '%s' tokenize differently", a, b);
}

static void test_cleaning(void **state) {
  same("salt &amp; pepper", "salt & pepper");
  same("salt &amp;amp; pepper", "salt & pepper");  /* unescaped more than once, as the reference */
  same("&lt;chair&gt;", "<chair>");
  same("caf&eacute; &#233; &#xE9;", "caf\xc3\xa9" " \xc3\xa9" " \xc3\xa9");
  same("&#8220;chair&#8221;", "\"chair\"");      /* entity then ftfy's quote fix */
  same("\xe2\x80\x9c" "chair" "\xe2\x80\x9d" " it" "\xe2\x80\x99" "s", "\"chair\" it's");
  same("\xef\xac\x81re", "fire");                 /* U+FB01 ligature */
  same("\xef\xbd\x83\xef\xbd\x88\xef\xbd\x81\xef\xbd\x89\xef\xbd\x92", "chair"); /* full-width */
  same("CHAIR\tand\n\n TABLE", "chair and table");
  same("\xc3\x89" "COLE", "\xc3\xa9" "cole");
  same("ch\x7f" "air", "chair");                  /* control characters dropped */
  same("&notanentity;", "& notanentity ;");
  int32_t ids[8];
  assert_int_equal(enc("", ids, 8), 0);
  assert_int_equal(enc(" \t\n ", ids, 8), 0);
  assert_int_equal(enc("<|endoftext|>", ids, 8), 1);
  assert_int_equal(ids[0], VLFF_CLIP_EOT);
}

static void test_bad_prompts(void **state) {
  char err[256];
  int32_t ids[8];
  const char bad[] = "chair \xc3(";
  assert_int_equal(vlff_tokenizer_encode(tok, bad, sizeof bad - 1, ids, 8, err, sizeof err), -1);
  assert_non_null(strstr(err, "invalid UTF-8 at byte 6"));
  const char surrogate[] = "\xed\xa0\x80";
  assert_int_equal(vlff_tokenizer_encode(tok, surrogate, 3, ids, 8, err, sizeof err), -1);
  size_t big = VLFF_TOKENIZER_MAX_TEXT + 1;
  char *huge = malloc(big);
  memset(huge, 'a', big);
  assert_int_equal(vlff_tokenizer_encode(tok, huge, big, ids, 8, err, sizeof err), -1);
  assert_non_null(strstr(err, "longer than the limit"));
  /* cap smaller than the count: the count is still exact */
  assert_int_equal(vlff_tokenizer_encode(tok, "a photo of a chair.", 19, ids, 2, err, sizeof err), 6);
  free(huge);
}

static char *slurp_gz(size_t *len) {
  gzFile g = gzopen(merges_path, "rb");
  assert_non_null(g);
  size_t cap = 8u << 20;
  char *buf = malloc(cap);
  int r = gzread(g, buf, (unsigned)cap);
  assert_true(r > 0);
  gzclose(g);
  *len = (size_t)r;
  return buf;
}

static void write_gz(const char *path, const char *data, size_t len) {
  gzFile g = gzopen(path, "wb");
  assert_non_null(g);
  assert_int_equal(gzwrite(g, data, (unsigned)len), (int)len);
  assert_int_equal(gzclose(g), Z_OK);
}

static void expect_refused(const char *path, const char *what) {
  char err[512] = "";
  struct vlff_tokenizer *t = vlff_tokenizer_open(path, err, sizeof err);
  if (t) fail_msg("accepted a bad merges file (expected: %s)", what);
  if (!strstr(err, what)) fail_msg("error '%s' does not mention '%s'", err, what);
  assert_non_null(strstr(err, path));
}

static void test_bad_merges_files(void **state) {
  char path[256];
  snprintf(path, sizeof path, "/tmp/vlff-test-bpe-%d.gz", (int)getpid());
  expect_refused("/nonexistent/bpe.txt.gz", "cannot open");

  size_t len;
  char *text = slurp_gz(&len);
  /* Short: a valid gzip holding only the first 1000 merges. */
  char *p = text;
  for (int i = 0; i < 1001; i++) p = strchr(p, '\n') + 1;
  write_gz(path, text, (size_t)(p - text));
  expect_refused(path, "only 1000 merges");

  /* Truncated gzip stream: half of the real compressed file. */
  FILE *in = fopen(merges_path, "rb");
  assert_non_null(in);
  char *raw = malloc(2u << 20);
  size_t rn = fread(raw, 1, 2u << 20, in);
  fclose(in);
  FILE *out = fopen(path, "wb");
  fwrite(raw, 1, rn / 2, out);
  fclose(out);
  expect_refused(path, "truncated or corrupt");

  /* Corrupt deflate data in the middle. */
  memcpy(raw + rn / 2, "garbage!garbage!garbage!", 24);
  out = fopen(path, "wb");
  fwrite(raw, 1, rn, out);
  fclose(out);
  expect_refused(path, "corrupt");
  free(raw);

  /* Not a merges file at all. */
  write_gz(path, "hello world\n", 12);
  expect_refused(path, "header");

  /* A merge line with three symbols. */
  char *bad = malloc(len);
  memcpy(bad, text, len);
  char *l5 = bad;
  for (int i = 0; i < 5; i++) l5 = strchr(l5, '\n') + 1;
  *strchr(l5, '\n') = ' '; /* join lines 6 and 7 */
  write_gz(path, bad, len);
  expect_refused(path, ":6: expected a merge");

  /* A merge of a symbol that no earlier line made. */
  memcpy(bad, text, len);
  l5 = bad;
  for (int i = 0; i < 5; i++) l5 = strchr(l5, '\n') + 1;
  memcpy(l5, "zq", 2);
  char *sp = strchr(l5, ' ');
  memmove(l5 + 2, sp, len - (size_t)(sp - bad));
  write_gz(path, bad, len - (size_t)(sp - l5 - 2));
  expect_refused(path, "unknown symbol 'zq'");
  free(bad);
  free(text);
  unlink(path);
}

VLFF_UNIT_MAIN(setup, teardown,
    cmocka_unit_test(test_reference_vectors), cmocka_unit_test(test_context),
    cmocka_unit_test(test_cleaning), cmocka_unit_test(test_bad_prompts),
    cmocka_unit_test(test_bad_merges_files))
