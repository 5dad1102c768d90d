#!/usr/bin/env bash
# Start-up adjustments on --status (issue 55: "publish.voxel_size_m 0.050 m
# needs more than shm.map_max_voxels; using 0.055 m" was only a warning at
# start-up, scrolled away). A box too fine for the map segment: the --status
# line names the adjustment; a box that fits: no "adjusted" on it.
# Usage: test_node_adjusted.sh NODE
set -u
node=$1
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
wait_until() { local k; for ((k = 0; k < $1; k++)); do eval "$2" && return 0; sleep 0.1; done; return 1; }
tmp=$(mktemp -d)
p=/nad-$$
cleanup() {
  [[ -n ${nodepid:-} ]] && kill -9 "$nodepid" 2>/dev/null
  rm -rf "$tmp"
  rm -f /dev/shm$p-*
}
trap cleanup EXIT
run() {  # run VOXELS: the node's --status output into $tmp/log until a status line shows
  printf 'node:\n  state_dir: %s\nsource:\n  kind: sim\npublish:\n  voxel_size_m: 0.05\n' "$tmp" >"$tmp/n.yaml"
  printf 'shm:\n  map_max_voxels: %s\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\n  feature_ring: %s-f\n' \
    "$1" $p $p $p $p >>"$tmp/n.yaml"
  "$node" --config "$tmp/n.yaml" --status 2>"$tmp/log" &
  nodepid=$!
  wait_until 300 'grep -q "mIoU 2D" "$tmp/log"'
  kill -TERM "$nodepid"; wait "$nodepid"; nodepid=
  rm -f /dev/shm$p-*
}
# the default box, 5 m a side: 1e6 voxels of 5 cm
run 500000
check "the status line shows the coarser voxels and why" \
  'grep -aq "| adjusted: publish.voxel_size_m 0.050 -> 0.0[0-9]* m (the box needs more than shm.map_max_voxels 500000)" "$tmp/log"'
run 2000000
check "a box that fits: nothing adjusted" 'grep -aq "mIoU 2D" "$tmp/log" && ! grep -aq "adjusted" "$tmp/log"'
echo "$passes passed, $fails failed"
(( fails == 0 )) || { echo "--- node log"; tail -c 2000 "$tmp/log"; }
(( fails == 0 ))
