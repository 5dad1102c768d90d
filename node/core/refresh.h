/*
 * The whole-map refresh's schedule (docs/node.md, "Publishing"): when the
 * trainer publishes the next slice of its round-robin refresh, and how much
 * of the grid it covers, so that rounds end every 1 / publish.rate_hz
 * whatever a training step costs.
 *
 * Why: a slice can only run between the trainer's steps. Fixed slices on a
 * fixed timer lost up to a step each, and rounds came late by that much; here
 * each pass of the loop refreshes what keeps the round on a
 * straight line from its start to its deadline one pass ahead, and the pass
 * before the deadline refreshes the rest.
 *
 * Rules:
 *  - a pass's time is the third quartile of the last VLFF_REFRESH_PASSES
 *    passes (their slices left out): a slower step shows at once, one rare
 *    long pass (a checkpoint) does not make the next slices refresh
 *    everything;
 *  - a slice covers at least VLFF_REFRESH_MIN_SLICE of the grid (the last
 *    excepted), or a fast loop would publish a sliver every pass, each a map
 *    version; and at most VLFF_REFRESH_MAX_SLICE of it, or two passes'
 *    worth when passes are longer than that allows: a round behind its plan
 *    (after a long pass) catches up over several passes, not in one slice
 *    that a keyframe arriving meanwhile would wait for;
 *  - rounds end on a grid of deadlines one period apart: the next round
 *    starts at this one's deadline, so a late round is made up by a shorter
 *    next one, by at most half a period (deadlines missed by more are given
 *    up, never caught up in a burst of rounds); a whole publish out of turn
 *    (new prompts, a reset, the first map) starts the grid over from it;
 *  - a round may take at most `share` of the trainer's time
 *    (VLFF_REFRESH_SHARE, less under a CPU budget: the caller lowers it):
 *    one that cost more (a map too large for the machine) stretches the
 *    next round's period to its cost over that share.
 *
 * Contract: pure arithmetic on the times it is given (seconds, any
 * monotonic origin); one owner (the trainer thread).
 */
#ifndef VLFF_REFRESH_H
#define VLFF_REFRESH_H

#include <stdbool.h>

#define VLFF_REFRESH_PASSES 8
#define VLFF_REFRESH_WINDOW 8 /* rounds the mean interval is taken over */
#define VLFF_REFRESH_MIN_SLICE (1.0 / 32)
#define VLFF_REFRESH_MAX_SLICE 0.25
#define VLFF_REFRESH_SHARE 0.7
/* Under node.cpu_budget below a core, the share is this times the budget:
 * publishing runs outside the pacer, and at 0.7 x 0.5 the refresh plus the
 * keyframes' sixth alone would pass a budget of half a core. */
#define VLFF_REFRESH_SHARE_BUDGETED 0.5

struct vlff_refresh {
  double period;   /* 1 / publish.rate_hz */
  double span;     /* this round's length: the period, or longer (share) */
  double share;    /* most of the trainer's time a round may take (0, 1]; VLFF_REFRESH_SHARE at init */
  double start;    /* when this round began (its deadline is start + span); < 0 before the first round */
  double cost;     /* seconds this round's slices took so far */
  double pass;     /* a loop pass without its slices, as the rules take it */
  double passes[VLFF_REFRESH_PASSES];
  int npass;
  double top;      /* when the current pass began, < 0 before the first */
  double sliced;   /* seconds of slices in the current pass */
  double last_end; /* when the last round ended, < 0 before the first */
  double ring[VLFF_REFRESH_WINDOW];
  int count;
};

/* period > 0: seconds between rounds' ends. */
void vlff_refresh_init(struct vlff_refresh *rf, double period);
/* A pass of the trainer's loop begins at now. */
void vlff_refresh_pass(struct vlff_refresh *rf, double now);
/* Where a slice published now should end, as a fraction of the grid (1: the
 * rest, ending the round), given the fraction `done` the round has
 * refreshed; -1 when none is due yet. Before the first round: 1 (the first
 * map is whole). */
double vlff_refresh_due(const struct vlff_refresh *rf, double now, double done);
/* A slice (or a whole publish) took `seconds` of the current pass. */
void vlff_refresh_sliced(struct vlff_refresh *rf, double seconds);
/* A round ended at `end`: by its last slice (whole false) or by a whole
 * publish (whole true, which restarts the grid of deadlines from it). The
 * mean time between the last VLFF_REFRESH_WINDOW counted rounds' ends
 * (counted: the time from the previous round's end to this one's is a
 * refresh interval), or -1 while there is none. */
double vlff_refresh_round_end(struct vlff_refresh *rf, double end, bool counted, bool whole);

#endif
