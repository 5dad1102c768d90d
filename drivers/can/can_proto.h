/*
 * The vlff CAN frame layouts as pure functions: no sockets, no threads, so
 * the host unit tests (whose kernel has no SocketCAN) cover every byte.
 * Used by vlff_can.c, the vlff-can tool and the tests; configs/vlff.dbc
 * describes the same layouts and a test checks both agree.
 *
 * All multi-byte signals are little-endian (DBC "@1+"). Scaled values
 * saturate at the signal's range; 0xFFFF in a u16 loss/fps field means
 * "invalid or above range".
 */
#ifndef VLFF_CAN_PROTO_H
#define VLFF_CAN_PROTO_H

#include <stdint.h>
#include <stdio.h>

#include "vlff_can.h"

#define VLFF_CANP_HEARTBEAT_BASE 0x700
#define VLFF_CANP_STATUS_FRAMES 7 /* TRAIN, LOSS, MAP, HEALTH, INGEST, MEMORY, PAGING */
#define VLFF_CANP_STATUS_FD_OFFSET 4 /* FD: one frame at base + 4 holding all seven payloads */
/* Seven 8-byte payloads and 8 zero bytes: CAN FD lengths go 48, then 64. */
#define VLFF_CANP_STATUS_FD_LEN 64
#define VLFF_CANP_CMD_LEN 4
#define VLFF_CANP_ACK_LEN 4

enum vlff_canp_status_index {
  VLFF_CANP_TRAIN = 0,
  VLFF_CANP_LOSS = 1,
  VLFF_CANP_MAP = 2,
  VLFF_CANP_HEALTH = 3,
  VLFF_CANP_INGEST = 4, /* classic id base + 5: base + 4 is the FD frame's */
  VLFF_CANP_MEMORY = 5, /* classic id base + 6 */
  VLFF_CANP_PAGING = 6  /* classic id base + 7 */
};

/* Classic frame id offset of status frame index (from status_base_id). */
int vlff_canp_status_offset(int index);
/* The status frame index of a classic id offset (0..3, 5..7); -1 for none
 * (4 is FD's). */
int vlff_canp_status_index(int offset);

/* What vlff_can adds to the node's snapshot in the HEALTH frame. */
struct vlff_canp_link {
  uint8_t nmt_state;
  uint8_t extra_flags;     /* VLFF_CAN_ERRF_* bits 4..6 */
  uint8_t can_errors;      /* VLFF_CAN_BUS_* latched this period */
  uint64_t cmd_rejected;   /* malformed + unknown + out of range, cumulative */
  uint64_t tx_dropped;     /* cumulative */
  int64_t map_age_ms;      /* -1 = never published */
  uint16_t refused_active; /* bit r-1: reason r refused a frame this period */
  uint32_t refused_period; /* frames refused this period */
};

/* The decoded (physical) values of the seven status frames. */
struct vlff_canp_status_view {
  uint32_t iteration;
  uint16_t keyframes;
  uint8_t prompt_set;
  uint8_t nmt_state;
  double loss_total, loss_color, loss_depth, loss_feature; /* <0: invalid */
  uint32_t map_version;
  uint16_t map_age_ms;     /* 65535 = never / >= 65.535 s */
  double fps_in, fps_dropped;
  uint8_t error_flags;
  uint16_t cmd_rejected;   /* saturating */
  uint16_t tx_dropped;     /* saturating */
  uint8_t can_errors;
  uint32_t frames_refused;
  uint8_t last_refusal;
  uint16_t refused_active;
  uint8_t refused_period;  /* saturating */
  /* MiB; -1: unknown or above the signal's range */
  double mem_rss_mb, mem_keyframes_mb, mem_keyframes_limit_mb, mem_evidence_mb, mem_evidence_limit_mb;
  /* PAGING, saturating */
  uint16_t keyframes_paged, keyframes_dropped, evidence_dropped;
  uint8_t box_growths, box_refused;
};

enum vlff_canp_cmd_check {
  VLFF_CANP_CMD_VALID = 0,
  VLFF_CANP_CMD_OTHER_NODE, /* well-formed, for another node: ignore, no ack */
  VLFF_CANP_CMD_MALFORMED,  /* wrong length or reserved bits: ignore, no ack */
  VLFF_CANP_CMD_UNKNOWN,    /* ack VLFF_CAN_RES_UNKNOWN */
  VLFF_CANP_CMD_RANGE,      /* ack VLFF_CAN_RES_RANGE */
};

/* One status frame's 8 bytes. index is enum vlff_canp_status_index. */
void vlff_canp_encode_status(int index, const struct vlff_can_status *st, const struct vlff_canp_link *link,
                             uint8_t out[8]);
/* Decode one status frame into view (only that frame's fields). Returns 0, or
 * -1 when len is not 8 or index unknown. */
int vlff_canp_decode_status(int index, const uint8_t *data, int len, struct vlff_canp_status_view *view);

/* Command frame: [0] target node (0 = every node) [1] code [2] arg [3] seq.
 * Returns enum vlff_canp_cmd_check; cmd is filled whenever the length is right. */
int vlff_canp_check_command(const uint8_t *data, int len, int node_id, int prompt_sets,
                            struct vlff_can_command *cmd);
void vlff_canp_encode_command(int target, const struct vlff_can_command *cmd, uint8_t out[4]);

/* Ack frame: [0] node id [1] code [2] result [3] seq. */
void vlff_canp_encode_ack(int node_id, const struct vlff_can_command *cmd, int result, uint8_t out[4]);

/* Error frame (can_id with CAN_ERR_FLAG, 8 data bytes) to VLFF_CAN_BUS_* bits;
 * desc receives a readable summary ("bus-off, tx error-passive"). */
uint32_t vlff_canp_decode_error(uint32_t can_id, const uint8_t data[8], char *desc, int desclen);

/* The DBC (Vector's CAN database text) of the node the can section describes: the
 * heartbeat, status, command and ack messages at the configured ids and
 * cycle times. Returns 0, or -1 with err naming the can.* key at fault
 * (vlff_can_check_config's checks) or the write error. */
int vlff_can_write_dbc(const struct vlff_cfg_can *cfg, FILE *out, char *err, size_t errlen);

/* Scaled u16: value/scale rounded, saturating; NaN/inf -> 0xFFFF. */
uint16_t vlff_canp_u16(double value, double scale);

#endif
