/*
 * The one monotonic clock of the node, the drivers and the tools:
 * CLOCK_MONOTONIC, the clock the shared-memory records' host stamps use
 * (libvlff-shm, which controllers link on its own, reads the same clock as
 * vlff_shm_now_ns; code in this tree calls vlff_now_ns). Also their one
 * wall-clock reader. Thread-safe, async-signal-safe.
 */
#ifndef VLFF_CLOCK_H
#define VLFF_CLOCK_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Nanoseconds since an arbitrary start (boot). */
uint64_t vlff_now_ns(void);
/* The same in seconds, for durations and rates. */
double vlff_seconds(void);
/* Wall-clock (CLOCK_REALTIME) nanoseconds since the UNIX epoch: for stamps
 * that leave the machine (Foxglove, PTP-stamped cameras) and absolute
 * deadlines of pthread_cond_timedwait; never for durations. */
uint64_t vlff_wall_ns(void);
/* CLOCK_MONOTONIC minus CLOCK_REALTIME now, ns: the wall clock read between
 * two monotonic reads, the tightest of a few tries kept, so that a thread
 * preempted between two reads does not skew the offset by as long as it
 * waited. For moving UNIX-time stamps onto vlff_now_ns's clock. */
int64_t vlff_mono_minus_wall_ns(void);

#ifdef __cplusplus
}
#endif

#endif
