#!/usr/bin/env bash
# DDS bridge benchmark (scripts/bench dds), in two network namespaces joined
# by a veth pair (tests/dds/netns_kit.sh; root needed): bench_dds publishes a
# 64x64x32 map at 1 Hz (a few small regions relabelled per version, a
# 160x120 label image) and 640x480 RGB frames at 2 Hz; vlff-dds in namespace
# A serves them; bench_dds subscribe in B (Cyclone's C API and the IDL only)
# takes the map, the label and camera images, camera info and tf. Measured
# over the run:
#  - dds_change_latency_p99_ms: a map version's publish into the segment
#    (its header stamp) to the remote subscriber's receipt, p99 (target <= 100);
#  - dds_bytes_per_s_per_robot: bytes A sent over the link per second (every
#    topic, discovery and DDS's own traffic), and dds_map_bytes_per_s the map
#    topics' payload alone (map/updates and the whole maps sent during the
#    run; not the histories a joining reader gets, nor the first whole map), against the baseline of
#    the map's changed bytes per second (voxels whose label, or a labelled
#    voxel's confidence, changed x 20 B, a PointCloud2 point):
#    dds_map_vs_changed as measured, and dds_map_vs_changed_amortized with
#    the whole map resent every dds.map_full_period_s (the run may be
#    shorter than that period) in place of the whole maps measured (target
#    <= 2);
#  - dds_bridge_cpu_frac: the bridge's CPU time over the run as a fraction of
#    one core (target <= 0.05);
#  - merge_miou3d and single_miou3d: tests/dds/test_dds_fleet.sh's scenario,
#    run after the above in the same run: three robots on three parts of the
#    simulated flat merged by vlff-merge, against one robot that walked it
#    all, each with the same node.cpu_budget and the same number of training
#    iterations (VLFF_FLEET_ITERS, default the test's); 3D mIoU against the
#    simulator's ground truth (target merge >= single - 2).
# Last line: RESULT ...
set -uo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
build=${VLFF_BUILD:-$root/build/release}
secs=${VLFF_DDS_BENCH_SECONDS:-30}
[[ -x $build/bench/bench_dds && -x $build/node/dds/vlff-dds ]] || { echo "bench dds: vlff-dds not built"; exit 1; }
[[ $(id -u) == 0 ]] || { echo "bench dds: needs root for ip netns"; exit 1; }
source "$root/tests/dds/netns_kit.sh"
echo "host load: $(cut -d' ' -f1-3 /proc/loadavg) on $(nproc) cores"
domain=$((($$ % 200) + 1)) ns=/bench
printf 'shm:\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\ndds:\n  domain_id: %d\n  namespace: %s\n  image_hz: 2\n' \
  $p $p $p $domain $ns >"$tmp/d.yaml"
period=$("$build/node/dds/vlff-dds" --check-config "$tmp/d.yaml" | awk '$1 == "dds.map_full_period_s:" { print $2 }')
"$build/bench/bench_dds" publish $p-m $p-r $((secs + 8)) >"$tmp/pub" 2>&1 &
pub=$!
pids+=($pub)
"${in_a[@]}" "$build/node/dds/vlff-dds" --config "$tmp/d.yaml" 2>"$tmp/dds.log" &
bridge=$!
pids+=($bridge)
"${in_b[@]}" "$build/bench/bench_dds" subscribe $domain $ns $((secs + 2)) >"$tmp/sub" 2>&1 &
sub=$!
pids+=($sub)
sleep 2   # discovery, and the subscriber takes the whole map from the history
txb() { ip -n "$nsa" -s -j link show "$va" | python3 -c 'import json,sys; print(json.load(sys.stdin)[0]["stats64"]["tx"]["bytes"])'; }
ticks() { awk '{print $14 + $15}' "/proc/$bridge/stat"; }
[[ $(cat /proc/$bridge/comm 2>/dev/null) == vlff-dds ]] || { echo "bench dds: pid $bridge is not the bridge"; exit 1; }
b0=$(txb) c0=$(ticks)
sleep "$secs"
b1=$(txb) c1=$(ticks)
wait $sub
wait $pub
kill -TERM $bridge; wait $bridge 2>/dev/null
hz=$(getconf CLK_TCK)
python3 - "$tmp" "$b0" "$b1" "$c0" "$c1" "$hz" "$secs" "$period" <<'PY'
import sys
tmp, b0, b1, c0, c1, hz, secs = sys.argv[1], *map(int, sys.argv[2:7]), float(sys.argv[7])
period = float(sys.argv[8])
def kv(f):
    return {k: float(v) for k, v in (l.split() for l in open(f"{tmp}/{f}") if len(l.split()) == 2)}
s, p = kv("sub"), kv("pub")
if "latency_p99_ms" not in s:
    sys.exit(f"bench dds: the subscriber measured no map latency: {s}")
versions = p["versions"]
changed = p["changed_voxels"] * 20 / (versions - 1) if versions > 1 else float("nan")  # B per version = per s (1 Hz)
link = (b1 - b0) / secs
sub_secs = secs + 2  # the subscriber's run
map_per_s = (s["map_bytes"] + s["update_bytes"]) / sub_secs
amortized = s["update_bytes"] / sub_secs + s["last_full_bytes"] / period
cpu = (c1 - c0) / hz / secs
print(f"{int(s['maps'])} whole maps and {int(s['updates'])} updates received (whole maps resent every {period:g} s "
      f"while the map changes, {s['last_full_bytes']:.0f} B each), latency p50 {s['latency_p50_ms']:.1f} ms p99 {s['latency_p99_ms']:.1f} ms "
      f"max {s['latency_max_ms']:.1f} ms; link {link:.0f} B/s; map topics {map_per_s:.0f} B/s ({amortized:.0f} B/s "
      f"amortized) against {changed:.0f} B/s of changed voxels; {int(s['label_images'])} label images, "
      f"{int(s['camera_images'])} camera images, {int(s['camera_infos'])} camera infos, {int(s['tfs'])} tf; "
      f"bridge cpu {cpu:.4f} of a core")
lat_ok = "yes" if s["latency_p99_ms"] <= 100 else "no"
bytes_ok = "yes" if max(map_per_s, amortized) <= 2 * changed else "no"
cpu_ok = "yes" if cpu <= 0.05 else "no"
open(f"{tmp}/result", "w").write(f"RESULT dds_change_latency_p99_ms={s['latency_p99_ms']:.1f} latency_target_met={lat_ok} "
      f"dds_bytes_per_s_per_robot={link:.0f} dds_map_bytes_per_s={map_per_s:.0f} "
      f"dds_changed_bytes_per_s={changed:.0f} dds_map_vs_changed={map_per_s / changed:.2f} "
      f"dds_map_vs_changed_amortized={amortized / changed:.2f} "
      f"bytes_target_met={bytes_ok} dds_bridge_cpu_frac={cpu:.4f} cpu_target_met={cpu_ok}")
PY
[[ -s $tmp/result ]] || exit 1
# The fleet: the same scenario as test_dds_fleet, its figures kept.
t=$build/tests/dds
VLFF_FLEET_RESULT=$tmp/fleet.result "$root/tests/dds/test_dds_fleet.sh" "$build/node/vlff-node" "$build/shm/vlff-shm" "$build/node/sim/vlff-sim" \
  "$build/node/dds/vlff-dds" \
  "$build/node/dds/vlff-merge" "$t/map_score" "$t/map_writer" >"$tmp/fleet.log" 2>&1
fleet_rc=$?
grep -E "miou3d|passed|FAIL" "$tmp/fleet.log"
read -r merge_kv single_kv < <(cat "$tmp/fleet.result" 2>/dev/null || echo "merge_miou3d=nan single_miou3d=nan")
fleet_ok=no
[[ $fleet_rc == 0 ]] && awk -v a="${merge_kv#*=}" -v b="${single_kv#*=}" 'BEGIN { exit !(a >= b - 2) }' && fleet_ok=yes
echo "$(cat "$tmp/result") $merge_kv $single_kv fleet_target_met=$fleet_ok"
