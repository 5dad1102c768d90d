/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * vlff-merge: a fleet of robots' maps, each received over DDS from its
 * vlff-dds (rt<ns>/vlff/map and rt<ns>/vlff/prompts), placed in one world
 * frame and merged into one map, written into a local map segment (read
 * with libvlff-shm like a node's) and published over DDS as the fleet's
 * rt<fleet ns>/vlff/map (docs/dds.md, "A fleet").
 *
 * Contract
 *  - Each robot has a transform robot map -> world: a rotation and a
 *    translation (vlff's world frame is the robot's first camera frame;
 *    robots on one floor differ by where they started and which way they
 *    faced). Configured ones are a yaw about +z; one a robot publishes on its
 *    tf is a quaternion (merge_main.c chooses which: a configured one wins).
 *  - A robot's cloud is taken only with the layout vlff-dds writes (fields
 *    x y z float32, label uint16, confidence float32 at 0 4 8 12 16,
 *    little-endian, point_step >= 20, data = width * height * point_step, at
 *    most VLFF_MERGE_MAX_POINTS points, finite coordinates, confidence 0..1,
 *    labels within its prompt list); anything else is refused whole, counted
 *    and logged rate-limited. A robot's prompt list is a JSON list checked by
 *    the rule of vlff-shm set-prompts; its cloud waits for its list.
 *  - The fleet's labels are the union of the robots' prompt texts in order of
 *    first appearance (at most VLFF_SHM_MAX_PROMPTS; the texts beyond that
 *    and the points labelled with them are left out and counted, per robot).
 *  - Each world voxel takes the label with the most evidence among the robot
 *    voxel centres falling in it: every point adds its confidence (0..1)
 *    times a recency weight 2^-(age / half_life_s) to its label, age being
 *    how long before the newest point held of any robot the point last
 *    changed (its label or confidence: a whole map that repeats a voxel keeps
 *    its time), and, for a robot whose camera path is known (the poses its
 *    vlff-dds sends), times 1 / (1 + (d / VLFF_MERGE_PATH_NEAR)^2), d the
 *    point's distance from the nearest position of that path. The voxel's confidence is the winner's evidence over the
 *    recency weights of all points there (a disagreeing point counts 0); a
 *    tie goes to the label changed last. A robot's whole map stamped no
 *    earlier than what is held replaces it; an update (map/updates: the same
 *    fields and a uint32 version at 20, point_step >= 24, labels free and
 *    unknown too) stamped later is applied to it, point by point at the same
 *    position (docs/dds.md, "Following the map"); earlier ones are skipped
 *    as held already.
 *  - Voxels outside the configured bounds are left out and counted.
 */
#ifndef VLFF_MERGE_H
#define VLFF_MERGE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "vlff/shm.h"

#define VLFF_MERGE_MAX_ROBOTS 8
#define VLFF_MERGE_MAX_POINTS (16u << 20)
#define VLFF_MERGE_MAX_PATH 1024   /* camera positions kept per robot, VLFF_MERGE_PATH_STEP apart */
#define VLFF_MERGE_PATH_STEP 0.25  /* m */
#define VLFF_MERGE_PATH_NEAR 1.0   /* m: a vote this far from the robot's path counts half */

struct vlff_merge_robot {
  char ns[256];        /* ROS namespace of its vlff-dds */
  double rot[9], t[3]; /* robot map -> world: w = rot * p + t (row-major) */
  /* what was received last */
  int nprompts;        /* -1 until its list came */
  char prompts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
  float *xyz;          /* n points, robot frame */
  uint16_t *label;
  uint8_t *conf;
  int64_t *changed_ns; /* when each point last changed (the stamp that brought it) */
  uint32_t n, cap;     /* points held (a cleared voxel's stays, label VLFF_LABEL_UNKNOWN), room */
  int64_t stamp_ns;    /* the header stamp of its whole map or update held last */
  uint32_t *slot;      /* its points by position (open addressing, UINT32_MAX empty), for updates */
  size_t nslot;
  uint64_t maps, updates, refused;
  uint32_t left_out;   /* bit i: its text i did not fit the fleet's VLFF_SHM_MAX_PROMPTS at the last merge */
  float path[VLFF_MERGE_MAX_PATH][3]; /* where its camera was (robot frame), VLFF_MERGE_PATH_STEP apart */
  uint32_t npath;
  uint64_t path_full;  /* positions not kept: the path was full */
};

struct vlff_merge_grid {
  double origin[3], voxel;
  uint32_t dims[3];
  uint16_t *labels;    /* dims product, VLFF_LABEL_UNKNOWN where no robot saw a label */
  uint8_t *conf;
  double half_life_s;  /* of the recency weight */
  int nprompts;
  char prompts[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
  uint64_t outside, no_label; /* points left out at the last merge: outside the bounds, text beyond the list */
  struct vlff_merge_vote *votes; /* scratch: one per point merged */
  size_t nvotes_cap;
};

struct vlff_merge_vote {
  uint32_t voxel;
  uint16_t label;
  float w;             /* confidence x recency */
  float rec;           /* recency x the path's weight: what a full confidence would add */
  int64_t changed_ns;
};

/* Adds a camera position (robot map frame) to the robot's path: 1 kept, 0
 * within VLFF_MERGE_PATH_STEP of one kept or the path full (counted), -1 not
 * finite. */
int vlff_merge_add_path(struct vlff_merge_robot *r, const double p[3]);

/* rot from a yaw about +z (radians), the configured transforms' form. */
void vlff_merge_yaw(double rot[9], double yaw);

/* rot from a unit quaternion (x y z w, ROS's order); 0, or -1 with why when
 * it is not finite or its norm is not within 1 +- 0.01. */
int vlff_merge_quat(double rot[9], const double q[4], char *why, size_t whylen);

/* A grid over [lo, hi) at voxel size, recency half-life half_life_s (> 0):
 * 0, or -1 with why (too large, bad bounds). */
int vlff_merge_grid_init(struct vlff_merge_grid *g, const double lo[3], const double hi[3], double voxel,
                         double half_life_s, char *why, size_t whylen);
void vlff_merge_grid_free(struct vlff_merge_grid *g);

/* Takes a robot's PointCloud2 fields as received; 0, or -1 with why (the
 * cloud refused whole, the robot's previous one kept). */
int vlff_merge_take_cloud(struct vlff_merge_robot *r, uint32_t width, uint32_t height, uint32_t point_step,
                          bool bigendian, const char *const names[], const uint32_t offsets[], const uint8_t types[],
                          uint32_t nfields, const uint8_t *data, size_t len, int64_t stamp_ns, char *why,
                          size_t whylen);

/* Applies a robot's update as received: 1 applied, 0 skipped (no whole map
 * held yet, or stamped no later than what is held), or -1 with why (refused
 * whole, nothing changed). */
int vlff_merge_take_update(struct vlff_merge_robot *r, uint32_t width, uint32_t height, uint32_t point_step,
                           bool bigendian, const char *const names[], const uint32_t offsets[], const uint8_t types[],
                           uint32_t nfields, const uint8_t *data, size_t len, int64_t stamp_ns, char *why,
                           size_t whylen);

/* Recomputes the fleet grid from every robot holding both a map and a prompt
 * list. Returns the number of labelled voxels, or -1 without memory for the
 * votes (the grid then holds no label). */
long vlff_merge_compute(struct vlff_merge_grid *g, struct vlff_merge_robot *robots, int nrobots);

void vlff_merge_robot_free(struct vlff_merge_robot *r);

#endif
