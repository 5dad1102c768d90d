#!/usr/bin/env bash
# Viewer benchmark (scripts/bench view): bench_view publishes a 64x54x32 map at
# 2 Hz (a few surfaces change per version, with a label image) and 640x480 frames
# at 5 Hz; vlff-view serves them to CLIENTS Foxglove-like clients subscribed to
# every channel. Measured over the run: the viewer's CPU time as a fraction of one
# core (target <= 0.05), against the baseline of a bare controller that snapshots
# every version in the same run; the p99 latency from a version's publish to a
# client's receipt of its delta; bytes per update per client; the camera image's
# bytes per frame against raw RGB (target <= 1/8); the map's Foxglove channel
# (/map/points, foxglove.PointCloud) bytes per update per client over the
# changed voxels' packed size, 20 bytes a point as /map/points packs them
# (view_bytes_per_update_vs_changed, target <= 2: what the change log saves the
# viewer from sending); the page's JSON /map the same way over the changed
# voxels' label and confidence bytes (view_json_bytes_per_update_vs_changed,
# its cubes are for the built-in page, not for Foxglove); and, after the clients left and 3 s
# without a subscriber, the age of a new client's first message on each channel
# (first_message_age_max_s, the oldest; each channel's latest is < its period old;
# /log, whose latest line is as old as its event, is printed but not counted).
# A second vlff-view, without clients, records every channel with --record over the
# same run (its CPU apart from the first's): mcap_ok is 1 when @mcap/core reads the
# file whole with its CRCs, mcap_mb_per_min its size per minute of recorded time.
# Last line: RESULT ...
set -uo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
build=${VLFF_BUILD:-$root/build/release}
secs=${VLFF_VIEW_BENCH_SECONDS:-30}
clients=${VLFF_VIEW_BENCH_CLIENTS:-10}
export NODE_PATH=$root/node/view/node_modules
[[ -x $build/bench/bench_view && -x $build/node/view/vlff-view ]] || { echo "bench view: vlff-view not built"; exit 1; }
[[ -d $NODE_PATH/ws ]] || { echo "bench view: npm packages missing (scripts/setup --test)"; exit 1; }
tag=bv$$
tmp=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null; done; wait 2>/dev/null; rm -rf "$tmp" /dev/shm/$tag-*; }
trap cleanup EXIT
echo "host load: $(cut -d' ' -f1-3 /proc/loadavg) on $(nproc) cores"
"$build/bench/bench_view" publish /$tag-map /$tag-frames $((secs + 16)) >"$tmp/pub" &
pids+=($!)
sleep 1
"$build/node/view/vlff-view" --port 0 --map /$tag-map --frames /$tag-frames --prompts /$tag-prompts \
  >"$tmp/view.out" 2>"$tmp/view.err" &
view=$!
pids+=($view)
for ((i = 0; i < 50; i++)); do grep -q serving "$tmp/view.out" && break; sleep 0.1; done
port=$(sed -n 's/.*127\.0\.0\.1:\([0-9]*\)\/.*/\1/p' "$tmp/view.out" | head -1)
[[ -n "$port" ]] || { echo "bench view: vlff-view did not start"; cat "$tmp/view.err"; exit 1; }
"$build/node/view/vlff-view" --port 0 --map /$tag-map --frames /$tag-frames --prompts /$tag-prompts \
  --record "$tmp/rec.mcap" >"$tmp/rec.out" 2>"$tmp/rec.err" &
rec=$!
pids+=($rec)
node "$root/tests/bench/view_clients.js" "$port" "$clients" $((secs + 3)) >"$tmp/clients" &
cl=$!
pids+=($cl)
sleep 3   # the clients connect and receive the whole map first
ticks() { awk '{print $14 + $15}' "/proc/$view/stat"; }
c0=$(ticks)
r0=$(awk '{print $14 + $15}' "/proc/$rec/stat")
"$build/bench/bench_view" read /$tag-map "$secs" >"$tmp/reader"
c1=$(ticks)
r1=$(awk '{print $14 + $15}' "/proc/$rec/stat")
wait $cl
wait "${pids[0]}"  # the publisher's totals
kill -INT $rec; wait $rec
node "$root/tests/bench/mcap_check.js" "$tmp/rec.mcap" >"$tmp/mcap"
hz=$(getconf CLK_TCK)
python3 - "$tmp" "$c0" "$c1" "$hz" "$secs" "$r0" "$r1" <<'PY'
import json, sys
tmp, c0, c1, hz, secs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
r0, r1 = int(sys.argv[6]), int(sys.argv[7])
mc = json.loads(open(f"{tmp}/mcap").read())
rec_cpu = (r1 - r0) / hz / secs
mb_min = mc["bytes"] / 1e6 / (mc["span_s"] / 60) if mc["span_s"] > 0 else float("nan")
print(f"recording: {mc['bytes']} B, {mc['messages']} messages on {mc['channels']} channels in {mc['chunks']} chunks "
      f"over {mc['span_s']:.1f} s; read by @mcap/core: {'ok' if mc['ok'] else mc['error']}; recorder cpu {rec_cpu:.4f} of a core")
r = dict(zip(*[iter(open(f"{tmp}/reader").read().split())] * 2))
pub = dict(zip(*[iter(open(f"{tmp}/pub").read().split())] * 2))
changed = float(pub.get("changed_bytes_per_version", "nan"))
packed = changed / 3 * 20  # bench_view counts 3 bytes (label, confidence) a changed voxel; a point is 20
c = json.loads(open(f"{tmp}/clients").read())
view = (c1 - c0) / hz / secs
reader = float(r["cpu_s"]) / float(r["wall_s"])
print(f"viewer cpu {view:.4f} of a core, bare snapshot reader {reader:.4f}; {c['versions']} versions to "
      f"{c['clients']} clients ({c['closed']} dropped); latency p50 {c['p50']:.1f} ms p99 {c['p99']:.1f} ms "
      f"max {c['max']:.1f} ms; per update and client {c['bytes_per_update_map']:.0f} B of map, "
      f"{c['bytes_per_update_voxels']:.0f} B of it the voxel channel, {c['bytes_per_update_all']:.0f} B in all "
      f"(images, pose, status too); camera image {c['image_bytes']:.0f} B of {c['image_raw_bytes']:.0f} B raw; "
      f"a late subscriber's first message ages (s): {json.dumps({k: round(v, 3) for k, v in c['first_age'].items()})}")
img = c['image_bytes'] / c['image_raw_bytes']
ok = "yes" if view <= 0.05 else "no"
print(f"RESULT view_cpu_frac_one_core={view:.4f} view_cpu_target=0.05 target_met={ok} "
      f"reader_cpu_frac_one_core={reader:.4f} view_vs_reader={view / reader if reader > 0 else float('nan'):.1f} "
      f"view_update_latency_p99_ms={c['p99']:.1f} view_bytes_per_update={c['bytes_per_update_map']:.0f} "
      f"view_bytes_per_update_voxels={c['bytes_per_update_voxels']:.0f} view_bytes_per_update_all_channels={c['bytes_per_update_all']:.0f} "
      f"view_points_bytes_per_update={c['bytes_per_update_points']:.0f} "
      f"view_bytes_per_update_vs_changed={c['bytes_per_update_points'] / packed if packed > 0 else float('nan'):.2f} "
      f"view_json_bytes_per_update_vs_changed={c['bytes_per_update_map'] / changed if changed > 0 else float('nan'):.2f} "
      f"image_bytes_vs_raw={img:.4f} image_target={1 / 8:.4f} first_message_age_max_s={c['first_age_max']:.3f} "
      f"clients={c['clients'] - c['closed']} mcap_ok={mc['ok']} mcap_mb_per_min={mb_min:.2f} "
      f"mcap_recorder_cpu_frac_one_core={rec_cpu:.4f}")
PY
