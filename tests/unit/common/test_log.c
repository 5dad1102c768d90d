/* Log lines and the live status line (log.h): a log line written while a
 * status line is shown starts on a line of its own, and ending the status
 * line writes one newline, only when one is shown. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <cmocka.h>

#include "log.h"
#include "unit.h"

/* Runs fn with stderr going to a temporary file; its contents in out. */
static size_t capture(void (*fn)(void), char *out, size_t cap) {
  FILE *tmp = tmpfile();
  assert_non_null(tmp);
  int saved = dup(STDERR_FILENO);
  assert_true(saved >= 0);
  assert_true(dup2(fileno(tmp), STDERR_FILENO) >= 0);
  fn();
  assert_true(dup2(saved, STDERR_FILENO) >= 0);
  close(saved);
  rewind(tmp);
  size_t n = fread(out, 1, cap - 1, tmp);
  out[n] = 0;
  fclose(tmp);
  return n;
}

static void status_then_logs(void) {
  vlff_log_status("st %d", 1);
  vlff_log_status("st %d", 2);
  VLFF_INFO("t", "hello");
  VLFF_INFO("t", "again");
  vlff_log_status("st %d", 3);
  vlff_log_status_end();
  vlff_log_status_end();
  VLFF_INFO("t", "after");
}

static size_t count(const char *s, char c) {
  size_t n = 0;
  for (; *s; s++) n += *s == c;
  return n;
}

static void test_log_line_not_glued_to_status(void **state) {
  (void)state;
  unsetenv("JOURNAL_STREAM");
  char out[4096];
  capture(status_then_logs, out, sizeof out);
  assert_true(strncmp(out, "\rst 1\rst 2\n[", 12) == 0);
  const char *h = strstr(out, "I t: hello\n[");
  assert_non_null(h);
  assert_non_null(strstr(h, "I t: again\n\rst 3\n["));
  assert_non_null(strstr(out, "I t: after\n"));
  /* One newline per log line (three) and one before each log line or end
   * that follows a shown status line (two), no more. */
  assert_int_equal(count(out, '\n'), 5);
  assert_null(strstr(out, "\n\n"));
}

static void long_line_after_status(void) {
  static char big[3000];
  memset(big, 'x', sizeof big - 1);
  vlff_log_status("%s", big);
  VLFF_WARN("t", "%s", big);
}

static void test_long_lines_bounded(void **state) {
  (void)state;
  unsetenv("JOURNAL_STREAM");
  char out[8192];
  size_t n = capture(long_line_after_status, out, sizeof out);
  /* The status line is cut to its buffer; the log line too, and still ends
   * with its newline after the one that ends the status line. */
  const char *nl = strchr(out, '\n');
  assert_non_null(nl);
  assert_true(nl - out < 600);
  assert_int_equal(out[n - 1], '\n');
  assert_true(n - (size_t)(nl + 1 - out) <= 1024);
  assert_int_equal(count(out, '\n'), 2);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_log_line_not_glued_to_status),
               cmocka_unit_test(test_long_lines_bounded))
