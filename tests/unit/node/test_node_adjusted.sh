#!/usr/bin/env bash
# Start-up adjustments on --status (issue 55: "publish.voxel_size_m 0.050 m
# needs more than shm.map_max_voxels; using 0.055 m" was only a warning at
# start-up, scrolled away). A box too fine for the map segment: the --status
# line names the adjustment; a box that fits: no "adjusted" on it.
# Usage: test_node_adjusted.sh NODE
set -u
node=$1
. "$(dirname "$0")/sh_kit.sh" nad
run() {  # run VOXELS: the node's --status output into $tmp/log until a status line shows
  printf 'node:\n  state_dir: %s\nsource:\n  kind: sim\npublish:\n  voxel_size_m: 0.05\n' "$tmp" >"$tmp/n.yaml"
  printf 'shm:\n  map_max_voxels: %s\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\n  feature_ring: %s-f\n' \
    "$1" $p $p $p $p >>"$tmp/n.yaml"
  : >"$tmp/log"  # now: the background redirection may come after the first wait reads it
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
verdict
