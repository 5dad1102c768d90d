/*
 * What every unit-test program shares: its main(), the cmocka tests run as
 * one group, and the build's programs as command words.
 *
 * Contract: VLFF_UNIT_MAIN(setup, teardown, cmocka_unit_test(a), ...) defines
 * main(void), runs the tests in the order given with the group's setup and
 * teardown (NULL for none) and returns cmocka's count of failures. Include it
 * after <cmocka.h>. vlff_test_emulator() names the emulator a cross-built
 * test runs under; vlff_test_in_child() runs a call that may block under an
 * alarm, in a child process. vlff_test_normal() draws a reproducible
 * standard normal value from a 64-bit seed it advances.
 * vlff_test_wait_peak() waits for a spawned child and gives its peak
 * resident set. vlff_test_status_kb() reads one "Key: N kB" line of this
 * process's /proc/self/status (-1 when absent).
 */
#ifndef VLFF_UNIT_H
#define VLFF_UNIT_H

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <unistd.h>

/* A program of the build (rel: its path in the build tree) as a command
 * word in buf: after $VLFF_EMULATOR (qemu-user in a cross-built tree, empty
 * otherwise). ctest sets $VLFF_BINARY_DIR. */
static inline const char *vlff_test_prog(char *buf, size_t cap, const char *rel) {
  const char *bin = getenv("VLFF_BINARY_DIR"), *emu = getenv("VLFF_EMULATOR");
  assert_non_null(bin);
  snprintf(buf, cap, "%s %s/%s", emu ? emu : "", bin, rel);
  return buf;
}

/* The emulator this test runs under ($VLFF_EMULATOR: qemu-user in a
 * cross-built tree), NULL when it runs natively. */
static inline double vlff_test_status_kb(const char *key) {
  FILE *f = fopen("/proc/self/status", "r");
  char line[256];
  size_t n = strlen(key);
  double kb = -1;
  while (f && fgets(line, sizeof line, f))
    if (!strncmp(line, key, n) && line[n] == ':' && sscanf(line + n + 1, "%lf", &kb) == 1) break;
  if (f) fclose(f);
  return kb;
}

static inline const char *vlff_test_emulator(void) {
  const char *emu = getenv("VLFF_EMULATOR");
  return emu && *emu ? emu : NULL;
}

/* A standard normal value, Box-Muller over two uniforms from a 64-bit LCG
 * (Knuth's MMIX constants) advanced in *seed: sensor noise a test can
 * reproduce exactly. */
static inline double vlff_test_normal(uint64_t *seed) {
  double u[2];
  for (int k = 0; k < 2; k++) {
    *seed = *seed * 6364136223846793005ull + 1442695040888963407ull;
    u[k] = ((double)(*seed >> 11) + 0.5) / 9007199254740992.0;
  }
  return sqrt(-2 * log(u[0])) * cos(6.283185307179586 * u[1]);
}

/* Runs fn(ctx) in a child process that an alarm ends after timeout_s, so
 * that a call which blocks (an open(2) of a FIFO) fails the test instead of
 * hanging it. Returns fn's value (the child's exit status, 0..255), or -1
 * when the child was killed. */
static inline int vlff_test_in_child(int (*fn)(void *ctx), void *ctx, unsigned timeout_s) {
  pid_t pid = fork();
  assert_true(pid >= 0);
  if (pid == 0) {
    alarm(timeout_s);
    _exit(fn(ctx));
  }
  int st;
  assert_int_equal(waitpid(pid, &st, 0), pid);
  return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

#define VLFF_UNIT_MAIN(setup, teardown, ...)                   \
  int main(void) {                                             \
    const struct CMUnitTest unit_tests_[] = {__VA_ARGS__};     \
    return cmocka_run_group_tests(unit_tests_, setup, teardown); \
  }

/* Waits for child pid (its wait status in *status) and returns its peak
 * resident set in MiB: VmHWM, the high-water mark of the memory its program
 * mapped, polled every 5 ms while it runs (0 if never read). Not wait4's
 * ru_maxrss: a child spawned by this test starts with the test process's own
 * peak, which its exec carries over, so a small program run from a large
 * test reads as large as the test. */
static inline double vlff_test_wait_peak(pid_t pid, int *status) {
  long peak = 0;
  char path[64], line[128];
  snprintf(path, sizeof path, "/proc/%d/status", (int)pid);
  for (;;) {
    FILE *f = fopen(path, "r");
    long kb = 0;
    if (f) {
      while (fgets(line, sizeof line, f))
        if (sscanf(line, "VmHWM: %ld kB", &kb) == 1) break;
      fclose(f);
    }
    if (kb > peak) peak = kb;
    pid_t w = waitpid(pid, status, WNOHANG);
    if (w == pid) return peak / 1024.0;
    if (w < 0) {
      *status = -1;
      return peak / 1024.0;
    }
    usleep(5000);
  }
}

#endif
