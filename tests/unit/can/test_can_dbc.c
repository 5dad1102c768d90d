/* configs/vlff.dbc against the encoder: every status, command and ack layout
 * decodes, with the DBC text alone, to the values the node handed over. The
 * VM test does the same with frames captured from a real vcan bus. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include <stdio.h>

#include "can_proto.h"
#include "config.h"
#include "dbc_check.h"
#include "node.h"
#include "unit.h"

static struct dbc db;

static int setup(void **state) {
  (void)state;
  return dbc_load_vlff(&db);
}

/* Every bit of each status payload belongs to at most one signal, and all
 * bits but HEALTH bit 7, the INGEST reason bits without a reason yet and the
 * FD frame's padding (its last 8 bytes) are described. */
static void test_layout_covers_payload(void **state) {
  (void)state;
  const char *names[] = {"VLFF_TRAIN",  "VLFF_LOSS",   "VLFF_MAP",       "VLFF_HEALTH",  "VLFF_INGEST",
                         "VLFF_MEMORY", "VLFF_PAGING", "VLFF_STATUS_FD", "VLFF_COMMAND", "VLFF_ACK",
                         "VLFF_HEARTBEAT"};
  /* Reason codes 1..VLFF_CAN_REFUSAL_CODES-1 fit the INGEST bits; those
   * the node does not define yet are unused. */
  const int reason_bits_unused = 16 - (VLFF_REFUSED_COUNT - 1);
  for (size_t i = 0; i < sizeof names / sizeof names[0]; i++) {
    const struct dbc_message *m = dbc_find_name(&db, names[i]);
    assert_non_null(m);
    int owner[512];
    memset(owner, -1, sizeof owner);
    for (int s = 0; s < m->nsig; s++) {
      assert_true(m->sig[s].little_endian);
      for (int b = m->sig[s].start; b < m->sig[s].start + m->sig[s].length; b++) {
        assert_true(b < m->dlc * 8);
        assert_int_equal(owner[b], -1);
        owner[b] = s;
      }
    }
    int unused = 0;
    for (int b = 0; b < m->dlc * 8; b++) unused += owner[b] < 0;
    int expect_unused = !strcmp(names[i], "VLFF_HEALTH")      ? 1
                        : !strcmp(names[i], "VLFF_INGEST")    ? reason_bits_unused
                        : !strcmp(names[i], "VLFF_STATUS_FD") ? 1 + reason_bits_unused + 64
                                                              : 0;
    assert_int_equal(unused, expect_unused);
  }
  /* Default ids (configs/default.yaml) are the DBC's ids. */
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  assert_int_equal(dbc_find_name(&db, "VLFF_HEARTBEAT")->id, 0x700 + cfg.can.node_id);
  assert_int_equal(dbc_find_name(&db, "VLFF_TRAIN")->id, cfg.can.status_base_id);
  assert_int_equal(dbc_find_name(&db, "VLFF_HEALTH")->id, cfg.can.status_base_id + 3);
  assert_int_equal(dbc_find_name(&db, "VLFF_STATUS_FD")->id, cfg.can.status_base_id + 4);
  assert_int_equal(dbc_find_name(&db, "VLFF_STATUS_FD")->dlc, VLFF_CANP_STATUS_FD_LEN);
  assert_int_equal(dbc_find_name(&db, "VLFF_INGEST")->id,
                   cfg.can.status_base_id + vlff_canp_status_offset(VLFF_CANP_INGEST));
  assert_int_equal(dbc_find_name(&db, "VLFF_MEMORY")->id, cfg.can.status_base_id + 6);
  assert_int_equal(dbc_find_name(&db, "VLFF_PAGING")->id, cfg.can.status_base_id + 7);
  /* One bit per reason the node defines, in code order, in both frames. */
  for (int r = 1; r < VLFF_REFUSED_COUNT; r++) {
    int found = 0;
    const struct dbc_message *ms[2] = {dbc_find_name(&db, "VLFF_INGEST"), dbc_find_name(&db, "VLFF_STATUS_FD")};
    for (int k = 0; k < 2; k++)
      for (int s = 0; s < ms[k]->nsig; s++)
        if (!strncmp(ms[k]->sig[s].name, "Refused", 7) && ms[k]->sig[s].length == 1 &&
            ms[k]->sig[s].start == (k ? 256 : 0) + 40 + r - 1)
          found++;
    if (found != 2) fail_msg("reason %d (%s) has no bit %d in VLFF_INGEST and VLFF_STATUS_FD", r, vlff_refusal_name(r),
                             40 + r - 1);
  }
  assert_int_equal(dbc_find_name(&db, "VLFF_COMMAND")->id, cfg.can.command_id);
  assert_int_equal(dbc_find_name(&db, "VLFF_ACK")->id, cfg.can.ack_id);
}

static float rnd(double hi) { return (float)(hi * rand() / RAND_MAX); }

static void test_random_status_decodes(void **state) {
  (void)state;
  const char *names[] = {"VLFF_TRAIN",  "VLFF_LOSS",   "VLFF_MAP",   "VLFF_HEALTH",
                         "VLFF_INGEST", "VLFF_MEMORY", "VLFF_PAGING"};
  _Static_assert(sizeof names / sizeof names[0] == VLFF_CANP_STATUS_FRAMES, "a name per status frame");
  const struct dbc_message *fd = dbc_find_name(&db, "VLFF_STATUS_FD");
  srand(7);
  for (int it = 0; it < 2000; it++) {
    struct vlff_can_status st = {
        .iteration = (uint32_t)rand() * 2u, .loss_total = rnd(80), .loss_color = rnd(8), .loss_depth = rnd(3),
        .loss_feature = rnd(1), .keyframes = (uint32_t)(rand() % 70000), .map_version = (uint32_t)rand(),
        .fps_in = rnd(700), .fps_dropped = rnd(50), .prompt_set = (uint32_t)(rand() % 300),
        .error_flags = (uint32_t)(rand() & 0x0f), .frames_refused = (uint32_t)rand() * 2u,
        .last_refusal = (uint32_t)(rand() % VLFF_REFUSED_COUNT), .mem_rss_mb = rnd(70000),
        .mem_keyframes_mb = rnd(17000), .mem_keyframes_limit_mb = rnd(17000), .mem_evidence_mb = rnd(4200),
        .mem_evidence_limit_mb = rnd(4200), .keyframes_paged = (uint32_t)(rand() % 70000),
        .keyframes_dropped = (uint32_t)(rand() % 70000), .evidence_dropped = (uint32_t)rand() * 2u,
        .box_growths = (uint32_t)(rand() % 300), .box_refused = (uint32_t)(rand() % 300)};
    if (it % 11 == 0) st.mem_rss_mb = -1, st.mem_evidence_mb = NAN;
    if (it % 10 == 0) st.loss_total = NAN;
    if (it % 13 == 0) st.loss_depth = -1;
    struct vlff_canp_link link = {.nmt_state = (uint8_t)(it % 2 ? VLFF_NMT_OPERATIONAL : VLFF_NMT_ERROR),
                                  .cmd_rejected = (uint64_t)(it * 40), .tx_dropped = (uint64_t)it,
                                  .can_errors = (uint8_t)it, .map_age_ms = it * 50,
                                  .refused_active = (uint16_t)(rand() & 0x0fff), .refused_period = (uint32_t)(it % 300)};
    uint8_t all[VLFF_CANP_STATUS_FD_LEN] = {0};
    for (int i = 0; i < VLFF_CANP_STATUS_FRAMES; i++) {
      vlff_canp_encode_status(i, &st, &link, all + 8 * i);
      const struct dbc_message *m = dbc_find_name(&db, names[i]);
      char why[256] = "";
      if (dbc_check_status(m, 0, all + 8 * i, 8, &st, link.nmt_state, why, sizeof why) < 0) fail_msg("%s", why);
    }
    for (int i = 0; i < VLFF_CANP_STATUS_FRAMES; i++) {
      char why[256] = "";
      if (dbc_check_status(fd, i, all, VLFF_CANP_STATUS_FD_LEN, &st, link.nmt_state, why, sizeof why) < 0)
        fail_msg("FD %s", why);
    }
    /* Link-derived signals. */
    const struct dbc_message *h = dbc_find_name(&db, "VLFF_HEALTH");
    const struct dbc_message *mp = dbc_find_name(&db, "VLFF_MAP");
    double v;
    assert_int_equal(dbc_decode(h, "CmdRejected", all + 24, 8, &v), 0);
    assert_true(v == (link.cmd_rejected > 65535 ? 65535 : (double)link.cmd_rejected));
    assert_int_equal(dbc_decode(h, "TxDropped", all + 24, 8, &v), 0);
    assert_true(v == (double)link.tx_dropped);
    assert_int_equal(dbc_decode(h, "BusOff", all + 24, 8, &v), 0);
    assert_true(v == (double)(it & 1));
    assert_int_equal(dbc_decode(h, "BusRestarted", all + 24, 8, &v), 0);
    assert_true(v == (double)((it >> 7) & 1));
    assert_int_equal(dbc_decode(mp, "MapAge", all + 16, 8, &v), 0);
    assert_true(v == (link.map_age_ms > 65535 ? 65535 : (double)link.map_age_ms));
    const struct dbc_message *ig = dbc_find_name(&db, "VLFF_INGEST");
    assert_int_equal(dbc_decode(ig, "RefusedPeriod", all + 32, 8, &v), 0);
    assert_true(v == (link.refused_period > 255 ? 255 : (double)link.refused_period));
    assert_int_equal(dbc_decode(ig, "RefusedNoPose", all + 32, 8, &v), 0);
    assert_true(v == (double)((link.refused_active >> (VLFF_REFUSED_NO_POSE - 1)) & 1));
    assert_int_equal(dbc_decode(ig, "RefusedNoDepth", all + 32, 8, &v), 0);
    assert_true(v == (double)((link.refused_active >> (VLFF_REFUSED_NO_DEPTH - 1)) & 1));
  }
}

static void test_command_ack_heartbeat(void **state) {
  (void)state;
  const struct dbc_message *cm = dbc_find_name(&db, "VLFF_COMMAND");
  const struct dbc_message *am = dbc_find_name(&db, "VLFF_ACK");
  struct vlff_can_command cmd = {.code = VLFF_CAN_CMD_PROMPT_SET, .arg = 5, .seq = 250};
  uint8_t f[4];
  double v;
  vlff_canp_encode_command(42, &cmd, f);
  assert_int_equal(dbc_decode(cm, "Target", f, 4, &v), 0);
  assert_true(v == 42);
  assert_int_equal(dbc_decode(cm, "Command", f, 4, &v), 0);
  assert_true(v == VLFF_CAN_CMD_PROMPT_SET);
  assert_int_equal(dbc_decode(cm, "Argument", f, 4, &v), 0);
  assert_true(v == 5);
  vlff_canp_encode_ack(42, &cmd, VLFF_CAN_RES_RANGE, f);
  assert_int_equal(dbc_decode(am, "Result", f, 4, &v), 0);
  assert_true(v == VLFF_CAN_RES_RANGE);
  assert_int_equal(dbc_decode(am, "Sequence", f, 4, &v), 0);
  assert_true(v == 250);
  const struct dbc_message *hb = dbc_find_name(&db, "VLFF_HEARTBEAT");
  uint8_t s = VLFF_NMT_PREOPERATIONAL;
  assert_int_equal(dbc_decode(hb, "NmtState", &s, 1, &v), 0);
  assert_true(v == 127);
  assert_int_equal(dbc_decode(hb, "NmtState", &s, 0, &v), -1); /* too short */
}

VLFF_UNIT_MAIN(setup, NULL,
    cmocka_unit_test(test_layout_covers_payload), cmocka_unit_test(test_random_status_decodes),
    cmocka_unit_test(test_command_ack_heartbeat))
