/* The one escaping routine every message quoting outside data goes through
 * (vlff/escape.h): each byte class, the bounds and the ellipsis. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

#include <cmocka.h>

#include <vlff/escape.h>

static const char *esc(const char *s, size_t n) {
  static char out[VLFF_ESC_LEN];
  return vlff_escape(out, sizeof out, s, n, (size_t)-1);
}

#define ESC(lit) esc(lit, sizeof(lit) - 1)

static void test_printable_ascii_kept(void **state) {
  (void)state;
  assert_string_equal(ESC("node.name: abc XYZ 0-9 ~!@#$%^&*()_+={}[]|:;<>,.?/`"),
                      "node.name: abc XYZ 0-9 ~!@#$%^&*()_+={}[]|:;<>,.?/`");
  assert_string_equal(ESC(""), "");
}

static void test_backslash_and_quotes_escaped(void **state) {
  (void)state;
  assert_string_equal(ESC("a\\b"), "a\\\\b");
  assert_string_equal(ESC("it's"), "it\\'s");
  assert_string_equal(ESC("say \"hi\""), "say \\\"hi\\\"");
  /* a forged "\x1b" in the data reads differently from an escaped ESC */
  assert_string_equal(ESC("\\x1b"), "\\\\x1b");
}

static void test_control_bytes_hex(void **state) {
  (void)state;
  assert_string_equal(ESC("\x1b]0;pwned\x07"), "\\x1b]0;pwned\\x07");
  assert_string_equal(ESC("\x1b[2J\x1b[31mred"), "\\x1b[2J\\x1b[31mred");
  assert_string_equal(ESC("a\nb\rc\td"), "a\\x0ab\\x0dc\\x09d");
  assert_string_equal(ESC("a\0b"), "a\\x00b");
  assert_string_equal(ESC("del\x7f"), "del\\x7f");
  for (int c = 0; c < 0x20; c++) {
    char in[1] = {(char)c}, want[8];
    snprintf(want, sizeof want, "\\x%02x", c);
    assert_string_equal(esc(in, 1), want);
  }
}

static void test_invalid_utf8_hex(void **state) {
  (void)state;
  assert_string_equal(ESC("\x80"), "\\x80");                   /* stray continuation byte */
  assert_string_equal(ESC("\xff\xfe"), "\\xff\\xfe");          /* never in UTF-8 */
  assert_string_equal(ESC("\xc0\xaf"), "\\xc0\\xaf");          /* overlong '/' */
  assert_string_equal(ESC("\xe0\x80\xaf"), "\\xe0\\x80\\xaf"); /* overlong, 3 bytes */
  assert_string_equal(ESC("\xed\xa0\x80"), "\\xed\\xa0\\x80"); /* surrogate U+D800 */
  assert_string_equal(ESC("\xf4\x90\x80\x80"), "\\xf4\\x90\\x80\\x80"); /* above U+10FFFF */
  assert_string_equal(ESC("caf\xc3"), "caf\\xc3");             /* cut short at the end */
  assert_string_equal(ESC("\xc3(x"), "\\xc3(x");               /* cut short by ASCII */
}

static void test_valid_utf8_kept(void **state) {
  (void)state;
  assert_string_equal(ESC("caf\xc3\xa9"), "caf\xc3\xa9");                        /* 2 bytes */
  assert_string_equal(ESC("\xe6\xa4\x85\xe5\xad\x90"), "\xe6\xa4\x85\xe5\xad\x90"); /* 3 bytes (chair) */
  assert_string_equal(ESC("\xf0\x9f\xaa\x91"), "\xf0\x9f\xaa\x91");              /* 4 bytes (U+1FA91) */
  assert_string_equal(ESC("\xd0\xbf\xd0\xbe\xd0\xbb"), "\xd0\xbf\xd0\xbe\xd0\xbb"); /* Cyrillic */
}

static void test_terminal_code_points_hex(void **state) {
  (void)state;
  assert_string_equal(ESC("\xc2\x9b" "31m"), "\\xc2\\x9b" "31m");   /* U+009B: C1 CSI */
  assert_string_equal(ESC("c1 \xc2\x85"), "c1 \\xc2\\x85");          /* U+0085 NEL */
  assert_string_equal(ESC("\xe2\x80\xae" "cod.exe"), "\\xe2\\x80\\xae" "cod.exe"); /* U+202E RLO */
  assert_string_equal(ESC("a\xe2\x80\xa8" "b"), "a\\xe2\\x80\\xa8" "b");     /* U+2028 */
  assert_string_equal(ESC("\xe2\x81\xa6"), "\\xe2\\x81\\xa6");               /* U+2066 LRI */
  assert_string_equal(ESC("\xc2\xa0"), "\xc2\xa0");                         /* U+00A0 is text */
}

static void test_bounded_with_ellipsis(void **state) {
  (void)state;
  char out[VLFF_ESC_LEN];
  /* max input bytes */
  assert_string_equal(vlff_escape(out, sizeof out, "abcdef", 6, 3), "abc...");
  assert_string_equal(vlff_escape(out, sizeof out, "abc", 3, 3), "abc");
  /* the output bound: every byte escaped, nothing cut in half */
  char big[4096];
  memset(big, 0x1b, sizeof big);
  vlff_escape(out, sizeof out, big, sizeof big, (size_t)-1);
  size_t l = strlen(out);
  assert_true(l < sizeof out);
  assert_string_equal(out + l - 3, "...");
  assert_int_equal((l - 3) % 4, 0);
  for (size_t k = 0; k + 3 < l; k += 4) assert_memory_equal(out + k, "\\x1b", 4);
  /* a small buffer: a UTF-8 character is not cut */
  char small[10];
  vlff_escape(small, sizeof small, "ab\xe6\xa4\x85\xe5\xad\x90", 8, (size_t)-1);
  assert_string_equal(small, "ab\xe6\xa4\x85...");
  /* a UTF-8 character cut by max is not split either */
  assert_string_equal(vlff_escape(out, sizeof out, "\xe6\xa4\x85", 3, 2), "\\xe6\\xa4...");
  /* exactly full, no ellipsis needed */
  assert_string_equal(vlff_escape(small, sizeof small, "abcde", 5, (size_t)-1), "abcde");
}

static void test_macros(void **state) {
  (void)state;
  char msg[2 * VLFF_ESC_LEN];
  snprintf(msg, sizeof msg, "%s: got '%s' and '%s'", VLFF_Q("/d/\x1b[2Jx\n.png"), VLFF_QMAX("\x1b]0;t\x07rest", 6),
           VLFF_QN("a\0b", 3));
  assert_string_equal(msg, "/d/\\x1b[2Jx\\x0a.png: got '\\x1b]0;t\\x07...' and 'a\\x00b'");
  assert_string_equal(VLFF_Q(NULL), "(null)");
}

int main(void) {
  const struct CMUnitTest tests[] = {
      cmocka_unit_test(test_printable_ascii_kept),     cmocka_unit_test(test_backslash_and_quotes_escaped),
      cmocka_unit_test(test_control_bytes_hex),        cmocka_unit_test(test_invalid_utf8_hex),
      cmocka_unit_test(test_valid_utf8_kept),          cmocka_unit_test(test_terminal_code_points_hex),
      cmocka_unit_test(test_bounded_with_ellipsis),    cmocka_unit_test(test_macros),
  };
  return cmocka_run_group_tests(tests, NULL, NULL);
}
