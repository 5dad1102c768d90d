/*
 * vlff_can: the node's status and command link on SocketCAN.
 *
 * A struct vlff_can owns one raw SocketCAN socket bound to a named interface
 * and one thread. The thread sends a CANopen-style heartbeat (COB-ID
 * 0x700 + node id, one NMT state byte, boot-up 0x00 first), the status
 * frames (status_base_id + 0..3 and + 5..7, or one CAN FD frame at status_base_id + 4)
 * and acknowledgements, receives commands on command_id and decodes error
 * frames. configs/vlff.dbc describes every frame; docs/can.md
 * has the table.
 *
 * Contract
 *  - Errors: functions returning int give 0 on success and -1 with errno set;
 *    vlff_can_open() returns NULL with errno set. Configuration problems are
 *    EINVAL and vlff_can_check_config() names the key.
 *  - The bus never blocks the caller: vlff_can_set_status() and
 *    vlff_can_set_state() are wait-free (a seqlock of atomics written by one
 *    thread), so the learner may call them at any rate. Frames the kernel
 *    cannot take (ENOBUFS, EAGAIN, interface down) are dropped and counted,
 *    never retried in a blocking way.
 *  - A missing or down interface is not an error at open: the thread retries
 *    with exponential backoff (50 ms to 2 s) and resumes sending when the
 *    interface comes back; the same happens when it goes down or disappears
 *    later.
 *  - Commands: a frame on command_id is checked first (length, target node,
 *    known code, argument in range). Malformed frames (wrong length, nonzero
 *    reserved byte) are dropped silently; well-formed frames with an unknown
 *    code or an out-of-range argument are acknowledged with
 *    VLFF_CAN_RES_UNKNOWN / VLFF_CAN_RES_RANGE. Both are counted, reported in
 *    the HEALTH status frame and never reach the callback. Valid commands
 *    call the callback on the CAN thread; its return value (enum
 *    vlff_can_result) is sent back as the ack. The callback must return
 *    quickly (post to a queue, set a flag): the heartbeat waits for it.
 *  - Ownership: vlff_can_open() copies what it needs from the config; the
 *    caller frees the object with vlff_can_close(), which stops the thread.
 *  - Thread-safety: set_status/set_state are for one writer thread (the
 *    node); get_stats may be called from any thread. open/close from one
 *    thread.
 */
#ifndef VLFF_CAN_H
#define VLFF_CAN_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

struct vlff_cfg_can;

/* NMT-like states carried by the heartbeat (CANopen values; ERROR is ours). */
enum vlff_can_nmt {
  VLFF_NMT_BOOTUP = 0x00,
  VLFF_NMT_STOPPED = 0x04,
  VLFF_NMT_OPERATIONAL = 0x05,
  VLFF_NMT_PREOPERATIONAL = 0x7f,
  VLFF_NMT_ERROR = 0x8f,
};

enum vlff_can_cmd_code {
  VLFF_CAN_CMD_START = 0x01,      /* start mapping */
  VLFF_CAN_CMD_STOP = 0x02,       /* stop mapping (keep the field) */
  VLFF_CAN_CMD_RESET = 0x03,      /* drop the field and keyframes */
  VLFF_CAN_CMD_SAVE = 0x04,       /* write a checkpoint now */
  VLFF_CAN_CMD_PROMPT_SET = 0x05, /* arg = prompt set index */
  VLFF_CAN_CMD_PUBLISH = 0x06,    /* publish the map now */
};

enum vlff_can_result {
  VLFF_CAN_RES_OK = 0x00,
  VLFF_CAN_RES_UNKNOWN = 0x01, /* unknown command code */
  VLFF_CAN_RES_RANGE = 0x02,   /* argument out of range */
  VLFF_CAN_RES_REFUSED = 0x03, /* not allowed in the current state */
  VLFF_CAN_RES_FAILED = 0x04,  /* accepted but the action failed */
  VLFF_CAN_RES_BUSY = 0x05,    /* the node cannot take it now */
};

/* Node error flags (HEALTH.error_flags bits 0..3). */
#define VLFF_CAN_ERRF_CAMERA_LOST 0x01u
#define VLFF_CAN_ERRF_POSE_STALE 0x02u
#define VLFF_CAN_ERRF_SHM_LAPPED 0x04u
#define VLFF_CAN_ERRF_CHECKPOINT_FAILED 0x08u
/* Bits 4..6 are set by vlff_can itself for the status period just ended. */
#define VLFF_CAN_ERRF_BUS_ERROR 0x10u    /* bus-off / error-passive / controller */
#define VLFF_CAN_ERRF_TX_DROPPED 0x20u   /* frames dropped (queue full, link down) */
#define VLFF_CAN_ERRF_CMD_REJECTED 0x40u /* malformed / unknown / out of range */

/* CAN bus error bits (HEALTH.can_errors), latched between status frames. */
#define VLFF_CAN_BUS_OFF 0x01u
#define VLFF_CAN_BUS_PASSIVE 0x02u
#define VLFF_CAN_BUS_WARNING 0x04u
#define VLFF_CAN_BUS_CONTROLLER 0x08u /* rx/tx overflow, other controller problem */
#define VLFF_CAN_BUS_TX_TIMEOUT 0x10u
#define VLFF_CAN_BUS_PROTOCOL 0x20u
#define VLFF_CAN_BUS_NO_ACK 0x40u
#define VLFF_CAN_BUS_RESTARTED 0x80u

/* Refusal reason codes the INGEST frame has room for (one bit each). */
#define VLFF_CAN_REFUSAL_CODES 16

/* What the node reports; a plain struct copied in by vlff_can_set_status(). */
struct vlff_can_status {
  uint32_t iteration;        /* training steps so far */
  float loss_total;          /* latest losses; NaN/inf are sent as "invalid" */
  float loss_color;
  float loss_depth;
  float loss_feature;
  uint32_t keyframes;        /* keyframes held */
  uint32_t map_version;      /* version of the last published map */
  int64_t map_published_ns;  /* CLOCK_MONOTONIC of that publish; 0 = never */
  float fps_in;              /* frames/s accepted from the camera */
  float fps_dropped;         /* frames/s dropped (ring lapped, bad pose, ...) */
  uint32_t prompt_set;       /* active prompt set index */
  uint32_t error_flags;      /* VLFF_CAN_ERRF_* bits 0..3 */
  /* Frames the learner refused (INGEST frame). Reason codes are the
   * node's (enum vlff_refusal, named in configs/vlff.dbc), 1..15. */
  uint32_t frames_refused;   /* all reasons, cumulative */
  uint32_t last_refusal;     /* reason of the latest refused frame, 0 = none yet */
  uint32_t refused[VLFF_CAN_REFUSAL_CODES]; /* per reason code, cumulative; [0] unused */
  /* Memory against its limits (MEMORY frame), MiB; negative = unknown. */
  float mem_rss_mb;                /* the process's resident set */
  float mem_keyframes_mb, mem_keyframes_limit_mb; /* the keyframe store, keyframes.memory_mb */
  float mem_evidence_mb, mem_evidence_limit_mb;   /* the evidence, publish.evidence_max_mb */
  /* What the limits pushed out (PAGING frame, which saturates them). */
  uint32_t keyframes_paged;   /* keyframes in the state directory's page file now */
  uint32_t keyframes_dropped; /* keyframes evicted with nowhere to go, since start */
  uint32_t evidence_dropped;  /* voxels whose evidence was given up for good, since start */
  uint32_t box_growths;       /* the map's box grown, since start */
  uint32_t box_refused;       /* keyframes whose box could not be grown to, since start */
};

struct vlff_can_command {
  uint8_t code; /* enum vlff_can_cmd_code */
  uint8_t arg;
  uint8_t seq;  /* echoed in the ack */
};

/* Called on the CAN thread for each valid command; returns enum vlff_can_result. */
typedef int (*vlff_can_command_fn)(void *ctx, const struct vlff_can_command *cmd);

struct vlff_can_stats {
  bool connected;           /* socket open on an up interface */
  uint64_t heartbeats_sent;
  uint64_t status_sent;     /* status frames (each classic frame counts) */
  uint64_t acks_sent;
  uint64_t tx_dropped;      /* frames the kernel refused or that found the link down */
  uint64_t tx_late;         /* heartbeat deadlines missed by more than a period */
  uint64_t hb_spin_ns;      /* time spent spinning before heartbeats (the price of punctuality) */
  uint64_t hb_timer_late;   /* heartbeat wakes already past the deadline (the margin fell short) */
  uint64_t cmd_ok;          /* commands passed to the callback */
  uint64_t cmd_malformed;
  uint64_t cmd_unknown;
  uint64_t cmd_range;
  uint64_t cmd_other_node;  /* well-formed, addressed to another node id */
  uint64_t err_frames;      /* error frames received */
  uint64_t bus_off, err_passive, err_warning, ctrl_problems, tx_timeouts, prot_errors;
  uint64_t reopens;         /* successful (re)opens after the first */
  uint32_t can_errors;      /* VLFF_CAN_BUS_* seen since open */
};

/* Check the can.* keys together (ranges, id overlaps). Returns 0, or -1
 * with err naming the key. */
int vlff_can_check_config(const struct vlff_cfg_can *cfg, char *err, size_t errlen);

/* Start the CAN thread for the can section, on its interface. prompt_set
 * commands are range-checked against prompt_sets (prompts.set_count).
 * fn may be NULL (every valid command is then acked REFUSED). */
struct vlff_can *vlff_can_open(const struct vlff_cfg_can *cfg, int prompt_sets, vlff_can_command_fn fn, void *ctx);

/* Stop the thread, close the socket, free. NULL is a no-op. */
void vlff_can_close(struct vlff_can *can);

/* Publish a status snapshot; wait-free, one writer thread. */
void vlff_can_set_status(struct vlff_can *can, const struct vlff_can_status *st);

/* Set the NMT state carried by the next heartbeat (enum vlff_can_nmt). */
void vlff_can_set_state(struct vlff_can *can, enum vlff_can_nmt state);

/* Snapshot of the counters. */
void vlff_can_get_stats(const struct vlff_can *can, struct vlff_can_stats *st);

/* Names for logs and tools ("operational", "save", "out-of-range", ...). */
const char *vlff_can_nmt_name(int state);
const char *vlff_can_cmd_name(int code);
const char *vlff_can_result_name(int result);

#endif
