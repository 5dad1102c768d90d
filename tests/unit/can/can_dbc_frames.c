/* Frames of one node encoded by the project's CAN code (can_proto.c), for an
 * outside DBC parser to decode (test_dbc_canmatrix.py): one line per frame,
 * "NAME ID HEX", for the ids of the config given. The values are fixed here
 * and restated in the Python test. */
#include <stdio.h>

#include "can_proto.h"
#include "config.h"

static void put(const char *name, int id, const unsigned char *d, int len) {
  printf("%s %d ", name, id);
  for (int i = 0; i < len; i++) printf("%02x", d[i]);
  printf("\n");
}

int main(int argc, char **argv) {
  struct vlff_config cfg;
  char err[512];
  if (argc != 2 || vlff_config_load(argv[1], &cfg, err, sizeof err)) {
    fprintf(stderr, "can_dbc_frames: %s\n", argc != 2 ? "usage: can_dbc_frames CONFIG" : err);
    return 2;
  }
  const struct vlff_can_status st = {.iteration = 123456, .loss_total = 1.234f, .loss_color = 0.0123f,
                                     .loss_depth = 0.0456f, .loss_feature = 0.789f, .keyframes = 41,
                                     .map_version = 77, .fps_in = 29.97f, .fps_dropped = 1.5f, .prompt_set = 2,
                                     .error_flags = VLFF_CAN_ERRF_CAMERA_LOST, .frames_refused = 193,
                                     .last_refusal = 6, .mem_rss_mb = 1435, .mem_keyframes_mb = 60,
                                     .mem_keyframes_limit_mb = 2048, .mem_evidence_mb = 9, .mem_evidence_limit_mb = 16,
                                     .keyframes_paged = 128, .keyframes_dropped = 3, .evidence_dropped = 70000,
                                     .box_growths = 12, .box_refused = 2};
  const struct vlff_canp_link link = {.nmt_state = VLFF_NMT_OPERATIONAL, .extra_flags = 0x40, .can_errors = 0x01,
                                      .cmd_rejected = 3, .tx_dropped = 4, .map_age_ms = 1500,
                                      .refused_active = 1u << (6 - 1), .refused_period = 15};
  static const char *const names[] = {"VLFF_TRAIN",  "VLFF_LOSS",   "VLFF_MAP",   "VLFF_HEALTH",
                                      "VLFF_INGEST", "VLFF_MEMORY", "VLFF_PAGING"};
  _Static_assert(sizeof names / sizeof names[0] == VLFF_CANP_STATUS_FRAMES, "a name per status frame");
  unsigned char fd[VLFF_CANP_STATUS_FD_LEN] = {0};
  for (int i = 0; i < VLFF_CANP_STATUS_FRAMES; i++) {
    vlff_canp_encode_status(i, &st, &link, fd + 8 * i);
    put(names[i], cfg.can.status_base_id + vlff_canp_status_offset(i), fd + 8 * i, 8);
  }
  put("VLFF_STATUS_FD", cfg.can.status_base_id + VLFF_CANP_STATUS_FD_OFFSET, fd, VLFF_CANP_STATUS_FD_LEN);
  unsigned char hb = VLFF_NMT_OPERATIONAL, d[4];
  put("VLFF_HEARTBEAT", VLFF_CANP_HEARTBEAT_BASE + cfg.can.node_id, &hb, 1);
  struct vlff_can_command cmd = {.code = VLFF_CAN_CMD_PROMPT_SET, .arg = 2, .seq = 17};
  vlff_canp_encode_command(cfg.can.node_id, &cmd, d);
  put("VLFF_COMMAND", cfg.can.command_id, d, 4);
  vlff_canp_encode_ack(cfg.can.node_id, &cmd, VLFF_CAN_RES_RANGE, d);
  put("VLFF_ACK", cfg.can.ack_id, d, 4);
  return 0;
}
