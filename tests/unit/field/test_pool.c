/*
 * The learner's thread pool: every task of a run runs exactly once, static
 * runs put task t on thread t % threads, dynamic runs hand tasks to any
 * thread, and runs stay correct across every hand-off the pool has: back to
 * back (spinning workers), after the workers went to sleep, and with tasks
 * that outlast the caller's spin. TSan checks the hand-offs' ordering: each
 * task's writes must be visible to the caller after the run, and the run's
 * arguments to the workers.
 */
#include <setjmp.h>
#include <stdatomic.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

#include <cmocka.h>

#include "field_internal.h"
#include "unit.h"

enum { MAXT = 200 };

struct rec {
  int ran[MAXT];      /* times task t ran */
  int thread[MAXT];   /* thread that ran it */
  long long value[MAXT];
  int sleep_us;       /* each task sleeps this long */
  int threads;
};

static void sleep_us(int us) {
  struct timespec ts = {0, (long)us * 1000};
  nanosleep(&ts, NULL);
}

static void record(void *ctx, int t, int thread) {
  struct rec *r = ctx;
  if (r->sleep_us) sleep_us(r->sleep_us);
  /* Plain writes: only the pool's hand-off orders them before the
   * caller's reads. */
  r->ran[t]++;
  r->thread[t] = thread;
  r->value[t] = (long long)t * t + 7;
}

static void check_run(struct vlff_pool *p, struct rec *r, int ntasks, int dynamic) {
  int threads = vlff_pool_threads(p);
  memset(r->ran, 0, sizeof r->ran);
  memset(r->thread, -1, sizeof r->thread);
  if (dynamic)
    vlff_pool_run_dynamic(p, ntasks, record, r);
  else
    vlff_pool_run(p, ntasks, record, r);
  for (int t = 0; t < MAXT; t++) {
    if (t >= ntasks) {
      assert_int_equal(r->ran[t], 0);
      continue;
    }
    if (r->ran[t] != 1) fail_msg("task %d of %d ran %d times (dynamic %d)", t, ntasks, r->ran[t], dynamic);
    assert_true(r->value[t] == (long long)t * t + 7);
    assert_in_range(r->thread[t], 0, threads - 1);
    if (!dynamic) assert_int_equal(r->thread[t], t % threads);
  }
}

static const int counts[] = {0, 1, 2, 3, 5, 16, 64, 199};

static void test_every_task_once(void **state) {
  (void)state;
  static struct rec r;
  for (int threads = 1; threads <= 4; threads++) {
    struct vlff_pool *p = vlff_pool_create(threads);
    assert_non_null(p);
    assert_int_equal(vlff_pool_threads(p), threads);
    for (size_t k = 0; k < sizeof counts / sizeof counts[0]; k++) {
      check_run(p, &r, counts[k], 0);
      check_run(p, &r, counts[k], 1);
    }
    vlff_pool_destroy(p);
  }
}

/* runs runs on a pool of threads, alternating static and dynamic, with
 * idle_us between runs and tasks of task_us each. */
static void hand_offs(int threads, int runs, int idle_us, int task_us) {
  static struct rec r;
  struct vlff_pool *p = vlff_pool_create(threads);
  assert_non_null(p);
  r.sleep_us = task_us;
  for (int i = 0; i < runs; i++) {
    if (idle_us) sleep_us(idle_us);
    check_run(p, &r, 1 + i % 17, i & 1);
  }
  vlff_pool_destroy(p);
}

/* Back to back: the workers never reach their sleep. */
static void test_back_to_back(void **state) {
  (void)state;
  hand_offs(3, 2000, 0, 0);
}

/* Idle longer than the spin between runs: the workers sleep on the
 * condition variable and the next run must wake them. */
static void test_after_sleep(void **state) {
  (void)state;
  hand_offs(2, 20, 2000, 0);
}

/* Tasks longer than the caller's spin: it waits on the condition variable
 * for the last worker. */
static void test_long_tasks(void **state) {
  (void)state;
  hand_offs(2, 10, 0, 1500);
}

/* Dynamic runs balance: while one thread holds a long task, the other
 * takes every other task. Task 0 waits (up to 10 s) until the rest are done;
 * with static shares its own thread's share would still be waiting. */
static atomic_int short_done;

static void unequal(void *ctx, int t, int thread) {
  struct rec *r = ctx;
  if (t == 0)
    for (int i = 0; i < 10000 && atomic_load(&short_done) < 39; i++) sleep_us(1000);
  r->ran[t]++;
  r->thread[t] = thread;
  if (t > 0) atomic_fetch_add(&short_done, 1);
}

static void test_dynamic_balances(void **state) {
  (void)state;
  static struct rec r;
  struct vlff_pool *p = vlff_pool_create(2);
  assert_non_null(p);
  memset(&r, 0, sizeof r);
  atomic_store(&short_done, 0);
  vlff_pool_run_dynamic(p, 40, unequal, &r);
  for (int t = 0; t < 40; t++) {
    assert_int_equal(r.ran[t], 1);
    if (t > 0) assert_int_not_equal(r.thread[t], r.thread[0]);
  }
  vlff_pool_destroy(p);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_every_task_once), cmocka_unit_test(test_back_to_back),
    cmocka_unit_test(test_after_sleep), cmocka_unit_test(test_long_tasks),
    cmocka_unit_test(test_dynamic_balances))
