#!/usr/bin/env bash
# Beyond the caps (docs/field.md "Beyond the caps", docs/shm.md "The far
# map"): the map's capacity (200000 voxels of 0.1 m: a view's box, not the
# flat's 240000) and the evidence's index (publish.evidence_max_mb 3:
# 196608 voxels) hold less than the simulator's 10 x 8 x 3 m flat. As the camera walks it (a loop per 6 s) the grids slide with
# it instead of refusing to grow (said in the log), and what the map's
# window leaves is published as far blocks beside it: vlff-shm reads class
# labels on walls the window no longer covers, stat shows the far map, and
# the stop line counts the slides and the far map's use.
set -u
node_field=$'field:\n  feature_dim: 64\n  hash_log2_size: 16\n  grow: true\n  scene_min: [-2, -2, -1.5]\n  scene_max: [2, 2, 1.5]'
node_yaml_extra=$'publish:\n  voxel_size_m: 0.1\n  evidence_max_mb: 3'
node_shm_extra='  map_max_voxels: 200000'
. "$(dirname "$0")/node_sh.sh" nsl "$@"
# The simulator's world: the flat in its own box.
sed -e '/^  grow: true$/d' -e 's/^  frames: 20$/  frames: 60\n  layout: flat/' \
  -e 's/^  scene_min: .*$/  scene_min: [-5, -4, -1.5]/' -e 's/^  scene_max: .*$/  scene_max: [5, 4, 1.5]/' \
  "$tmp/n.yaml" >"$tmp/s.yaml"
"$sim" --config "$tmp/s.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 600 'grep -q "slid at shm.map_max_voxels" "$tmp/log"'
check "a growth past the map's capacity slides it: $(grep -m1 -o 'box grown for keyframe.*slid at shm.map_max_voxels' "$tmp/log")" \
  'grep -q "slid at shm.map_max_voxels" "$tmp/log"'
far_blocks() { "$shm" stat "$p-m" 2>/dev/null | awk '$1 == "far_blocks" { print $2 }'; }
wait_until 600 '(( $(far_blocks) > 0 ))'
sleep 8 # a loop of the walk more (60 frames at 10 Hz), then the world stops
kill "$simpid"; wait "$simpid"; simpid=
sleep 2 # the last keyframes published
read -r _ ox oy oz < <("$shm" stat "$p-m" | grep '^grid_origin ')
read -r _ vs < <("$shm" stat "$p-m" | grep '^grid_voxel_size ')
read -r _ dx dy dz < <("$shm" stat "$p-m" | grep '^grid_dims ')
cap=$("$shm" stat "$p-m" | awk '$1 == "max_voxels" { print $2 }')
check "the window stays within shm.map_max_voxels ($dx x $dy x $dz voxels of $vs m, segment $cap)" \
  '(( dx * dy * dz <= 200000 && cap <= 200000 ))'
blocks=$("$shm" stat "$p-m" | awk '$1 == "far_blocks" { print $2 }')
check "vlff-shm stat shows the far map ($("$shm" stat "$p-m" | grep -E '^far_' | tr '\n' ' '))" '(( ${blocks:-0} > 0 ))'
# Class labels on the flat's end walls (x = +-4.9 m), counted where the
# window covers the probe and where it does not: those the far map answers.
probe() {
inside=0 outside=0
for x in -4.85 -4.75 -4.65 4.65 4.75 4.85; do
  for y in -2 -1 0 1 2; do
    for z in -1 0 1; do
      out=$("$shm" label "$p-m" "$x" "$y" "$z" 2>/dev/null)
      [[ $out =~ ^label\ ([0-9]+)\  ]] && (( BASH_REMATCH[1] < 65534 )) || continue
      if awk -v x="$x" -v y="$y" -v z="$z" -v ox="$ox" -v oy="$oy" -v oz="$oz" -v v="$vs" -v dx="$dx" -v dy="$dy" -v dz="$dz" \
        'BEGIN { exit !(x >= ox && x < ox + dx * v && y >= oy && y < oy + dy * v && z >= oz && z < oz + dz * v) }'; then
        inside=$((inside + 1))
      else
        outside=$((outside + 1))
      fi
    done
  done
done
}
probe
check "walls the window left read class labels from the far map ($outside probes beyond the window, $inside within)" \
  '(( outside > 0 ))'
stop_node
line=$(grep "the map slid" "$tmp/log")
check "the stop line counts the slides and the far map ($line)" \
  '[[ $line =~ the\ map\ slid\ ([0-9]+)\ times.*holds\ ([0-9]+)\ blocks ]] && (( BASH_REMATCH[1] > 0 && BASH_REMATCH[2] > 0 ))'
check "no growth refused" 'grep -q "0 growths refused" "$tmp/log"'
# Restarted on its checkpoint: the far map comes back with the first map,
# and the segment, far room and all, is taken over in place (the version
# goes on) rather than replaced.
check "the checkpoint holds the far map and the evidence the window left ($(cd "$tmp" && ls map.*.obs.far map.*.obs.evfar 2>/dev/null | tr '\n' ' '))" \
  'ls "$tmp"/map.*.obs.far >/dev/null 2>&1 && ls "$tmp"/map.*.obs.evfar >/dev/null 2>&1'
version=$("$shm" stat "$p-m" | awk '$1 == "version" { print $2 }')
"$node" --config "$tmp/n.yaml" 2>"$tmp/log2" &
nodepid=$!
wait_until 600 'grep -q "resumed from" "$tmp/log2" && (( $(far_blocks) > 0 )) && (( $("$shm" stat "$p-m" | awk "\$1 == \"version\" { print \$2 }") > version ))'
check "restarted, the segment taken over in place (version $version, now $("$shm" stat "$p-m" | awk '$1 == "version" { print $2 }'))"   '(( $("$shm" stat "$p-m" | awk "\$1 == \"version\" { print \$2 }") > version )) && (( $("$shm" stat "$p-m" | awk "\$1 == \"generation\" { print \$2 }") > 0 ))'
read -r _ ox oy oz < <("$shm" stat "$p-m" | grep '^grid_origin ')
read -r _ dx dy dz < <("$shm" stat "$p-m" | grep '^grid_dims ')
probe
check "restarted, the far map is published again from the checkpoint ($(far_blocks) blocks; $outside probes beyond the window labelled)"   '(( outside > 0 ))'
check "no far map or far evidence refused on the restart" \
  '! grep -q "far map not restored\|window not restored\|window given up" "$tmp/log2"'
stop_node
# Started afresh on the same segment, the camera on again: its first map
# says the far map too, empty, rather than leave the last run's published
# beside a new grid.
version=$("$shm" stat "$p-m" | awk '$1 == "version" { print $2 }')
"$node" --config "$tmp/n.yaml" --fresh 2>"$tmp/log3" &
nodepid=$!
"$sim" --config "$tmp/s.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 600 '(( $("$shm" stat "$p-m" | awk "\$1 == \"version\" { print \$2 }") > version ))'
fresh_blocks=$(far_blocks) # read at once: the new walk slides only once it leaves its first window
kill "$simpid"; wait "$simpid"; simpid=
check "started afresh, the last run's far map is not published (far_blocks $fresh_blocks at its first maps)" \
  '[[ $fresh_blocks == 0 ]] && ! compgen -G "$tmp/map.*.obs.*far" >/dev/null'
stop_node
verdict
