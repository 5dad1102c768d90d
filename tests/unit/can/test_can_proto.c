/* Frame layouts, command validation and error decoding: the pure part of
 * drivers/can, on the host (no SocketCAN needed). */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>
#include <linux/can.h>
#include <linux/can/error.h>
#include <math.h>
#include <string.h>

#include "can_proto.h"
#include "config.h"
#include "unit.h"

static void test_status_roundtrip(void **state) {
  (void)state;
  struct vlff_can_status st = {.iteration = 0xdeadbeef, .loss_total = 1.234f, .loss_color = 0.0123f,
                               .loss_depth = 0.5f, .loss_feature = 0.25f, .keyframes = 41, .map_version = 7,
                               .fps_in = 29.97f, .fps_dropped = 1.5f, .prompt_set = 3,
                               .error_flags = VLFF_CAN_ERRF_POSE_STALE | 0xf0u, .frames_refused = 0x01020304,
                               .last_refusal = 6, .mem_rss_mb = 1435.4f, .mem_keyframes_mb = 58.3f,
                               .mem_keyframes_limit_mb = 2048, .mem_evidence_mb = 9.6f, .mem_evidence_limit_mb = 16,
                               .keyframes_paged = 0x0102, .keyframes_dropped = 0x0304, .evidence_dropped = 0x0506,
                               .box_growths = 7, .box_refused = 8};
  struct vlff_canp_link link = {.nmt_state = VLFF_NMT_OPERATIONAL, .extra_flags = VLFF_CAN_ERRF_TX_DROPPED,
                                .can_errors = VLFF_CAN_BUS_OFF, .cmd_rejected = 70000, .tx_dropped = 12,
                                .map_age_ms = 250, .refused_active = 0x0120, .refused_period = 300};
  uint8_t f[VLFF_CANP_STATUS_FRAMES][8];
  struct vlff_canp_status_view v;
  memset(&v, 0, sizeof v);
  for (int i = 0; i < VLFF_CANP_STATUS_FRAMES; i++) {
    vlff_canp_encode_status(i, &st, &link, f[i]);
    assert_int_equal(vlff_canp_decode_status(i, f[i], 8, &v), 0);
  }
  assert_int_equal(f[0][0], 0xef);  /* little-endian on the wire */
  assert_int_equal(f[0][3], 0xde);
  assert_int_equal(v.iteration, 0xdeadbeef);
  assert_int_equal(v.keyframes, 41);
  assert_int_equal(v.prompt_set, 3);
  assert_int_equal(v.nmt_state, VLFF_NMT_OPERATIONAL);
  assert_true(fabs(v.loss_total - 1.234) <= 0.0005);
  assert_true(fabs(v.loss_color - 0.0123) <= 0.00005);
  assert_true(fabs(v.loss_depth - 0.5) <= 0.00005);
  assert_int_equal(v.map_version, 7);
  assert_int_equal(v.map_age_ms, 250);
  assert_true(fabs(v.fps_in - 29.97) <= 0.005);
  assert_true(fabs(v.fps_dropped - 1.5) <= 0.005);
  /* Node flags keep bits 0..3 only; the link adds 4..6. */
  assert_int_equal(v.error_flags, VLFF_CAN_ERRF_POSE_STALE | VLFF_CAN_ERRF_TX_DROPPED);
  assert_int_equal(v.cmd_rejected, 0xffff); /* saturates */
  assert_int_equal(v.tx_dropped, 12);
  assert_int_equal(v.can_errors, VLFF_CAN_BUS_OFF);
  assert_int_equal(v.frames_refused, 0x01020304);
  assert_int_equal(f[4][0], 0x04);
  assert_int_equal(v.last_refusal, 6);
  assert_int_equal(v.refused_active, 0x0120);
  assert_int_equal(v.refused_period, 255); /* saturates */
  assert_int_equal(vlff_canp_decode_status(0, f[0], 7, &v), -1);
  /* MEMORY: MiB rounded, the keyframe store's in 4 MiB steps. */
  assert_true(v.mem_rss_mb == 1435);
  assert_true(v.mem_keyframes_mb == 60);
  assert_true(v.mem_keyframes_limit_mb == 2048);
  assert_true(v.mem_evidence_mb == 10);
  assert_true(v.mem_evidence_limit_mb == 16);
  assert_int_equal(f[5][0] | f[5][1] << 8, 1435);
  /* PAGING: each count in its own place, little-endian. */
  assert_int_equal(v.keyframes_paged, 0x0102);
  assert_int_equal(v.keyframes_dropped, 0x0304);
  assert_int_equal(v.evidence_dropped, 0x0506);
  assert_int_equal(v.box_growths, 7);
  assert_int_equal(v.box_refused, 8);
  const uint8_t paging[8] = {0x02, 0x01, 0x04, 0x03, 0x06, 0x05, 7, 8};
  assert_memory_equal(f[6], paging, 8);
  assert_int_equal(vlff_canp_decode_status(VLFF_CANP_STATUS_FRAMES, f[0], 8, &v), -1);
  /* INGEST's, MEMORY's and PAGING's classic ids skip base + 4, the FD frame's. */
  assert_int_equal(vlff_canp_status_offset(VLFF_CANP_HEALTH), 3);
  assert_int_equal(vlff_canp_status_offset(VLFF_CANP_INGEST), 5);
  assert_int_equal(vlff_canp_status_offset(VLFF_CANP_MEMORY), 6);
  assert_int_equal(vlff_canp_status_offset(VLFF_CANP_PAGING), 7);
  for (int i = 0; i < VLFF_CANP_STATUS_FRAMES; i++) assert_int_equal(vlff_canp_status_index(vlff_canp_status_offset(i)), i);
  assert_int_equal(vlff_canp_status_index(VLFF_CANP_STATUS_FD_OFFSET), -1);
  assert_int_equal(vlff_canp_status_index(8), -1);
  assert_int_equal(vlff_canp_status_index(-1), -1);
}

static void test_scaling_saturates(void **state) {
  (void)state;
  assert_int_equal(vlff_canp_u16(NAN, 0.001), 0xffff);
  assert_int_equal(vlff_canp_u16(INFINITY, 0.001), 0xffff);
  assert_int_equal(vlff_canp_u16(-3.0, 0.001), 0);
  assert_int_equal(vlff_canp_u16(1e9, 0.001), 0xffff);
  assert_int_equal(vlff_canp_u16(65.534, 0.001), 65534);
  assert_int_equal(vlff_canp_u16(0.00049, 0.001), 0);
  assert_int_equal(vlff_canp_u16(0.0005, 0.001), 1);
  struct vlff_can_status st = {.loss_total = NAN, .map_version = 1};
  struct vlff_canp_link link = {.map_age_ms = -1};
  uint8_t f[8];
  struct vlff_canp_status_view v;
  vlff_canp_encode_status(VLFF_CANP_LOSS, &st, &link, f);
  vlff_canp_decode_status(VLFF_CANP_LOSS, f, 8, &v);
  assert_true(v.loss_total < 0); /* invalid */
  vlff_canp_encode_status(VLFF_CANP_MAP, &st, &link, f);
  vlff_canp_decode_status(VLFF_CANP_MAP, f, 8, &v);
  assert_int_equal(v.map_age_ms, 0xffff); /* never published */
  link.map_age_ms = 1000000;
  vlff_canp_encode_status(VLFF_CANP_MAP, &st, &link, f);
  vlff_canp_decode_status(VLFF_CANP_MAP, f, 8, &v);
  assert_int_equal(v.map_age_ms, 0xffff);
  /* Memory: unknown (negative, NaN) and above range read back unknown;
   * neither wraps into a small value. */
  st.mem_rss_mb = -1, st.mem_keyframes_mb = NAN, st.mem_keyframes_limit_mb = 1 << 20;
  st.mem_evidence_mb = 4094.6f, st.mem_evidence_limit_mb = 65536;
  vlff_canp_encode_status(VLFF_CANP_MEMORY, &st, &link, f);
  vlff_canp_decode_status(VLFF_CANP_MEMORY, f, 8, &v);
  assert_true(v.mem_rss_mb < 0 && v.mem_keyframes_mb < 0 && v.mem_keyframes_limit_mb < 0);
  assert_true(v.mem_evidence_mb < 0); /* 4094.6 rounds to the all-ones raw value */
  assert_true(v.mem_evidence_limit_mb < 0);
  st.mem_evidence_mb = 4094.4f, st.mem_keyframes_limit_mb = 16376;
  vlff_canp_encode_status(VLFF_CANP_MEMORY, &st, &link, f);
  vlff_canp_decode_status(VLFF_CANP_MEMORY, f, 8, &v);
  assert_true(v.mem_evidence_mb == 4094 && v.mem_keyframes_limit_mb == 16376);
  /* Paging counts saturate at their signals' width, never wrap. */
  st.keyframes_paged = 65536, st.keyframes_dropped = 65535, st.evidence_dropped = UINT32_MAX;
  st.box_growths = 256, st.box_refused = 255;
  vlff_canp_encode_status(VLFF_CANP_PAGING, &st, &link, f);
  vlff_canp_decode_status(VLFF_CANP_PAGING, f, 8, &v);
  assert_int_equal(v.keyframes_paged, 65535);
  assert_int_equal(v.keyframes_dropped, 65535);
  assert_int_equal(v.evidence_dropped, 65535);
  assert_int_equal(v.box_growths, 255);
  assert_int_equal(v.box_refused, 255);
  st.keyframes_paged = 65534, st.box_growths = 254;
  vlff_canp_encode_status(VLFF_CANP_PAGING, &st, &link, f);
  vlff_canp_decode_status(VLFF_CANP_PAGING, f, 8, &v);
  assert_true(v.keyframes_paged == 65534 && v.box_growths == 254);
}

static void test_command_validation(void **state) {
  (void)state;
  struct vlff_can_command c;
  const uint8_t ok[4] = {42, VLFF_CAN_CMD_SAVE, 0, 9};
  assert_int_equal(vlff_canp_check_command(ok, 4, 42, 3, &c), VLFF_CANP_CMD_VALID);
  assert_int_equal(c.code, VLFF_CAN_CMD_SAVE);
  assert_int_equal(c.seq, 9);
  const uint8_t all[4] = {0, VLFF_CAN_CMD_START, 0, 1};
  assert_int_equal(vlff_canp_check_command(all, 4, 42, 3, &c), VLFF_CANP_CMD_VALID);
  for (int len = 0; len <= 8; len++)
    if (len != 4) assert_int_equal(vlff_canp_check_command(ok, len, 42, 3, &c), VLFF_CANP_CMD_MALFORMED);
  const uint8_t other[4] = {7, VLFF_CAN_CMD_SAVE, 0, 1};
  assert_int_equal(vlff_canp_check_command(other, 4, 42, 3, &c), VLFF_CANP_CMD_OTHER_NODE);
  const uint8_t topbit[4] = {0x80 | 42, VLFF_CAN_CMD_SAVE, 0, 1};
  assert_int_equal(vlff_canp_check_command(topbit, 4, 42, 3, &c), VLFF_CANP_CMD_MALFORMED);
  const uint8_t unknown[4] = {42, 0x77, 0, 1};
  assert_int_equal(vlff_canp_check_command(unknown, 4, 42, 3, &c), VLFF_CANP_CMD_UNKNOWN);
  const uint8_t zero[4] = {42, 0, 0, 1};
  assert_int_equal(vlff_canp_check_command(zero, 4, 42, 3, &c), VLFF_CANP_CMD_UNKNOWN);
  const uint8_t ps2[4] = {42, VLFF_CAN_CMD_PROMPT_SET, 2, 1};
  const uint8_t ps3[4] = {42, VLFF_CAN_CMD_PROMPT_SET, 3, 1};
  assert_int_equal(vlff_canp_check_command(ps2, 4, 42, 3, &c), VLFF_CANP_CMD_VALID);
  assert_int_equal(c.arg, 2);
  assert_int_equal(vlff_canp_check_command(ps3, 4, 42, 3, &c), VLFF_CANP_CMD_RANGE);
  const uint8_t arg[4] = {42, VLFF_CAN_CMD_PUBLISH, 1, 1};
  assert_int_equal(vlff_canp_check_command(arg, 4, 42, 3, &c), VLFF_CANP_CMD_RANGE);

  uint8_t frame[4], ack[4];
  struct vlff_can_command cmd = {.code = VLFF_CAN_CMD_PROMPT_SET, .arg = 1, .seq = 200};
  vlff_canp_encode_command(42, &cmd, frame);
  assert_int_equal(vlff_canp_check_command(frame, 4, 42, 2, &c), VLFF_CANP_CMD_VALID);
  assert_memory_equal(&c, &cmd, sizeof c);
  vlff_canp_encode_ack(42, &cmd, VLFF_CAN_RES_REFUSED, ack);
  const uint8_t want[4] = {42, VLFF_CAN_CMD_PROMPT_SET, VLFF_CAN_RES_REFUSED, 200};
  assert_memory_equal(ack, want, 4);
}

static void test_error_frames(void **state) {
  (void)state;
  uint8_t d[8] = {0};
  char desc[160];
  assert_int_equal(vlff_canp_decode_error(CAN_ERR_FLAG | CAN_ERR_BUSOFF, d, desc, sizeof desc), VLFF_CAN_BUS_OFF);
  assert_string_equal(desc, "bus-off");
  d[1] = CAN_ERR_CRTL_TX_PASSIVE | CAN_ERR_CRTL_TX_WARNING;
  assert_int_equal(vlff_canp_decode_error(CAN_ERR_FLAG | CAN_ERR_CRTL, d, desc, sizeof desc),
                   VLFF_CAN_BUS_PASSIVE | VLFF_CAN_BUS_WARNING);
  assert_non_null(strstr(desc, "tx error-passive"));
  d[1] = CAN_ERR_CRTL_RX_OVERFLOW;
  assert_int_equal(vlff_canp_decode_error(CAN_ERR_FLAG | CAN_ERR_CRTL, d, desc, sizeof desc),
                   VLFF_CAN_BUS_CONTROLLER);
  d[1] = 0;
  assert_int_equal(vlff_canp_decode_error(CAN_ERR_FLAG | CAN_ERR_TX_TIMEOUT | CAN_ERR_ACK, d, desc, sizeof desc),
                   VLFF_CAN_BUS_TX_TIMEOUT | VLFF_CAN_BUS_NO_ACK);
  assert_string_equal(desc, "tx timeout, no ack");
  assert_int_equal(vlff_canp_decode_error(CAN_ERR_FLAG | CAN_ERR_PROT | CAN_ERR_RESTARTED, d, desc, sizeof desc),
                   VLFF_CAN_BUS_PROTOCOL | VLFF_CAN_BUS_RESTARTED);
  assert_int_equal(vlff_canp_decode_error(CAN_ERR_FLAG | CAN_ERR_LOSTARB, d, desc, sizeof desc), 0);
  assert_string_equal(desc, "lost arbitration");
  /* A tiny buffer is never overrun. */
  char small[6];
  vlff_canp_decode_error(CAN_ERR_FLAG | CAN_ERR_BUSOFF | CAN_ERR_TX_TIMEOUT, d, small, sizeof small);
  assert_true(strlen(small) < sizeof small);
}

static void test_config_check(void **state) {
  (void)state;
  struct vlff_config cfg;
  char err[256];
  vlff_config_defaults(&cfg);
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), 0);
  cfg.can.command_id = cfg.can.status_base_id + 2;
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), -1);
  assert_non_null(strstr(err, "can.command_id"));
  vlff_config_defaults(&cfg);
  cfg.can.ack_id = 0x700 + cfg.can.node_id;
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), -1);
  assert_non_null(strstr(err, "heartbeat"));
  vlff_config_defaults(&cfg);
  cfg.can.ack_id = cfg.can.command_id;
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), -1);
  assert_non_null(strstr(err, "can.ack_id"));
  vlff_config_defaults(&cfg);
  cfg.can.status_base_id = 0x7fd;
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), -1);
  assert_non_null(strstr(err, "can.status_base_id"));
  vlff_config_defaults(&cfg);
  cfg.can.fd = true;
  cfg.can.command_id = cfg.can.status_base_id + 4; /* the FD frame's id */
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), -1);
  /* Classic frames end at base + 7 (PAGING). */
  for (int off = 5; off <= 7; off++) {
    vlff_config_defaults(&cfg);
    cfg.can.command_id = cfg.can.status_base_id + off;
    assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), -1);
    assert_non_null(strstr(err, "can.command_id"));
  }
  vlff_config_defaults(&cfg);
  cfg.can.command_id = cfg.can.status_base_id + 8;
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), 0);
  cfg.can.status_base_id = 0x7f8; /* PAGING at 0x7ff */
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), 0);
  cfg.can.status_base_id = 0x7f9;
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), -1);
  cfg.can.fd = true; /* one frame at base + 4 fits */
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), 0);
  vlff_config_defaults(&cfg);
  snprintf(cfg.can.interface, sizeof cfg.can.interface, "an-interface-name-too-long");
  assert_int_equal(vlff_can_check_config(&cfg.can, err, sizeof err), -1);
  assert_non_null(strstr(err, "can.interface"));
  /* open refuses a bad config without starting anything */
  assert_null(vlff_can_open(&cfg.can, cfg.prompts.set_count, NULL, NULL));
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_status_roundtrip), cmocka_unit_test(test_scaling_saturates),
    cmocka_unit_test(test_command_validation), cmocka_unit_test(test_error_frames),
    cmocka_unit_test(test_config_check))
