#!/usr/bin/env bash
# Node benchmark: bench_node (time to a useful map on the live 5 Hz stream)
# on today's room (configs/demo-sim.yaml), on the flat
# (tests/bench/node-flat.yaml), on the building
# (tests/bench/node-building.yaml: its first walk through three flats,
# scored at its end and for forgetting; docs/sim.md, bench_node.c), the
# building again with half the memory (bldg_half: keyframes.memory_mb 512
# and publish.evidence_max_mb 32, half the defaults the building fills;
# what the budgets give up is paged or evicted), on the
# room with a chair moved at 30 s ("change": bench_node's change_visible_s,
# 60 s unless VLFF_BENCH_SECONDS says), then the room under node.cpu_budget
# (docs/node.md, "CPU budget"). RESULT: the room's keys as bench_node
# prints them, then the flat's with a _flat suffix, the building's with a
# bldg_ prefix, then bldg_half_budget_miou3d_end and _rss_peak_mb (target:
# within 5 points of bldg_miou3d_end), then the building from a +-2.5 m
# first box that grows (bldg_grow: field.grow; the simulator renders the
# building in its own box, sim.scene_min/max; the first box's levels and
# occupancy cells keep the building config's sizes in metres):
# bldg_grow_miou3d_end, _fusion_end, _forgetting_pts, _rss_peak_mb,
# _frame_to_map_p99_ms (target: as the configured box's), then the growing
# building again with a map capacity of 350000 voxels, less than half the
# building's (bldg_slide: the map's grid slides with the camera and keeps
# what it leaves in the far map, docs/field.md "Beyond the caps"; scored
# through the far map as any reader reads it): bldg_slide_miou3d_end,
# _forgetting_pts, _rss_peak_mb, _frame_to_map_p99_ms (target: within 5
# points of bldg_grow_miou3d_end), then change_visible_s, then per
# budget B (0.5 -> 05)
# cpu_cores_used_budgetB (the process's cores over the run) and
# cpu_cores_used_budgetB_ratio (over B; target 0.95..1.05), and
# miou3d_end_1core: the 3D mIoU at the end of the same walk as the room's
# miou3d_end with a budget of 1 (target >= miou3d_end - 5).
# Env: VLFF_BUILD (release build dir), VLFF_BENCH_SECONDS (passed on; the
# budget-1 run walks as long), VLFF_NODE_SCENES (default "room flat bldg
# bldg_half bldg_grow bldg_slide change"), VLFF_NODE_BUDGETS (default "1 0.5 2"; "" for none),
# VLFF_BENCH_BUDGET_SECONDS (the other budgets' runs, default 60).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${VLFF_BUILD:-$here/../../build/release}
exe=$build/bench/bench_node
[[ -x $exe ]] || { echo "node.sh: $exe not built" >&2; exit 1; }
kv_of() { grep '^RESULT ' <<<"$1" | sed 's/^RESULT //' | tr '\n' ' '; }
val_of() { tr ' ' '\n' <<<"$1" | sed -n "s/^$2=//p" | head -1; }
res="RESULT"
# The building at half the memory: the same config with the two budgets halved.
half=$(mktemp --suffix=.yaml)
sed 's/^publish:$/publish:\n  evidence_max_mb: 32/' "$here/node-building.yaml" >"$half"
printf 'keyframes:\n  memory_mb: 512\n' >>"$half"
# The building from a first box of +-2.5 m that grows: 256 cells over 5 m
# at the finest level and 3 at the coarsest are the building config's 1250
# and 16 over 24.4 m (2 cm and 1.5 m); 24 occupancy cells over 5 m, 21 cm
# cubes, are about the 64 over the building's box.
grow=$(mktemp --suffix=.yaml)
slide=$(mktemp --suffix=.yaml)
trap 'rm -f "$half" "$grow" "$slide"' EXIT
sed -e 's/^  finest_resolution: 1250$/  finest_resolution: 256\n  base_resolution: 3\n  grow: true/' \
    -e 's/^  scene_min: \[-12.2, -5, -1.5\]$/  scene_min: [-2.5, -2.5, -2.5]/' \
    -e 's/^  scene_max: \[12.2, 5, 1.5\]$/  scene_max: [2.5, 2.5, 2.5]/' \
    -e 's/^sim:$/sim:\n  scene_min: [-12.2, -5, -1.5]\n  scene_max: [12.2, 5, 1.5]/' \
    -e 's/^train:$/train:\n  occupancy_resolution: 24/' "$here/node-building.yaml" >"$grow"
(( $(grep -c 'grow: true\|scene_min: \[-2.5\|scene_min: \[-12.2\|occupancy_resolution: 24\|base_resolution: 3' "$grow") == 5 )) \
  || { echo "node.sh: tests/bench/node-building.yaml changed: its growing variant could not be made" >&2; exit 1; }
sed 's/^shm:$/shm:\n  map_max_voxels: 350000/' "$grow" >"$slide"
for sc in ${VLFF_NODE_SCENES:-room flat bldg bldg_half bldg_grow bldg_slide change}; do
  echo "--- $sc"
  case $sc in
    room) log=$("$exe" | tee /dev/stderr) ;;
    flat) log=$(VLFF_BENCH_CONFIG=$here/node-flat.yaml "$exe" | tee /dev/stderr) ;;
    bldg) log=$(VLFF_BENCH_CONFIG=$here/node-building.yaml "$exe" | tee /dev/stderr) ;;
    bldg_half) log=$(VLFF_BENCH_CONFIG=$half "$exe" | tee /dev/stderr) ;;
    bldg_grow) log=$(VLFF_BENCH_CONFIG=$grow "$exe" | tee /dev/stderr) ;;
    bldg_slide) log=$(VLFF_BENCH_CONFIG=$slide "$exe" | tee /dev/stderr) ;;
    change) log=$(VLFF_BENCH_CHANGE=1 VLFF_BENCH_SECONDS=${VLFF_BENCH_SECONDS:-60} "$exe" | tee /dev/stderr) ;;
    *) echo "node.sh: unknown scene '$sc'" >&2; exit 1 ;;
  esac
  kv=$(kv_of "$log")
  if [[ $sc == room ]]; then res="$res $kv"
  elif [[ $sc == bldg ]]; then for p in $kv; do res="$res bldg_$p"; done
  elif [[ $sc == bldg_half ]]; then
    res="$res bldg_half_budget_miou3d_end=$(val_of "$kv" miou3d_end) bldg_half_budget_rss_peak_mb=$(val_of "$kv" rss_peak_mb)"
  elif [[ $sc == bldg_grow ]]; then
    for k in miou3d_end miou3d_fusion_end forgetting_pts rss_peak_mb frame_to_map_p99_ms; do
      res="$res bldg_grow_$k=$(val_of "$kv" $k)"
    done
  elif [[ $sc == bldg_slide ]]; then
    for k in miou3d_end forgetting_pts rss_peak_mb frame_to_map_p99_ms; do
      res="$res bldg_slide_$k=$(val_of "$kv" $k)"
    done
  elif [[ $sc == change ]]; then res="$res $(grep -o 'change_visible_s=[^ ]*' <<<"$kv" || true)"
  else for p in $kv; do res="$res ${p%%=*}_$sc=${p#*=}"; done; fi
done
for b in ${VLFF_NODE_BUDGETS-1 0.5 2}; do
  echo "--- room, node.cpu_budget $b"
  secs=${VLFF_BENCH_SECONDS:-120}
  [[ $b == 1 ]] || secs=${VLFF_BENCH_BUDGET_SECONDS:-60}
  kv=$(kv_of "$(VLFF_BENCH_BUDGET=$b VLFF_BENCH_SECONDS=$secs "$exe" | tee /dev/stderr)")
  key=budget${b/./}
  res="$res cpu_cores_used_$key=$(val_of "$kv" cpu_cores_used) cpu_cores_used_${key}_ratio=$(val_of "$kv" cpu_budget_ratio)"
  [[ $b == 1 ]] && res="$res miou3d_end_1core=$(val_of "$kv" miou3d_end)"
done
echo "$res"
