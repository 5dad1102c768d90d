/*
 * The node's status as the map segment carries it (vlff_node_map_status,
 * node.h): every field of struct vlff_map_status comes from its own field
 * of the node's status, each given a value of its own here, so that a field
 * left out, or taken from a neighbour, fails. What controllers read
 * (vlff-shm stat, the viewer, the DDS bridge) is that block.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <string.h>

#include "node.h"
#include "vlff/shm.h"

static void test_every_field_carried(void **state) {
  (void)state;
  struct vlff_node_status st;
  memset(&st, 0, sizeof st);
  st.state = VLFF_NODE_OPERATIONAL;
  st.error_flags = VLFF_NODE_ERR_POSE_STALE;
  st.frames_in = 101, st.frames_lost = 102, st.frames_invalid = 103;
  st.keyframes = 104, st.keyframes_evicted = 105, st.iteration = 106;
  st.it_per_s = 10.5, st.fps_in = 11.5;
  st.loss = 0.25, st.loss_rgb = 0.125, st.loss_depth = 0.0625, st.loss_feat = 0.03125, st.psnr = 27.5;
  st.cpu_budget = 1.5, st.cpu_used = 1.25;
  st.frame_to_map_ms_p50 = 120.5, st.frame_to_map_ms_p99 = 340.5, st.publish_interval_s = 1.75;
  st.label_flips = 107, st.label_flips_refresh = 108, st.label_flips_total = 109, st.label_flip_frac = 0.0125;
  st.mem_keyframes_mb = 58.5, st.mem_keyframes_limit_mb = 64, st.mem_evidence_mb = 9.5;
  st.mem_evidence_limit_mb = 16, st.mem_field_mb = 300.5, st.mem_rss_mb = 494.5;
  st.keyframes_paged = 110, st.keyframes_paged_out = 111, st.keyframes_paged_in = 112, st.keyframes_dropped = 113;
  st.keyframes_page_mb = 67.25, st.keyframes_page_limit_mb = 128;
  st.evidence_paged = 114, st.evidence_paged_out = 115, st.evidence_paged_in = 116, st.evidence_dropped = 117;
  const double lo[3] = {-7.5, -6.25, -2.5}, hi[3] = {8.5, 5.75, 3.25};
  memcpy(st.box_lo, lo, sizeof lo), memcpy(st.box_hi, hi, sizeof hi);
  st.box_growths = 118, st.box_refused = 119;
  for (int r = 1; r < VLFF_REFUSED_COUNT; r++) st.refused[r] = 1000 + r;

  struct vlff_map_status ms;
  memset(&ms, 0xab, sizeof ms);
  vlff_node_map_status(&st, &ms);
  assert_int_equal(ms.t_ns, 0);
  assert_int_equal(ms.updates, 0);
  assert_int_equal(ms.state, VLFF_NODE_OPERATIONAL);
  assert_string_equal(ms.state_name, "operational");
  assert_int_equal(ms.error_flags, VLFF_NODE_ERR_POSE_STALE);
  assert_int_equal(ms.frames_in, 101);
  assert_int_equal(ms.frames_lost, 102);
  assert_int_equal(ms.frames_refused, 103);
  assert_int_equal(ms.keyframes, 104);
  assert_int_equal(ms.keyframes_evicted, 105);
  assert_int_equal(ms.iterations, 106);
  assert_true(ms.iterations_per_s == 10.5 && ms.fps_in == 11.5);
  assert_true(ms.loss == 0.25 && ms.loss_rgb == 0.125 && ms.loss_depth == 0.0625 && ms.loss_feat == 0.03125);
  assert_true(ms.psnr == 27.5 && ms.cpu_budget == 1.5 && ms.cpu_used == 1.25);
  assert_true(ms.frame_to_map_ms_p50 == 120.5 && ms.frame_to_map_ms_p99 == 340.5 && ms.publish_interval_s == 1.75);
  assert_int_equal(ms.label_flips, 107);
  assert_int_equal(ms.label_flips_refresh, 108);
  assert_int_equal(ms.label_flips_total, 109);
  assert_true(ms.label_flip_frac == 0.0125);
  assert_true(ms.mem_keyframes_mb == 58.5 && ms.mem_keyframes_limit_mb == 64 && ms.mem_evidence_mb == 9.5);
  assert_true(ms.mem_evidence_limit_mb == 16 && ms.mem_field_mb == 300.5 && ms.mem_rss_mb == 494.5);
  /* Paging and the box (ABI 8). */
  assert_int_equal(ms.keyframes_paged, 110);
  assert_int_equal(ms.keyframes_paged_out, 111);
  assert_int_equal(ms.keyframes_paged_in, 112);
  assert_int_equal(ms.keyframes_dropped, 113);
  assert_true(ms.keyframes_page_mb == 67.25 && ms.keyframes_page_limit_mb == 128);
  assert_int_equal(ms.evidence_paged, 114);
  assert_int_equal(ms.evidence_paged_out, 115);
  assert_int_equal(ms.evidence_paged_in, 116);
  assert_int_equal(ms.evidence_dropped, 117);
  assert_memory_equal(ms.box_lo, lo, sizeof lo);
  assert_memory_equal(ms.box_hi, hi, sizeof hi);
  assert_int_equal(ms.box_growths, 118);
  assert_int_equal(ms.box_refused, 119);
  /* Every reason by name, in code order, and nothing stale beyond them. */
  assert_int_equal(ms.reason_count, VLFF_REFUSED_COUNT - 1);
  for (int r = 1; r < VLFF_REFUSED_COUNT; r++) {
    assert_string_equal(ms.reason[r - 1].name, vlff_refusal_name(r));
    assert_int_equal(ms.reason[r - 1].count, 1000 + r);
  }
  for (int i = VLFF_REFUSED_COUNT - 1; i < VLFF_SHM_MAX_REASONS; i++) {
    assert_int_equal(ms.reason[i].count, 0);
    assert_int_equal(ms.reason[i].name[0], 0);
  }
}

int main(void) {
  const struct CMUnitTest tests[] = {cmocka_unit_test(test_every_field_carried)};
  return cmocka_run_group_tests(tests, NULL, NULL);
}
