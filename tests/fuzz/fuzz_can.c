/* libFuzzer target: any CAN frame a bus can deliver (id, flags, 0..64 bytes)
 * goes through command validation, status and error decoding without
 * crashing, and a frame judged valid really is a well-formed command. */
#include <linux/can.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "can_proto.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  if (size < 5) return 0;
  uint32_t id;
  memcpy(&id, data, 4);
  int node = 1 + data[4] % 127;
  const uint8_t *payload = data + 5;
  int len = (int)(size - 5 > CANFD_MAX_DLEN ? CANFD_MAX_DLEN : size - 5);
  uint8_t buf[CANFD_MAX_DLEN] = {0};
  memcpy(buf, payload, (size_t)len);

  struct vlff_can_command cmd;
  int check = vlff_canp_check_command(buf, len, node, 1 + (int)(id % 8), &cmd);
  if (check == VLFF_CANP_CMD_VALID) {
    if (len != VLFF_CANP_CMD_LEN || (buf[0] != 0 && buf[0] != node)) __builtin_trap();
    if (cmd.code < VLFF_CAN_CMD_START || cmd.code > VLFF_CAN_CMD_PUBLISH) __builtin_trap();
    uint8_t again[4];
    vlff_canp_encode_command(buf[0], &cmd, again);
    if (memcmp(again, buf, 4) != 0) __builtin_trap();
  }
  struct vlff_canp_status_view v;
  for (int i = 0; i <= VLFF_CANP_STATUS_FRAMES; i++) {
    int rc = vlff_canp_decode_status(i, buf, len, &v);
    if (rc == 0 && (len != 8 || i >= VLFF_CANP_STATUS_FRAMES)) __builtin_trap();
  }
  char desc[64];
  vlff_canp_decode_error(id | CAN_ERR_FLAG, buf, desc, sizeof desc);
  if (strlen(desc) >= sizeof desc) __builtin_trap();
  return 0;
}
