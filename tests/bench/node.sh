#!/usr/bin/env bash
# Node benchmark: bench_node (time to a useful map on the live 5 Hz stream)
# on today's room (configs/demo-sim.yaml), on the flat
# (tests/bench/node-flat.yaml), on the building
# (tests/bench/node-building.yaml: its first walk through three flats,
# scored at its end and for forgetting; docs/sim.md, bench_node.c), and on
# the room with a chair moved at 30 s ("change": bench_node's
# change_visible_s, 60 s unless VLFF_BENCH_SECONDS says). RESULT: the
# room's keys as bench_node prints them, then the flat's with a _flat
# suffix, the building's with a bldg_ prefix, then change_visible_s.
# Env: VLFF_BUILD (release build dir), VLFF_BENCH_SECONDS (passed on),
# VLFF_NODE_SCENES (default "room flat bldg change").
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${VLFF_BUILD:-$here/../../build/release}
exe=$build/bench/bench_node
[[ -x $exe ]] || { echo "node.sh: $exe not built" >&2; exit 1; }
res="RESULT"
for sc in ${VLFF_NODE_SCENES:-room flat bldg change}; do
  echo "--- $sc"
  case $sc in
    room) log=$("$exe" | tee /dev/stderr) ;;
    flat) log=$(VLFF_BENCH_CONFIG=$here/node-flat.yaml "$exe" | tee /dev/stderr) ;;
    bldg) log=$(VLFF_BENCH_CONFIG=$here/node-building.yaml "$exe" | tee /dev/stderr) ;;
    change) log=$(VLFF_BENCH_CHANGE=1 VLFF_BENCH_SECONDS=${VLFF_BENCH_SECONDS:-60} "$exe" | tee /dev/stderr) ;;
    *) echo "node.sh: unknown scene '$sc'" >&2; exit 1 ;;
  esac
  kv=$(grep '^RESULT ' <<<"$log" | sed 's/^RESULT //' | tr '\n' ' ')
  if [[ $sc == room ]]; then res="$res $kv"
  elif [[ $sc == bldg ]]; then for p in $kv; do res="$res bldg_$p"; done
  elif [[ $sc == change ]]; then res="$res $(grep -o 'change_visible_s=[^ ]*' <<<"$kv" || true)"
  else for p in $kv; do res="$res ${p%%=*}_$sc=${p#*=}"; done; fi
done
echo "$res"
