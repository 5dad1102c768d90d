#!/usr/bin/env bash
# A forged checkpoint through the real programs (issue 51): a node learns
# from vlff-sim and checkpoints on SIGTERM; the file is forged with a NaN
# parameter and its checksum recomputed as the format does (docs/field.md).
# The restarted node refuses it by file, tensor and index, counts it, and
# starts a new field instead of resuming NaN (it used to log "resumed").
set -u
. "$(dirname "$0")/node_sh.sh" nck "$@"
val() { awk -v k="$1" '$1 == k { print $2 }' "$tmp/stat"; }
"$sim" --config "$tmp/n.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 1200 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null; [[ $(val iterations) -gt 0 ]] 2>/dev/null'
kill "$simpid"; wait "$simpid"; simpid=
stop_node
ckpt=$(ls "$tmp"/field.*.ckpt 2>/dev/null | head -1)
check "the node checkpointed on SIGTERM ($ckpt)" '[[ -f $ckpt ]]'
python3 - "$ckpt" <<'PY'
import struct, sys
path = sys.argv[1]
b = bytearray(open(path, "rb").read())
b[80:84] = struct.pack("<f", float("nan"))  # params[0], right after the 80-byte header
M = (1 << 64) - 1
h, body = 0xcbf29ce484222325, bytes(b[:-8])
for i in range(0, len(body) + 1, 8):
    chunk = body[i:i + 8]
    w = int.from_bytes(chunk.ljust(8, b"\0"), "little")
    if len(chunk) < 8:
        w ^= len(chunk) << 56
    h = ((h ^ w) * 0x100000001b3) & M
    h ^= h >> 29
    if len(chunk) < 8:
        break
b[-8:] = h.to_bytes(8, "little")
open(path, "wb").write(b)
PY
"$node" --config "$tmp/n.yaml" 2>"$tmp/log" &
nodepid=$!
wait_until 300 'grep -q "waiting for ring\|resumed from" "$tmp/log"'
check "the forged checkpoint is refused by file, tensor and index" \
  'grep -q "checkpoint refused, skipped: checkpoint $ckpt: refused: params\[0\] (hash table) = nan, not finite" "$tmp/log"'
check "the node does not resume from it" '! grep -q "resumed from" "$tmp/log"'
stop_node
verdict
