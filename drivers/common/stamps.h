/*
 * Trigger timestamps from another thread (GPIO pulses or edges) matched to
 * frames: a single-producer single-consumer queue of CLOCK_MONOTONIC ns.
 *
 * Contract
 *  - vlff_stamps_push() from exactly one producer thread, vlff_stamps_match()
 *    from exactly one consumer thread; lock-free (C11 acquire/release).
 *  - A full queue drops the oldest unconsumed stamp on the consumer side:
 *    the producer never waits.
 *  - vlff_stamps_match(q, arrival, window) consumes every stamp <= arrival
 *    and returns the newest of them if it is within window_ns before
 *    arrival (the trigger that exposed this frame), else 0.
 */
#ifndef VLFF_STAMPS_H
#define VLFF_STAMPS_H

#include <stdatomic.h>
#include <stdint.h>

#define VLFF_STAMPS_CAP 256

struct vlff_stamps {
  _Atomic uint64_t head, tail;
  _Atomic uint64_t t[VLFF_STAMPS_CAP];
};

void vlff_stamps_init(struct vlff_stamps *q);
void vlff_stamps_push(struct vlff_stamps *q, uint64_t t_ns);
uint64_t vlff_stamps_match(struct vlff_stamps *q, uint64_t arrival_ns, uint64_t window_ns);

#endif
