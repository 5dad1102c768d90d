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

#include "clock.h"
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

/* A line that comes with every trainer iteration (issue 51, item 3: 224 lines a
 * second for ever): the first five, then at most one every 5 s saying how many it
 * left out. Two call sites (two counters) are limited apart. */
static uint64_t flood_a, flood_b;
static void flood(void) {
  for (int i = 0; i < 20000; i++) vlff_warn_limited(&flood_a, "t", "flood a %d", i);
  for (int i = 0; i < 3; i++) vlff_warn_limited(&flood_b, "t", "flood b %d", i);
}
static void flood_later(void) { vlff_warn_limited(&flood_a, "t", "flood a again"); }

static int count_lines(const char *s, const char *what) {
  int n = 0;
  for (const char *p = s; (p = strstr(p, what)); p++) n++;
  return n;
}

static void test_warn_limited_by_time(void **state) {
  (void)state;
  static char out[1 << 16];
  double t0 = (double)vlff_now_ns() / 1e9;
  capture(flood, out, sizeof out);
  double took = (double)vlff_now_ns() / 1e9 - t0;
  int a = count_lines(out, "flood a"), limit = 5 + 1 + (int)(took / 5.0);
  if (a > limit) fail_msg("%d lines of 20000 in %.1f s (at most %d):\n%s", a, took, limit, out);
  assert_int_equal(count_lines(out, "flood b"), 3);
  assert_int_equal(flood_a, 20000);
  sleep(6); /* past the interval: the next one is shown with what was left out */
  capture(flood_later, out, sizeof out);
  if (!strstr(out, "flood a again [") || !strstr(out, "more like this in the last"))
    fail_msg("after the interval: %s", out);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_log_line_not_glued_to_status),
               cmocka_unit_test(test_warn_limited_by_time),
               cmocka_unit_test(test_long_lines_bounded))
