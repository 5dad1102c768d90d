/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * inputs.h - the node's inputs (frame, pose and feature ring records) as MCAP
 * messages: written by vlff-record, read back by vlff-replay.
 *
 * Channels (JSON messages with JSON Schemas, like vlff-view's own channels, so
 * that Foxglove shows them and any MCAP tool reads them without a schema
 * compiler):
 *   /input/color        foxglove.RawImage: the frame's colour plane as the ring
 *                       holds it (encoding rgb8, bgr8, mono8, mono16,
 *                       bayer_rggb8/bggr8/grbg8/gbrg8), rows packed (step =
 *                       width x bytes per pixel), data base64
 *   /input/depth        foxglove.RawImage: the depth plane, 16UC1 (uint16
 *                       millimetres, 0 = invalid) or 32FC1 (float metres); absent
 *                       for a frame without depth
 *   /input/calibration  foxglove.CameraCalibration: the frame's intrinsics, K and
 *                       P in OpenCV's convention (principal point half a pixel
 *                       left of and above the ring's); it closes the frame
 *   /input/pose         foxglove.FrameTransform world -> camera: a pose ring
 *                       record (camera-to-world), rotation as a quaternion
 *   /input/frame_pose   foxglove.FrameTransform: the pose a frame record carries
 *                       itself (VLFF_FRAME_POSE_VALID: a camera with its own
 *                       tracker), stamped with its pose_t_ns
 *   /input/features     vlff.FeatureMap: a feature ring record, {timestamp,
 *                       frame_id (the frame's number in the ring), dim, height,
 *                       width, encoding "float16", data: base64 of the ring's
 *                       [dim][height][width] little-endian IEEE half floats}
 * A frame is its colour message, then its depth message, then its own pose, then
 * its calibration, consecutive, the images and the calibration with one
 * timestamp: the frame's t_host_ns. A pose's timestamp
 * is its t_ns; a feature map's is its t_host_ns (the frame's host time, by which
 * vlff-replay finds the frame it belongs to). Numbers are written with 17
 * significant digits, so that every double reads back as the same double.
 * Each message's log time is its timestamp.
 *
 * The reader validates every message before handing it out: JSON shape and
 * types, sizes (1..VLFF_MAX_IMAGE_SIDE, data exactly step x height, encodings
 * known), intrinsics within physical bounds (bounds.h), feature shape (dim
 * 1..VLFF_IN_MAX_DIM, data exactly 2 x dim x height x width, at most
 * VLFF_IN_MAX_FEATURE_BYTES), unit quaternions (|q| within 1e-6 of 1) and
 * finite translations within bounds.h's absolute bound, and each channel's
 * stamps non-decreasing (strictly increasing for frames). Every frame of a
 * recording has the first frame's size and formats, every feature map the
 * first map's shape (a ring has one slot size). An error names the channel and
 * the message's index in the file (0-based, all channels counted).
 *
 * CONTRACT
 * Errors: int functions return -1 (pointer functions NULL) with one line in
 *   why[len].
 * Ownership: the reader borrows the file's bytes like vlff_mcap_reader; an
 *   event's pointers (color, depth, features) are the reader's own buffers,
 *   valid until the next call.
 * Threads: an object is used by one thread at a time.
 */
#ifndef VLFF_VIEW_INPUTS_H
#define VLFF_VIEW_INPUTS_H

#include <stddef.h>
#include <stdint.h>

#include "mcap.h"

#define VLFF_IN_MAX_DIM 4096
#define VLFF_IN_MAX_FEATURE_BYTES ((size_t)256 << 20)

enum vlff_in_channel {
  VLFF_IN_COLOR = 1,
  VLFF_IN_DEPTH,
  VLFF_IN_CALIBRATION,
  VLFF_IN_POSE,
  VLFF_IN_FEATURES,
  VLFF_IN_FRAME_POSE,
  VLFF_IN_CHANNELS = VLFF_IN_FRAME_POSE
};
/* The topic of channel ch (1..VLFF_IN_CHANNELS). */
const char *vlff_in_topic(int ch);

/* --------------------------------------------------------------- writing */

/* The JSON Schemas of foxglove.CameraCalibration and foxglove.FrameTransform,
 * shared with vlff-view's channels of the same names (schemas.c). */
extern const char vlff_schema_camera_calibration[];
extern const char vlff_schema_frame_transform[];

/* Declares the channels on w (ids 1..VLFF_IN_CHANNELS) with their schemas. */
int vlff_in_declare(struct vlff_mcap_writer *w, char *why, size_t len);
/* One ring record as its messages: a frame record (its planes, intrinsics and
 * t_host_ns; a record that vlff_frame_validate refuses is refused), a pose
 * record, a feature record (vlff_feature_validate). Scratch memory is kept in
 * *scratch (free it with free() when done; NULL to start). */
int vlff_in_write_frame(struct vlff_mcap_writer *w, const void *record, size_t rec_len, char **scratch,
                        size_t *scratch_cap, char *why, size_t len);
int vlff_in_write_pose(struct vlff_mcap_writer *w, uint64_t t_ns, const double c2w[16], char *why, size_t len);
int vlff_in_write_features(struct vlff_mcap_writer *w, const void *record, size_t rec_len, char **scratch,
                           size_t *scratch_cap, char *why, size_t len);

/* --------------------------------------------------------------- reading */

enum vlff_in_kind { VLFF_IN_EV_FRAME = 1, VLFF_IN_EV_POSE, VLFF_IN_EV_FEATURES };

struct vlff_in_event {
  int kind;            /* enum vlff_in_kind */
  uint64_t t_ns;       /* the record's stamp */
  uint64_t index;      /* the message's index in the file (a frame: its colour's) */
  /* frame */
  uint32_t width, height;
  uint32_t color_format, depth_format; /* enum vlff_pixfmt; depth VLFF_PIX_NONE = none */
  const uint8_t *color, *depth;        /* packed rows */
  double fx, fy, cx, cy;               /* the ring's convention */
  int has_pose;                        /* the frame's own pose (in pose, at pose_t_ns) */
  uint64_t pose_t_ns;
  /* pose (and a frame's own): camera-to-world, row-major */
  double pose[16];
  /* features */
  uint64_t frame_id;
  uint32_t dim, feat_height, feat_width;
  const uint16_t *features; /* [dim][h][w] host-order half floats */
};

struct vlff_in_reader;
/* A reader of the recording d[n] (see mcap.h's vlff_mcap_reader_new). */
struct vlff_in_reader *vlff_in_reader_new(const uint8_t *d, size_t n, char *why, size_t len);
void vlff_in_reader_free(struct vlff_in_reader *r);
/* The next input record, validated: 1 with *ev set, 0 at the end of the
 * recording, -1 on anything malformed or out of bounds, and on a file cut short
 * (without its footer: a recorder that was killed), naming where. Messages on
 * other channels (a vlff-view recording's) are passed over and counted. */
int vlff_in_next(struct vlff_in_reader *r, struct vlff_in_event *ev, char *why, size_t len);
/* Back to the first record. */
void vlff_in_rewind(struct vlff_in_reader *r);
/* Messages passed over so far (not on an /input/ channel). */
uint64_t vlff_in_other_messages(const struct vlff_in_reader *r);
/* The recording's offset before which no byte is needed again until a
 * rewind (vlff_mcap_consumed): an event's images and features are copies. */
size_t vlff_in_consumed(const struct vlff_in_reader *r);

#endif /* VLFF_VIEW_INPUTS_H */
