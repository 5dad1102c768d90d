/* The map refresh's schedule (refresh.h) on a virtual clock: a trainer loop
 * whose passes cost what its steps cost and whose slices cost their share of
 * a whole round. Rounds end every period whatever the step costs, one rare
 * long pass (a checkpoint) included; a round too costly for its share of the
 * trainer stretches the period instead; slices are never slivers. Before the
 * schedule, fixed slices on a timer lost up to a step each: rounds came
 * every 1.23 s at 1 Hz on the flat. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include "refresh.h"
#include "unit.h"

struct run {
  double max_slice; /* the largest slice */
  double mean;      /* mean time between rounds' ends, the first few left out */
  double worst;     /* the longest of those */
  double share;     /* the refresh's share of the time */
  double min_slice; /* the smallest slice but a round's last */
  int rounds;
};

/* Passes cost steps[i % nsteps] each; a whole round of slices costs `round`
 * seconds. The first publish is whole (the first map). */
static struct run simulate(double period, double round, const double *steps, int nsteps, int rounds) {
  struct vlff_refresh rf;
  vlff_refresh_init(&rf, period);
  struct run r = {.min_slice = 1};
  double t = 0, done = 0, last = -1, sum = 0, sliced = 0, t_from = -1;
  int counted = 0, ended = 0;
  for (long i = 0; ended < rounds && i < 10000000; i++) {
    vlff_refresh_pass(&rf, t);
    t += steps[i % nsteps];
    double to = vlff_refresh_due(&rf, t, done);
    if (to < 0) continue;
    const bool whole = rf.start < 0;
    double b = whole ? 1 : fmin(1, to), cost = (whole ? 1 : b - done) * round;
    if (!whole && b < 1 && b - done < r.min_slice) r.min_slice = b - done;
    if (!whole && b - done > r.max_slice) r.max_slice = b - done;
    t += cost;
    vlff_refresh_sliced(&rf, cost);
    if (ended >= 3) sliced += cost;
    done = b;
    if (b < 1) continue;
    vlff_refresh_round_end(&rf, t, !whole, whole);
    done = 0;
    ended++;
    if (ended == 3) t_from = t;
    if (ended > 3) {
      double gap = t - last;
      sum += gap, counted++;
      if (gap > r.worst) r.worst = gap;
    }
    last = t;
  }
  r.mean = counted ? sum / counted : -1;
  r.share = sliced / (t - t_from);
  r.rounds = counted;
  return r;
}

static void test_on_time_whatever_a_step_costs(void **state) {
  (void)state;
  const double steps[][1] = {{0.01}, {0.05}, {0.15}, {0.4}};
  for (int k = 0; k < 4; k++) {
    struct run r = simulate(1.0, 0.2, steps[k], 1, 60);
    print_message("step %.2f s: a round every %.3f s (worst %.3f), refresh share %.2f, smallest slice %.3f\n",
                  steps[k][0], r.mean, r.worst, r.share, r.min_slice);
    assert_int_equal(r.rounds, 57);
    assert_true(fabs(r.mean - 1.0) < 0.02);
    assert_true(r.worst < 1.0 + steps[k][0] + 0.2 + 1e-9); /* at most a pass and the round's cost late */
    assert_true(r.min_slice >= VLFF_REFRESH_MIN_SLICE - 1e-9);
  }
  /* Steps of every cost in turn, and at 2 Hz. */
  const double mixed[] = {0.02, 0.3, 0.05, 0.12, 0.02, 0.2};
  struct run r = simulate(0.5, 0.1, mixed, 6, 60);
  print_message("mixed steps at 2 Hz: a round every %.3f s (worst %.3f)\n", r.mean, r.worst);
  assert_true(fabs(r.mean - 0.5) < 0.01);
}

/* A checkpoint's pass of 1.5 s every 30 s (500 passes of 0.06 s): that
 * round is late, the next one makes up half a period of it on the same
 * deadlines, and no slice after it takes the whole rest of the grid because
 * of it. */
static double steps_ckpt[500];
static void test_long_pass(void **state) {
  (void)state;
  for (int i = 0; i < 500; i++) steps_ckpt[i] = i == 250 ? 1.5 : 0.06;
  struct run r = simulate(1.0, 0.2, steps_ckpt, 500, 240);
  print_message("a 1.5-s pass every 30 s: a round every %.3f s (worst %.3f), slices %.3f to %.3f\n", r.mean, r.worst,
                r.min_slice, r.max_slice);
  assert_true(fabs(r.mean - 1.0) < 0.03);
  assert_true(r.worst < 2.8);
  assert_true(r.min_slice >= VLFF_REFRESH_MIN_SLICE - 1e-9);
  assert_true(r.max_slice <= VLFF_REFRESH_MAX_SLICE + 1e-9); /* caught up over several passes */
}

/* A round that costs more than VLFF_REFRESH_SHARE of the period: the
 * period stretches so the refresh keeps to its share, and training goes
 * on. */
static void test_costly_round_stretches(void **state) {
  (void)state;
  const double step[] = {0.05};
  struct run r = simulate(1.0, 0.8, step, 1, 30);
  print_message("a round costing 0.8 s at 1 Hz: every %.3f s, refresh share %.2f\n", r.mean, r.share);
  assert_true(r.mean >= 0.8 / VLFF_REFRESH_SHARE - 0.05);
  assert_true(r.share <= VLFF_REFRESH_SHARE + 0.02);
}

/* The first map is whole; a whole publish out of turn restarts the grid of
 * deadlines; nothing is due before a slice's worth of the period passed. */
static void test_rounds_start(void **state) {
  (void)state;
  struct vlff_refresh rf;
  vlff_refresh_init(&rf, 1.0);
  assert_true(vlff_refresh_due(&rf, 5, 0) == 1);
  vlff_refresh_pass(&rf, 5);
  assert_true(vlff_refresh_round_end(&rf, 5.2, false, true) < 0); /* nothing counted yet */
  assert_true(vlff_refresh_due(&rf, 5.2, 0) < 0);
  assert_true(fabs(vlff_refresh_due(&rf, 5.2 + 0.5, 0.3) - 0.5) < 1e-9);
  assert_true(fabs(vlff_refresh_due(&rf, 5.2 + 0.5, 0) - VLFF_REFRESH_MAX_SLICE) < 1e-9); /* behind: a bounded slice */
  assert_true(vlff_refresh_due(&rf, 6.2, 0.9) == 1);
  vlff_refresh_sliced(&rf, 0.1);
  assert_true(fabs(vlff_refresh_round_end(&rf, 6.25, true, false) - 1.05) < 1e-9);
  /* The next deadline is 7.2, on the grid, not 7.25. */
  assert_true(vlff_refresh_due(&rf, 7.2, 0.8) == 1);
  assert_true(vlff_refresh_due(&rf, 7.1, 0.5) < 1);
  /* New prompts: a whole publish at 6.5 restarts the grid from there. */
  vlff_refresh_round_end(&rf, 6.5, false, true);
  assert_true(vlff_refresh_due(&rf, 7.2, 0) < 1);
  assert_true(vlff_refresh_due(&rf, 7.5, 0.9) == 1);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_on_time_whatever_a_step_costs), cmocka_unit_test(test_long_pass),
               cmocka_unit_test(test_costly_round_stretches), cmocka_unit_test(test_rounds_start))
