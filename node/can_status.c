#include "can_status.h"

#include <string.h>

/* A count for CAN's 32-bit words: saturating, never wrapped to a small one
 * (the PAGING frame saturates it again to its signals' width). */
static uint32_t can_count(long long v) { return v <= 0 ? 0 : v >= (long long)UINT32_MAX ? UINT32_MAX : (uint32_t)v; }

void vlff_node_can_status(const struct vlff_node_status *st, double dropped_per_s, int64_t now_ns,
                          struct vlff_can_status *out, enum vlff_can_nmt *nmt) {
  *out = (struct vlff_can_status){
      .iteration = (uint32_t)st->iteration,
      .loss_total = (float)st->loss,
      .loss_color = (float)st->loss_rgb,
      .loss_depth = (float)st->loss_depth,
      .loss_feature = (float)st->loss_feat,
      .keyframes = (uint32_t)st->keyframes,
      .map_version = (uint32_t)st->map_version,
      .map_published_ns = st->map_age_s < 0 ? 0 : now_ns - (int64_t)(st->map_age_s * 1e9),
      .fps_in = (float)st->fps_in,
      .fps_dropped = (float)dropped_per_s,
      .prompt_set = st->prompt_set < 0 ? 0xff : (uint32_t)st->prompt_set,
      .error_flags = st->error_flags & 0x0f, /* the node's bits 0..3 are CAN's */
      .frames_refused = (uint32_t)st->frames_invalid,
      .last_refusal = (uint32_t)st->last_refusal,
      .mem_rss_mb = (float)st->mem_rss_mb,
      .mem_keyframes_mb = (float)st->mem_keyframes_mb,
      .mem_keyframes_limit_mb = (float)st->mem_keyframes_limit_mb,
      .mem_evidence_mb = (float)st->mem_evidence_mb,
      .mem_evidence_limit_mb = (float)st->mem_evidence_limit_mb,
      .keyframes_paged = can_count(st->keyframes_paged),
      .keyframes_dropped = can_count(st->keyframes_dropped),
      .evidence_dropped = can_count(st->evidence_dropped),
      .box_growths = can_count(st->box_growths),
      .box_refused = can_count(st->box_refused),
  };
  _Static_assert(VLFF_REFUSED_COUNT <= VLFF_CAN_REFUSAL_CODES, "every refusal reason has a bit in INGEST");
  for (int r = 1; r < VLFF_REFUSED_COUNT; r++) out->refused[r] = (uint32_t)st->refused[r];
  *nmt = st->state == VLFF_NODE_OPERATIONAL ? VLFF_NMT_OPERATIONAL
         : st->state == VLFF_NODE_STOPPED   ? VLFF_NMT_STOPPED
         : st->state == VLFF_NODE_ERROR     ? VLFF_NMT_ERROR
                                            : VLFF_NMT_PREOPERATIONAL;
}
