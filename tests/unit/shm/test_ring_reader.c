/*
 * vlff_ring_wait_reader: a producer that paces itself by its consumer sees
 * the consumer only once it has read everything, never while it lags, and
 * times out when nobody reads.
 */
#include <errno.h>
#include <pthread.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stdatomic.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <time.h>
#include <unistd.h>
#include <cmocka.h>

#include "unit.h"
#include "vlff/shm.h"

static char name[64];
static atomic_int consumed, go;
static atomic_int hold; /* the consumer stalls before each read while set */

static void *consumer(void *arg) {
  (void)arg;
  struct vlff_ring *c = vlff_ring_attach(name, VLFF_RECORD_RAW);
  atomic_store(&go, 1);
  if (!c) return NULL;
  for (;;) {
    while (atomic_load(&hold)) usleep(1000);
    uint64_t v;
    ssize_t n = vlff_ring_read_copy(c, &v, sizeof v, NULL, 100 * 1000 * 1000ull);
    if (n == (ssize_t)sizeof v) {
      atomic_fetch_add(&consumed, 1);
      if (v == UINT64_MAX) break;
    }
  }
  vlff_ring_close(c);
  return NULL;
}

static void test_waits_for_the_reader(void **state) {
  (void)state;
  snprintf(name, sizeof name, "/vlff-test-rr-%d", (int)getpid());
  vlff_shm_unlink(name);
  struct vlff_ring_params rp = {VLFF_RECORD_RAW, 4, 64, {0600, NULL}};
  struct vlff_ring *p = vlff_ring_create(name, &rp);
  assert_non_null(p);
  /* Nobody attached: the wait times out and says so. */
  assert_int_equal(vlff_ring_wait_reader(p, 20 * 1000 * 1000ull), -1);
  assert_int_equal(errno, ETIMEDOUT);

  pthread_t th;
  assert_int_equal(pthread_create(&th, NULL, consumer, NULL), 0);
  while (!atomic_load(&go)) usleep(1000);
  /* Paced by the reader, 200 records through 4 slots lose none. */
  for (uint64_t i = 0; i < 200; i++) {
    assert_int_equal(vlff_ring_wait_reader(p, 5ull * 1000 * 1000 * 1000), 0);
    assert_true(atomic_load(&consumed) == (int)i);
    assert_int_equal(vlff_ring_write(p, &i, sizeof i), 0);
  }
  /* A consumer busy elsewhere (not reading) is not caught up. */
  assert_int_equal(vlff_ring_wait_reader(p, 5ull * 1000 * 1000 * 1000), 0);
  atomic_store(&hold, 1);
  uint64_t x = 7;
  assert_int_equal(vlff_ring_write(p, &x, sizeof x), 0);
  usleep(20 * 1000);
  assert_int_equal(vlff_ring_wait_reader(p, 50 * 1000 * 1000ull), -1);
  assert_int_equal(errno, ETIMEDOUT);
  atomic_store(&hold, 0);
  assert_int_equal(vlff_ring_wait_reader(p, 5ull * 1000 * 1000 * 1000), 0);
  assert_int_equal(atomic_load(&consumed), 201);
  uint64_t end = UINT64_MAX;
  assert_int_equal(vlff_ring_write(p, &end, sizeof end), 0);
  pthread_join(th, NULL);
  assert_int_equal(atomic_load(&consumed), 202);

  /* Only a producer handle may wait. */
  struct vlff_ring *c = vlff_ring_attach(name, VLFF_RECORD_RAW);
  assert_non_null(c);
  assert_int_equal(vlff_ring_wait_reader(c, 0), -1);
  assert_int_equal(errno, EINVAL);
  vlff_ring_close(c);
  vlff_ring_close(p);
  vlff_shm_unlink(name);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_waits_for_the_reader))
