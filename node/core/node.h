/*
 * vlff_node: the online learner process, as a library so that tests and
 * benchmarks drive exactly what vlff-node runs.
 *
 * Data path: frame ring -> ingest thread (validate, pose, keyframe
 * selection, features) -> candidate queue -> trainer thread (pose check,
 * keyframe store, field steps, publishing, checkpoints) -> map segment.
 * The trainer thread is the only user of the field, so training, queries
 * and checkpoints never race.
 *
 * Contract
 *  - vlff_node_create() validates the config, creates the map and prompt
 *    segments, restores the newest valid checkpoint from node.state_dir (a
 *    corrupt one is reported, counted and skipped) and starts the threads.
 *    It returns NULL with err filled on failure.
 *  - vlff_node_stop() asks the threads to finish; vlff_node_destroy() joins
 *    them, writes a final checkpoint when save_on_exit is set, and frees.
 *  - vlff_node_status() and vlff_node_command() may be called from any
 *    thread at any time (they take a short internal lock; the trainer never
 *    waits on callers).
 */
#ifndef VLFF_NODE_H
#define VLFF_NODE_H

#include <stdbool.h>
#include <stdint.h>

#include "config.h"
#include "publish.h"
#include "source.h"

struct vlff_node;
struct vlff_map_status;

enum vlff_node_state { /* CANopen NMT-like */
  VLFF_NODE_BOOT = 0x00,
  VLFF_NODE_PREOP = 0x7f,   /* running, not yet learning (too few keyframes) */
  VLFF_NODE_OPERATIONAL = 0x05,
  VLFF_NODE_STOPPED = 0x04, /* mapping stopped by command */
  VLFF_NODE_ERROR = 0x7e
};

enum vlff_node_error_flags {
  VLFF_NODE_ERR_CAMERA_LOST = 1u << 0, /* no frame for 3 frame intervals, at least 1 s (watch.h) */
  VLFF_NODE_ERR_POSE_STALE = 1u << 1,  /* recent frames lack a usable pose */
  VLFF_NODE_ERR_SHM_LAPPED = 1u << 2,  /* the ring lapped us recently */
  VLFF_NODE_ERR_CHECKPOINT = 1u << 3   /* the last checkpoint failed */
};

/* Why the ingest thread refused a frame from the ring. Each reason is
 * counted in vlff_node_status.refused[], logged at info (the first with
 * its detail, then counts every few seconds while they go on) and carried
 * on CAN (VLFF_INGEST, configs/vlff.dbc); the values are the DBC's. */
enum vlff_refusal {
  VLFF_REFUSED_NONE = 0,
  VLFF_REFUSED_MALFORMED = 1,      /* not a well-formed frame record, or larger than a slot */
  VLFF_REFUSED_OVERSIZE = 2,       /* larger than shm.max_width x shm.max_height */
  VLFF_REFUSED_PIXEL_FORMAT = 3,   /* colour plane neither RGB8 nor Mono8 */
  VLFF_REFUSED_NO_INTRINSICS = 4,  /* intrinsics not flagged valid, or not finite */
  VLFF_REFUSED_BAD_INTRINSICS = 5, /* focal lengths or principal point implausible for the image size */
  VLFF_REFUSED_NO_POSE = 6,        /* none in the frame, none in the pose ring within pose_tolerance_s */
  VLFF_REFUSED_BAD_POSE = 7,       /* not a rigid transform (NaN, rotation not orthonormal) */
  VLFF_REFUSED_POSE_RANGE = 8,     /* camera far outside the box or the world, or a step between keyframe
                                      candidates beyond their depth: wrong units or frame */
  VLFF_REFUSED_NO_DEPTH = 9,       /* no depth plane of the colour plane's size in a depth format */
  VLFF_REFUSED_EMPTY_DEPTH = 10,   /* depth plane without one valid pixel */
  VLFF_REFUSED_TOO_SMALL = 11,     /* under 4x4 pixels at train.image_scale */
  VLFF_REFUSED_NO_FEATURES = 12,   /* simulated features could not be rendered */
  VLFF_REFUSED_FUTURE_POSE = 13,   /* pose stamped ahead of the clock beyond pose.future_tolerance_s */
  VLFF_REFUSED_FEATURES_LATE = 14, /* a keyframe's features (ring or model) did not come in time */
  VLFF_REFUSED_FUTURE_FRAME = 15,  /* frame stamped ahead of the clock beyond pose.future_tolerance_s */
  VLFF_REFUSED_COUNT
};

/* Short fixed name of a reason ("no pose"); "unknown" out of range. */
const char *vlff_refusal_name(int reason);

struct vlff_node_status {
  int state;                    /* enum vlff_node_state */
  unsigned error_flags;         /* enum vlff_node_error_flags */
  long long iteration;
  double loss, loss_rgb, loss_depth, loss_feat, psnr;
  double it_per_s;
  int keyframes;
  long long keyframes_evicted;
  long long keyframes_retired;  /* dropped because newer depth saw through what they show */
  /* Keyframe paging (keyframes.page_mb): evicted keyframes in the state
   * directory's page file now, written there and brought back since the
   * start (or the last reset), and evicted with nowhere to go (no page
   * file, it full, an I/O error). */
  long long keyframes_paged, keyframes_paged_out, keyframes_paged_in, keyframes_dropped;
  /* The keyframes' page file, MiB: in use, and its limit (keyframes.page_mb;
   * 0 when there is none: page_mb 0, or the file could not be made). */
  double keyframes_page_mb, keyframes_page_limit_mb;
  /* Evidence paging (publish.evidence_page_mb; docs/field.md): voxels whose
   * evidence is in the state directory's page file now, written there and
   * brought back since the start (or the last reset), and given up for
   * good (no page file, or it full). */
  long long evidence_paged, evidence_paged_out, evidence_paged_in, evidence_dropped;
  /* The map's box (metres), how often it grew since the start, and the
   * keyframes whose box the field or the map could not grow to (field.grow:
   * the world's limit, train.occupancy_max_mb, shm.map_max_voxels, the
   * evidence's index budget). */
  double box_lo[3], box_hi[3];
  long long box_growths, box_refused;
  /* Beyond the caps (docs/field.md): how often the map's grid slid with
   * the robot, and the far map it left behind (publish.h, far.h): blocks,
   * MiB and its limit (shm.map_far_max_mb), blocks dropped for that limit. */
  long long box_slides, far_blocks, far_dropped;
  double far_mb, far_limit_mb;
  long long frames_in;          /* frames read from the ring */
  long long frames_lost;        /* lapped or torn in the ring */
  long long frames_invalid;     /* refused, all reasons: the sum of refused[] */
  long long refused[VLFF_REFUSED_COUNT]; /* per enum vlff_refusal; [0] unused */
  int last_refusal;             /* reason of the latest refused frame, 0 = none yet */
  long long poses_rejected;     /* keyframes refused by the depth-residual pose check */
  long long features_timeout;   /* keyframes whose features never arrived */
  long long candidates_dropped; /* keyframes the trainer could not take in time */
  double fps_in;
  uint64_t map_version;
  double map_age_s;             /* since the last publish; -1 before the first */
  int prompt_set;               /* index of the active configured set, -1 = posted texts */
  int prompt_count;
  long long checkpoints;
  long long checkpoint_failures; /* saves that failed, and checkpoints refused on load */
  /* Steps whose loss came out non-finite (no update applied), and times the
   * field's own state was found non-finite (after such a step, or at
   * checkpoint time) and rolled back to the newest checkpoint that loads,
   * or re-initialised when none does. */
  long long steps_nonfinite;
  long long field_rollbacks;
  double miou2d, miou3d;        /* against synthetic ground truth; -1 when unknown */
  long long miou2d_frame;       /* the frame id of the view miou2d scored; -1 when unknown */
  double last_pose_residual_m;
  /* From a keyframe's capture stamp to the first map version whose change
   * log covers its voxels (the last LAT_CAP keyframes), ms; -1 before any. */
  double frame_to_map_ms_p50, frame_to_map_ms_p99;
  /* node.cpu_budget in cores (0 = no limit), the process's measured use in
   * cores over the last 3 seconds (all its threads; -1 before the first
   * second), and the learner's worker threads (at most ceil(budget)). */
  double cpu_budget, cpu_used;
  int threads;
  /* Label flips: voxels whose published label changed at the last publish;
   * since start, those that changed although no keyframe observed them
   * since the publish before (label_flips_elsewhere), among the labelled
   * voxels no keyframe observed in between (label_mapped_elsewhere), summed
   * over publishes (publish.h, hold.h). A voxel labelled for the first
   * time is not a flip. label_flips_total: all flips since start;
   * label_flips_refresh: those of the publishes during the last whole
   * refresh of the map (keyframe publishes included), and label_flip_frac
   * the share of the voxels mapped elsewhere then that flipped (-1 before
   * the first refresh, or when none was mapped elsewhere). */
  long long label_flips, label_flips_elsewhere, label_mapped_elsewhere;
  long long label_flips_total, label_flips_refresh;
  double label_flip_frac;
  /* Seconds between whole refreshes of the map (the mean of the last 8;
   * the target is 1 / publish.rate_hz); -1 before the second. */
  double publish_interval_s;
  /* Memory, MiB (docs/node.md, "Memory"): the keyframe store's use and
   * its limit (keyframes.memory_mb); the evidence's use (voxels holding
   * evidence at their share of the budget) and its limit
   * (publish.evidence_max_mb); the field's parameters, Adam moments and
   * step buffers (fixed at create); the process's resident set (-1 until
   * read). */
  double mem_keyframes_mb, mem_keyframes_limit_mb;
  double mem_evidence_mb, mem_evidence_limit_mb;
  double mem_field_mb, mem_rss_mb;
  /* Monotonic ns (vlff_now_ns) of the trainer's and the ingest thread's
   * last loop pass; both pass at least every few hundred ms while alive,
   * busy or idle. */
  uint64_t trainer_beat_ns, ingest_beat_ns;
  /* What start-up changed in the config to make it work, "key from -> to
   * (why)" joined by "; " ("" when nothing): shown on --status, where the
   * user looks, besides the warning in the log. */
  char adjusted[192];
};

enum vlff_node_command {
  VLFF_CMD_START = 1,    /* resume mapping */
  VLFF_CMD_STOP = 2,     /* keep the map, stop learning and admitting keyframes */
  VLFF_CMD_RESET = 3,    /* forget the field and keyframes, start over */
  VLFF_CMD_SAVE = 4,     /* checkpoint now */
  VLFF_CMD_PROMPT_SET = 5, /* arg = configured prompt set index */
  VLFF_CMD_PUBLISH = 6   /* publish the map now */
};

/* What vlff_node_create refuses before it makes anything (node/core/
 * check.c): a source kind it does not read, features or a text encoder this
 * build lacks, prompts without a text encoder, the simulator's features
 * without the simulator. With load_files, also what it then reads: the
 * embeddings file (with every prompt of every set in it), the text encoder
 * (vlm.text_model and vlm.bpe_vocab) and the image encoder (source.features:
 * model), loaded and released; vlff-node --check-config runs that. 0, or -1
 * with err naming the key. hooks as for vlff_node_create. */
int vlff_node_check(const struct vlff_config *cfg, const struct vlff_source_hooks *hooks, bool load_files, char *err,
                    size_t errlen);

/* hooks: what the source gives beyond the frame ring (source.h; the
 * simulator's from vlff_sim_source_create), NULL for none; copied, their ctx
 * must outlive the node. */
struct vlff_node *vlff_node_create(const struct vlff_config *cfg, const struct vlff_source_hooks *hooks, char *err,
                                   size_t errlen);
void vlff_node_stop(struct vlff_node *n);
/* For a process that hosts a node (vlff-node, bench_node): call first,
 * before any thread starts. Allocations of 1 MiB and more (a keyframe's
 * feature map is 20 MB at 320 x 240 and D = 512) are mapped and unmapped
 * on their own. glibc's default raises that threshold to the size of each
 * large block freed, up to 32 MB, after which keyframes came from the
 * threads' arenas, and what the trainer freed of the ingest thread's
 * blocks stayed there: a building's walk grew the node's resident set past
 * its limits (2.1 GB and rising with the keyframe store full at 1 GB,
 * against 1.5 GB flat with the threshold fixed; docs/node.md, "Memory"). */
void vlff_node_process_setup(void);
/* True once the node stopped by itself (node.run_seconds) or was asked to. */
bool vlff_node_finished(struct vlff_node *n);
void vlff_node_destroy(struct vlff_node *n, bool save_on_exit);
/* Stop the threads and wait for them: vlff_node_status then holds the
 * counts the node stopped with (before, the last a pass shared: a pass
 * under a sanitizer can last seconds). */
void vlff_node_join(struct vlff_node *n);

/* Stop the threads (as vlff_node_stop, and wait for them), publish once
 * more, then take the publisher's snapshot (publish.h) into out, which the
 * caller frees with vlff_snapshot_free. 0, or -1 with err. */
int vlff_node_snapshot(struct vlff_node *n, struct vlff_snapshot *out, char *err, size_t errlen);

void vlff_node_status(struct vlff_node *n, struct vlff_node_status *out);
/* The status as the map segment carries it to controllers (vlff-shm stat,
 * the viewer, the DDS bridge; vlff/shm.h, struct vlff_map_status): every
 * figure that has a field there, the state's name, and every refusal reason
 * by name, counted or not. t_ns and updates are left 0 (the library sets
 * them). A function of its own so that a test sees each field carried. */
void vlff_node_map_status(const struct vlff_node_status *st, struct vlff_map_status *out);

/* Queue a command for the trainer. Returns 0, or -1 for an unknown command
 * or an out-of-range argument (nothing is queued then). */
int vlff_node_command(struct vlff_node *n, int cmd, int arg);

#endif
