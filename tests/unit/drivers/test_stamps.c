/*
 * Trigger stamp queue (drivers/common/stamps): the hand-off between a GPIO
 * thread (pulses or edges) and vlff-camd's frame loop. Semantics single
 * threaded, then the real two-thread shape under load (labelled tsan: the
 * ThreadSanitizer build checks the acquire/release pairing).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <pthread.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <time.h>

#include "stamps.h"
#include "unit.h"

static struct vlff_stamps q;

static void test_newest_before_arrival_within_window(void **state) {
  (void)state;
  vlff_stamps_init(&q);
  assert_int_equal(vlff_stamps_match(&q, 1000, 1000), 0); /* empty */
  vlff_stamps_push(&q, 100);
  vlff_stamps_push(&q, 200);
  vlff_stamps_push(&q, 900);
  /* Arrival 500: 100 and 200 are consumed, 200 is the trigger; 900 waits. */
  assert_int_equal(vlff_stamps_match(&q, 500, 400), 200);
  assert_int_equal(vlff_stamps_match(&q, 500, 400), 0); /* consumed */
  /* Arrival 1000 but window 50: 900 is consumed yet too old to match. */
  assert_int_equal(vlff_stamps_match(&q, 1000, 50), 0);
  assert_int_equal(vlff_stamps_match(&q, 2000, 5000), 0);
  vlff_stamps_push(&q, 3000);
  assert_int_equal(vlff_stamps_match(&q, 3000, 0), 3000); /* a stamp at arrival counts */
}

static void test_overflow_keeps_the_newest(void **state) {
  (void)state;
  vlff_stamps_init(&q);
  for (uint64_t i = 1; i <= 10 * VLFF_STAMPS_CAP; i++) vlff_stamps_push(&q, i * 10);
  /* The producer never waited; the consumer still gets the newest stamp. */
  assert_int_equal(vlff_stamps_match(&q, UINT64_MAX / 2, UINT64_MAX / 2), 10 * VLFF_STAMPS_CAP * 10);
  assert_int_equal(vlff_stamps_match(&q, UINT64_MAX / 2, UINT64_MAX / 2), 0);
}

static uint64_t mono_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

#define PUSHES 4000
static atomic_bool producer_done;
static _Atomic uint64_t last_pushed;

/* Like the GPIO edge thread: a stamp of "now" every ~100 us. */
static void *producer(void *arg) {
  (void)arg;
  for (int i = 0; i < PUSHES; i++) {
    uint64_t t = mono_ns();
    vlff_stamps_push(&q, t);
    atomic_store(&last_pushed, t);
    struct timespec d = {0, 100000};
    nanosleep(&d, NULL);
  }
  atomic_store(&producer_done, true);
  return NULL;
}

static void test_two_threads(void **state) {
  (void)state;
  vlff_stamps_init(&q);
  atomic_store(&producer_done, false);
  atomic_store(&last_pushed, 0);
  pthread_t th;
  assert_int_equal(pthread_create(&th, NULL, producer, NULL), 0);
  uint64_t prev = 0;
  int matched = 0;
  /* Like vlff-camd's loop: a frame "arrives" every ~1 ms. */
  while (!atomic_load(&producer_done)) {
    uint64_t arrival = mono_ns();
    uint64_t s = vlff_stamps_match(&q, arrival, 1000000000u);
    if (s) {
      if (s > arrival) fail_msg("stamp %llu after arrival %llu", (unsigned long long)s, (unsigned long long)arrival);
      if (s <= prev) fail_msg("stamp %llu not after the previous match %llu", (unsigned long long)s,
                              (unsigned long long)prev);
      prev = s;
      matched++;
    }
    struct timespec d = {0, 1000000};
    nanosleep(&d, NULL);
  }
  pthread_join(th, NULL);
  /* Everything pushed is visible: the last match is the last stamp. */
  uint64_t s = vlff_stamps_match(&q, mono_ns(), 1000000000u);
  uint64_t last = atomic_load(&last_pushed);
  assert_true(s == last || (s == 0 && prev == last));
  assert_true(matched > 10);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_newest_before_arrival_within_window),
    cmocka_unit_test(test_overflow_keeps_the_newest), cmocka_unit_test(test_two_threads))
