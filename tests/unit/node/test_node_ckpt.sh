#!/usr/bin/env bash
# A forged checkpoint through the real programs (issue 51): a node learns
# from vlff-sim and checkpoints on SIGTERM; the file is forged with a NaN
# parameter and its checksum recomputed as the format does (docs/field.md).
# The restarted node refuses it by file, tensor and index, counts it, and
# starts a new field instead of resuming NaN (it used to log "resumed").
# Then a file whose values are within the bounds but overflow together.
set -u
# A small hash table: the forger below recomputes the checksum in Python,
# word by word, and the default table made that the test's longest step.
node_field=$'field:\n  feature_dim: 64\n  hash_log2_size: 14'
. "$(dirname "$0")/node_sh.sh" nck "$@"
val() { awk -v k="$1" '$1 == k { print $2 }' "$tmp/stat"; }
"$sim" --config "$tmp/n.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 1200 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null; [[ $(val iterations) -gt 0 ]] 2>/dev/null'
kill "$simpid"; wait "$simpid"; simpid=
stop_node
ckpt=$(ls -t "$tmp"/field.*.ckpt 2>/dev/null | head -1)  # the newest: the one resumed first
check "the node checkpointed on SIGTERM ($ckpt)" '[[ -f $ckpt ]]'
# forge FILE nan|mlp: a NaN in params[0], or every MLP weight (params after the
# hash table) set to 1e6, within the load bounds; then the checksum recomputed
# as the format does (docs/field.md).
forge() {
python3 - "$1" "$2" <<'PY'
import struct, sys
path, mode = sys.argv[1], sys.argv[2]
b = bytearray(open(path, "rb").read())
nparams, ntable = struct.unpack_from("<QQ", b, 24)  # after magic, version, BOM, config hash
p0 = 80 + 24 + 24  # params[0]: after the 80-byte header, the box and the cells' size (version 7)
if mode == "nan":
    b[p0:p0 + 4] = struct.pack("<f", float("nan"))
else:
    for i in range(ntable, nparams):
        struct.pack_into("<f", b, p0 + 4 * i, 1e6)
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
}
cp "$ckpt" "$tmp/genuine.ckpt"  # forged below with values within the bounds
forge "$ckpt" nan
# Emptied here, not only by the background start's redirection, which may
# come after the waits below have read the previous run's log.
: >"$tmp/log"
"$node" --config "$tmp/n.yaml" 2>"$tmp/log" &
nodepid=$!
wait_until 300 'grep -q "waiting for ring\|attached to ring\|resumed from" "$tmp/log"'
check "the forged checkpoint is refused by file, tensor and index" \
  'grep -q "checkpoint refused, skipped: checkpoint $ckpt: refused: params\[0\] (hash table) = nan, not finite" "$tmp/log"'
check "the node does not resume from it" '! grep -q "resumed from" "$tmp/log"'

# Values within the bounds that overflow together: weights of 1e6 through the
# MLPs drove Adam's m to 2e10 with every loss finite (1e29), and the node
# trained on that for good. It resumes from the file, its scan (at the first
# step, then every 200) finds the field out of bounds, and with no other
# checkpoint it starts anew, learns and checkpoints finite values.
stop_node
rm -f "$tmp"/field.*.ckpt "$tmp"/map.*.obs  # the forged file alone: nothing good to go back to
mv "$tmp/genuine.ckpt" "$ckpt"
forge "$ckpt" mlp
# Emptied here, not only by the background start's redirection, which may
# come after the waits below have read the previous run's log.
: >"$tmp/log"
"$node" --config "$tmp/n.yaml" 2>"$tmp/log" &
nodepid=$!
"$sim" --config "$tmp/n.yaml" --quiet 2>>"$tmp/simlog" &
simpid=$!
check "the node resumes from the file, whose values are within the bounds" \
  'wait_until 300 "grep -q \"resumed from $ckpt\" \"$tmp/log\""'
check "the diverging field is found and re-initialised" \
  'wait_until 600 "grep -q \"the field diverged (.*): re-initialised\" \"$tmp/log\""'
wait_until 1200 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null; (( $(val iterations) > 0 )) 2>/dev/null && grep -q "diverged" "$tmp/log"'
kill "$simpid"; wait "$simpid"; simpid=
stop_node
check "the new field checkpoints on SIGTERM" 'grep -q "I node: checkpoint .* at step" "$tmp/log"'
check "it diverged once, not again" '[[ $(grep -c "the field diverged" "$tmp/log") == 1 ]]'

# The same forgery in the newest slot with a genuine checkpoint in the other:
# the node resumes the forged one, and its rollback passes over the slot it
# came from and takes the other, naming it.
good=$(ls -t "$tmp"/field.*.ckpt | head -1)
bad=$tmp/field.$((1 - ${good: -6:1})).ckpt
cp "$good" "$bad"
forge "$bad" mlp
touch -d '+1 second' "$bad"
# Emptied here, not only by the background start's redirection, which may
# come after the waits below have read the previous run's log.
: >"$tmp/log"
"$node" --config "$tmp/n.yaml" 2>"$tmp/log" &
nodepid=$!
"$sim" --config "$tmp/n.yaml" --quiet 2>>"$tmp/simlog" &
simpid=$!
check "the node resumes from the forged newest slot" 'wait_until 300 "grep -q \"resumed from $bad\" \"$tmp/log\""'
check "it rolls back to the other slot, named" \
  'wait_until 600 "grep -q \"the field diverged (.*): rolled back to $good at step\" \"$tmp/log\""'
kill "$simpid"; wait "$simpid"; simpid=
stop_node
check "it diverged once" '[[ $(grep -c "the field diverged" "$tmp/log") == 1 ]]'
verdict
