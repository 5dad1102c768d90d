/* The clocks (clock.h): the offset between CLOCK_MONOTONIC and UNIX time
 * that moves wall-clock stamps (vlff-pose --clock realtime, Aravis's
 * arrival stamps) onto the node's clock. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include "clock.h"

/* The offset lies between what two monotonic reads around one wall read
 * give, give or take the wall clock's slewing over the test. */
static void test_offset_matches_the_clocks(void **state) {
  (void)state;
  for (int i = 0; i < 100; i++) {
    const int64_t off = vlff_mono_minus_wall_ns();
    const uint64_t m0 = vlff_now_ns(), r = vlff_wall_ns(), m1 = vlff_now_ns();
    const int64_t lo = (int64_t)m0 - (int64_t)r, hi = (int64_t)m1 - (int64_t)r;
    if (off < lo - 1000000 || off > hi + 1000000)
      fail_msg("offset %lld ns, the clocks read [%lld, %lld] ns", (long long)off, (long long)lo, (long long)hi);
  }
}

/* Many reads agree within a millisecond: one read's bracket preempted
 * (a timeslice, milliseconds) is not the one kept while a tighter try
 * follows it. */
static void test_offset_is_steady(void **state) {
  (void)state;
  int64_t lo = INT64_MAX, hi = INT64_MIN;
  for (int i = 0; i < 20000; i++) {
    const int64_t off = vlff_mono_minus_wall_ns();
    lo = off < lo ? off : lo, hi = off > hi ? off : hi;
  }
  if (hi - lo > 1000000) fail_msg("offsets spread over %lld ns", (long long)(hi - lo));
}

int main(void) {
  const struct CMUnitTest tests[] = {
      cmocka_unit_test(test_offset_matches_the_clocks),
      cmocka_unit_test(test_offset_is_steady),
  };
  return cmocka_run_group_tests(tests, NULL, NULL);
}
