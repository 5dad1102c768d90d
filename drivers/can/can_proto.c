/*
 * Frame layouts of the vlff CAN protocol (see can_proto.h and
 * configs/vlff.dbc). Kept free of sockets so every byte is unit-tested on
 * hosts without SocketCAN.
 */
#include "can_proto.h"

#include <linux/can.h>
#include <linux/can/error.h>
#include <math.h>
#include <stdio.h>
#include <string.h>

static void put16(uint8_t *p, uint16_t v) {
  p[0] = (uint8_t)v;
  p[1] = (uint8_t)(v >> 8);
}

static void put32(uint8_t *p, uint32_t v) {
  for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static uint16_t get16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

static uint32_t get32(const uint8_t *p) {
  return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

static uint16_t sat16(uint64_t v) { return v > 0xffff ? 0xffff : (uint16_t)v; }
static uint8_t sat8(uint64_t v) { return v > 0xff ? 0xff : (uint8_t)v; }

/* An unsigned field of len bits (len <= 16) from bit start, little-endian
 * (DBC "@1+"). */
static void put_bits(uint8_t *p, int start, int len, uint32_t v) {
  for (int i = 0; i < len; i++)
    if (v >> i & 1) p[(start + i) / 8] |= (uint8_t)(1u << ((start + i) % 8));
}

static uint32_t get_bits(const uint8_t *p, int start, int len) {
  uint32_t v = 0;
  for (int i = 0; i < len; i++) v |= (uint32_t)(p[(start + i) / 8] >> ((start + i) % 8) & 1) << i;
  return v;
}

/* MiB in a len-bit field of scale MiB: rounded; all ones = unknown (NaN,
 * negative) or above range. */
static uint32_t mib_field(double mb, double scale, int len) {
  const uint32_t all = (1u << len) - 1;
  if (!(mb >= 0)) return all;
  double raw = mb / scale + 0.5;
  return raw >= all ? all : (uint32_t)raw;
}

static double mib_value(uint32_t raw, double scale, int len) {
  return raw == (1u << len) - 1 ? -1.0 : raw * scale;
}

uint16_t vlff_canp_u16(double value, double scale) {
  if (!isfinite(value)) return 0xffff;
  if (value <= 0) return 0;
  double raw = value / scale + 0.5;
  return raw >= 65535.0 ? 0xffff : (uint16_t)raw;
}

/* A u16 scaled value back; 0xFFFF is "invalid or above range". */
static double unscale(uint16_t raw, double scale) { return raw == 0xffff ? -1.0 : raw * scale; }

int vlff_canp_status_offset(int index) {
  return index >= VLFF_CANP_INGEST ? index + 1 : index;
}

int vlff_canp_status_index(int offset) {
  if (offset < 0 || offset == VLFF_CANP_STATUS_FD_OFFSET || offset > VLFF_CANP_STATUS_FRAMES) return -1;
  return offset > VLFF_CANP_STATUS_FD_OFFSET ? offset - 1 : offset;
}

void vlff_canp_encode_status(int index, const struct vlff_can_status *st, const struct vlff_canp_link *link,
                             uint8_t out[8]) {
  memset(out, 0, 8);
  switch (index) {
    case VLFF_CANP_TRAIN:
      put32(out, st->iteration);
      put16(out + 4, sat16(st->keyframes));
      out[6] = st->prompt_set > 0xff ? 0xff : (uint8_t)st->prompt_set;
      out[7] = link->nmt_state;
      break;
    case VLFF_CANP_LOSS:
      put16(out, vlff_canp_u16(st->loss_total, 0.001));
      put16(out + 2, vlff_canp_u16(st->loss_color, 0.0001));
      put16(out + 4, vlff_canp_u16(st->loss_depth, 0.0001));
      put16(out + 6, vlff_canp_u16(st->loss_feature, 0.0001));
      break;
    case VLFF_CANP_MAP:
      put32(out, st->map_version);
      put16(out + 4, link->map_age_ms < 0 ? 0xffff : sat16((uint64_t)link->map_age_ms));
      put16(out + 6, vlff_canp_u16(st->fps_in, 0.01));
      break;
    case VLFF_CANP_HEALTH:
      out[0] = (uint8_t)((st->error_flags & 0x0f) | (link->extra_flags & 0x70));
      put16(out + 1, vlff_canp_u16(st->fps_dropped, 0.01));
      put16(out + 3, sat16(link->cmd_rejected));
      put16(out + 5, sat16(link->tx_dropped));
      out[7] = link->can_errors;
      break;
    case VLFF_CANP_INGEST:
      put32(out, st->frames_refused);
      out[4] = st->last_refusal > 0xff ? 0xff : (uint8_t)st->last_refusal;
      put16(out + 5, link->refused_active);
      out[7] = link->refused_period > 0xff ? 0xff : (uint8_t)link->refused_period;
      break;
    case VLFF_CANP_MEMORY:
      /* The keyframe store is the large one (GiB on a building): 4 MiB
       * steps reach 16 GiB; the evidence's budget is MiB to a few GiB. */
      put16(out, (uint16_t)mib_field(st->mem_rss_mb, 1, 16));
      put_bits(out, 16, 12, mib_field(st->mem_keyframes_mb, 4, 12));
      put_bits(out, 28, 12, mib_field(st->mem_keyframes_limit_mb, 4, 12));
      put_bits(out, 40, 12, mib_field(st->mem_evidence_mb, 1, 12));
      put_bits(out, 52, 12, mib_field(st->mem_evidence_limit_mb, 1, 12));
      break;
    case VLFF_CANP_PAGING:
      /* Saturating: a controller needs to see that keyframes or evidence
       * are being lost, or that the box stopped growing; the exact counts
       * are in the map's status (vlff-shm stat). Growths are few (one per
       * keyframe that sees past the box), hence a byte each. */
      put16(out, sat16(st->keyframes_paged));
      put16(out + 2, sat16(st->keyframes_dropped));
      put16(out + 4, sat16(st->evidence_dropped));
      out[6] = sat8(st->box_growths);
      out[7] = sat8(st->box_refused);
      break;
    default:
      break;
  }
}

int vlff_canp_decode_status(int index, const uint8_t *d, int len, struct vlff_canp_status_view *v) {
  if (len != 8) return -1;
  switch (index) {
    case VLFF_CANP_TRAIN:
      v->iteration = get32(d);
      v->keyframes = get16(d + 4);
      v->prompt_set = d[6];
      v->nmt_state = d[7];
      return 0;
    case VLFF_CANP_LOSS:
      v->loss_total = unscale(get16(d), 0.001);
      v->loss_color = unscale(get16(d + 2), 0.0001);
      v->loss_depth = unscale(get16(d + 4), 0.0001);
      v->loss_feature = unscale(get16(d + 6), 0.0001);
      return 0;
    case VLFF_CANP_MAP:
      v->map_version = get32(d);
      v->map_age_ms = get16(d + 4);
      v->fps_in = unscale(get16(d + 6), 0.01);
      return 0;
    case VLFF_CANP_HEALTH:
      v->error_flags = d[0];
      v->fps_dropped = unscale(get16(d + 1), 0.01);
      v->cmd_rejected = get16(d + 3);
      v->tx_dropped = get16(d + 5);
      v->can_errors = d[7];
      return 0;
    case VLFF_CANP_INGEST:
      v->frames_refused = get32(d);
      v->last_refusal = d[4];
      v->refused_active = get16(d + 5);
      v->refused_period = d[7];
      return 0;
    case VLFF_CANP_MEMORY:
      v->mem_rss_mb = mib_value(get16(d), 1, 16);
      v->mem_keyframes_mb = mib_value(get_bits(d, 16, 12), 4, 12);
      v->mem_keyframes_limit_mb = mib_value(get_bits(d, 28, 12), 4, 12);
      v->mem_evidence_mb = mib_value(get_bits(d, 40, 12), 1, 12);
      v->mem_evidence_limit_mb = mib_value(get_bits(d, 52, 12), 1, 12);
      return 0;
    case VLFF_CANP_PAGING:
      v->keyframes_paged = get16(d);
      v->keyframes_dropped = get16(d + 2);
      v->evidence_dropped = get16(d + 4);
      v->box_growths = d[6];
      v->box_refused = d[7];
      return 0;
    default:
      return -1;
  }
}

int vlff_canp_check_command(const uint8_t *d, int len, int node_id, int prompt_sets,
                            struct vlff_can_command *cmd) {
  if (len != VLFF_CANP_CMD_LEN) return VLFF_CANP_CMD_MALFORMED;
  cmd->code = d[1];
  cmd->arg = d[2];
  cmd->seq = d[3];
  /* Node ids are 1..127 (CANopen); the top bit is reserved. */
  if (d[0] & 0x80) return VLFF_CANP_CMD_MALFORMED;
  if (d[0] != 0 && d[0] != node_id) return VLFF_CANP_CMD_OTHER_NODE;
  switch (cmd->code) {
    case VLFF_CAN_CMD_START:
    case VLFF_CAN_CMD_STOP:
    case VLFF_CAN_CMD_RESET:
    case VLFF_CAN_CMD_SAVE:
    case VLFF_CAN_CMD_PUBLISH:
      /* No argument: a nonzero one means the sender speaks another dialect. */
      return cmd->arg == 0 ? VLFF_CANP_CMD_VALID : VLFF_CANP_CMD_RANGE;
    case VLFF_CAN_CMD_PROMPT_SET:
      return cmd->arg < prompt_sets ? VLFF_CANP_CMD_VALID : VLFF_CANP_CMD_RANGE;
    default:
      return VLFF_CANP_CMD_UNKNOWN;
  }
}

void vlff_canp_encode_command(int target, const struct vlff_can_command *cmd, uint8_t out[4]) {
  out[0] = (uint8_t)target;
  out[1] = cmd->code;
  out[2] = cmd->arg;
  out[3] = cmd->seq;
}

void vlff_canp_encode_ack(int node_id, const struct vlff_can_command *cmd, int result, uint8_t out[4]) {
  out[0] = (uint8_t)node_id;
  out[1] = cmd->code;
  out[2] = (uint8_t)result;
  out[3] = cmd->seq;
}

static void append(char *desc, int desclen, int *n, const char *what) {
  if (!desc || desclen <= 0 || *n >= desclen - 1) return;
  int w = snprintf(desc + *n, (size_t)(desclen - *n), "%s%s", *n ? ", " : "", what);
  if (w > 0) *n += w;
}

uint32_t vlff_canp_decode_error(uint32_t can_id, const uint8_t d[8], char *desc, int desclen) {
  uint32_t bits = 0;
  int n = 0;
  if (desc && desclen > 0) desc[0] = 0;
  if (can_id & CAN_ERR_BUSOFF) {
    bits |= VLFF_CAN_BUS_OFF;
    append(desc, desclen, &n, "bus-off");
  }
  if (can_id & CAN_ERR_TX_TIMEOUT) {
    bits |= VLFF_CAN_BUS_TX_TIMEOUT;
    append(desc, desclen, &n, "tx timeout");
  }
  if (can_id & CAN_ERR_CRTL) {
    uint8_t c = d[1];
    if (c & (CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE)) {
      bits |= VLFF_CAN_BUS_PASSIVE;
      append(desc, desclen, &n, (c & CAN_ERR_CRTL_TX_PASSIVE) ? "tx error-passive" : "rx error-passive");
    }
    if (c & (CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING)) {
      bits |= VLFF_CAN_BUS_WARNING;
      append(desc, desclen, &n, "error-warning");
    }
    if (c & (CAN_ERR_CRTL_RX_OVERFLOW | CAN_ERR_CRTL_TX_OVERFLOW)) {
      bits |= VLFF_CAN_BUS_CONTROLLER;
      append(desc, desclen, &n, (c & CAN_ERR_CRTL_RX_OVERFLOW) ? "rx overflow" : "tx overflow");
    }
    if (c & CAN_ERR_CRTL_ACTIVE) append(desc, desclen, &n, "back to error-active");
    if (c == CAN_ERR_CRTL_UNSPEC) {
      bits |= VLFF_CAN_BUS_CONTROLLER;
      append(desc, desclen, &n, "controller problem");
    }
  }
  if (can_id & (CAN_ERR_PROT | CAN_ERR_BUSERROR)) {
    bits |= VLFF_CAN_BUS_PROTOCOL;
    append(desc, desclen, &n, "protocol error");
  }
  if (can_id & CAN_ERR_ACK) {
    bits |= VLFF_CAN_BUS_NO_ACK;
    append(desc, desclen, &n, "no ack");
  }
  if (can_id & CAN_ERR_TRX) {
    bits |= VLFF_CAN_BUS_CONTROLLER;
    append(desc, desclen, &n, "transceiver problem");
  }
  if (can_id & CAN_ERR_RESTARTED) {
    bits |= VLFF_CAN_BUS_RESTARTED;
    append(desc, desclen, &n, "controller restarted");
  }
  if (can_id & CAN_ERR_LOSTARB) append(desc, desclen, &n, "lost arbitration");
  if (desc && desclen > 0 && n == 0) snprintf(desc, (size_t)desclen, "error frame 0x%x", can_id & CAN_ERR_MASK);
  return bits;
}
