/*
 * The end-to-end rig shared by test_rig_e2e and bench_e2e: the simulator's
 * room (the e2e tests' seed, size and rate) either as the node's built-in
 * source (vlff-sim into the frame ring, as test_node_e2e), or served by vlff-scenecam through two Aravis fake GigE cameras
 * (colour 127.0.0.1, range 127.0.0.2), paired by the real vlff-camd, posed
 * by the real vlff-pose from TUM lines over UDP, with the sim's features
 * published into the feature ring.
 *
 * The cameras live in a private network namespace: 127.0.0.2 must be an
 * interface address for Aravis' fake camera, and a namespace of its own
 * also keeps the GigE Vision port free of every other test's fake camera.
 * rig_netns_enter() re-executes the program inside one (unshare + ip);
 * programs started afterwards inherit it.
 *
 * The rig runs the shipped tolerances: source.pose_tolerance_s and
 * pose.future_tolerance_s each the smallest of the compiled-in default and
 * configs/default.yaml, aravis-gige.yaml and aravis-rgbd.yaml (a larger
 * tolerance accepts every pose a smaller one accepts),
 * depth_camera.pair_tolerance_s that of configs/aravis-rgbd.yaml, against
 * vlff-scenecam's 30 Hz pose stream (each pose sent at its own stamp).
 *
 * Contract: functions returning int give 0, or -1 with a message in err.
 * rig_stop() ends and reaps every child the rig started; rig_free()
 * removes the rig's files and shared memory. Single-threaded use.
 */
#ifndef VLFF_TEST_RIG_H
#define VLFF_TEST_RIG_H

#include <stddef.h>
#include <stdint.h>
#include <sys/types.h>

#include "config.h"
#include "sim.h"

/* Frames of the room's trajectory (looped by both sources). */
#define RIG_FRAMES 150

struct vlff_node;

struct rig {
  char dir[256], tag[64], cfg_path[320], calib_path[320];
  char camd_out[320], scenecam_out[320], pose_out[320], node_log[320];
  double pose_tol_s, pose_wait_s, future_tol_s, pair_tol_s; /* the shipped tolerances the rig runs */
  int saved_stderr;              /* rig_capture_stderr: the real stderr, else -1 */
  int cameras; /* 1: the camera rig, 0: the node's sim source */
  struct vlff_config cfg;
  struct vlff_sim_points gt;
  pid_t scenecam, camd, pose; /* scenecam: vlff-sim for the sim source */
  double camd_cpu_s; /* vlff-camd's user + system CPU time, after rig_stop */
};

/* Re-executes argv inside a new user + network namespace with loopback up
 * and 127.0.0.2 on it, unless already inside (VLFF_RIG_NETNS set). Returns
 * 1 when inside, 0 when that is impossible here (the caller skips); on
 * success it does not return. */
int rig_netns_enter(int argc, char **argv);

int rig_init(struct rig *r, int cameras, char *err, size_t errlen);
/* Starts vlff-scenecam, vlff-camd and vlff-pose (cameras), or vlff-sim. */
int rig_start(struct rig *r, char *err, size_t errlen);
void rig_stop(struct rig *r);
void rig_free(struct rig *r);

/* 3D mIoU (percent) of the published map at the room's labelled points,
 * read through libvlff-shm; -1 before the first publish. */
double rig_miou3d(const struct rig *r, uint64_t *version);

/* The node's log (this process's stderr) into r->node_log from now on,
 * until rig_release_stderr, which copies what was captured to the real
 * stderr. */
int rig_capture_stderr(struct rig *r, char *err, size_t errlen);
void rig_release_stderr(struct rig *r);

/* Stops the range camera (vlff-scenecam's SIGUSR1) and waits up to
 * timeout_s for the node to say so: its status (what --status shows) with
 * VLFF_NODE_ERR_CAMERA_LOST and no frame rate, and its log (captured) with
 * 'no frame from ring'. Returns the seconds from the range camera's last
 * frame to the later of the two, -1 on timeout (err says which is missing). */
double rig_lose_range_camera(struct rig *r, struct vlff_node *n, double timeout_s, char *err, size_t errlen);

/* The value of key in vlff-camd's stats line (after rig_stop), or -1. */
long long rig_camd_stat(const struct rig *r, const char *key);
/* The number after key (its text up to the number, e.g. "range frames of a
 * skipped colour tick: ") in vlff-scenecam's summary (after rig_stop), or -1. */
long long rig_scenecam_stat(const struct rig *r, const char *key);

#endif
