#!/usr/bin/env bash
# vlff-dds follows the map (netns_kit.sh: namespaces A and B joined by a veth
# pair): in A a map segment changed by many partial publishes (map_writer
# churn: a 3x3x2 box relabelled per version, free and unknown included, the
# prompt list grown halfway) and vlff-dds; in B dds_probe follow (Cyclone's
# C API and the IDL only), once from the start and once as a late joiner
# after the last version. Each must hold exactly the segment's last map,
# built from a whole map and the updates stamped after it, its last update
# numbered with the segment's version; every whole map sent meanwhile must
# equal what the updates built, and the same replay without the last update
# must differ. The bridge sends updates per version and the whole map only
# for its reasons (the first, new prompts, the updates' history full, the
# period while the map changes), never while nothing changes.
# Needs root for ip netns: exits 77 (skipped) without it.
# Usage: test_dds_updates.sh DDS MAP_WRITER PROBE
set -u
dds=$1 writer=$2 probe=$3
source "$(dirname "$0")/netns_kit.sh"

domain=$((($$ % 200) + 1)) ns=/u$$ versions=150
# depth 30: the whole map goes out again before a late joiner would miss an update
printf 'dds:\n  domain_id: %d\n  namespace: %s\n  poll_hz: 50\n  map_full_period_s: 2\n  status: false\n  prompts_in: false\n  label_image: false\n  camera_image: false\n  camera_info: false\n  tf: false\n  qos:\n    map_updates:\n      depth: 30\n' \
  $domain $ns >"$tmp/d.yaml"
check "--check-config names the updates topic" \
  '"$dds" --check-config "$tmp/d.yaml" | grep -q "^map_updates: rt$ns/vlff/map/updates <- .* (reliable, transient_local, keep last 30)$"'
"$writer" churn $p-m $versions 20 40 >"$tmp/writer" 2>&1 & w=$!
pids+=($w)
"${in_a[@]}" "$dds" -c "$tmp/d.yaml" -m $p-m -v 2>"$tmp/dds.log" & b=$!
pids+=($b)
final=$((versions + 1))
"${in_b[@]}" "$probe" follow $domain $ns $p-m $final 40 >"$tmp/early" 2>&1 & e=$!
pids+=($e)
wait_until 300 'grep -q "^final" "$tmp/writer"'
check "the writer published $final versions" 'grep -qx "final $final" "$tmp/writer"'
"${in_b[@]}" "$probe" follow $domain $ns $p-m $final 20 >"$tmp/late" 2>&1; rc=$?
check "a late joiner holds the segment's map: the whole map and the updates after it (rc=$rc)" '[[ $rc == 0 ]]'
wait $e; rc=$?
check "a subscriber from the start holds the segment's map, whole maps equal to its updates (rc=$rc)" '[[ $rc == 0 ]]'
wholes() { grep -c "(whole: " "$tmp/dds.log"; }
updates=$(grep -c ": update of " "$tmp/dds.log")
check "an update per version ($updates of $versions)" '(( updates >= versions * 2 / 3 ))'
check "whole maps for their reasons only ($(wholes))" '(( $(wholes) >= 3 && $(wholes) <= versions / 10 ))'
check "the first whole map, then one for the new prompts and one when the updates' history filled" \
  'grep -q "(whole: a whole copy of the segment)" "$tmp/dds.log" && grep -q "(whole: new prompts)" "$tmp/dds.log" &&
   grep -q "(whole: the updates. history is full)" "$tmp/dds.log"'
sleep 2.5  # past dds.map_full_period_s since the last change
n=$(wholes)
sleep 3
check "no whole map resent while nothing changes ($n, then $(wholes))" '[[ $(wholes) == "$n" ]]'
kill -TERM $b; wait $b; rc=$?
check "vlff-dds exits 0 on SIGTERM (rc=$rc)" '[[ $rc == 0 ]]'
kill -TERM $w; wait $w

# dds.history_max_mb: a 4000-voxel map without a far map (81 KB a whole map) and the prompt
# list leave 30 updates 8 points each; the churn's updates change 18 voxels,
# so every version goes as a whole map, none as an update.
printf 'dds:\n  domain_id: %d\n  namespace: %ss\n  poll_hz: 50\n  status: false\n  prompts_in: false\n  label_image: false\n  camera_image: false\n  camera_info: false\n  tf: false\n  history_max_mb: 0.1247\n  qos:\n    map_updates:\n      depth: 30\nshm:\n  map_max_voxels: 4000\n  map_far_max_mb: 0\n' \
  $domain $ns >"$tmp/s.yaml"
check "--check-config gives map updates their share" \
  '"$dds" --check-config "$tmp/s.yaml" | grep -qx "dds.history_max_mb: 0.1247 (map updates of up to 8 points)"'
"$writer" churn $p-s 12 20 20 >"$tmp/swriter" 2>&1 & w=$!
pids+=($w)
"${in_a[@]}" "$dds" -c "$tmp/s.yaml" -m $p-s -v 2>"$tmp/sdds.log" & b=$!
pids+=($b)
wait_until 300 'grep -q "map version 13: .*(whole: " "$tmp/sdds.log"'
check "updates over their share of dds.history_max_mb go as whole maps, to the last version" \
  'grep -q "map version 13: .*(whole: an update larger than its share of dds.history_max_mb)" "$tmp/sdds.log"'
check "no update sent over its share" '! grep -q ": update of " "$tmp/sdds.log"'
kill -TERM $b $w; wait $b $w
for f in early late; do grep -v "^probe ok" "$tmp/$f"; done
echo "$passes passed, $fails failed"
if (( fails )); then
  for f in writer dds.log swriter sdds.log; do echo "--- $f"; grep -v ": update of " "$tmp/$f" | tail -20; done
fi
(( fails == 0 ))
