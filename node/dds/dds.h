/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * vlff-dds: the bridge from the node's map segment and prompt mailbox to DDS
 * (Eclipse Cyclone DDS), with ROS 2's wire conventions, so that a ROS 2 node
 * on rmw_cyclonedds, or any DDS program built on idl/, reads vlff's map and
 * status and posts prompt sets without vlff code (docs/dds.md).
 *
 * Contract
 *  - Topics are "rt" + dds.namespace + "/vlff/" + leaf: ROS 2's
 *    "/<ns>/vlff/map" on the wire; the camera pose goes to "rt<ns>/tf"
 *    (ROS's /tf, namespaced as a robot's tf is remapped). Type names are
 *    ROS 2's "<pkg>::msg::dds_::<Type>_" (the files in idl/), CDR (XCDR1,
 *    final), as rmw_cyclonedds writes them. Each topic is switched and given
 *    its QoS (reliability, durability, keep-last depth) by the config
 *    (dds.<name>, dds.qos.<name>.*); the defaults are below.
 *  - map: sensor_msgs/PointCloud2, one point per labelled voxel (label
 *    0..VLFF_LABEL_MAX; free and unknown voxels are left out) at the voxel's
 *    centre in the map's world frame, fields x y z (float32) label (uint16)
 *    confidence (float32, 0..1), little-endian, point_step 20, height 1.
 *    Reliable, transient local, keep last 1: a reader joining late gets the
 *    latest whole map. Sent only when a subscriber could not follow the
 *    updates otherwise: the first version the bridge reads, a whole copy of
 *    the segment (a restarted writer, a change log the bridge fell behind,
 *    a new geometry), a new prompt list, more updates since the last whole
 *    map than dds.qos.map_updates.depth (when that history is transient
 *    local: a late joiner needs them all), and every dds.map_full_period_s
 *    while the map changes; never while nothing changed. With map_updates
 *    off, once per version that changed what subscribers see.
 *  - map_updates ("map/updates"): sensor_msgs/PointCloud2 of the voxels a
 *    map version changed as a subscriber sees them (the label, or a
 *    labelled voxel's confidence), read from the segment's change log
 *    (vlff_map_snapshot_follow) against what was sent: the map's fields,
 *    free (65534) and unknown (65535) voxels included so that subscribers
 *    clear them, and "version" (uint32 at 20, the low 32 bits of the map
 *    version the update brings a subscriber to), point_step 24. Reliable,
 *    transient local, keep last 200: a late joiner applies the updates
 *    stamped later than the whole map it got. An update of more than
 *    opts.update_points_max points (its share of dds.history_max_mb) is
 *    not sent: the whole map goes instead, so the updates' history holds at
 *    most depth x that many points.
 *    Stamps: a version's whole map and update carry the same header stamp,
 *    its publish time in system time, fixed when the bridge reads it and
 *    increasing from version to version.
 *  - prompts: std_msgs/String, the map's prompt list as a JSON list (label
 *    i is element i), sent when it changes; reliable, transient local, keep
 *    last 1 (ROS's latched topic).
 *  - label_image: sensor_msgs/Image "mono16", the map's 2D label image
 *    (label per pixel, 65534 free, 65535 unknown), frame dds.camera_frame_id,
 *    stamped with the frame it was rendered for; label_image/compressed:
 *    the same as a PNG in the label palette (off by default). At most
 *    dds.image_hz a second, once per new label image.
 *  - camera/image_raw: sensor_msgs/Image of the frame ring's newest frame
 *    (encoding rgb8, bgr8, mono8, mono16 or bayer_*8, step the ring's
 *    stride), camera/image_raw/compressed a JPEG of it (off by default),
 *    camera/camera_info its pinhole intrinsics (plumb_bob, no distortion:
 *    ring frames are undistorted), at most dds.image_hz a second.
 *  - tf: tf2_msgs/TFMessage, the camera pose dds.frame_id -> 
 *    dds.camera_frame_id (an optical frame: x right, y down, z forward), from
 *    the frames when they carry a pose, else from the label image's view.
 *  - status: diagnostic_msgs/DiagnosticArray at dds.status_hz, two entries:
 *    "vlff: learner" (the segment's status, level OK/WARN/ERROR, STALE
 *    when the writer is gone) and "vlff-dds: bridge" (the bridge's counts).
 *  - prompts_in: std_msgs/String whose data is a JSON list of prompt texts,
 *    or a JSON integer, the index of a configured prompt set.
 *    A message longer than dds.max_prompt_bytes, not a JSON list of
 *    strings, refused by vlff_prompt_check() (the rule of vlff-shm
 *    set-prompts), a valid set coming sooner than 1/dds.prompt_rate_hz after
 *    the last one posted (a flood), or one the mailbox cannot take now (the
 *    previous request unanswered, no mailbox) is refused, counted by kind
 *    and logged through vlff_warn_limited; only a checked set is posted,
 *    with vlff_prompts_try_post (never waits on the learner). The reader
 *    keeps dds.qos.prompts_in.depth messages: a flood beyond that is
 *    dropped by DDS before the bridge sees it.
 *  - Writers keep last N: a subscriber that never reads never blocks the
 *    bridge (a reliable writer with a keep-last history drops the oldest).
 *  - The node may start, stop and restart under a running bridge: segments
 *    are attached when they appear and again after they are replaced; a
 *    restarted bridge sends the current map, prompt list and images anew.
 *  - Single-threaded, and one struct vlff_dds per process (the status is
 *    built in static storage).
 */
#ifndef VLFF_DDS_H
#define VLFF_DDS_H

#include <stddef.h>
#include <stdint.h>

#include "config.h"
#include "vlff/shm.h"

/* PointField datatypes and DiagnosticStatus levels (the ROS 2 constants). */
enum { VLFF_DDS_UINT16 = 4, VLFF_DDS_UINT32 = 6, VLFF_DDS_FLOAT32 = 7 };
enum { VLFF_DDS_OK = 0, VLFF_DDS_WARN = 1, VLFF_DDS_ERROR = 2, VLFF_DDS_STALE = 3 };
#define VLFF_DDS_POINT_STEP 20u  /* map */
#define VLFF_DDS_UPDATE_STEP 24u /* map/updates: a map point, then its version */

/* What the bridge reads and where it writes. */
struct vlff_dds_opts {
  struct vlff_cfg_dds dds;
  char map[VLFF_CFG_STR];     /* map segment name */
  char frames[VLFF_CFG_STR];  /* frame ring name (the camera) */
  char prompts[VLFF_CFG_STR]; /* prompt mailbox name */
  char hardware_id[VLFF_CFG_STR]; /* DiagnosticStatus.hardware_id (the host's name) */
  uint64_t update_points_max; /* most points of one map update: vlff_config_dds_update_points() */
  double run_seconds;         /* 0 = until vlff_dds_stop */
};

/* Why prompt messages were refused, and what was done. */
struct vlff_dds_counts {
  uint64_t maps_sent, map_updates_sent, map_update_points, status_sent, prompt_lists_sent, label_images_sent, camera_images_sent, tf_sent;
  uint64_t prompts_posted, prompts_oversized, prompts_flood, prompts_malformed, prompts_invalid, prompts_busy;
};

/* "rt<ns>/vlff/<leaf>" into out. 0, or -1 if it does not fit. */
int vlff_dds_topic(char *out, size_t len, const char *ns, const char *leaf);
/* A topic's DDS name by id (enum vlff_dds_topic_id): "rt<ns>/vlff/<leaf>",
 * "rt<ns>/tf" for the pose. 0, or -1 if it does not fit. */
int vlff_dds_topic_of(char *out, size_t len, const char *ns, int id);
/* A topic's config name (dds.<name>), NULL for an id out of range. */
const char *vlff_dds_topic_key(int id);

/* 1 when this build can publish CompressedImage (it has OpenCV's encoders). */
int vlff_dds_can_compress(void);

/* sensor_msgs/image_encodings name of a ring pixel format, NULL if none. */
const char *vlff_dds_encoding(uint32_t pixfmt);
/* A prompt list as a JSON list into a malloc'd string, NULL/ENOMEM: the
 * snapshot's, or count texts. */
char *vlff_dds_prompt_json(const struct vlff_map_snapshot *snap, int count);
char *vlff_dds_prompt_list_json(const char *const texts[], int count);

/* Parses a prompt message: a JSON list of 1..VLFF_SHM_MAX_PROMPTS strings,
 * each passing vlff_prompt_check (returns the count, texts filled), or a
 * JSON integer 0..INT32_MAX, the index of a configured set, as vlff-shm
 * set-prompts -i takes it (returns 0, *set_index set; else it is -1).
 * -1 with the reason in why and *invalid = 0 (not JSON, not a list of
 * strings or an integer) or 1 (refused by the mailbox's rule). */
int vlff_dds_parse_prompts(const char *data, size_t len, char texts[][VLFF_SHM_PROMPT_LEN], int *set_index,
                           int *invalid, char *why, size_t whylen);

/* Grid element i as a map point (VLFF_DDS_POINT_STEP bytes) at p, whatever
 * its label. */
void vlff_dds_put_point(uint8_t *p, const struct vlff_map_grid *g, size_t i);
/* The point cloud's payload of a snapshot: little-endian points as in the
 * contract, into a malloc'd buffer (*out, *npoints): the grid's labelled
 * voxels, then far's (the snapshot's far map, NULL: none) where the grid
 * does not cover them, at most far_max, the nearest blocks first
 * (far_walk.h; *far_left, may be NULL: those left out). 0, or -1/ENOMEM. */
int vlff_dds_cloud(const struct vlff_map_info *info, const struct vlff_map_far *far, size_t far_max, uint8_t **out,
                   uint32_t *npoints, size_t *far_left);

struct vlff_dds;
/* Creates the participant, topics, writers and reader. NULL with err. */
struct vlff_dds *vlff_dds_create(const struct vlff_dds_opts *opts, char *err, size_t errlen);
/* Runs until vlff_dds_stop, a signal (vlff_cli_stop) or run_seconds. 0 or -1. */
int vlff_dds_run(struct vlff_dds *b);
void vlff_dds_stop(struct vlff_dds *b); /* async-signal-safe */
const struct vlff_dds_counts *vlff_dds_counts(const struct vlff_dds *b);
void vlff_dds_destroy(struct vlff_dds *b);

#endif
