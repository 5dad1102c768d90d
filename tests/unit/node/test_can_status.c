/* The node's status as CAN reports it (node/can_status.h): every field of
 * vlff_node_status that a CAN frame carries lands in its word, the PAGING
 * counts saturate instead of wrapping, a negative count reads 0, only the
 * node's error bits 0..3 go out, no prompt set reads 0xff, the map's age
 * becomes its publish time, and each node state its NMT state. The VM's
 * can_node case checks the frames on a real vcan bus; this checks the copy
 * field by field, which a frame whose counts are all 0 there cannot. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

#include "can_status.h"
#include "unit.h"

static struct vlff_node_status sample(void) {
  struct vlff_node_status st;
  memset(&st, 0, sizeof st);
  st.state = VLFF_NODE_OPERATIONAL;
  st.error_flags = VLFF_NODE_ERR_POSE_STALE | VLFF_NODE_ERR_CHECKPOINT | (1u << 9);
  st.iteration = 12345;
  st.loss = 0.5, st.loss_rgb = 0.25, st.loss_depth = 0.125, st.loss_feat = 0.0625;
  st.keyframes = 77;
  st.map_version = 901;
  st.map_age_s = 1.5;
  st.fps_in = 29.5;
  st.prompt_set = 2;
  st.frames_invalid = 40;
  st.last_refusal = VLFF_REFUSED_NO_POSE;
  for (int r = 1; r < VLFF_REFUSED_COUNT; r++) st.refused[r] = 100 + r;
  st.mem_rss_mb = 812.5, st.mem_keyframes_mb = 300, st.mem_keyframes_limit_mb = 1024;
  st.mem_evidence_mb = 50, st.mem_evidence_limit_mb = 64;
  st.keyframes_paged = 12, st.keyframes_dropped = 3, st.evidence_dropped = 4000;
  st.box_growths = 5, st.box_refused = 1;
  return st;
}

static void test_every_field(void **state) {
  (void)state;
  struct vlff_node_status st = sample();
  struct vlff_can_status cs;
  enum vlff_can_nmt nmt;
  memset(&cs, 0xa5, sizeof cs); /* every field must be written */
  vlff_node_can_status(&st, 2.5, 10000000000, &cs, &nmt);
  assert_int_equal(nmt, VLFF_NMT_OPERATIONAL);
  assert_int_equal(cs.iteration, 12345);
  assert_true(cs.loss_total == 0.5f && cs.loss_color == 0.25f && cs.loss_depth == 0.125f &&
              cs.loss_feature == 0.0625f);
  assert_int_equal(cs.keyframes, 77);
  assert_int_equal(cs.map_version, 901);
  assert_int_equal(cs.map_published_ns, 8500000000); /* 1.5 s before now */
  assert_true(cs.fps_in == 29.5f);
  assert_true(cs.fps_dropped == 2.5f);
  assert_int_equal(cs.prompt_set, 2);
  assert_int_equal(cs.error_flags, VLFF_NODE_ERR_POSE_STALE | VLFF_NODE_ERR_CHECKPOINT); /* bit 9 is not CAN's */
  assert_int_equal(cs.frames_refused, 40);
  assert_int_equal(cs.last_refusal, VLFF_REFUSED_NO_POSE);
  assert_int_equal(cs.refused[0], 0);
  for (int r = 1; r < VLFF_REFUSED_COUNT; r++) assert_int_equal(cs.refused[r], 100 + r);
  for (int r = VLFF_REFUSED_COUNT; r < VLFF_CAN_REFUSAL_CODES; r++) assert_int_equal(cs.refused[r], 0);
  assert_true(cs.mem_rss_mb == 812.5f && cs.mem_keyframes_mb == 300 && cs.mem_keyframes_limit_mb == 1024 &&
              cs.mem_evidence_mb == 50 && cs.mem_evidence_limit_mb == 64);
  assert_int_equal(cs.keyframes_paged, 12);
  assert_int_equal(cs.keyframes_dropped, 3);
  assert_int_equal(cs.evidence_dropped, 4000);
  assert_int_equal(cs.box_growths, 5);
  assert_int_equal(cs.box_refused, 1);
}

static void test_edges(void **state) {
  (void)state;
  struct vlff_node_status st = sample();
  st.map_age_s = -1; /* nothing published yet */
  st.prompt_set = -1; /* texts posted, no configured set */
  st.keyframes_paged = 5000000000LL, st.evidence_dropped = (long long)UINT32_MAX + 1;
  st.box_growths = -3, st.keyframes_dropped = (long long)UINT32_MAX, st.box_refused = 0;
  st.iteration = (1LL << 32) + 7; /* the low 32 bits, as the frame's counter */
  st.mem_rss_mb = -1;              /* unknown goes out as unknown */
  struct vlff_can_status cs;
  enum vlff_can_nmt nmt;
  vlff_node_can_status(&st, 0, 5, &cs, &nmt);
  assert_int_equal(cs.map_published_ns, 0);
  assert_int_equal(cs.prompt_set, 0xff);
  assert_int_equal(cs.keyframes_paged, UINT32_MAX);
  assert_int_equal(cs.evidence_dropped, UINT32_MAX);
  assert_int_equal(cs.keyframes_dropped, UINT32_MAX);
  assert_int_equal(cs.box_growths, 0);
  assert_int_equal(cs.box_refused, 0);
  assert_int_equal(cs.iteration, 7);
  assert_true(cs.mem_rss_mb < 0);
  /* each node state as the heartbeat carries it */
  const int states[][2] = {{VLFF_NODE_OPERATIONAL, VLFF_NMT_OPERATIONAL},
                           {VLFF_NODE_STOPPED, VLFF_NMT_STOPPED},
                           {VLFF_NODE_ERROR, VLFF_NMT_ERROR},
                           {VLFF_NODE_PREOP, VLFF_NMT_PREOPERATIONAL},
                           {VLFF_NODE_BOOT, VLFF_NMT_PREOPERATIONAL}};
  for (size_t i = 0; i < sizeof states / sizeof states[0]; i++) {
    st.state = states[i][0];
    vlff_node_can_status(&st, 0, 5, &cs, &nmt);
    assert_int_equal(nmt, states[i][1]);
  }
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_every_field), cmocka_unit_test(test_edges))
