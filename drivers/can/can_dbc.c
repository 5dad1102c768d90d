/*
 * The DBC of one configured node: configs/vlff.dbc's messages with the ids
 * and cycle times of the config's can.* keys, so that a controller's tools
 * decode a node whose can.node_id is not the default without a hand-edited
 * file. configs/vlff.dbc is this writer's output for the default config
 * (a test compares them byte for byte).
 */
#include <errno.h>
#include <stdbool.h>
#include <stdio.h>
#include <string.h>

#include "can_proto.h"
#include "config.h"

/* {NAME} marks a value taken from the config. A line naming a message the
 * configured node does not send (write_dbc decides which) is left out, and
 * with a BO_ line its whole message, up to the blank line that ends it. */
static const char dbc_template[] =
    "VERSION \"vlff 1\"\n"
    "\n"
    "NS_ :\n"
    "\tCM_\n"
    "\tBA_DEF_\n"
    "\tBA_\n"
    "\tVAL_\n"
    "\tBA_DEF_DEF_\n"
    "\n"
    "BS_:\n"
    "\n"
    "BU_: VLFF CONTROLLER\n"
    "\n"
    "BO_ {HB} VLFF_HEARTBEAT: 1 VLFF\n"
    " SG_ NmtState : 0|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    "\n"
    "BO_ {S0} VLFF_TRAIN: 8 VLFF\n"
    " SG_ Iteration : 0|32@1+ (1,0) [0|4294967295] \"\" CONTROLLER\n"
    " SG_ Keyframes : 32|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ PromptSet : 48|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ NmtState : 56|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    "\n"
    "BO_ {S1} VLFF_LOSS: 8 VLFF\n"
    " SG_ LossTotal : 0|16@1+ (0.001,0) [0|65.535] \"\" CONTROLLER\n"
    " SG_ LossColor : 16|16@1+ (0.0001,0) [0|6.5535] \"\" CONTROLLER\n"
    " SG_ LossDepth : 32|16@1+ (0.0001,0) [0|6.5535] \"\" CONTROLLER\n"
    " SG_ LossFeature : 48|16@1+ (0.0001,0) [0|6.5535] \"\" CONTROLLER\n"
    "\n"
    "BO_ {S2} VLFF_MAP: 8 VLFF\n"
    " SG_ MapVersion : 0|32@1+ (1,0) [0|4294967295] \"\" CONTROLLER\n"
    " SG_ MapAge : 32|16@1+ (1,0) [0|65535] \"ms\" CONTROLLER\n"
    " SG_ FpsIn : 48|16@1+ (0.01,0) [0|655.35] \"1/s\" CONTROLLER\n"
    "\n"
    "BO_ {S3} VLFF_HEALTH: 8 VLFF\n"
    " SG_ ErrCameraLost : 0|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrPoseStale : 1|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrShmLapped : 2|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrCheckpointFailed : 3|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrBus : 4|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrTxDropped : 5|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrCmdRejected : 6|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ FpsDropped : 8|16@1+ (0.01,0) [0|655.35] \"1/s\" CONTROLLER\n"
    " SG_ CmdRejected : 24|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ TxDropped : 40|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ BusOff : 56|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusPassive : 57|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusWarning : 58|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusController : 59|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusTxTimeout : 60|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusProtocol : 61|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusNoAck : 62|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusRestarted : 63|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    "\n"
    "BO_ {S5} VLFF_INGEST: 8 VLFF\n"
    " SG_ FramesRefused : 0|32@1+ (1,0) [0|4294967295] \"\" CONTROLLER\n"
    " SG_ LastRefusal : 32|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ RefusedMalformed : 40|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedOversize : 41|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedPixelFormat : 42|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedNoIntrinsics : 43|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedBadIntrinsics : 44|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedNoPose : 45|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedBadPose : 46|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedPoseRange : 47|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedNoDepth : 48|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedEmptyDepth : 49|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedTooSmall : 50|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedNoFeatures : 51|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedFuturePose : 52|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedFeaturesLate : 53|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedFutureFrame : 54|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedPeriod : 56|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    "\n"
    "BO_ {S6} VLFF_MEMORY: 8 VLFF\n"
    " SG_ MemRss : 0|16@1+ (1,0) [0|65535] \"MiB\" CONTROLLER\n"
    " SG_ MemKeyframes : 16|12@1+ (4,0) [0|16380] \"MiB\" CONTROLLER\n"
    " SG_ MemKeyframesLimit : 28|12@1+ (4,0) [0|16380] \"MiB\" CONTROLLER\n"
    " SG_ MemEvidence : 40|12@1+ (1,0) [0|4095] \"MiB\" CONTROLLER\n"
    " SG_ MemEvidenceLimit : 52|12@1+ (1,0) [0|4095] \"MiB\" CONTROLLER\n"
    "\n"
    "BO_ {S7} VLFF_PAGING: 8 VLFF\n"
    " SG_ KeyframesPaged : 0|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ KeyframesDropped : 16|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ EvidenceDropped : 32|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ BoxGrowths : 48|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ BoxRefused : 56|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    "\n"
    "BO_ {S4} VLFF_STATUS_FD: 64 VLFF\n"
    " SG_ Iteration : 0|32@1+ (1,0) [0|4294967295] \"\" CONTROLLER\n"
    " SG_ Keyframes : 32|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ PromptSet : 48|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ NmtState : 56|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ LossTotal : 64|16@1+ (0.001,0) [0|65.535] \"\" CONTROLLER\n"
    " SG_ LossColor : 80|16@1+ (0.0001,0) [0|6.5535] \"\" CONTROLLER\n"
    " SG_ LossDepth : 96|16@1+ (0.0001,0) [0|6.5535] \"\" CONTROLLER\n"
    " SG_ LossFeature : 112|16@1+ (0.0001,0) [0|6.5535] \"\" CONTROLLER\n"
    " SG_ MapVersion : 128|32@1+ (1,0) [0|4294967295] \"\" CONTROLLER\n"
    " SG_ MapAge : 160|16@1+ (1,0) [0|65535] \"ms\" CONTROLLER\n"
    " SG_ FpsIn : 176|16@1+ (0.01,0) [0|655.35] \"1/s\" CONTROLLER\n"
    " SG_ ErrCameraLost : 192|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrPoseStale : 193|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrShmLapped : 194|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrCheckpointFailed : 195|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrBus : 196|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrTxDropped : 197|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ ErrCmdRejected : 198|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ FpsDropped : 200|16@1+ (0.01,0) [0|655.35] \"1/s\" CONTROLLER\n"
    " SG_ CmdRejected : 216|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ TxDropped : 232|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ BusOff : 248|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusPassive : 249|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusWarning : 250|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusController : 251|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusTxTimeout : 252|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusProtocol : 253|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusNoAck : 254|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ BusRestarted : 255|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ FramesRefused : 256|32@1+ (1,0) [0|4294967295] \"\" CONTROLLER\n"
    " SG_ LastRefusal : 288|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ RefusedMalformed : 296|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedOversize : 297|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedPixelFormat : 298|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedNoIntrinsics : 299|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedBadIntrinsics : 300|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedNoPose : 301|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedBadPose : 302|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedPoseRange : 303|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedNoDepth : 304|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedEmptyDepth : 305|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedTooSmall : 306|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedNoFeatures : 307|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedFuturePose : 308|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedFeaturesLate : 309|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedFutureFrame : 310|1@1+ (1,0) [0|1] \"\" CONTROLLER\n"
    " SG_ RefusedPeriod : 312|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ MemRss : 320|16@1+ (1,0) [0|65535] \"MiB\" CONTROLLER\n"
    " SG_ MemKeyframes : 336|12@1+ (4,0) [0|16380] \"MiB\" CONTROLLER\n"
    " SG_ MemKeyframesLimit : 348|12@1+ (4,0) [0|16380] \"MiB\" CONTROLLER\n"
    " SG_ MemEvidence : 360|12@1+ (1,0) [0|4095] \"MiB\" CONTROLLER\n"
    " SG_ MemEvidenceLimit : 372|12@1+ (1,0) [0|4095] \"MiB\" CONTROLLER\n"
    " SG_ KeyframesPaged : 384|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ KeyframesDropped : 400|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ EvidenceDropped : 416|16@1+ (1,0) [0|65535] \"\" CONTROLLER\n"
    " SG_ BoxGrowths : 432|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ BoxRefused : 440|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    "\n"
    "BO_ {CMD} VLFF_COMMAND: 4 CONTROLLER\n"
    " SG_ Target : 0|8@1+ (1,0) [0|255] \"\" VLFF\n"
    " SG_ Command : 8|8@1+ (1,0) [0|255] \"\" VLFF\n"
    " SG_ Argument : 16|8@1+ (1,0) [0|255] \"\" VLFF\n"
    " SG_ Sequence : 24|8@1+ (1,0) [0|255] \"\" VLFF\n"
    "\n"
    "BO_ {ACK} VLFF_ACK: 4 VLFF\n"
    " SG_ Node : 0|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ Command : 8|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ Result : 16|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    " SG_ Sequence : 24|8@1+ (1,0) [0|255] \"\" CONTROLLER\n"
    "\n"
    "CM_ BO_ {HB} \"Heartbeat, CANopen convention: COB-ID 0x700 + can.node_id ({NODE} here). Boot-up (0) is sent once first, then the state every can.heartbeat_ms.\";\n"
    "CM_ BO_ {S0} \"Training progress, every can.status_ms at can.status_base_id + 0.\";\n"
    "CM_ BO_ {S1} \"Latest loss terms at can.status_base_id + 1; raw 0xFFFF = invalid (NaN/inf) or above range.\";\n"
    "CM_ BO_ {S2} \"Published map at can.status_base_id + 2.\";\n"
    "CM_ BO_ {S3} \"Health at can.status_base_id + 3; counters saturate at 65535; Err*/Bus* bits 4..6 and 56..63 cover the status period just ended.\";\n"
    "CM_ BO_ {S5} \"Frames the node refused, at can.status_base_id + 5 (+ 4 is the FD frame's id): total since start, the latest reason, one bit per reason that refused a frame in the status period just ended, and how many were refused in it. vlff-node --status and its log give the per-reason counts.\";\n"
    "CM_ BO_ {S6} \"Memory against its limits at can.status_base_id + 6, MiB: the process's resident set, the keyframe store and keyframes.memory_mb (4 MiB steps), the evidence and publish.evidence_max_mb. A signal with every bit set is unknown or above its range.\";\n"
    "CM_ BO_ {S7} \"What the memory limits pushed out, at can.status_base_id + 7: the keyframes in the state directory's page file now, the keyframes dropped with nowhere to go and the voxels whose evidence was given up since start (saturating at 65535), the map box's growths and refused growths since start (saturating at 255). vlff-shm stat has the exact counts.\";\n"
    "CM_ BO_ {S4} \"With can.fd: the seven status payloads (TRAIN, LOSS, MAP, HEALTH, INGEST, MEMORY, PAGING, 8 bytes each, in that order; bytes 56..63 zero, CAN FD having no 56-byte length) in one CAN FD frame at can.status_base_id + 4 instead of seven classic frames.\";\n"
    "CM_ BO_ {CMD} \"Command from a controller at can.command_id. Exactly 4 bytes; Target 0 = every node. Other lengths are dropped and counted.\";\n"
    "CM_ BO_ {ACK} \"Acknowledgement at can.ack_id for every well-formed command addressed to this node.\";\n"
    "CM_ SG_ {S2} MapAge \"Age of the published map; 65535 = never published or older than 65.534 s.\";\n"
    "CM_ SG_ {S3} CmdRejected \"Malformed, unknown and out-of-range commands since start.\";\n"
    "CM_ SG_ {S3} TxDropped \"Frames dropped since start (tx queue full, link down).\";\n"
    "CM_ SG_ {S5} LastRefusal \"Reason of the latest refused frame; 0 = none refused since start.\";\n"
    "CM_ SG_ {S5} RefusedPeriod \"Frames refused in the status period just ended, saturating at 255.\";\n"
    "CM_ SG_ {S5} RefusedNoPose \"No pose in the frame and none in the pose ring within source.pose_tolerance_s: is vlff-pose (or the SLAM adapter) running, on the same clock?\";\n"
    "CM_ SG_ {S5} RefusedFuturePose \"The frame's pose, or the newest in the pose ring, is stamped more than pose.future_tolerance_s ahead of the clock: the pose source's clock or clock offset is wrong.\";\n"
    "CM_ SG_ {S5} RefusedFeaturesLate \"A keyframe's features did not come within vlm.feature_timeout_s, or 16 newer keyframes already waited for theirs: the feature source is slower than the keyframes come, or stopped.\";\n"
    "CM_ SG_ {S5} RefusedFutureFrame \"A frame was stamped ahead of the clock beyond pose.future_tolerance_s: the camera driver's clock or clock offset is wrong.\";\n"
    "CM_ SG_ {S7} KeyframesDropped \"Keyframes evicted from a full store with nowhere to go (keyframes.page_mb 0, the page file full or failing); each is logged.\";\n"
    "CM_ SG_ {S7} BoxRefused \"Keyframes whose box the field or the map could not grow to (field.world_limit_m, train.occupancy_max_mb, shm.map_max_voxels, the evidence's index budget).\";\n"
    "CM_ SG_ {CMD} Argument \"prompt-set: index into prompts.sets; other commands: 0.\";\n"
    "BA_DEF_ BO_ \"VFrameFormat\" ENUM \"StandardCAN\",\"ExtendedCAN\",\"reserved\",\"J1939PG\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"reserved\",\"StandardCAN_FD\",\"ExtendedCAN_FD\";\n"
    "BA_DEF_ BO_ \"GenMsgCycleTime\" INT 0 65535;\n"
    "BA_DEF_DEF_ \"VFrameFormat\" \"StandardCAN\";\n"
    "BA_DEF_DEF_ \"GenMsgCycleTime\" 0;\n"
    "BA_ \"VFrameFormat\" BO_ {S4} 14;\n"
    "BA_ \"GenMsgCycleTime\" BO_ {HB} {HBMS};\n"
    "BA_ \"GenMsgCycleTime\" BO_ {S0} {STMS};\n"
    "BA_ \"GenMsgCycleTime\" BO_ {S1} {STMS};\n"
    "BA_ \"GenMsgCycleTime\" BO_ {S2} {STMS};\n"
    "BA_ \"GenMsgCycleTime\" BO_ {S3} {STMS};\n"
    "BA_ \"GenMsgCycleTime\" BO_ {S4} {FDMS};\n"
    "BA_ \"GenMsgCycleTime\" BO_ {S5} {STMS};\n"
    "BA_ \"GenMsgCycleTime\" BO_ {S6} {STMS};\n"
    "BA_ \"GenMsgCycleTime\" BO_ {S7} {STMS};\n"
    "VAL_ {HB} NmtState 0 \"BootUp\" 4 \"Stopped\" 5 \"Operational\" 127 \"PreOperational\" 143 \"Error\" ;\n"
    "VAL_ {S0} NmtState 0 \"BootUp\" 4 \"Stopped\" 5 \"Operational\" 127 \"PreOperational\" 143 \"Error\" ;\n"
    "VAL_ {S4} NmtState 0 \"BootUp\" 4 \"Stopped\" 5 \"Operational\" 127 \"PreOperational\" 143 \"Error\" ;\n"
    "VAL_ {S5} LastRefusal 0 \"none\" 1 \"malformed\" 2 \"oversize\" 3 \"pixel format\" 4 \"no intrinsics\" 5 \"bad intrinsics\" 6 \"no pose\" 7 \"bad pose\" 8 \"pose out of range\" 9 \"no depth\" 10 \"empty depth\" 11 \"too small\" 12 \"no features\" 13 \"future pose\" 14 \"features late\" 15 \"future frame\" ;\n"
    "VAL_ {S4} LastRefusal 0 \"none\" 1 \"malformed\" 2 \"oversize\" 3 \"pixel format\" 4 \"no intrinsics\" 5 \"bad intrinsics\" 6 \"no pose\" 7 \"bad pose\" 8 \"pose out of range\" 9 \"no depth\" 10 \"empty depth\" 11 \"too small\" 12 \"no features\" 13 \"future pose\" 14 \"features late\" 15 \"future frame\" ;\n"
    "VAL_ {CMD} Command 1 \"Start\" 2 \"Stop\" 3 \"Reset\" 4 \"Save\" 5 \"PromptSet\" 6 \"Publish\" ;\n"
    "VAL_ {ACK} Command 1 \"Start\" 2 \"Stop\" 3 \"Reset\" 4 \"Save\" 5 \"PromptSet\" 6 \"Publish\" ;\n"
    "VAL_ {ACK} Result 0 \"Ok\" 1 \"UnknownCommand\" 2 \"OutOfRange\" 3 \"Refused\" 4 \"Failed\" 5 \"Busy\" ;\n";

struct subst {
  const char *name;
  int value;
};

/* Writes one template line, replacing each {NAME}. */
static int put_line(FILE *out, const char *line, size_t len, const struct subst *s, size_t ns) {
  for (size_t i = 0; i < len; i++) {
    if (line[i] == '{') {
      const char *close = memchr(line + i, '}', len - i);
      size_t k = close ? (size_t)(close - line - i - 1) : 0;
      size_t j = 0;
      for (; close && j < ns; j++)
        if (strlen(s[j].name) == k && !memcmp(s[j].name, line + i + 1, k)) break;
      if (close && j < ns) {
        if (fprintf(out, "%d", s[j].value) < 0) return -1;
        i += k + 1;
        continue;
      }
    }
    if (fputc(line[i], out) == EOF) return -1;
  }
  return 0;
}

int vlff_can_write_dbc(const struct vlff_cfg_can *cfg, FILE *out, char *err, size_t errlen) {
  if (vlff_can_check_config(cfg, err, errlen)) return -1;
  const int base = cfg->status_base_id, hb = VLFF_CANP_HEARTBEAT_BASE + cfg->node_id;
  const int fd_id = base + VLFF_CANP_STATUS_FD_OFFSET;
  const int ingest_id = base + vlff_canp_status_offset(VLFF_CANP_INGEST);
  /* With can.fd the node sends its status only as the FD frame: the seven
   * classic status messages are left out, lest a controller's DBC-driven
   * timeout monitor wait for frames that never come. Without it the FD
   * message stays for reference (a controller may switch) while its id is
   * free, but with no cycle time, since the node never sends it. */
  const bool with_fd = cfg->fd || (fd_id <= 0x7ff && fd_id != hb && fd_id != cfg->command_id &&
                                       fd_id != cfg->ack_id);
  const bool with_classic = !cfg->fd;
  const struct subst s[] = {
      {"HB", hb},
      {"S0", base + VLFF_CANP_TRAIN},
      {"S1", base + VLFF_CANP_LOSS},
      {"S2", base + VLFF_CANP_MAP},
      {"S3", base + VLFF_CANP_HEALTH},
      {"S4", fd_id},
      {"S5", ingest_id},
      {"S6", base + vlff_canp_status_offset(VLFF_CANP_MEMORY)},
      {"S7", base + vlff_canp_status_offset(VLFF_CANP_PAGING)},
      {"CMD", cfg->command_id},
      {"ACK", cfg->ack_id},
      {"NODE", cfg->node_id},
      {"HBMS", cfg->heartbeat_ms},
      {"STMS", cfg->status_ms},
      {"FDMS", cfg->status_ms},
  };
  static const char classic[][5] = {"{S0}", "{S1}", "{S2}", "{S3}", "{S5}", "{S6}", "{S7}"};
  bool skipping = false;
  for (const char *p = dbc_template; *p;) {
    const char *nl = strchr(p, '\n');
    size_t len = (size_t)(nl - p) + 1;
    bool gone = (!with_fd && memmem(p, len, "{S4}", 4)) || (!cfg->fd && memmem(p, len, "{FDMS}", 6));
    for (int k = 0; !with_classic && !gone && k < (int)(sizeof classic / sizeof classic[0]); k++)
      gone = memmem(p, len, classic[k], 4) != NULL;
    if (gone && !strncmp(p, "BO_ ", 4)) skipping = true;
    bool drop = skipping || gone;
    if (skipping && len == 1) skipping = false; /* the blank line ends the message */
    if (!drop && put_line(out, p, len, s, sizeof s / sizeof s[0])) {
      snprintf(err, errlen, "writing the DBC: %s", strerror(errno));
      return -1;
    }
    p += len;
  }
  if (fflush(out)) {
    snprintf(err, errlen, "writing the DBC: %s", strerror(errno));
    return -1;
  }
  return 0;
}
