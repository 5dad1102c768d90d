/*
 * The node's status as CAN reports it (docs/can.md): what vlff-node copies,
 * ten times a second, from vlff_node_status into vlff_can_set_status and
 * vlff_can_set_state.
 *
 * Contract: a pure function of its arguments. The PAGING frame's counts go
 * into CAN's 32-bit words saturated (a negative one as 0), never wrapped
 * to a small number; the iteration, keyframes, map version and the INGEST
 * totals as their low 32 bits; the node's error bits 0..3 only; prompt set
 * -1 (none) as 0xff; the map's age as the CLOCK_MONOTONIC time of its
 * publish (0 = never).
 */
#ifndef VLFF_CAN_STATUS_H
#define VLFF_CAN_STATUS_H

#include <stdint.h>

#include "node.h"
#include "vlff_can.h"

/* st's fields into *out, and the heartbeat's NMT state for st->state into
 * *nmt. dropped_per_s: frames dropped per second over the last period;
 * now_ns: CLOCK_MONOTONIC now. */
void vlff_node_can_status(const struct vlff_node_status *st, double dropped_per_s, int64_t now_ns,
                          struct vlff_can_status *out, enum vlff_can_nmt *nmt);

#endif
