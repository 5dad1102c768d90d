#!/usr/bin/env bash
# vlff-merge on a real network stack (netns_kit.sh): in namespace A two
# robots, each a map segment of known content (map_writer) served by its own
# vlff-dds (/r1, /r2), robot 1's with a far map beyond its grid (which its
# bridge sends with the whole map), changed by a partial publish after 2 s (so the fleet
# is right only if vlff-merge applies the robots' map/updates); in B
# vlff-merge (dds.merge) with robot 2 moved by 1 m in x and turned 90
# degrees, so that the two maps overlap: robot 2's transform is not
# configured but published by its localisation (dds_probe tf: world -> map
# on /r2/tf_static), robot 1's is configured (the identity) and wins over
# the different one it publishes. The fleet segment must hold, in every
# voxel, the text with the most evidence among the robot voxels falling in
# it, with its confidence, and nothing elsewhere (map_writer check, reading
# the robots' segments); a third robot sending a malformed cloud and prompt
# list (dds_probe badmap) is refused, counted and logged and changes
# nothing; bad --robot, --bounds and --map are refused naming them.
# Needs root for ip netns: exits 77 (skipped) without it.
# Usage: test_dds_merge.sh DDS MERGE MAP_WRITER PROBE
set -u
dds=$1 merge=$2 writer=$3 probe=$4
source "$(dirname "$0")/netns_kit.sh"
check "a bad --robot transform is a usage error naming it" \
  '! "$merge" -r /a -r /b@1,2 -m $p-x -b 0,0,0,1,1,1 2>"$tmp/e1" && grep -q "expected NS@X,Y,Z,YAW" "$tmp/e1"'
check "a bad robot namespace is refused by the namespace rule" \
  '! "$merge" -r /a -r b -m $p-x -b 0,0,0,1,1,1 2>"$tmp/e2" && grep -q "a leading" "$tmp/e2"'
check "bounds too large for a map are refused" \
  '! "$merge" -r /a -r /b -m $p-x -b 0,0,0,1000,1000,100 --voxel 0.01 2>"$tmp/e3" && grep -q "more than" "$tmp/e3"'
printf 'shm:\n  map: %s-node\n  ring: %s-ring\n' $p $p >"$tmp/n.yaml"
check "--map naming the node's map segment (shm.map) is refused, not replaced" \
  '! "$merge" -c "$tmp/n.yaml" -r /a -r /b -m $p-node -b 0,0,0,1,1,1 --seconds 1 2>"$tmp/e4" && grep -q "distinct from shm.map" "$tmp/e4" && [[ ! -e /dev/shm$p-node ]]'
check "--map naming the node's frame ring (shm.ring) is refused, not replaced" \
  '! "$merge" -c "$tmp/n.yaml" -r /a -r /b -m $p-ring -b 0,0,0,1,1,1 --seconds 1 2>"$tmp/e6" && grep -q "distinct from shm.ring" "$tmp/e6" && [[ ! -e /dev/shm$p-ring ]]'
check "an empty --map is refused with the name quoted" \
  '! "$merge" -r /a -r /b -m "" -b 0,0,0,1,1,1 --seconds 1 2>"$tmp/e5" && grep -q "map segment '"''"':" "$tmp/e5"'

check "a bad Cyclone config fails before the fleet's segment is created, naming DDS" \
  '! CYCLONEDDS_URI="<CycloneDDS><Domain><General><NoSuchSetting/></General></Domain></CycloneDDS>" "$merge" -r /a -r /b -m $p-badcfg -b 0,0,0,1,1,1 --seconds 1 2>"$tmp/e7" && grep -q "DDS participant" "$tmp/e7" && [[ ! -e /dev/shm$p-badcfg ]]'
check "a bad --frame-id is a usage error naming it" \
  '! "$merge" -r /a -r /b -m $p-x -b 0,0,0,1,1,1 --frame-id /world 2>"$tmp/e8" && grep -q "frame-id" "$tmp/e8"'

domain=$((($$ % 200) + 1))
printf 'dds:\n  domain_id: %d\n  status: false\n  prompts_in: false\n  label_image: false\n  camera_image: false\n  camera_info: false\n  tf: false\n' $domain >"$tmp/d.yaml"
# The fleet from the config (the bridges ignore dds.merge).
cp "$tmp/d.yaml" "$tmp/f.yaml"
printf '  merge:\n    robots:\n      - {namespace: /r1, transform: [0, 0, 0, 0]}\n      - namespace: /r2\n      - namespace: /r3\n      - namespace: /r4\n    map: %s-fleet\n    bounds: [-3, -3, -1, 3, 3, 2]\n' $p >>"$tmp/f.yaml"
"$writer" write $p-m1 1 60 >"$tmp/w1" & w1=$!
"$writer" write $p-m2 2 60 >"$tmp/w2" & w2=$!
pids+=($w1 $w2)
"${in_a[@]}" "$dds" -c "$tmp/d.yaml" -n /r1 -m $p-m1 2>"$tmp/b1.log" & b1=$!
"${in_a[@]}" "$dds" -c "$tmp/d.yaml" -n /r2 -m $p-m2 2>"$tmp/b2.log" & b2=$!
"${in_a[@]}" "$probe" badmap $domain /r3 - - 60 >"$tmp/bad" 2>&1 & bad=$!
# the robots' localisation: robot 2's transform as published; robot 1's published one is not its configured one
"${in_a[@]}" "$probe" tf $domain /r2 1.0,0,0,90 world:map 60 >"$tmp/tf2" 2>&1 & tf2=$!
"${in_a[@]}" "$probe" tf $domain /r1 5,5,0,45 world:map 60 >"$tmp/tf1" 2>&1 & tf1=$!
pids+=($tf1 $tf2)
# a fourth robot with 32 texts of its own: 4 do not fit beside the others' 4
"${in_a[@]}" "$probe" texts $domain /r4 - - 60 >"$tmp/texts" 2>&1 & r4=$!
pids+=($r4)
"${in_b[@]}" "$merge" -c "$tmp/f.yaml" -v 2>"$tmp/merge.log" & mg=$!
pids+=($b1 $b2 $mg $bad)
# after 2 s each robot's map changes: the bridges send updates (not the whole
# map), which vlff-merge applies
wait_until 100 'grep -q changed "$tmp/w1" && grep -q changed "$tmp/w2"'
wait_until 300 '"$writer" check $p-fleet $p-m1@0,0,0,0 $p-m2@1.0,0,0,90 >"$tmp/check" 2>&1'
check "the fleet map holds the text with the most evidence in each voxel, the robots' updates applied, robot 2 placed by its tf ($(tail -1 "$tmp/check"))" \
  '"$writer" check $p-fleet $p-m1@0,0,0,0 $p-m2@1.0,0,0,90 >"$tmp/check" 2>&1'
check "the fleet's labels are the union of the robots' texts, 32 at most (wall floor chair table, thing 0..27)" 'grep -q ", 32 labels$" "$tmp/check"'
check "robot 1's far map beyond its grid (256 floor, 1536 wall voxels) reached the fleet through its bridge's map" \
  'grep -q "1792 robot voxels from far maps), 0 mismatches" "$tmp/check"'
check "the texts left out are logged, naming the robot and the texts" \
  'grep -q "/r4: 4 of its 32 prompt texts left out of the fleet.s labels (at most 32 in all), with the points labelled with them: .thing 28., .thing 29., .thing 30., .thing 31.$" "$tmp/merge.log"'
check "the check fails against another transform (robot 2 not turned), or it proves nothing" \
  '! "$writer" check $p-fleet $p-m1@0,0,0,0 $p-m2@1.0,0,0,0 >"$tmp/check-wrong" 2>&1'
check "robot 2's transform came from its tf_static (world -> map), logged" \
  'grep -q "/r2: map -> world from its tf: world -> map, t (1.000 0.000 0.000)" "$tmp/merge.log"'
check "robot 1's configured transform won: its tf was not read" '! grep -q "/r1: map -> world from its tf" "$tmp/merge.log"'
check "the malformed robot's cloud and list were refused and logged" \
  'wait_until 50 "grep -q \"/r3: map refused: 1000 points\" \"$tmp/merge.log\"" && grep -q "/r3: prompt list refused: not JSON" "$tmp/merge.log"'
kill -TERM $mg; wait $mg; rc=$?
check "vlff-merge exits 0 on SIGTERM (rc=$rc)" '[[ $rc == 0 ]]'
check "and counts the refused messages and the texts left out" 'grep -Eq "merges, 2 robot messages refused, [1-9][0-9]* times robots. texts left out" "$tmp/merge.log"'
kill -TERM $b1 $b2 $w1 $w2 $bad $tf1 $tf2 $r4 2>/dev/null
wait $b1 $b2 $w1 $w2 $bad $tf1 $tf2 $r4
cat "$tmp/check"
echo "$passes passed, $fails failed"
if (( fails )); then
  for f in check merge.log b1.log; do echo "--- $f"; tail -20 "$tmp/$f"; done
fi
(( fails == 0 ))
