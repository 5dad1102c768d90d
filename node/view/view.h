/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * view.h - vlff-view, the live viewer: a Foxglove WebSocket server and its own page.
 *
 * The viewer is a controller like any other: it attaches read-only to the map segment
 * and the frame ring through libvlff-shm (vlff/shm.h) and never makes the node wait.
 * Two parts:
 *   - the feed (feed.c) turns what the segments hold into Foxglove messages: it keeps
 *     the last map version it sent and, for a new version, encodes only the voxels
 *     and bricks (4x4x4 voxels by default) that changed;
 *   - the server (server.c) speaks the foxglove.websocket.v1 subprotocol through
 *     libwebsockets on one port, serves the page's files on the same port, fans each
 *     message out to the clients subscribed to its channel and drops a client whose
 *     queue grows past a bound instead of waiting for it; it pings clients silent for
 *     a third of idle_timeout_s and closes those silent for all of it, and posts prompt
 *     sets without waiting for the mailbox (the learner's answer is polled for);
 *   - the page (page.c, page.h) holds the files under the www directory, read once
 *     at start, and checks every HTTP request head before libwebsockets parses it:
 *     a request that is not a GET or HEAD of one of those files or a WebSocket
 *     upgrade, or whose Host or Origin is not the viewer's own or configured, gets
 *     an HTTP status and a sentence, and is counted;
 *   - request.c parses what clients send (JSON, strictly; clientPublish headers);
 *   - recordings: the server writes every message it makes to an MCAP file when
 *     given a writer (mcap.h), and play.c serves such a file instead of the feed.
 *
 * CONTRACT
 * Errors: functions returning a pointer return NULL, functions returning int return
 *   -1, and write one line naming what failed to stderr (the viewer is a program, its
 *   errors are for the operator).
 * Ownership: messages are reference counted: vlff_view_msg_new returns one reference,
 *   vlff_view_msg_ref adds one, vlff_view_msg_unref drops one and frees the last.
 *   Everything else is owned by the object that created it.
 * Threads: single-threaded; everything runs on the server's event loop.
 */
#ifndef VLFF_VIEW_H
#define VLFF_VIEW_H

#include <stddef.h>
#include <stdint.h>

#include <vlff/shm.h>

/* The channels the server advertises; the id is also the Foxglove channel id. */
enum vlff_view_channel {
  VLFF_VIEW_CH_SCENE = 1,  /* /map: foxglove.SceneUpdate, one entity of cubes per brick */
  VLFF_VIEW_CH_VOXELS,     /* /map/voxels: vlff.VoxelDelta, changed voxels with labels */
  VLFF_VIEW_CH_IMAGE,      /* /camera/image: foxglove.CompressedImage, the latest camera frame as JPEG */
  VLFF_VIEW_CH_LABELS,     /* /camera/labels: foxglove.CompressedImage, the label image in prompt
                              colours as PNG (lossless: a colour is a class) */
  VLFF_VIEW_CH_POSE,       /* /tf: foxglove.FrameTransform, world -> camera */
  VLFF_VIEW_CH_STATUS,     /* /vlff/status: vlff.Status JSON */
  VLFF_VIEW_CH_CALIB,      /* /camera/calibration: foxglove.CameraCalibration, the pinhole
                              intrinsics the frames carry (from the source's config), with each image */
  VLFF_VIEW_CH_LOG,        /* /log: foxglove.Log, what changed in the status (logch.c) */
  VLFF_VIEW_CH_CLOUD,      /* /map/points: foxglove.PointCloud in protobuf (cloud.c), the occupied
                              voxels (whole, in pieces) and then the voxels that changed */
  VLFF_VIEW_CH_DEPTH,      /* /camera/depth: foxglove.RawImage in protobuf, the latest frame's depth
                              as 16UC1 millimetres, with each camera image */
  VLFF_VIEW_CH_GRID,       /* /map/grid: foxglove.Grid in protobuf, the map seen from above (per
                              column the highest occupied voxel) or a slice at a height */
  VLFF_VIEW_CH_COUNT = VLFF_VIEW_CH_GRID
};

/* JPEG quality of the camera image channel. */
#define VLFF_VIEW_JPEG_QUALITY 80

struct vlff_view_channel_def {
  const char *topic;
  const char *schema_name;
  const char *schema; /* JSON Schema text; for protobuf, the FileDescriptorSet in base64 */
  const char *encoding; /* "json" (messages and schema), or "protobuf" */
};
/* The definition of channel id ch (1..VLFF_VIEW_CH_COUNT). */
const struct vlff_view_channel_def *vlff_view_channel(int ch);

/* Bytes before a message's payload: libwebsockets' frame header room plus the
 * Foxglove binary header (opcode, subscription id, timestamp), which the server
 * fills per client in place. */
#define VLFF_VIEW_FOX_HDR 13
size_t vlff_view_headroom(void);

/* A message payload (JSON text) with headroom, shared between clients. */
struct vlff_view_msg {
  int refs;
  int channel;       /* enum vlff_view_channel */
  uint64_t t_ns;     /* Foxglove log time, ns since the epoch */
  uint64_t version;  /* map version it describes (map channels), else 0 */
  int whole;         /* map channels: the whole map (a new subscriber's, a recording's
                        periodic one), not the changes since the previous version */
  size_t len, cap;   /* payload bytes, capacity */
  unsigned char *buf; /* headroom + cap bytes */
  /* the next piece of a message sent in pieces (the map channels'), sent right
   * after this one; a message holds a reference to its next */
  struct vlff_view_msg *next;
};
struct vlff_view_msg *vlff_view_msg_new(int channel, size_t cap);
unsigned char *vlff_view_msg_payload(struct vlff_view_msg *m);
struct vlff_view_msg *vlff_view_msg_ref(struct vlff_view_msg *m);
void vlff_view_msg_unref(struct vlff_view_msg *m);

/* ------------------------------------------------------ protobuf channels */

/* A protobuf channel's schema (cloud.c): the FileDescriptorSet of its message and
 * the messages it uses (binary, as MCAP holds it; *len its size), and in base64,
 * as the WebSocket protocol advertises it; NULL for a JSON channel. */
const uint8_t *vlff_view_descriptor(int ch, size_t *len);
const char *vlff_view_descriptor_b64(int ch);

/* /map/points (cloud.c): foxglove.PointCloud in protobuf, in the map's frame, identity
 * pose; each point VLFF_VIEW_CLOUD_STRIDE bytes: x, y, z (float32, the voxel's
 * centre, m), red, green, blue, alpha (uint8: the prompt's colour; alpha 0 for a
 * voxel no longer occupied), label (uint16, as in the map), confidence (uint8), one
 * byte unused; little-endian. */
#define VLFF_VIEW_CLOUD_STRIDE 20
/* PointClouds of the n packed points, in pieces of at most piece_bytes each
 * (chained through next; at least one, empty when n is 0), stamped t_ns; the
 * number made in *pieces. NULL out of memory. */
struct vlff_view_msg *vlff_view_cloud_msgs(int channel, const char *frame, const uint8_t *points, size_t n,
                                           uint64_t t_ns, size_t piece_bytes, int *pieces);

/* /map/grid: a foxglove.Grid of cols x rows cells, row-major (a row runs along x),
 * each VLFF_VIEW_GRID_STRIDE bytes: red, green, blue, alpha (uint8, the label's
 * colour; alpha 0 where no voxel is occupied), label (uint16), confidence (uint8),
 * one byte unused, elevation (float32, m above the grid's plane); little-endian.
 * The grid's corner is at corner[] in frame, with the frame's axes; cells are cell
 * metres square. NULL out of memory. */
#define VLFF_VIEW_GRID_STRIDE 12
struct vlff_view_msg *vlff_view_grid_msg(int channel, const char *frame, uint64_t t_ns, const double corner[3],
                                         double cell, uint32_t cols, uint32_t rows, const uint8_t *cells);
/* /camera/depth: a foxglove.RawImage, encoding 16UC1, of w x h packed little-endian
 * uint16 millimetres (0 = no depth). NULL out of memory. */
struct vlff_view_msg *vlff_view_depth_msg(int channel, const char *frame, uint64_t t_ns, uint32_t w, uint32_t h,
                                          const uint8_t *mm);

/* ------------------------------------------------------------------ feed */

struct vlff_feed_params {
  const char *map_name;     /* map segment */
  const char *frames_name;  /* frame ring, NULL or "" = no camera image */
  double image_hz;          /* most camera images per second sent */
  double map_hz;            /* most map updates per second sent (0 = every version) */
  uint32_t brick;           /* brick edge in voxels for the scene channel */
  size_t cloud_piece_bytes; /* the largest piece of a point cloud, scene or voxel message (0 = 1 MiB) */
  double grid_hz;           /* most /map/grid messages per second (0 = 1), sent while the map changes */
  /* the largest grid or depth image sent (0 = no bound): one message above a
   * client's queue limit would drop the client, again at every reconnection */
  size_t max_message_bytes;
  /* the grid: per column the highest occupied voxel (seen from above), or with
   * grid_slice the voxels of the layer holding height grid_z (m, in the map's frame) */
  int grid_slice;
  double grid_z;
  /* the map's frame (the scene, the point cloud, the pose's parent) and the
   * camera's (images, calibration, the pose's child): NULL = "world", "camera" */
  const char *world_frame, *camera_frame;
};

/* The HTTP statuses requests are refused with: 400 malformed, 403 a Host or Origin
 * not allowed, 404 no such file, 405 not GET or HEAD, 408 no whole head in time,
 * 414 target too long, 426 WebSocket version not 13, 431 head too large, 503 too
 * many clients or waiting connections, 505 not HTTP/1.x. */
#define VLFF_VIEW_HTTP_N 10
/* The status of counter i (0..VLFF_VIEW_HTTP_N-1). */
int vlff_view_http_status(int i);
/* The counter of a status (the inverse), -1 for a status not counted. */
int vlff_view_http_index(int status);

/* What the server counts, reported in the status channel. refused counts every
 * refusal, HTTP and WebSocket; http_refused[i] those answered with status
 * vlff_view_http_status(i). */
struct vlff_view_counters {
  int clients;
  uint64_t connections, dropped_slow, refused, bad_requests, prompts_posted;
  uint64_t messages_sent, bytes_sent;
  uint64_t http_refused[VLFF_VIEW_HTTP_N];
};

struct vlff_feed;
struct vlff_feed *vlff_feed_new(const struct vlff_feed_params *p);
void vlff_feed_free(struct vlff_feed *f);

/* Checks the segments (attaching when they appear, re-attaching when a creator
 * replaced them) and appends the new messages to out (at most out_cap): a map delta
 * on the scene and voxel channels for a new map version, the label image and pose,
 * a camera image when the frame ring has a new frame and the rate allows, a status
 * message at least once a second. Channels whose bit (1u << channel) is clear in
 * wanted have no subscriber and are not encoded at all (the map copy is still kept
 * current, so that vlff_feed_current can build the whole map for a first
 * subscriber). Returns the number of messages appended; the caller owns them. */
int vlff_feed_poll(struct vlff_feed *f, const struct vlff_view_counters *c, unsigned wanted, struct vlff_view_msg **out,
                   int out_cap);
/* A new subscriber's first message on channel ch: the whole map (scene, voxels) or
 * the latest image, calibration, labels or pose (never one kept from before the last
 * poll when the channel had no subscriber then: it is read from the segments now), or
 * a status built now with the counters c (NULL: zeros). NULL when there is nothing
 * yet. One new reference. */
struct vlff_view_msg *vlff_feed_current(struct vlff_feed *f, int ch, const struct vlff_view_counters *c);
/* The map version the feed last sent (0 = none). */
uint64_t vlff_feed_version(const struct vlff_feed *f);
/* How many messages the feed has encoded for channel ch since it was made. */
uint64_t vlff_feed_encoded(const struct vlff_feed *f, int ch);

/* --------------------------------------------------------------- requests */

/* What the viewer parses of client messages itself (request.c). A JSON text s[n]
 * (a request, or a published message after its header): one JSON value in strict
 * mode, valid UTF-8, nothing but whitespace after it. The value (json-c, the caller
 * puts it), or NULL with the reason in why[len]. */
struct json_object;
struct json_object *vlff_view_parse_json(const char *s, size_t n, char *why, size_t len);
/* The 5-byte header of clientPublish message data (opcode 1, channel id LE): 0 with
 * *channel set, or -1 with the reason in why[len]. */
int vlff_view_publish_header(const unsigned char *d, size_t n, uint32_t *channel, char *why, size_t len);

/* -------------------------------------------------------------------- log */

/* The /log channel (logch.c): lines made from the status messages the feed makes,
 * when something in them changes (segments attached or gone, the map's writer
 * alive or silent, the learner's state and error flags, frames refused per reason
 * and lost, these at most one line per reason every 10 s with the count since). */
struct vlff_view_log;
struct vlff_view_log *vlff_view_log_new(void);
void vlff_view_log_free(struct vlff_view_log *l);
/* The lines status (a /vlff/status message) gives, at most cap, into out; the
 * caller owns them. */
int vlff_view_log_status(struct vlff_view_log *l, const struct vlff_view_msg *status, struct vlff_view_msg **out,
                         int cap);
/* The latest line (one new reference), or NULL. */
struct vlff_view_msg *vlff_view_log_current(struct vlff_view_log *l);

/* ------------------------------------------------------ recording, playback */

/* The most channels a server carries: a recording played back may hold others
 * than this build's (subscriptions are kept in a 32-bit mask). */
#define VLFF_VIEW_CH_MAX 31

/* A channel as the server advertises it. */
struct vlff_view_chan {
  const char *topic, *encoding, *schema_name, *schema_encoding, *schema;
};

/* An MCAP recording served as if live (play.c): read whole into memory and every
 * record checked once when opened (mcap.h's bounds; a file cut short by a killed
 * recorder plays up to its last whole chunk, with a warning); its channels are
 * numbered 1..n in the order the file defines them. Playback starts when a client
 * first subscribes and sends each message when as much time has passed since the
 * first as passed between their log times (a jump forward of more than 60 s, a
 * recorder's clock stepped, is not waited out), with its publish time as the Foxglove
 * timestamp; a new subscriber gets the latest message played on its channel. */
struct vlff_view_play;
/* NULL (the reason on stderr) for a file that is not a readable recording. */
struct vlff_view_play *vlff_view_play_open(const char *path);
/* Plays rate times as fast as recorded (default 1). */
void vlff_view_play_rate(struct vlff_view_play *p, double rate);
void vlff_view_play_free(struct vlff_view_play *p);
int vlff_view_play_channels(const struct vlff_view_play *p);
/* Channel ch, 1..vlff_view_play_channels. */
const struct vlff_view_chan *vlff_view_play_channel(const struct vlff_view_play *p, int ch);
/* The messages due at now_ns (CLOCK_MONOTONIC), at most out_cap; starts the clock
 * at the first call with wanted non-zero. The number appended; the caller owns them. */
int vlff_view_play_poll(struct vlff_view_play *p, unsigned wanted, uint64_t now_ns, struct vlff_view_msg **out,
                        int out_cap);
/* The latest message played on channel ch (one new reference), or NULL. */
struct vlff_view_msg *vlff_view_play_current(struct vlff_view_play *p, int ch);
/* Messages played so far, in the file; 1 once all are played. */
uint64_t vlff_view_play_sent(const struct vlff_view_play *p);
uint64_t vlff_view_play_total(const struct vlff_view_play *p);
int vlff_view_play_done(const struct vlff_view_play *p);

/* ---------------------------------------------------------------- server */

struct vlff_mcap_writer;
struct vlff_view_params {
  const char *address;      /* listening address, "127.0.0.1" */
  int port;                 /* 0 = any free port (see vlff_view_port) */
  const char *www_dir;      /* the page's files, read at start (page.h) */
  const char *prompts_name; /* prompt mailbox */
  const char *token;        /* NULL = posting prompts disabled */
  double poll_hz;           /* segment checks per second */
  int max_clients;
  size_t max_queue_bytes;   /* a client with more unsent bytes is dropped */
  size_t max_request_bytes; /* largest client message accepted */
  double head_timeout_s;    /* a connection's whole request head, or 408 (0 = 5 s) */
  double idle_timeout_s;    /* a WebSocket client silent this long is closed; pinged after
                               a third of it (0 = 30 s) */
  const char *const *allow_origins; /* more origins (and their hosts) than the viewer's own */
  int n_allow_origins;
  int verbose;
  /* a recording to serve instead of the feed (the feed is then NULL) */
  struct vlff_view_play *play;
  /* a recording (mcap.h) every message sent on a channel is written to, with the
   * channels declared by vlff_view_new; the caller closes it after the server */
  struct vlff_mcap_writer *record;
  /* while the map changes, the whole map (voxels, point cloud, scene) goes into the
   * recording every record_map_s seconds (0 = 10), each time opening a chunk, so
   * that a reader seeking into the file finds it shortly before any point */
  double record_map_s;
};

struct vlff_view;
struct vlff_view *vlff_view_new(const struct vlff_view_params *p, struct vlff_feed *feed);
/* The port it listens on (the chosen one when params asked for 0). */
int vlff_view_port(const struct vlff_view *v);
/* Serves until vlff_view_stop (async-signal-safe) is called. 0, or -1. */
int vlff_view_run(struct vlff_view *v);
void vlff_view_stop(struct vlff_view *v);
void vlff_view_free(struct vlff_view *v);

#endif /* VLFF_VIEW_H */
