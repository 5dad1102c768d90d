#!/usr/bin/env bash
# A fleet on a real network stack: three robots, each a network namespace
# with vlff-node on the simulated flat (docs/sim.md) walking one third of the
# walk (sim.range_first/range_count) and its vlff-dds, and vlff-merge in a
# fourth, all four joined by veth pairs to a bridge (Cyclone's multicast
# discovery across it). At the same time one robot walks the whole flat
# alone. Each node has the same node.cpu_budget and runs until it has made
# the same number of training iterations (its status in its map segment),
# then is stopped (its last map stays in its segment, and its bridge keeps
# serving it): the same compute per robot, whatever the load on the test's
# machine, and the same load on each (they run together).
# The fleet segment must label what the robots' last maps label, each voxel
# with a text one of them gave there (map_writer check-any: the votes are
# also weighed by the robots' camera paths, which the segments do not keep), and its 3D mIoU against the simulator's ground truth
# (map_score) must be near the single robot's (5 points; the issue's
# target, 2, is scripts/bench dds's) and well above each fleet robot's own.
# Needs root for ip netns: exits 77 (skipped) without it.
# Usage: test_dds_fleet.sh NODE SHM SIM DDS MERGE MAP_SCORE MAP_WRITER
# Environment (scripts/bench dds): VLFF_FLEET_ITERS (iterations per robot),
# VLFF_FLEET_RESULT (a file that gets "merge_miou3d=M single_miou3d=S").
set -u
node=$1 shm=$2 sim=$3 dds=$4 merge=$5 score=$6 writer=$7
source "$(dirname "$0")/netns_kit.sh"
iters=${VLFF_FLEET_ITERS:-100}
budget=0.5
domain=$((($$ % 200) + 1))
# The kit's A is robot 1, its B the fleet; robots 2 and 3 are two more
# namespaces. B holds the bridge: the kit's veth end in B is its first port.
nsc=vlffdds-c-$$ nsd=vlffdds-d-$$
vc=vddc$$ vd=vddd$$ br=vddbr$$
cleanup_fleet() { cleanup; ip netns del "$nsc" 2>/dev/null; ip netns del "$nsd" 2>/dev/null; }
trap cleanup_fleet EXIT
ip netns add "$nsc" && ip netns add "$nsd" || { echo "FAIL: network namespaces"; exit 1; }
ip -n "$nsb" link add "$br" type bridge mcast_snooping 0 || { echo "FAIL: bridge"; exit 1; }
ip -n "$nsb" addr flush dev "$vb"
ip -n "$nsb" link set "$vb" master "$br"
ip -n "$nsb" addr add 10.213.0.2/24 dev "$br"
ip -n "$nsb" link set "$br" up
k=3
for pair in "$nsc:$vc" "$nsd:$vd"; do
  n=${pair%%:*} v=${pair##*:}
  ip link add "$v" netns "$n" type veth peer name "${v}p" netns "$nsb" || { echo "FAIL: veth $v"; exit 1; }
  ip -n "$nsb" link set "${v}p" master "$br"
  ip -n "$nsb" link set "${v}p" up
  ip -n "$n" addr add 10.213.0.$k/24 dev "$v"
  ip -n "$n" link set lo up
  ip -n "$n" link set "$v" up
  k=$((k + 1))
done
ub=$(uri "$br")
in_b=(ip netns exec "$nsb" env CYCLONEDDS_URI="$ub")
in_c=(ip netns exec "$nsc" env CYCLONEDDS_URI="$(uri "$vc")")
in_d=(ip netns exec "$nsd" env CYCLONEDDS_URI="$(uri "$vd")")

# The flat at a small scale: 60 frames of 320x240 at 10 Hz, D = 64, one
# thread; each fleet robot walks 20 consecutive frames of it. Not 160x120:
# there the bathroom's toilet, sink and bathtub are a few feature pixels
# each, and which of them a voxel took depended on the frames a run
# admitted: one robot alone scored 52 to 62 from run to run on a quiet
# machine, so the comparison below failed by chance. At 320x240 the same
# robot scored within a point of 65 in every run measured.
robot_yaml() { # NAME RANGE_FIRST RANGE_COUNT
  printf 'node:\n  state_dir: %s/%s\n  threads: 1\n  cpu_budget: %s\nsource:\n  kind: sim\n  features: sim\n' "$tmp" "$1" $budget
  printf 'sim:\n  layout: flat\n  seed: 4\n  frames: 60\n  rate_hz: 10\n  width: 320\n  height: 240\n  range_first: %d\n  range_count: %d\n' "$2" "$3"
  printf 'field:\n  feature_dim: 64\n  scene_min: [-5, -4, -1.5]\n  scene_max: [5, 4, 1.5]\nkeyframes:\n  start_after: 2\n'
  printf 'publish:\n  rate_hz: 2\n  voxel_size_m: 0.1\n'
  printf 'shm:\n  ring: %s-%s-r\n  map: %s-%s-m\n  prompts: %s-%s-p\n  feature_ring: %s-%s-f\n  pose_ring: %s-%s-q\n' $p $1 $p $1 $p $1 $p $1 $p $1
  printf 'dds:\n  domain_id: %d\n  namespace: /%s\n  status: false\n  prompts_in: false\n  label_image: false\n  camera_image: false\n  camera_info: false\n' $domain "$1"
}
robot_yaml f1 0 20 >"$tmp/f1.yaml"
check "vlff-sim --range beyond sim.frames is a usage error naming it" \
  '! "$sim" --config "$tmp/f1.yaml" --range 50..60 --count 1 2>"$tmp/e1" && grep -q "range: expected A..B with 0 <= A <= B < sim.frames (60)" "$tmp/e1"'
robot_yaml f2 20 20 >"$tmp/f2.yaml"
robot_yaml f3 40 20 >"$tmp/f3.yaml"
robot_yaml one 0 0 >"$tmp/one.yaml"
# The fleet: the robots' maps share the simulator's world frame (configured
# identity). Recency is left out here (a half-life of months): the check
# below recomputes the merge from the robots' segments, which keep no times.
cp "$tmp/f1.yaml" "$tmp/m.yaml"
printf '  merge:\n    robots:\n      - {namespace: /f1, transform: [0, 0, 0, 0]}\n      - {namespace: /f2, transform: [0, 0, 0, 0]}\n      - {namespace: /f3, transform: [0, 0, 0, 0]}\n    map: %s-fleet\n    bounds: [-5, -4, -1.5, 5, 4, 1.5]\n    voxel_size_m: 0.1\n    half_life_s: 1e7\n' $p >>"$tmp/m.yaml"

iterations() { "$shm" stat "$1" 2>/dev/null | awk '$1 == "iterations" { print $2 }'; }
# Runs nodes (NAME:NS-PREFIX-ARRAY ...) until each has made $iters
# iterations; each is stopped (SIGTERM) as it gets there. 0 when all did.
run_until_iters() {
  local -A pid=() spid=()
  local name left stopping=()
  for name in "$@"; do
    local -n pre=in_$(case $name in f1|one) echo a;; f2) echo c;; f3) echo d;; esac)
    "${pre[@]}" "$node" --config "$tmp/$name.yaml" 2>"$tmp/$name.log" &
    pid[$name]=$!
    "$sim" --config "$tmp/$name.yaml" --no-features --quiet 2>"$tmp/sim-$name.log" &
    spid[$name]=$!
    pids+=(${pid[$name]} ${spid[$name]})
  done
  # generous: the slowest of them on a loaded machine
  for ((t = 0; t < 2400; t++)); do
    left=0
    for name in "${!pid[@]}"; do
      [[ -z ${pid[$name]} ]] && continue
      if [[ $(iterations $p-$name-m) -ge $iters ]] 2>/dev/null; then
        # Not waited for here: the others would train on while this one
        # writes its checkpoint, and the last stopped would have learned most.
        kill -TERM "${pid[$name]}" "${spid[$name]}"; stopping+=(${pid[$name]} ${spid[$name]}); pid[$name]=
        echo "$name: $iters iterations, stopped"
      elif ! kill -0 "${pid[$name]}" 2>/dev/null; then
        echo "FAIL: node $name ended before $iters iterations: $(tail -3 "$tmp/$name.log")"
        return 1
      else
        left=$((left + 1))
      fi
    done
    ((left == 0)) && { wait "${stopping[@]}"; return 0; }
    sleep 0.1
  done
  echo "FAIL: nodes did not reach $iters iterations: $(for name in "$@"; do echo -n "$name $(iterations $p-$name-m) "; done)"
  return 1
}

bridges=()
"${in_b[@]}" "$merge" -c "$tmp/m.yaml" 2>"$tmp/merge.log" & mg=$!
pids+=($mg)
for r in f1 f2 f3; do
  case $r in f1) pre=("${in_a[@]}");; f2) pre=("${in_c[@]}");; f3) pre=("${in_d[@]}");; esac
  "${pre[@]}" "$dds" -c "$tmp/$r.yaml" 2>"$tmp/b-$r.log" & bridges+=($!)
done
pids+=("${bridges[@]}")
# The single robot learns at the same time as the fleet's: the same machine's
# load on all four, so that none has more wall time (frames, publishes) per
# iteration than another.
check "the three fleet robots and the single robot each made $iters iterations" 'run_until_iters f1 f2 f3 one'
# The fleet map follows: it equals the merge of the robots' last maps.
wait_until 600 '"$writer" check-any $p-fleet $p-f1-m@0,0,0,0 $p-f2-m@0,0,0,0 $p-f3-m@0,0,0,0 >"$tmp/check" 2>&1'
check "the fleet segment labels the voxels the three robots' last maps label, each with a text one of them gave ($(tail -1 "$tmp/check"))" \
  '"$writer" check-any $p-fleet $p-f1-m@0,0,0,0 $p-f2-m@0,0,0,0 $p-f3-m@0,0,0,0 >"$tmp/check" 2>&1'
"$score" "$tmp/one.yaml" $p-fleet $p-one-m $p-f1-m $p-f2-m $p-f3-m >"$tmp/score" 2>&1
cat "$tmp/score"
fleet=$(awk -v m=$p-fleet '$1 == m { print $3 }' "$tmp/score")
one=$(awk -v m=$p-one-m '$1 == m { print $3 }' "$tmp/score")
check "both maps scored (fleet $fleet, one robot $one)" '[[ -n $fleet && -n $one ]] && awk -v a="$fleet" -v b="$one" "BEGIN { exit !(a > 0 && b > 0) }"'
# The issue's target is the fleet within 2 points of one robot
# (scripts/bench dds reports it). The runs measured put the fleet 0.6 below
# to 2.5 above the single robot, with the machine idle or its two cores
# oversubscribed twice (docs/dds.md), so the test holds the fleet to 3: a
# merge that kept one robot's map, or counted every robot's glimpses as its
# walk, is 5 to 15 below.
check "the fleet's 3D mIoU $fleet is within 3 points of one robot's $one" 'awk -v a="$fleet" -v b="$one" "BEGIN { exit !(a >= b - 3) }"'
for r in f1 f2 f3; do
  m=$(awk -v m=$p-$r-m '$1 == m { print $3 }' "$tmp/score")
  check "robot $r alone, a third of the flat, scores 8 points or more below the fleet ($m, $fleet)" 'awk -v a="$m" -v b="$fleet" "BEGIN { exit !(a + 8 <= b) }"'
done
[[ -n ${VLFF_FLEET_RESULT:-} ]] && echo "merge_miou3d=$fleet single_miou3d=$one" >"$VLFF_FLEET_RESULT"
kill -TERM $mg "${bridges[@]}"; wait $mg; rc=$?
wait "${bridges[@]}"
check "vlff-merge exits 0 on SIGTERM (rc=$rc)" '[[ $rc == 0 ]]'
echo "$passes passed, $fails failed"
if (( fails )); then
  for f in check merge.log f1.log one.log b-f1.log; do echo "--- $f"; tail -20 "$tmp/$f"; done
fi
(( fails == 0 ))
