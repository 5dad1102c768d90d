/*
 * What the process-level tests of the node share: a scratch directory and a
 * segment-name tag per test process, the build's programs as children
 * (killed at teardown, also after a failed assertion), waits on text in a
 * log, the published map's 3D mIoU read as a controller reads it, and a node
 * created with the simulator's source hooks.
 *
 * Contract: one struct tk per test program, set up before its tests and torn
 * down after; not thread-safe (cmocka runs tests one at a time).
 */
#ifndef VLFF_TESTKIT_H
#define VLFF_TESTKIT_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <sys/types.h>

#include "config.h"
#include "node.h"
#include "sim.h"
#include "sim_source.h"

#define TK_CHILDREN 8

struct tk {
  char tag[48];  /* "<prefix><pid>": every segment of the test is "/<tag>-..." */
  char dir[128]; /* /tmp/vlff-<tag> */
  pid_t children[TK_CHILDREN];
  int nchildren;
  double scale;  /* $VLFF_E2E_SCALE (sanitizer builds run slower): timeouts, never thresholds */
  char shm_names[384];
  char cfg_path[160];
};

/* $VLFF_E2E_SCALE, 1 when unset or not positive. */
double tk_time_scale(void);
/* Names the test's tag, creates its directory, reads the time scale. */
void tk_setup(struct tk *t, const char *prefix);
/* Kills the children left, removes the directory and every /dev/shm/<tag>-*
 * segment. 0, or -1 when something could not be removed. */
int tk_teardown(struct tk *t);

/* The five keys of a shm: section that name the test's segments, each an
 * indented line: ring /<tag>-f, map -m, prompts -p, pose_ring -q and
 * feature_ring -x. The text lives in t. */
const char *tk_shm_names(struct tk *t);
/* Writes the config fmt (printf-style) as <dir>/node.yaml and loads it into
 * cfg; a load error fails the test. Returns the file's path (in t). */
const char *tk_config(struct tk *t, struct vlff_config *cfg, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));

/* Starts a program of the build (relative to $VLFF_BINARY_DIR) with args
 * (NULL-terminated), stdout and stderr into out (NULL: inherited). */
pid_t tk_spawn(struct tk *t, const char *prog, const char *const *args, const char *out);
/* Waits for the child: its exit status, or 128 + the signal that ended it. */
int tk_wait_child(struct tk *t, pid_t pid);
/* Sends sig and reaps the child. */
void tk_stop_child(struct tk *t, pid_t pid, int sig);

void tk_sleep_s(double s);
/* The file's first MiB as text ("" when it cannot be read); the buffer is
 * reused by the next call. */
const char *tk_slurp(const char *path);
/* Polls path every 0.1 s until it holds text; false at the timeout. */
bool tk_wait_for_text(const char *path, const char *text, double timeout_s);

/* 3D mIoU (percent) of the published map at the scene's labelled points,
 * read through libvlff-shm as a controller would; -1 before the first
 * publish. version and prompt_count may be NULL. */
double tk_map_miou3d(const char *map, const struct vlff_sim_points *gt, uint64_t *version, int *prompt_count);

/* Polls the map's 3D mIoU every 2 s until it reaches want or timeout_s
 * passed; the best seen, -1 when no map was published. */
double tk_wait_miou3d(const char *map, const struct vlff_sim_points *gt, double want, double timeout_s,
                      uint64_t *version);
/* Prints the node's status beside the map's quality after t seconds. */
void tk_report(struct vlff_node *n, double t, double best, uint64_t version, struct vlff_node_status *st);

/* The synthetic scene and a frame ring of slots records of up to w x h
 * (RGB8 + 16-bit depth) on cfg's shm.ring, written as a camera driver
 * would. */
struct tk_scene {
  struct vlff_sim *sim;
  struct vlff_sim_frame *frame;
  struct vlff_ring *ring;
};
void tk_scene_open(struct tk_scene *sc, const struct vlff_config *cfg, int slots, int w, int h);
void tk_scene_close(struct tk_scene *sc);
/* The ring's next slot laid out as a w x h frame of RGB8 and depth_format
 * (VLFF_PIX_DEPTH_U16_MM or VLFF_PIX_NONE), frame id stamped t_ns with f's
 * intrinsics and pose, both flagged valid; the pixels are left to the
 * caller. *len is what vlff_ring_commit takes. */
struct vlff_frame_hdr *tk_frame_reserve(struct vlff_ring *ring, const struct vlff_sim_frame *f, long long id,
                                        uint64_t t_ns, int w, int h, int depth_format, uint64_t *len);

/* vlff_node_create with the simulator's hooks when cfg uses them; *src is
 * destroyed by the caller after the node (tk_node_destroy does both). A node
 * a failed test leaves behind is destroyed by tk_teardown. */
struct vlff_node *tk_node_create(const struct vlff_config *cfg, struct vlff_sim_source **src, char *err,
                                 size_t errlen);
void tk_node_destroy(struct vlff_node *n, struct vlff_sim_source *src);

/* tk_scene_open, then a node on cfg (tk_node_create: an error fails the
 * test), given half a second for its ingest thread to attach to the ring. */
struct vlff_node *tk_scene_node(struct tk_scene *sc, const struct vlff_config *cfg, int slots, int w, int h,
                                struct vlff_sim_source **src);

#endif
