/*
 * The node's CPU budget (node.cpu_budget, in cores, fractional): kept by the
 * node's own threads rather than by a cgroup the user must set up, so a
 * robot's localisation, planning and control keep the rest of the machine.
 *
 * Two parts:
 *  - vlff_budget_threads: the learner's worker pool gets at most
 *    ceil(budget) threads, so no more cores than that ever run the field at
 *    once.
 *  - struct vlff_pacer: a token bucket over the whole process's CPU time
 *    (CLOCK_PROCESS_CPUTIME_ID: ingest, the trainer and its pool, the
 *    publisher, encoders). Each call adds the CPU time used since the last
 *    call and takes away budget x the wall time gone by; what is left over
 *    is the debt. While in debt, the caller (the trainer, before a training
 *    step) sleeps until budget x sleep repays it, at most max_sleep_s at a
 *    time, so its loop keeps beating, publishing and taking commands.
 *    Training is the only work the pacer delays: everything else the node
 *    does is paid for by fewer steps. Credit saved while idle is capped at
 *    PACER_CREDIT_S of budget, so use stays at the budget over any window of
 *    a second or so, not only on average over the run. Debt is capped at
 *    PACER_DEBT_S of budget: a burst of other work (a checkpoint, a large
 *    publish) is repaid in full up to that, and delays training by at most
 *    that long; beyond it (threads other than training alone over the
 *    budget for seconds) the excess is forgiven rather than stalling
 *    training for as long again once they calm down. Whatever the debt, a
 *    step is allowed at least every PACER_DEBT_S: when the node's other work
 *    alone takes more than the budget, training goes on slowly rather than
 *    never (the status and a warning say the budget is exceeded).
 *  - The pacer also measures the process's use in cores, with or without a
 *    budget, for the status: each PACER_WINDOW_S or so, over the last
 *    PACER_WINDOWS windows. One second alone swings with each keyframe
 *    publish (a controller, and the budget's own warning, want the use, not
 *    its bursts).
 *
 * Thread: a pacer belongs to the one thread that calls vlff_pacer_pace.
 */
#ifndef VLFF_BUDGET_H
#define VLFF_BUDGET_H

#include <stdbool.h>

#define PACER_CREDIT_S 0.1
#define PACER_DEBT_S 5.0
#define PACER_WINDOW_S 1.0
#define PACER_WINDOWS 3

/* Worker threads for a field under a budget: threads as node.threads (0 =
 * one per online core), then at most ceil(budget) when budget > 0. At
 * least 1. */
int vlff_budget_threads(double budget, int threads);

struct vlff_pacer {
  double budget;         /* cores; 0 = measure only */
  double wall, cpu;      /* seconds at the last call (monotonic, process CPU) */
  double debt;           /* CPU seconds used beyond budget x wall time; negative = credit */
  /* the last PACER_WINDOWS + 1 window boundaries (monotonic, process CPU), oldest first */
  double win_wall[PACER_WINDOWS + 1], win_cpu[PACER_WINDOWS + 1];
  int wins;              /* boundaries held */
  double used;           /* cores used over the windows held; -1 before the first ends */
  double slept_s;        /* seconds slept in total, for the tests and the log */
  double last_step;      /* monotonic seconds of the last step allowed */
};

void vlff_pacer_init(struct vlff_pacer *p, double budget);

/* Accounts the CPU time used since the last call. With a budget and
 * want_step, sleeps while in debt, at most max_sleep_s. Returns true when a
 * training step may run now: no budget, or the debt is repaid by the sleep
 * (false: more sleep is needed; call again on the next loop pass). *used is
 * set, when a window has just ended, to the cores used over the last
 * PACER_WINDOWS windows (fewer at first), else to -1. */
bool vlff_pacer_pace(struct vlff_pacer *p, bool want_step, double max_sleep_s, double *used);

/* The process's CPU time in seconds (all threads). */
double vlff_process_cpu_s(void);

#endif
