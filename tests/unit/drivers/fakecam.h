/*
 * Test helper: runs Aravis' fake GigE Vision camera (arv-fake-gv-camera-0.8)
 * on 127.0.0.1 as a child process. It can only listen on 127.0.0.1:3956, so
 * one runs at a time machine-wide: start() takes an exclusive flock on a
 * lock file held until stop(). The child dies with the test (PDEATHSIG).
 */
#ifndef VLFF_TEST_FAKECAM_H
#define VLFF_TEST_FAKECAM_H

#include <sys/types.h>

/* Takes the lock (waits for it) unless already held, then starts the camera
 * and waits until it answers. lost_per_thousand: GVSP packets it drops.
 * Returns the child's pid, or -1. */
pid_t fakecam_start(int lost_per_thousand);
/* Kills the camera (SIGKILL: like a camera losing power); keeps the lock. */
void fakecam_kill(pid_t pid);
/* Kills it if running and releases the lock. */
void fakecam_stop(pid_t pid);

#endif
