/*
 * The one monotonic clock of the node, the drivers and the tools:
 * CLOCK_MONOTONIC, the clock the shared-memory records' host stamps use
 * (libvlff-shm, which controllers link on its own, reads the same clock as
 * vlff_shm_now_ns). Thread-safe, async-signal-safe.
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

#ifdef __cplusplus
}
#endif

#endif
