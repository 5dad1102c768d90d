/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * vlff/shm.h - the shared-memory layer of vlff, and the controller reader library.
 *
 * Segments (POSIX shared memory, shm_open + mmap, names start with '/'):
 *   - rings (vlff_ring_*): one producer, any number of consumers, N fixed-size slots.
 *     Frames (drivers -> learner), features (external extractor -> learner) and poses
 *     (external SLAM -> learner) are records in such rings.
 *   - the map (vlff_map_*): the learner's latest segmented voxel map, prompt list and
 *     2D label image, and the learner's status (vlff_map_get_status), read by
 *     controllers.
 *   - the prompt mailbox (vlff_prompts_*): controllers post a new prompt set, the learner
 *     picks it up.
 *
 * CONTRACT (every function follows it unless its comment says otherwise)
 *
 * Errors: functions returning a pointer return NULL on failure, functions returning int
 *   return -1 on failure (0 or a documented non-negative value on success), and set
 *   errno. Segment-level failures also record, per thread, a vlff_shm_err code and a
 *   message naming the segment and what is wrong ("/vlff-map: ABI version 7, this
 *   library speaks 1"): read them with vlff_shm_last_error() and vlff_shm_last_message()
 *   right after the failing call. errno values used: ENOENT (no such segment), EEXIST
 *   (a live creator owns it), EACCES (permissions), EPROTO (not a vlff segment, or
 *   a vlff segment of another kind), EPROTONOSUPPORT (other ABI version), EBADMSG
 *   (truncated or corrupt header), EMSGSIZE (record does not fit a slot), EINVAL (bad
 *   argument), EAGAIN (nothing new / try again), ETIMEDOUT (wait timed out), ESTALE
 *   (the record was overwritten while being read), EPIPE (the segment was abandoned:
 *   its creator replaced it with a new one, its file was truncated under this
 *   handle, or, seen by a reader while it waits, removed from /dev/shm; detach
 *   and attach again), EBUSY (the prompt mailbox is busy).
 *
 * Ownership: every object returned by a *_create, *_attach or *_new function is owned
 *   by the caller and released with the matching *_close / *_detach / *_free function
 *   (which accept NULL). Pointers returned into a segment (vlff_ring_reserve, views,
 *   snapshot accessors) live until the next call on the same object or its release,
 *   whichever comes first. Closing a creator's handle does not remove the segment (a
 *   restarted creator takes it over); vlff_shm_unlink() removes it.
 *
 * Threads and processes: one object may be used by one thread at a time; different
 *   objects (including several handles to the same segment, in one or many processes)
 *   may be used concurrently without locks. Exactly one producer per ring and one
 *   writer per map (the creator); vlff_*_create refuses a second live creator.
 *   Nothing in this library ever makes a producer or map writer wait for a reader
 *   (a replay tool may choose to, with vlff_ring_wait_reader): readers detect that
 *   data changed underneath them and retry or count it as lost.
 *
 * Hostile files (docs/shm.md says why each choice was made):
 *   - A segment's file may be truncated at any moment by anyone with write access to
 *     it. No user of this library dies of it: attach checks the size against the
 *     header (read with pread, never through a mapping), and every mapping is
 *     registered with a SIGBUS guard that, on a fault inside it, replaces the whole
 *     mapping with private zero-filled memory and flags the handle. This covers
 *     accesses through pointers handed out (reserved slots, views) as well as the
 *     library's own, in any thread. The next call on the handle fails with EPIPE
 *     and VLFF_SHM_ERR_TRUNCATED: readers attach again; creators (map writer, ring
 *     producer, the learner's mailbox) have by then replaced the segment by a new one
 *     whose numbering (map version, record numbers, request numbers) goes on, and
 *     the next call works. Until then whatever was read through the handle is zeros
 *     that no seqlock check accepts.
 *   - The guard is a process-wide SIGBUS handler, installed when a segment is mapped
 *     (again if something replaced it since). Faults outside every segment go to the
 *     handler installed before it, or to the default action. An application that
 *     installs its own SIGBUS handler after attaching must chain to the previous one
 *     for faults it does not recognise.
 *   - A creator never takes over or removes a file its uid does not own (EACCES,
 *     VLFF_SHM_ERR_PERM, naming the owner), never touches a non-vlff or non-regular
 *     file (EEXIST, VLFF_SHM_ERR_FOREIGN), and replaces rather than takes over in place
 *     a stale segment of its own whose mode or group is wider than configured. Every
 *     attacher refuses world-writable and non-regular files; vlff_ring_attach_owned()
 *     also demands an owner and a mode.
 *
 * Clocks: every timestamp is CLOCK_MONOTONIC in nanoseconds (vlff_shm_now_ns()).
 *
 * Coordinates: poses are 4x4 row-major double camera-to-world matrices, OpenCV camera
 *   convention (x right, y down, z forward), world units metres.
 *
 * The header is C99 and needs only libc; link with -lvlff-shm (pkg-config vlff-shm).
 */
#ifndef VLFF_SHM_H
#define VLFF_SHM_H

#include <stddef.h>
#include <stdint.h>
#include <sys/types.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Bumped on every incompatible change of any segment layout. */
#define VLFF_SHM_ABI_VERSION 10

/* ------------------------------------------------------------------ errors */

enum vlff_shm_err {
  VLFF_SHM_OK = 0,
  VLFF_SHM_ERR_SYS,       /* a system call failed; errno says which */
  VLFF_SHM_ERR_INVAL,     /* bad argument */
  VLFF_SHM_ERR_MISSING,   /* no segment of that name */
  VLFF_SHM_ERR_EXISTS,    /* the segment is owned by a live creator */
  VLFF_SHM_ERR_PERM,      /* permission denied */
  VLFF_SHM_ERR_FOREIGN,   /* not a vlff segment (wrong magic) */
  VLFF_SHM_ERR_KIND,      /* a vlff segment, but of another kind or record type */
  VLFF_SHM_ERR_VERSION,   /* another ABI version */
  VLFF_SHM_ERR_TRUNCATED, /* the segment is smaller than its header says */
  VLFF_SHM_ERR_CORRUPT,   /* header fields inconsistent or checksum wrong */
  VLFF_SHM_ERR_NOTREADY,  /* the creator has not finished initialising it */
  VLFF_SHM_ERR_ABANDONED, /* replaced by a new segment of the same name: re-attach */
  VLFF_SHM_ERR_SIZE,      /* a record or argument is larger than the segment allows */
  VLFF_SHM_ERR_NOSPACE    /* no space left in /dev/shm for the segment's pages */
};

/* The code and message of the last failure of this library in the calling thread.
 * The message is valid until the thread's next failing call into this library. */
int vlff_shm_last_error(void);
const char *vlff_shm_last_message(void);
/* A static description of a code ("segment truncated"). Never NULL. */
const char *vlff_shm_strerror(int err);

/* CLOCK_MONOTONIC now, ns. */
uint64_t vlff_shm_now_ns(void);

/* Removes a segment name (shm_unlink). Processes still attached keep their mapping. */
int vlff_shm_unlink(const char *name);

/* Creation options shared by every *_create call. */
struct vlff_shm_perm {
  mode_t mode;        /* permission bits; 0 = 0640. World-write bits are refused (EINVAL). */
  const char *group;  /* group name or numeric gid owning the segment; NULL or "" = creator's */
};

/* What vlff_shm_stat() reports for any vlff segment (used by the CLI). */
enum vlff_shm_kind { VLFF_SHM_KIND_RING = 1, VLFF_SHM_KIND_MAP = 2, VLFF_SHM_KIND_PROMPTS = 3 };
struct vlff_shm_info {
  uint32_t kind;          /* enum vlff_shm_kind */
  uint32_t abi_version;
  uint32_t record_kind;   /* rings: enum vlff_record_kind */
  uint32_t generation;    /* bumped each time a creator (re)starts on the segment */
  int32_t creator_pid;
  int creator_alive;      /* 1 if creator_pid exists (or cannot be checked) and, where the header
                           * keeps it, started when the creator did; else 0 */
  uint64_t total_size;    /* bytes */
  uint32_t slots;         /* rings; prompts: times the learner put a forged request number or
                           * answered word back (saturates) */
  uint64_t slot_size;     /* rings: usable bytes per record; map: voxel capacity; prompts:
                           * times the learner set its forged state word back to ready */
  uint64_t head;          /* rings: records committed so far; map: version; prompts: sequence */
  uint64_t last_ns;       /* rings: last commit; map: heartbeat; prompts: last post */
};
/* Validates any vlff segment by name and fills *info. Same errors as the attach calls. */
int vlff_shm_stat(const char *name, struct vlff_shm_info *info);

/* -------------------------------------------------------------------- rings */

/* What the records of a ring are; checked on attach so that a frame consumer never
 * attaches to a pose ring. VLFF_RECORD_ANY on attach accepts any. */
enum vlff_record_kind {
  VLFF_RECORD_ANY = 0,
  VLFF_RECORD_RAW = 1,     /* application-defined bytes */
  VLFF_RECORD_FRAME = 2,   /* struct vlff_frame_hdr + planes */
  VLFF_RECORD_FEATURE = 3, /* struct vlff_feature_hdr + [D,h,w] float16 */
  VLFF_RECORD_POSE = 4     /* struct vlff_pose_rec */
};

struct vlff_ring; /* opaque: a producer (from create) or a consumer (from attach) */

struct vlff_ring_params {
  uint32_t record_kind;  /* enum vlff_record_kind, not ANY */
  uint32_t slots;        /* >= 2 */
  uint64_t slot_size;    /* bytes per record, > 0 */
  struct vlff_shm_perm perm;
};

/* Creates the ring and becomes its producer. The segment is created O_EXCL. If a
 * segment of that name exists whose creator is dead, it is taken over: with the same
 * geometry and permissions in place (generation + 1, record numbering continues,
 * attached consumers see the new generation and carry on), otherwise it is marked
 * abandoned (consumers get EPIPE) and replaced. A live creator gives EEXIST, a file
 * of another uid EACCES. If the file is truncated later, vlff_ring_reserve (before
 * handing out a slot) or vlff_ring_commit (for a record written into the shrunk
 * mapping, which is lost) fail once with EPIPE after replacing the ring. */
struct vlff_ring *vlff_ring_create(const char *name, const struct vlff_ring_params *params);

/* Attaches as a consumer, read-only: validates magic, ABI version, kind, sizes and
 * that the file is as large as the header says. The read cursor starts after the newest
 * committed record (live data, not history); see vlff_ring_seek_oldest(). */
struct vlff_ring *vlff_ring_attach(const char *name, uint32_t record_kind);
/* Same, and the segment's file must belong to uid and have no permission bit outside
 * mode (0 = any but world-writable); otherwise -1/EACCES (VLFF_SHM_ERR_PERM) naming
 * the owner or the mode found. A learner attaches its input rings this way. */
struct vlff_ring *vlff_ring_attach_owned(const char *name, uint32_t record_kind, uid_t uid, mode_t mode);

/* Releases the handle (unmaps). Never removes the segment. */
void vlff_ring_close(struct vlff_ring *ring);

uint32_t vlff_ring_slots(const struct vlff_ring *ring);
uint64_t vlff_ring_slot_size(const struct vlff_ring *ring);
uint32_t vlff_ring_generation(const struct vlff_ring *ring);
/* Records committed so far (over all generations). */
uint64_t vlff_ring_head(const struct vlff_ring *ring);

/* Producer: returns the next slot's record area (slot_size bytes, 64-byte aligned) to
 * fill in place; *seq receives its record number (may be NULL). Never waits. Calling
 * it again before commit returns the same slot. Consumers cannot see the slot's old
 * record any more once this returns. */
void *vlff_ring_reserve(struct vlff_ring *ring, uint64_t *seq);
/* Producer: publishes the reserved record with its length (<= slot_size) and wakes
 * waiting consumers. Returns 0, or -1 (EINVAL: nothing reserved; EMSGSIZE). */
int vlff_ring_commit(struct vlff_ring *ring, size_t len);
/* Producer: copy-in convenience = reserve + memcpy + commit. */
int vlff_ring_write(struct vlff_ring *ring, const void *data, size_t len);

/* Producer: waits until a consumer sleeps in vlff_ring_read_begin for a record newer
 * than the newest committed one, i.e. until some consumer has read everything. For
 * tools that replay recorded data as fast as their reader takes it; live producers
 * never wait. Consumers that poll with timeout 0 are never seen; with several
 * consumers the first one that catches up ends the wait. Finding a sleeping consumer
 * wakes it once; it finds nothing new and sleeps again. Returns 0, or -1 with
 * ETIMEDOUT, EINVAL (not a producer handle). */
int vlff_ring_wait_reader(struct vlff_ring *ring, uint64_t timeout_ns);

/* A record being read in place by a consumer. */
struct vlff_ring_view {
  const void *data;      /* record bytes, in the segment; may change under you */
  size_t len;
  uint64_t seq;          /* record number */
  uint32_t generation;   /* producer generation that wrote it */
  uint32_t new_generation; /* 1 if the producer restarted since the previous read */
};

/* Consumer: waits up to timeout_ns (0 = do not wait, UINT64_MAX = forever) for the next
 * unread record and points *view at it. If the producer lapped this consumer, skips to
 * the oldest record still intact and adds the skipped records to vlff_ring_lost().
 * Returns 0, or -1 with EAGAIN (timeout 0, nothing new), ETIMEDOUT, EINTR, EPIPE.
 * The data may be overwritten while you read it: copy or use what you need, then call
 * vlff_ring_read_end() and trust what you read only if it returns 0. */
int vlff_ring_read_begin(struct vlff_ring *ring, struct vlff_ring_view *view, uint64_t timeout_ns);
/* Consumer: 0 if the record was not touched since read_begin (what you read is whole),
 * -1 with ESTALE if it was overwritten (discard what you read; it is counted as lost).
 * Either way the cursor moves past it. */
int vlff_ring_read_end(struct vlff_ring *ring, const struct vlff_ring_view *view);
/* Consumer: read_begin + copy into buf (cap bytes) + read_end, retrying torn records.
 * Returns the record length, or -1 (EMSGSIZE if cap is too small: the record is
 * skipped and counted as lost, and errors of read_begin). */
ssize_t vlff_ring_read_copy(struct vlff_ring *ring, void *buf, size_t cap,
                            struct vlff_ring_view *info, uint64_t timeout_ns);
/* Consumer: copies the newest committed record without moving the cursor (CLI, tools).
 * Returns its length, or -1 (EAGAIN: ring empty; EMSGSIZE). */
ssize_t vlff_ring_read_latest(struct vlff_ring *ring, void *buf, size_t cap,
                              struct vlff_ring_view *info);
/* Consumer: records this consumer lost to lapping or overwrite since attach. Exact:
 * every record number up to the last one returned was either delivered by a
 * successful read_end/read_copy or counted here. */
uint64_t vlff_ring_lost(const struct vlff_ring *ring);
/* Consumer: moves the cursor to the oldest record still held / past the newest one. */
void vlff_ring_seek_oldest(struct vlff_ring *ring);
void vlff_ring_seek_newest(struct vlff_ring *ring);

/* ------------------------------------------------------------ frame records */

enum vlff_pixfmt {
  VLFF_PIX_NONE = 0,
  VLFF_PIX_RGB8 = 1,
  VLFF_PIX_BGR8 = 2,
  VLFF_PIX_MONO8 = 3,
  VLFF_PIX_MONO16 = 4,
  VLFF_PIX_BAYER_RG8 = 5,
  VLFF_PIX_BAYER_BG8 = 6,
  VLFF_PIX_BAYER_GR8 = 7,
  VLFF_PIX_BAYER_GB8 = 8,
  VLFF_PIX_DEPTH_U16_MM = 16, /* depth, uint16 millimetres, 0 = invalid */
  VLFF_PIX_DEPTH_F32_M = 17   /* depth, float32 metres, 0 or NaN = invalid */
};
/* Bytes per pixel of a format, 0 for an unknown one. */
unsigned vlff_pixfmt_bpp(uint32_t fmt);
const char *vlff_pixfmt_name(uint32_t fmt);

enum { VLFF_PLANE_COLOR = 0, VLFF_PLANE_DEPTH = 1, VLFF_FRAME_MAX_PLANES = 2 };

struct vlff_plane {
  uint32_t width, height;
  uint32_t stride;   /* bytes per row */
  uint32_t format;   /* enum vlff_pixfmt; VLFF_PIX_NONE = plane absent */
  uint64_t offset;   /* of the first pixel from the start of the record (64-aligned) */
  uint64_t size;     /* bytes = stride * height */
};

enum vlff_frame_flags {
  VLFF_FRAME_POSE_VALID = 1u << 0,     /* pose[] and pose_t_ns hold a pose */
  VLFF_FRAME_POSE_UNTRUSTED = 1u << 1, /* tracker reported loss / low quality */
  VLFF_FRAME_INTRINSICS_VALID = 1u << 2,
  VLFF_FRAME_DROPPED_BEFORE = 1u << 3  /* the source dropped frames just before this one */
};

/* The record of a VLFF_RECORD_FRAME ring: this header, then the planes at their
 * offsets. Fixed layout, 512 bytes, no implicit padding. */
struct vlff_frame_hdr {
  uint32_t hdr_size;     /* sizeof(struct vlff_frame_hdr) */
  uint32_t flags;        /* enum vlff_frame_flags */
  uint64_t frame_id;     /* per-sensor counter from the source */
  uint64_t t_device_ns;  /* camera clock, as reported (0 = unknown) */
  uint64_t t_host_ns;    /* CLOCK_MONOTONIC at arrival */
  uint32_t sensor_id;
  uint32_t nplanes;      /* planes in use, 1 or 2 */
  struct vlff_plane plane[VLFF_FRAME_MAX_PLANES];
  double fx, fy, cx, cy; /* pinhole intrinsics in pixels of the color plane; pixel (u,v)
                            is centred at (u+0.5, v+0.5) (OpenCV's cx is this cx - 0.5) */
  double pose[16];       /* camera-to-world, row-major */
  uint64_t pose_t_ns;    /* timestamp of the pose source sample */
  uint8_t reserved[512 - 4 * 4 - 3 * 8 - VLFF_FRAME_MAX_PLANES * 32 - 4 * 8 - 16 * 8 - 8];
};

/* Bytes a slot needs for frames up to max_w x max_h with a color plane of color_fmt and
 * optionally a depth plane of depth_fmt (VLFF_PIX_NONE = none). 0 on bad arguments. */
uint64_t vlff_frame_slot_size(uint32_t max_w, uint32_t max_h, uint32_t color_fmt, uint32_t depth_fmt);
/* Fills hdr->plane[] (offsets, strides, sizes) for the given geometry, tightly packed
 * after the header; zeroes the rest of hdr except what is kept below. Returns the
 * record length, or 0 if it would exceed slot_size. Callers then set ids, times,
 * intrinsics, pose and flags. */
uint64_t vlff_frame_layout(struct vlff_frame_hdr *hdr, uint64_t slot_size, uint32_t w, uint32_t h,
                           uint32_t color_fmt, uint32_t depth_fmt);
/* Checks that a record of len bytes holds a well-formed frame (sizes, formats,
 * planes inside the record, finite intrinsics/pose when flagged valid). 0 or -1/EBADMSG. */
int vlff_frame_validate(const void *record, size_t len);
/* Pointer to plane i's first pixel inside a validated record, NULL if absent. */
const void *vlff_frame_plane(const void *record, unsigned i);

/* ---------------------------------------------------------- feature records */

enum { VLFF_FEAT_F16 = 1 };
/* The record of a VLFF_RECORD_FEATURE ring: this header, then dim*height*width IEEE
 * half floats laid out [D][h][w] at data_offset. */
struct vlff_feature_hdr {
  uint32_t hdr_size;   /* sizeof(struct vlff_feature_hdr) */
  uint32_t dtype;      /* VLFF_FEAT_F16 */
  uint64_t frame_id;   /* of the frame the features were computed from */
  uint64_t t_host_ns;  /* that frame's host timestamp */
  uint32_t sensor_id;
  uint32_t dim, height, width;
  uint64_t data_offset; /* from the record start, 64-aligned */
  uint64_t data_size;   /* bytes = 2 * dim * height * width */
  uint8_t reserved[128 - 4 * 2 - 8 * 2 - 4 * 4 - 8 * 2];
};
uint64_t vlff_feature_slot_size(uint32_t dim, uint32_t h, uint32_t w);
/* Fills the layout fields; returns the record length or 0 if over slot_size. */
uint64_t vlff_feature_layout(struct vlff_feature_hdr *hdr, uint64_t slot_size, uint32_t dim, uint32_t h, uint32_t w);
int vlff_feature_validate(const void *record, size_t len);

/* ------------------------------------------------------------- pose records */

/* The record of a VLFF_RECORD_POSE ring: one timestamped camera-to-world pose. */
struct vlff_pose_rec {
  uint64_t t_ns;
  uint32_t flags;       /* VLFF_FRAME_POSE_UNTRUSTED may be set */
  uint32_t source_id;
  double pose[16];      /* camera-to-world, row-major; rotation block orthonormal */
};

/* Pure helper: the unit quaternion (w, x, y, z; Hamilton) of a pose's
 * rotation block, by Shepperd's method (well conditioned for any rotation). */
void vlff_pose_quaternion(const double pose[16], double q_wxyz[4]);
/* Pure helper: the pose at time t between a (t_a <= t) and b (t >= t), translation
 * linear, rotation slerp. 0, or -1/EINVAL if t is outside [a.t_ns, b.t_ns]. */
int vlff_pose_interpolate(const struct vlff_pose_rec *a, const struct vlff_pose_rec *b, uint64_t t_ns,
                          double out_pose[16]);
/* Finds the pose for t_ns in a pose ring (a consumer handle; its cursor is untouched):
 * the two consecutive poses bracketing t_ns, both within tolerance_ns of it, are
 * interpolated; a pose at exactly t_ns is returned as is. The result's flags are the
 * OR of the bracketing poses' flags. Returns 0, or -1 with EAGAIN (t_ns is newer than
 * every pose: it may still arrive), ERANGE (no bracketing pair within tolerance: reject
 * the frame), ENOENT (ring empty). */
int vlff_pose_lookup(struct vlff_ring *poses, uint64_t t_ns, uint64_t tolerance_ns, struct vlff_pose_rec *out);

/* ---------------------------------------------------------------- the map */

/* Labels 0..VLFF_LABEL_MAX index the map's prompt list. */
#define VLFF_LABEL_MAX 0xFFFDu
#define VLFF_LABEL_FREE 0xFFFEu    /* observed empty space */
#define VLFF_LABEL_UNKNOWN 0xFFFFu /* never observed */
#define VLFF_SHM_MAX_PROMPTS 32
/* A map grid's physical bounds: its voxel size in metres, and how far from
 * the world's origin any of its corners may lie (1e8 m holds UTM
 * coordinates); a publish outside them is refused (EINVAL) and a segment
 * holding one reads as corrupt. */
#define VLFF_MAP_VOXEL_MIN_M 1e-4
#define VLFF_MAP_VOXEL_MAX_M 1e3
#define VLFF_MAP_COORD_MAX_M 1e8
#define VLFF_SHM_PROMPT_LEN 64     /* bytes including the terminating NUL */

struct vlff_map; /* opaque: the writer (create) or a reader (attach) */
struct vlff_map_snapshot; /* opaque: a reader's private consistent copy */

struct vlff_map_params {
  uint32_t max_voxels;                     /* grid capacity */
  uint32_t label_max_width, label_max_height; /* 2D label image capacity (0 = none) */
  struct vlff_shm_perm perm;
};

/* A voxel grid: voxel (i,j,k) covers origin + [i,i+1)*voxel_size in x (j in y, k in z)
 * and is stored at index i + dims[0] * (j + dims[1] * k). */
struct vlff_map_grid {
  double origin[3];      /* world position of the grid's min corner, metres */
  double voxel_size;     /* metres, > 0 */
  uint32_t dims[3];
  const uint16_t *labels;     /* dims[0]*dims[1]*dims[2] labels */
  const uint8_t *confidence;  /* same count, 0..255; NULL = all 255 */
};

/* The latest 2D label image and the view it was rendered from. */
struct vlff_map_label_image {
  uint32_t width, height;
  const uint16_t *labels;     /* width*height, row-major */
  const uint8_t *confidence;  /* same count; NULL = all 255 */
  double fx, fy, cx, cy;
  double pose[16];            /* camera-to-world */
  uint64_t t_ns;              /* capture time of the frame it was rendered for */
};

/* A run of grid elements, [first, first + count), in the grid's storage order
 * (vlff_map_grid: the voxel index). The change log speaks only of such runs, so
 * that a later grid layout (tiles, a sparse grid) keeps the same contract: follow
 * versions, learn which elements changed. */
struct vlff_map_range {
  uint32_t first, count;
};

/* What a publish replaces; a NULL member keeps the previous value.
 *
 * With grid and ranges: a partial publish. The elements inside the ranges are
 * replaced from grid->labels / grid->confidence, which still hold the whole grid's
 * current values (a coarsened run, below, also reads the elements between the runs
 * it joins); the rest of the map stays as it was. The grid's geometry
 * must be the published one (EINVAL otherwise, and before the first publish).
 * Ranges may come in any order and overlap; range_count 0 changes no element.
 * The writer logs them (merged, and coarsened to at most a quarter of the log when
 * there are more: a logged run may cover unchanged elements, never miss a changed
 * one). A grid without ranges replaces and logs the whole grid. */
struct vlff_map_update {
  const struct vlff_map_grid *grid;
  const char *const *prompts; /* prompt_count texts; label i = prompts[i] */
  int prompt_count;           /* -1 = keep (when prompts is NULL) */
  const struct vlff_map_label_image *label_image;
  const struct vlff_map_range *ranges; /* NULL = the whole grid (when grid is given) */
  size_t range_count;
};

/* Writer: creates the map segment (same O_EXCL / stale-creator / owner rules as
 * rings; a taken-over segment keeps its last map and bumps the generation, and its
 * dead writer's status reads as none until this writer sets one). A publish
 * or heartbeat that finds the file truncated fails once with EPIPE after replacing
 * the segment (version numbering on, the previous map is gone: publish it again). */
struct vlff_map *vlff_map_create(const char *name, const struct vlff_map_params *params);
/* Writer: publishes a new consistent version (version + 1, publish time and heartbeat
 * = now). Never waits for readers. -1/EMSGSIZE if the grid, image or a prompt is
 * larger than the segment allows, EINVAL for malformed input. */
int vlff_map_publish(struct vlff_map *map, const struct vlff_map_update *update);
/* Writer: says "alive" without a new map. */
int vlff_map_heartbeat(struct vlff_map *map);
/* Writer: makes room for grids of up to max_voxels voxels (0 when the segment
 * holds that many already). A new segment, sized for it, holding what the map
 * holds now (the published grid, label image, prompts, status, version), takes
 * the name (ABI 9); the old one is marked moved, and every reader attached to it
 * attaches the new one at its next call and reads on, the same labels at the same
 * points (docs/shm.md "A map that grows"). The next publish may then be a grid of
 * up to max_voxels. -1 (EINVAL: not a writer or max_voxels above 2^32 - 1;
 * ENOSPC and others: the new segment could not be made; the old one is kept). */
int vlff_map_reserve(struct vlff_map *map, uint64_t max_voxels);
/* The grid size the segment holds (voxels), as the handle sees it now. */
uint64_t vlff_map_capacity(const struct vlff_map *map);

/* The far map (ABI 10). A robot's world is larger than any grid a controller
 * should copy: the grid above is the window around the robot, and what the
 * writer moved out of it as the robot went on is kept beside it, compacted,
 * as far blocks: cubes of VLFF_MAP_FAR_EDGE voxels of voxel_size on a lattice
 * from origin (block key k covers origin + [k x EDGE, (k + 1) x EDGE) x
 * voxel_size on each axis), each a run-length list of (label, confidence)
 * over its EDGE^3 voxels in the grid's order (x fastest, then y, z). Where the
 * grid covers a point, the grid answers; elsewhere the far block holding it,
 * else VLFF_LABEL_UNKNOWN. vlff_map_label_at and the snapshots read both
 * (docs/shm.md "The far map"). */
#define VLFF_MAP_FAR_EDGE 16u
struct vlff_map_far_block {
  int32_t key[3];     /* block coordinates on the far lattice */
  uint32_t first_run; /* its runs: [first_run, the next block's first_run or nruns) */
};
struct vlff_map_far_run {
  uint16_t label; /* as the grid's: a prompt, VLFF_LABEL_FREE or VLFF_LABEL_UNKNOWN */
  uint16_t count; /* voxels, >= 1; a block's counts sum to EDGE^3 */
  uint8_t conf;
  uint8_t pad;
};
struct vlff_map_far {
  double origin[3], voxel_size;
  uint32_t nblocks, nruns;
  const struct vlff_map_far_block *blocks; /* sorted by key: z, then y, then x; each key once */
  const struct vlff_map_far_run *runs;
};
/* The bytes a far map of nblocks blocks and nruns runs takes in the segment
 * (each of its two buffers holds one). */
uint64_t vlff_map_far_bytes(uint32_t nblocks, uint32_t nruns);
/* NULL when far keeps the contract above (blocks and runs, sorted unique
 * keys, every block's runs of at least one voxel summing to EDGE^3, a
 * geometry within the grid's physical bounds), else a constant text naming
 * what it breaks: for a writer checking a far map it read back (a
 * checkpoint) before it publishes it. */
const char *vlff_map_far_check(const struct vlff_map_far *far);
/* Writer: the far map the next publish carries (any publish, partial ones
 * too), copied now; NULL or no blocks: none. Until then readers read the far
 * map they had. -1: EINVAL for one that breaks the contract above (unsorted
 * or repeated keys, a block whose runs do not sum to EDGE^3, a run of 0, a
 * geometry outside the grid's physical bounds), EMSGSIZE when it passes the
 * segment's far capacity (vlff_map_reserve_far), ENOMEM. */
int vlff_map_set_far(struct vlff_map *map, const struct vlff_map_far *far);
/* Writer: as vlff_map_create, with room for a far map of far_bytes from the
 * start (a restarted writer asks for the far capacity its segment had, so
 * that it takes the segment over in place rather than replacing it). */
struct vlff_map *vlff_map_create_far(const char *name, const struct vlff_map_params *params, uint64_t far_bytes);
/* Writer: as vlff_map_reserve, also making room for a far map of far_bytes
 * (vlff_map_far_bytes); neither capacity shrinks. */
int vlff_map_reserve_far(struct vlff_map *map, uint64_t max_voxels, uint64_t far_bytes);
/* The far map's capacity in bytes, as the handle sees it now. */
uint64_t vlff_map_far_capacity(const struct vlff_map *map);

/* Reader: attaches read-only and validates the segment. A reader's handle follows
 * its writer's vlff_map_reserve by itself. */
struct vlff_map *vlff_map_attach(const char *name);
/* Releases either handle; the segment stays. */
void vlff_map_detach(struct vlff_map *map);

/* Reader: the label and confidence of the voxel holding world point (x,y,z) in the
 * current version, read consistently: the grid's voxel, else the far map's
 * (above). 0 and the label (VLFF_LABEL_UNKNOWN outside both, or before the
 * first publish), or -1 (EINVAL: a NaN or infinite
 * coordinate; EPIPE; EAGAIN if the writer kept changing it for too long; EBADMSG:
 * inconsistent map metadata). conf may be NULL. */
int vlff_map_label_at(struct vlff_map *map, double x, double y, double z, uint16_t *label, uint8_t *conf);
/* Reader: copies the prompt text of a label (NUL-terminated, truncated to len) into buf.
 * Returns 0, or -1/ENOENT for a label without a prompt (FREE, UNKNOWN, >= count). */
int vlff_map_prompt(struct vlff_map *map, uint16_t label, char *buf, size_t len);
/* The current map version (0 = nothing published yet); for the writer, the last
 * version it published. */
uint64_t vlff_map_version(struct vlff_map *map);
/* ns since the current version was published; UINT64_MAX if never. */
uint64_t vlff_map_age_ns(struct vlff_map *map);
/* 1 if the writer's heartbeat is younger than max_silence_ns and its process exists,
 * else 0. */
int vlff_map_writer_alive(struct vlff_map *map, uint64_t max_silence_ns);
uint32_t vlff_map_generation(struct vlff_map *map);

/* Reader: a snapshot buffer sized for this map's capacity. */
struct vlff_map_snapshot *vlff_map_snapshot_new(struct vlff_map *map);
void vlff_map_snapshot_free(struct vlff_map_snapshot *snap);
/* Reader: copies the current version into snap, retrying while the writer overwrites
 * it. 0, or -1 (EAGAIN after many retries, EPIPE, EBADMSG for a map whose metadata
 * is inconsistent, ENOMEM when snap could not grow for a map its writer grew:
 * vlff_shm_last_message says which). */
int vlff_map_snapshot_take(struct vlff_map *map, struct vlff_map_snapshot *snap);

/* Reader: brings snap up to the current version by copying only what changed since
 * the version it holds, read from the map's change log: a bounded ring of (version,
 * changed runs) that every publish appends to beside the consistent full map. Falls
 * back to a whole copy, as vlff_map_snapshot_take, when snap is empty (never taken,
 * or a take or follow failed), the log no longer reaches back to snap's version
 * (the reader fell too far behind), or the writer's generation or the grid's
 * geometry changed. Prompts, the label image and the metadata are always current
 * afterwards. The copy is as consistent as a take: never a mix of two versions.
 * Returns 1 (a whole copy), 0 (only changed runs, possibly none: snap was current),
 * or -1 (as vlff_map_snapshot_take; snap is then empty, and the next follow copies
 * everything). */
int vlff_map_snapshot_follow(struct vlff_map *map, struct vlff_map_snapshot *snap);
/* The grid elements the last take or follow changed in snap: *ranges (sorted,
 * disjoint, not adjacent; valid until the next call on snap) and their count.
 * *all (may be NULL) is 1 when the whole grid was copied (the ranges then are the
 * one run of the whole grid, or none for a map without a grid). A run may hold
 * elements whose value did not change (the writer logged what it relabelled). */
size_t vlff_map_snapshot_changes(const struct vlff_map_snapshot *snap, const struct vlff_map_range **ranges,
                                 int *all);

/* Accessors of a taken snapshot; pointers live as long as snap's contents. */
struct vlff_map_info {
  uint64_t version;
  uint64_t publish_ns;
  uint32_t generation;
  int prompt_count;
  struct vlff_map_grid grid;               /* labels/confidence point into snap */
  int has_label_image;
  struct vlff_map_label_image label_image; /* idem */
};
int vlff_map_snapshot_info(const struct vlff_map_snapshot *snap, struct vlff_map_info *info);
uint16_t vlff_map_snapshot_label_at(const struct vlff_map_snapshot *snap, double x, double y, double z,
                                    uint8_t *conf);
/* The snapshot's far map (pointers into snap; nblocks 0 when it has none),
 * checked against the contract when it was copied (a take or follow of a
 * far map that breaks it fails with EBADMSG). 0, or -1 (EINVAL) for NULL
 * arguments. */
int vlff_map_snapshot_far(const struct vlff_map_snapshot *snap, struct vlff_map_far *far);
/* The version of the publish that gave the snapshot's far map (the last
 * vlff_map_set_far before it, an empty far map too), 0 when none ever did
 * or snap is NULL or holds no map (2.4.0). A reader that sends the far map
 * on (a viewer, a bridge) sends it again when this differs from the one it
 * sent: the grid's geometry can stay the same when it changes. */
uint64_t vlff_map_snapshot_far_version(const struct vlff_map_snapshot *snap);
/* Prompt text of a label, NULL if none. */
const char *vlff_map_snapshot_prompt(const struct vlff_map_snapshot *snap, uint16_t label);

/* ------------------------------------------------------- the writer's status */

/* Besides the map, the map segment carries its writer's status: what the learner
 * took in, refused and learned, so that any controller reads it without asking the
 * learner. The writer replaces it whole, as often as it likes (the node: at each
 * heartbeat and publish); readers copy it under its own sequence word and retry
 * while it moves, so neither ever waits for the other. The reasons for refused
 * frames travel with their names, so that readers need not know the writer's list.
 * This struct is also the segment's layout (fixed, no implicit padding): changing
 * it changes VLFF_SHM_ABI_VERSION. */
#define VLFF_SHM_MAX_REASONS 16
#define VLFF_SHM_REASON_LEN 24 /* bytes including the terminating NUL */
#define VLFF_SHM_STATE_LEN 16

struct vlff_map_reason {
  char name[VLFF_SHM_REASON_LEN]; /* short text ("no pose"); never empty in a used entry */
  uint64_t count;
};

struct vlff_map_status {
  uint64_t t_ns;           /* when it was set (set by vlff_map_set_status); 0 = none (never set, or withdrawn by a writer that took the segment over) */
  uint64_t updates;        /* 1, 2, ... per vlff_map_set_status on this segment */
  int32_t state;           /* writer-defined code (vlff-node: enum vlff_node_state) */
  uint32_t error_flags;    /* writer-defined bits (vlff-node: enum vlff_node_error_flags) */
  char state_name[VLFF_SHM_STATE_LEN]; /* the state as text ("operational") */
  uint64_t frames_in;      /* frames read from the input */
  uint64_t frames_lost;    /* frames lost before they could be read */
  uint64_t frames_refused; /* frames refused, all reasons */
  uint64_t keyframes;      /* keyframes held now */
  uint64_t keyframes_evicted;
  uint64_t iterations;     /* training steps so far */
  double iterations_per_s;
  double fps_in;           /* frames read per second */
  double loss, loss_rgb, loss_depth, loss_feat; /* latest training loss and its terms */
  double psnr;             /* dB of the colour term; NaN when unknown */
  double cpu_budget;       /* cores the writer allows itself (vlff-node: node.cpu_budget); 0 = no limit */
  double cpu_used;         /* cores the writer's process used lately (vlff-node: the last 3 s); -1 unknown */
  uint32_t reason_count;   /* used entries of reason[] */
  uint32_t pad;
  struct vlff_map_reason reason[VLFF_SHM_MAX_REASONS]; /* refused frames per reason */
  /* How current the map is (vlff-node; docs/node.md, "Publishing"): ms from a
   * keyframe's capture to the first map version whose change log covers its
   * voxels (median and 99th percentile of the recent ones), and s between
   * whole refreshes of the map; -1 while unknown. */
  double frame_to_map_ms_p50, frame_to_map_ms_p99;
  double publish_interval_s;
  /* Label churn (vlff-node; docs/shm.md, "The writer's status"): voxels whose
   * published label changed (one labelled for the first time is new, not a flip)
   * at the last publish, over the publishes of the last whole refresh, and since
   * the writer started; label_flip_frac: over the last whole refresh, the share of
   * the labelled voxels that no new observation reached that flipped anyway; -1
   * while unknown. */
  uint64_t label_flips, label_flips_refresh, label_flips_total;
  double label_flip_frac;
  /* Memory, MiB (vlff-node; docs/node.md, "Memory"): the keyframe store's use
   * and limit, the evidence's use and limit, the field's fixed size, the
   * writer process's resident set; -1 while unknown. */
  double mem_keyframes_mb, mem_keyframes_limit_mb, mem_evidence_mb, mem_evidence_limit_mb;
  double mem_field_mb, mem_rss_mb;
  /* Paging (vlff-node; docs/node.md, "Memory"): what no longer fits the
   * memory limits above goes to page files in the writer's state directory
   * and comes back when the robot returns, and what has nowhere to go is
   * dropped and counted. Keyframes: in the page file now, written there and
   * brought back since the start (or the last reset), dropped; the page
   * file's MiB in use and its limit (vlff-node: keyframes.page_mb; 0 = no
   * page file). Evidence: voxels whose evidence is in its page file now,
   * written there and brought back since the start, given up for good. */
  uint64_t keyframes_paged, keyframes_paged_out, keyframes_paged_in, keyframes_dropped;
  double keyframes_page_mb, keyframes_page_limit_mb;
  uint64_t evidence_paged, evidence_paged_out, evidence_paged_in, evidence_dropped;
  /* The map's box in world metres (min and max corners; it may grow: docs/
   * shm.md, "A map that grows"), how often it grew since the start, and how
   * many growths were refused (the map or the field at a configured limit). */
  double box_lo[3], box_hi[3];
  uint64_t box_growths, box_refused;
};

/* Writer: replaces the status (t_ns and updates are set here, the rest is taken as
 * given). Never waits for readers. 0, or -1: EINVAL (not a writer handle, more than
 * VLFF_SHM_MAX_REASONS reasons, a used reason without a name, a name or state that
 * does not fit), EPIPE (as vlff_map_heartbeat after a truncation: set it again). */
int vlff_map_set_status(struct vlff_map *map, const struct vlff_map_status *status);
/* Reader (or writer): copies the latest status into *out, consistently; strings are
 * NUL-terminated and reason_count is at most VLFF_SHM_MAX_REASONS. 0, or -1: ENOENT
 * (no status set yet: *out is zeroed), EAGAIN (the writer kept changing it for too
 * long), EBADMSG (inconsistent block), EPIPE. */
int vlff_map_get_status(struct vlff_map *map, struct vlff_map_status *out);

/* -------------------------------------------------------- prompt mailbox */

struct vlff_prompts; /* opaque */

/* A prompt set posted to the mailbox: either texts, or the index of a set the learner
 * has configured (set_index >= 0, count = 0). */
struct vlff_prompt_request {
  uint64_t seq;        /* 1, 2, ... per post; 0 = nothing posted yet */
  uint64_t t_ns;       /* when posted */
  int32_t poster_pid;
  int32_t set_index;   /* -1 when texts are given */
  int count;
  char text[VLFF_SHM_MAX_PROMPTS][VLFF_SHM_PROMPT_LEN];
};

/* The prompt mailbox: posts are serialised by flock() on the segment's file, a lock
 * the kernel drops with its holder, so a poster killed mid-post never blocks the next
 * one; the learner's poll never waits for a poster; every request gets an answer that
 * the poster can wait for (the answers to the last 8 requests are kept).
 *
 * The learner creates the mailbox (same O_EXCL / stale-creator / owner rules; use
 * mode 0660 with a group so that controllers may post). */
struct vlff_prompts *vlff_prompts_create(const char *name, const struct vlff_shm_perm *perm);
/* A controller attaches read-write to post. */
struct vlff_prompts *vlff_prompts_attach(const char *name);
void vlff_prompts_close(struct vlff_prompts *p);

/* Checks a prompt set as the learner will, and as the embeddings file format checks
 * prompts: 1..VLFF_SHM_MAX_PROMPTS texts, each 1..VLFF_SHM_PROMPT_LEN-1 bytes of valid
 * UTF-8 without control characters (tabs and newlines included), none repeated.
 * 0, or -1/EINVAL with the reason in vlff_shm_last_message(). */
int vlff_prompt_check(const char *const *texts, int count);

/* Posts texts (checked with vlff_prompt_check). Posts are serialised by a lock that
 * dies with its holder, none is torn, and a post waits until the learner has answered
 * the previous request, so no request is ever overwritten unread. Returns 0 (the
 * request's number is vlff_prompts_last_post()), or -1: EINVAL (texts refused),
 * EBUSY (the previous request still had no answer, or another poster held the lock,
 * after a bounded wait; the message says which and whether the learner runs), EPIPE
 * (mailbox abandoned or truncated: attach again). */
int vlff_prompts_post(struct vlff_prompts *p, const char *const *texts, int count);
/* Posts "switch to configured set index". Same rules. */
int vlff_prompts_post_index(struct vlff_prompts *p, int set_index);
/* Posts like vlff_prompts_post (texts, count >= 1) or vlff_prompts_post_index (texts
 * NULL, set_index >= 0) but never waits, for an event loop: -1/EBUSY at once when a
 * request still waits for the learner's answer or another poster holds the lock;
 * otherwise the same results. Poll vlff_prompts_wait_answer with timeout 0 for the
 * answer. */
int vlff_prompts_try_post(struct vlff_prompts *p, const char *const *texts, int count, int set_index);
/* The number of this handle's last successful post, 0 if none. */
uint64_t vlff_prompts_last_post(const struct vlff_prompts *p);

enum vlff_prompt_answer { VLFF_PROMPT_PENDING = 0, VLFF_PROMPT_ACCEPTED = 1, VLFF_PROMPT_REFUSED = 2 };
/* Poster: waits up to timeout_ns (UINT64_MAX = forever) for the learner's answer to
 * request seq. Returns VLFF_PROMPT_ACCEPTED or VLFF_PROMPT_REFUSED (the reason, NUL
 * terminated, in reason[len]), or -1: ETIMEDOUT (the message says whether the learner
 * runs), ENOENT (never answered: a later request was answered instead), EPIPE. */
int vlff_prompts_wait_answer(struct vlff_prompts *p, uint64_t seq, uint64_t timeout_ns, char *reason, size_t len);

/* Learner: copies the newest request if its seq differs from *last_seq, then updates
 * *last_seq. Never waits for a poster. Returns 1 (new request in *req: apply it, then
 * vlff_prompts_answer it), 0 (nothing new, or a post is being written: poll again
 * later), -1 with a message worth logging: EBADMSG (a malformed request, or one left
 * half-written by a poster that died; it has been answered "refused" with the reason
 * and *last_seq moved past it), EPIPE (the mailbox file was truncated; it has been
 * replaced by a new one, numbering on). */
int vlff_prompts_poll(struct vlff_prompts *p, uint64_t *last_seq, struct vlff_prompt_request *req);
/* Learner: answers request seq: accepted, or refused with a reason (truncated to a
 * line of text) that the poster's vlff_prompts_wait_answer returns. 0 or -1. */
int vlff_prompts_answer(struct vlff_prompts *p, uint64_t seq, int accepted, const char *reason);

#ifdef __cplusplus
}
#endif

#endif /* VLFF_SHM_H */
