#!/usr/bin/env bash
# vlff-dds on a real network stack: network namespaces A (vlff-node on the
# simulator, vlff-sim, vlff-dds) and B (dds_probe: Cyclone's C API and the
# IDL only) joined by a veth pair; DDS discovery is Cyclone's own SPDP
# multicast over the veth link. The probe checks the map, the status, the
# prompt list, the label image, the camera image, camera info and tf field
# by field against the map segment and the frame ring (shared memory is not
# network state: both namespaces see /dev/shm), a late joiner gets the whole map
# from the writer's history with no resend, and bad, oversized and
# flooding prompt messages are refused and counted while exactly one good
# set reaches the mailbox. Needs root for ip netns: exits 77 (skipped)
# without it.
# Usage: test_dds_netns.sh NODE SHM SIM DDS PROBE
set -u
node=$1 shm=$2 sim=$3 dds=$4 probe=$5
host=$(hostname) # the status's hardware_id
source "$(dirname "$0")/netns_kit.sh"

domain=$((($$ % 200) + 1)) ns=/t$$
# A small field and scene: a map of labelled voxels within seconds, on one thread.
printf 'node:\n  state_dir: %s\n  threads: 1\nsource:\n  kind: sim\nsim:\n  frames: 20\n  rate_hz: 10\n  width: 160\n  height: 120\nfield:\n  feature_dim: 64\n  hash_log2_size: 14\n  finest_resolution: 256\ntrain:\n  rays_per_step: 256\nkeyframes:\n  start_after: 2\nshm:\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\n  feature_ring: %s-f\n  pose_ring: %s-q\npublish:\n  rate_hz: 2\n  voxel_size_m: 0.1\ndds:\n  domain_id: %d\n  namespace: %s\n  status_hz: 5\n  prompt_rate_hz: 0.2\n' \
  "$tmp" $p $p $p $p $p $domain $ns >"$tmp/n.yaml"
check "vlff-dds --check-config names the topics" \
  '"$dds" --check-config "$tmp/n.yaml" >"$tmp/check" && grep -q "^map: rt$ns/vlff/map <- $p-m (reliable, transient_local, keep last 1)$" "$tmp/check" && grep -qx "dds.domain_id: $domain" "$tmp/check"'
check "--namespace overrides the file, with the file's checks" \
  '"$dds" -c "$tmp/n.yaml" --namespace /other --check-config "$tmp/n.yaml" | grep -q "^status: rt/other/vlff/status <- "'
check "a bad --namespace is a usage error naming it" \
  '! "$dds" -c "$tmp/n.yaml" --namespace robot1 --check-config "$tmp/n.yaml" 2>"$tmp/err" && grep -q "dds.namespace.*a leading ./." "$tmp/err"'

# The compressed images where the build has an encoder (OpenCV).
z=""
printf 'dds:\n  label_image_compressed: true\n  camera_image_compressed: true\n' >"$tmp/z.yaml"
if "$dds" --check-config "$tmp/z.yaml" >/dev/null 2>"$tmp/z.err"; then
  z=compressed
  printf '  label_image_compressed: true\n  camera_image_compressed: true\n' >>"$tmp/n.yaml"
else
  check "a build without an encoder refuses compressed topics, naming the key" 'grep -q "dds.label_image_compressed: this build has no image encoder" "$tmp/z.err"'
fi

"${in_a[@]}" "$node" --config "$tmp/n.yaml" 2>"$tmp/node.log" & nodepid=$!
"${in_a[@]}" "$dds" --config "$tmp/n.yaml" 2>"$tmp/dds.log" & ddspid=$!
pids+=($nodepid $ddspid)
# The probe joins before the map exists and reads its last version once the node is gone.
"${in_b[@]}" "$probe" final $domain $ns $p-m "$host" 60 $p-r $z >"$tmp/final" 2>&1 & probepid=$!
"${in_a[@]}" "$sim" --config "$tmp/n.yaml" --quiet 2>"$tmp/sim.log" & simpid=$!
pids+=($probepid $simpid)
val() { "$shm" stat $p-m 2>/dev/null | awk -v k="$1" '$1 == k { print $2 }'; }
wait_until 300 '[[ $(val version) -ge 3 ]] 2>/dev/null'
check "the node published maps ($(val version))" '[[ $(val version) -ge 3 ]]'
kill "$simpid"; wait "$simpid"; simpid=
kill -TERM "$nodepid"; wait "$nodepid"; rc=$?; nodepid=
check "the node exits 0 (rc=$rc)" '[[ $rc == 0 ]]'
wait "$probepid"; rc=$?
check "across the link the map, status, prompt list, label and camera images, camera info and tf equal the segment's and ring's (rc=$rc)" '[[ $rc == 0 ]]'
sent=$(awk '$1 == "maps_sent" { print $2 }' "$tmp/final")
check "the bridge sent the map at most once per version ($sent <= $(val version))" '[[ -n $sent && $sent -ge 1 && $sent -le $(val version) ]]'

"${in_b[@]}" "$probe" late $domain $ns $p-m "$host" 30 >"$tmp/late" 2>&1; rc=$?
check "a late joiner gets the whole map from the history (rc=$rc)" '[[ $rc == 0 ]]'
check "and the bridge resent nothing for it" '[[ $(awk '"'"'$1 == "maps_sent" { print $2 }'"'"' "$tmp/late") == "$sent" ]]'
# The QoS keys reach the wire: a second bridge whose map is volatile keeps no
# history, so the same late joiner gets its status but no map.
cp "$tmp/n.yaml" "$tmp/v.yaml"
printf '  qos:\n    map:\n      durability: volatile\n' >>"$tmp/v.yaml"
"${in_a[@]}" "$dds" --config "$tmp/v.yaml" --namespace $ns/v -v 2>"$tmp/dds-v.log" & vpid=$!
pids+=($vpid)
wait_until 100 'grep -q "map version" "$tmp/dds-v.log"'   # sent before the joiner is there
"${in_b[@]}" "$probe" late $domain $ns/v $p-m "$host" 4 >"$tmp/late-v" 2>&1; rc=$?
check "with dds.qos.map.durability volatile a late joiner gets no map (rc=$rc)" \
  '[[ $rc != 0 ]] && grep -q "FAIL: no map received" "$tmp/late-v" && ! grep -q "FAIL: no status" "$tmp/late-v"'
kill -TERM $vpid; wait $vpid

posts0=$("$shm" stat $p-p | awk '$1 == "posts" { print $2 }')
"${in_b[@]}" "$probe" prompts $domain $ns $p-m "$host" 30 >"$tmp/prompts" 2>&1; rc=$?
check "bad prompt messages refused and counted by kind (rc=$rc)" '[[ $rc == 0 ]]'
posts1=$("$shm" stat $p-p | awk '$1 == "posts" { print $2 }')
check "exactly the one good set reached the mailbox ($posts0 -> $posts1)" '[[ $((posts1 - posts0)) == 1 ]]'
check "refusals logged, rate-limited" 'grep -q "prompts_in: refused" "$tmp/dds.log" && (( $(grep -c "prompts_in: refused" "$tmp/dds.log") <= 5 ))'

kill -TERM "$ddspid"; wait "$ddspid"; rc=$?; ddspid=
check "vlff-dds exits 0 on SIGTERM (rc=$rc)" '[[ $rc == 0 ]]'
check "and logs its counts" 'grep -q "prompt sets posted" "$tmp/dds.log"'
for f in final late prompts; do grep -v "^probe ok" "$tmp/$f"; done
echo "$passes passed, $fails failed"
if (( fails )); then
  for f in final late prompts dds.log node.log; do echo "--- $f"; tail -20 "$tmp/$f"; done
fi
(( fails == 0 ))
