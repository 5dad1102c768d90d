/* node.cpu_budget's parts (budget.h): the pool's size, and the pacer that
 * keeps a working loop's process CPU at the budget. Not timed: the pacer's
 * own accounting and the process's CPU clock are asserted, with margins a
 * loaded host cannot break (it only makes the loop use less). */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <time.h>
#include <unistd.h>
#include <cmocka.h>

#include "budget.h"
#include "clock.h"
#include "unit.h"

static void test_threads(void **state) {
  (void)state;
  assert_int_equal(vlff_budget_threads(0, 4), 4); /* no budget: node.threads */
  assert_int_equal(vlff_budget_threads(0.5, 4), 1);
  assert_int_equal(vlff_budget_threads(1, 4), 1);
  assert_int_equal(vlff_budget_threads(1.5, 4), 2);
  assert_int_equal(vlff_budget_threads(2, 4), 2);
  assert_int_equal(vlff_budget_threads(3, 2), 2); /* node.threads is the smaller */
  assert_int_equal(vlff_budget_threads(0.1, 0), 1);
  long n = sysconf(_SC_NPROCESSORS_ONLN);
  assert_int_equal(vlff_budget_threads(0, 0), n > 0 ? n : 1); /* one per core */
  assert_int_equal(vlff_budget_threads(256, 0), n > 0 ? n : 1);
}

/* Uses ms of this process's CPU. */
static void burn(double ms) {
  double end = vlff_process_cpu_s() + ms * 1e-3;
  volatile double x = 1;
  while (vlff_process_cpu_s() < end) x = x * 1.0000001 + 1e-9;
}

/* A loop that would use a whole core, paced at budget cores for wall_s:
 * the cores it used, by the process's CPU clock. */
static double paced_loop(struct vlff_pacer *p, double budget, double wall_s, int *steps, double *reported) {
  vlff_pacer_init(p, budget);
  double t0 = vlff_seconds(), c0 = vlff_process_cpu_s();
  *steps = 0;
  *reported = -1;
  while (vlff_seconds() - t0 < wall_s) {
    double used;
    if (vlff_pacer_pace(p, true, 0.1, &used)) {
      burn(5); /* a training step */
      ++*steps;
    }
    if (used >= 0) *reported = used;
  }
  return (vlff_process_cpu_s() - c0) / (vlff_seconds() - t0);
}

static void test_paced(void **state) {
  (void)state;
  struct vlff_pacer p;
  int steps;
  double reported;
  /* A budget far below what even a loaded host gives a busy loop, so the
   * pacer, not the host, is what holds it. */
  const double b = 0.02;
  double used = paced_loop(&p, b, 1.5, &steps, &reported);
  print_message("budget 0.02: %.3f cores by the process clock, %.3f reported, %d steps, %.2f s slept\n", used, reported,
                steps, p.slept_s);
  assert_true(steps > 0);
  assert_true(p.slept_s > 0.5); /* mostly asleep */
  assert_true(used <= b * 1.3);
  assert_true(reported > 0 && reported <= b * 1.3);
  /* No budget: measured, never slept. */
  used = paced_loop(&p, 0, 0.3, &steps, &reported);
  assert_true(p.slept_s == 0 && steps > 0);
}

/* Idle time banks at most PACER_CREDIT_S of budget: a node that waited for
 * keyframes does not then burst over its budget for as long. */
static void test_credit_capped(void **state) {
  (void)state;
  struct vlff_pacer p;
  vlff_pacer_init(&p, 1);
  struct timespec nap = {0, 300 * 1000 * 1000};
  nanosleep(&nap, NULL);
  double used;
  assert_true(vlff_pacer_pace(&p, true, 0.1, &used));
  assert_true(fabs(p.debt + PACER_CREDIT_S) < 1e-9);
}

/* Other work alone over the budget (the review's node.cpu_budget 0.1 never
 * trained: ingest and publishing took more): training still gets a step at
 * least every PACER_DEBT_S. Before, the debt never fell and no step came. */
static void test_steps_despite_debt(void **state) {
  (void)state;
  struct vlff_pacer p;
  vlff_pacer_init(&p, 0.1);
  double used, t0 = vlff_seconds(), first = -1;
  while (vlff_seconds() - t0 < PACER_DEBT_S + 2 && first < 0) {
    double c0 = vlff_process_cpu_s();
    while (vlff_process_cpu_s() - c0 < 0.05) {
    } /* other work: 50 ms of CPU a pass, half a core with the naps */
    if (vlff_pacer_pace(&p, true, 0.1, &used)) first = vlff_seconds() - t0;
  }
  print_message("first step after %.2f s\n", first);
  assert_true(first > 0 && first <= PACER_DEBT_S + 1);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_threads), cmocka_unit_test(test_paced),
               cmocka_unit_test(test_credit_capped), cmocka_unit_test(test_steps_despite_debt))
