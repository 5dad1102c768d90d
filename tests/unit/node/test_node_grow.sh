#!/usr/bin/env bash
# A box that grows (field.grow; docs/field.md "Growth", docs/shm.md "A map
# that grows"): the node starts in a first box of +-2.5 m while the
# simulator walks a 10 x 8 m flat. The keyframes that see beyond it grow the
# field's, the evidence's and the map's boxes (said in the log, counted in
# the stop line); the map segment keeps its name, grows with the map (a
# larger segment takes the name, vlff_map_reserve) and shows the grown grid,
# labelled beyond the first box; a restarted node resumes in the
# grown box from its checkpoint. The map's capacity holds twice the flat (10 x 8
# x 3 m, 240000 voxels of 0.1 m) but not the flat and the first box's 5 m of
# height, nor the margins growths add: the map is refitted at it (docs/field.md
# "Growth"), nothing refused, and the restarted node takes the refitted grid,
# which does not hold its first box.
set -u
node_field=$'field:\n  feature_dim: 64\n  hash_log2_size: 16\n  grow: true'
node_yaml_extra=$'publish:\n  voxel_size_m: 0.1'
node_shm_extra='  map_max_voxels: 480000'
. "$(dirname "$0")/node_sh.sh" ngr "$@"
# The simulator's world: the flat in its own box (the node's config without
# growth, with the flat's box and layout).
sed -e '/^  grow: true$/d' -e 's/^  frames: 20$/  frames: 40\n  layout: flat/' \
  -e 's/^  hash_log2_size: 16$/  hash_log2_size: 16\n  scene_min: [-5, -4, -1.5]\n  scene_max: [5, 4, 1.5]/' \
  "$tmp/n.yaml" >"$tmp/s.yaml"
"$sim" --config "$tmp/s.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 600 'grep -q "box grown for keyframe" "$tmp/log"'
check "a keyframe that sees beyond the first box grows it: $(grep -m1 -o 'box grown for keyframe.*' "$tmp/log")" \
  'grep -q "box grown for keyframe at" "$tmp/log"'
# The map segment: the grid beyond +-2.5 m on x, on the first box's lattice.
read_map() {
  read -r _ ox oy oz < <("$shm" stat "$p-m" | grep '^grid_origin ')
  read -r _ vs < <("$shm" stat "$p-m" | grep '^grid_voxel_size ')
  read -r _ dx dy dz < <("$shm" stat "$p-m" | grep '^grid_dims ')
}
past_first_box() { awk -v o="$ox" -v d="$dx" -v v="$vs" "BEGIN { exit !(o < -2.6 || o + d * v > 2.6) }"; }
wait_until 600 'read_map && past_first_box'
sleep 3 # a few keyframes more in the grown map (the simulator walks the flat round)
kill "$simpid"; wait "$simpid"; simpid=
sleep 1
read_map
check "the map's grid grew past the first box (origin $ox $oy $oz, $dx x $dy x $dz voxels of $vs m)" past_first_box
check "on the first box's lattice (origin -2.5 + whole voxels)" \
  'awk -v o="$ox" -v v="$vs" "BEGIN { k = (o + 2.5) / v; r = k - int(k + (k < 0 ? -0.5 : 0.5)); exit !(r < 1e-6 && r > -1e-6) }"'
# A labelled voxel beyond the first box: the flat's walls at x = +-4.9 m.
beyond=0
for x in -4.85 -4.75 -4.65 4.65 4.75 4.85; do
  for y in -1 0 1; do
    for z in -1 0 1; do
      out=$("$shm" label "$p-m" "$x" "$y" "$z" 2>/dev/null)
      [[ $out =~ ^label\ ([0-9]+)\  ]] && (( BASH_REMATCH[1] < 65534 )) && beyond=$((beyond + 1))
    done
  done
done
check "voxels beyond the first box carry class labels ($beyond of 54 probed at the flat's end walls)" '(( beyond > 0 ))'
# The segment started with room for the first box (50^3 voxels of 0.1 m) and
# grew with the map, within shm.map_max_voxels.
cap=$("$shm" stat "$p-m" | awk '$1 == "max_voxels" { print $2 }')
last=$(grep -o 'its segment now holds [0-9]*' "$tmp/log" | tail -1 | awk '{ print $5 }')
check "the map's segment started with room for the first box: $(grep -m1 -o 'map /[^ ]*: 50 x 50 x 50 voxels.*' "$tmp/log")" \
  'grep -q "map /[^ ]*: 50 x 50 x 50 voxels of 0.100 m (its segment: 125000 voxels)" "$tmp/log"'
check "the map's segment grew with it, within shm.map_max_voxels (to $cap voxels, $(grep -c 'its segment now holds' "$tmp/log") moves)" \
  '[[ -n $last && $cap == "$last" ]] && (( cap > 125000 && cap <= 480000 ))'
check "the map was refitted at its capacity: $(grep -m1 -o 'map \[[^]]*\] x .*refitted at shm.map_max_voxels' "$tmp/log")" \
  'grep -q "refitted at shm.map_max_voxels" "$tmp/log"'
stop_node
line=$(grep "the box grew" "$tmp/log")
check "the stop line counts the growths ($line)" \
  '[[ $line =~ the\ box\ grew\ ([0-9]+)\ times,\ to\ \[(-?[0-9.]+),\ (-?[0-9.]+)\].*\ ([0-9]+)\ growths\ refused ]] && (( BASH_REMATCH[1] > 0 && BASH_REMATCH[4] == 0 ))'
# The stopped node's map status has the box and its counts as the stop line
# says them (to its 0.1 m), for any controller.
"$shm" stat "$p-m" >"$tmp/stat"
read -r _ lx ly lz < <(grep '^box_lo ' "$tmp/stat")
read -r _ hx hy hz < <(grep '^box_hi ' "$tmp/stat")
stat_line=$(awk -v lx="$lx" -v ly="$ly" -v lz="$lz" -v hx="$hx" -v hy="$hy" -v hz="$hz" \
  '$1 == "box_growths" { g = $2 } $1 == "box_refused" { r = $2 } END { printf "the box grew %d times, to [%.1f, %.1f] x [%.1f, %.1f] x [%.1f, %.1f] m; %d growths refused", g, lx, hx, ly, hy, lz, hz, r }' "$tmp/stat")
check "vlff-shm stat: box $lx $ly $lz .. $hx $hy $hz m, $(grep -E '^box_(growths|refused) ' "$tmp/stat" | tr '\n' ' '): the stop line's" \
  '[[ -n $hz && $line == *"$stat_line" ]]'
# Restarted on its checkpoint: the field and the map resume in the grown box.
# The grid the stopped node saved: its box in the status it stopped with
# (a keyframe still queued when the map was read above may have grown it
# before the stop, and that growth is in the checkpoint: seen under ASan).
dims_before=$(awk -v lx="$lx" -v ly="$ly" -v lz="$lz" -v hx="$hx" -v hy="$hy" -v hz="$hz" -v v="$vs" \
  'BEGIN { printf "%d %d %d", (hx - lx) / v + 0.5, (hy - ly) / v + 0.5, (hz - lz) / v + 0.5 }')
"$node" --config "$tmp/n.yaml" 2>"$tmp/log2" &
nodepid=$!
wait_until 600 '"$shm" stat "$p-m" 2>/dev/null | grep -q "^grid_dims $dims_before\$" && grep -q "resum\|restor" "$tmp/log2"'
check "restarted, the map is the grown grid again ($("$shm" stat "$p-m" | grep '^grid_dims '), was $dims_before)" \
  '"$shm" stat "$p-m" | grep -q "^grid_dims $dims_before\$"'
check "no checkpoint or map refused on the restart" '! grep -qi "refused\|not an observation grid" "$tmp/log2"'
check "restarted, the node asked for the segment's grown size and took it over ($(grep -m1 -o 'its segment: [0-9]* voxels' "$tmp/log2"))" \
  'grep -q "(its segment: $cap voxels)" "$tmp/log2"'
stop_node
verdict
