#!/usr/bin/env bash
# The node's status in its map segment, read as any controller reads it: with
# vlff-sim streaming, `vlff-shm stat` shows the frames, keyframes and iterations
# of a learning node, every refusal reason by name, and after the node stopped,
# the counts it stopped with.
set -u
# Memory limits of its own, so that the status shows the config's.
node_yaml_extra=$'keyframes:\n  memory_mb: 64\npublish:\n  evidence_max_mb: 16'
# A fixed box (the box's status below; test_node_grow has a growing one).
node_field=$'field:\n  feature_dim: 64\n  hash_log2_size: 16\n  grow: false'
. "$(dirname "$0")/node_sh.sh" nst "$@"
val() { awk -v k="$1" '$1 == k { print $2 }' "$tmp/stat"; }
wait_until 200 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null && [[ -n $(val frames_in) ]]'
check "a waiting node's status: no frames yet, every reason listed at 0" \
  '[[ $(val frames_in) == 0 && $(val iterations) == 0 && $(grep -c "^refused 0 " "$tmp/stat") -ge 12 ]]'
check "the reasons carry their names" 'grep -q "^refused 0 no pose$" "$tmp/stat" && grep -q "^refused 0 bad intrinsics$" "$tmp/stat"'

"$sim" --config "$tmp/n.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 1200 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null; [[ $(val iterations) -gt 0 && $(val keyframes) -gt 0 ]] 2>/dev/null'
check "vlff-shm stat: frames in ($(val frames_in))" '[[ $(val frames_in) -gt 0 ]]'
check "vlff-shm stat: keyframes ($(val keyframes))" '[[ $(val keyframes) -gt 0 ]]'
check "vlff-shm stat: iterations ($(val iterations))" '[[ $(val iterations) -gt 0 ]]'
check "vlff-shm stat: a state, a loss and a recent status ($(val state), loss $(val loss), age $(val status_age))" \
  '[[ $(val state) =~ ^(preoperational|operational)$ && $(val loss) != 0 && $(val status_age) =~ ^[0-9]+\.[0-9]+s$ ]]'
# Incremental publication (issue 49): a keyframe's voxels reach the map's
# change log, timed from its capture, and the whole map is refreshed round by
# round; both figures reach controllers through the status.
pos() { awk -v v="$1" 'BEGIN { exit !(v + 0 > 0) }'; }
wait_until 600 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null; pos "$(val frame_to_map_ms_p99)" && pos "$(val publish_interval_s)"'
check "vlff-shm stat: frame to map p50 $(val frame_to_map_ms_p50) p99 $(val frame_to_map_ms_p99) ms, whole refresh every $(val publish_interval_s) s" \
  'pos "$(val frame_to_map_ms_p50)" && pos "$(val frame_to_map_ms_p99)" && pos "$(val publish_interval_s)"'
# Label churn (issue 49): the flips of the last publish, of the last whole
# refresh and since start, and the share flipped where nothing was seen again.
frac_ok() { awk -v v="$1" 'BEGIN { exit !(v == -1 || (v >= 0 && v <= 1)) }'; }
check "vlff-shm stat: label flips $(val label_flips), $(val label_flips_refresh) over the last refresh, $(val label_flips_total) in all, share $(val label_flip_frac)" \
  '[[ $(val label_flips) =~ ^[0-9]+$ && $(val label_flips_refresh) =~ ^[0-9]+$ ]] && (( $(val label_flips_total) >= $(val label_flips_refresh) && $(val label_flips_total) >= $(val label_flips) )) && frac_ok "$(val label_flip_frac)"'
# Memory (issue 48): each component's use within its limit, the limits the
# config's, the field's size and the process's resident set known; the
# resident set holds at least what the components take.
le() { awk -v a="$1" -v b="$2" 'BEGIN { exit !(a + 0 <= b + 0) }'; }
check "vlff-shm stat: memory keyframes $(val mem_keyframes_mb)/$(val mem_keyframes_limit_mb), evidence $(val mem_evidence_mb)/$(val mem_evidence_limit_mb), field $(val mem_field_mb), rss $(val mem_rss_mb) MiB" \
  'pos "$(val mem_keyframes_mb)" && le "$(val mem_keyframes_mb)" "$(val mem_keyframes_limit_mb)" && [[ $(val mem_keyframes_limit_mb) == 64.0 && $(val mem_evidence_limit_mb) == 16.0 ]] && le "$(val mem_evidence_mb)" "$(val mem_evidence_limit_mb)" && pos "$(val mem_field_mb)" && le "$(val mem_field_mb)" "$(val mem_rss_mb)" && le "$(val mem_keyframes_mb)" "$(val mem_rss_mb)"'
# Paging and the box (issue 48): the keyframes' page file is there with the
# default limit (keyframes.page_mb 2048) and holds at most what was written
# to it; the simulated room loses nothing for good; the fixed box
# (field.grow off) never grows and holds the room.
check "vlff-shm stat: keyframes paged $(val keyframes_paged) of $(val keyframes_paged_out) out, $(val keyframes_dropped) dropped, page file $(val keyframes_page_mb) of $(val keyframes_page_limit_mb) MiB, evidence $(val evidence_dropped) dropped, box $(grep '^box_lo ' "$tmp/stat" | cut -d' ' -f2-) .. $(grep '^box_hi ' "$tmp/stat" | cut -d' ' -f2-) grown $(val box_growths), refused $(val box_refused)" \
  '(( $(val keyframes_paged) <= $(val keyframes_paged_out) && $(val keyframes_paged_in) <= $(val keyframes_paged_out) && $(val keyframes_dropped) == 0 && $(val evidence_dropped) == 0 && $(val box_growths) == 0 && $(val box_refused) == 0 )) && le "$(val keyframes_page_mb)" 2048 && [[ $(val keyframes_page_limit_mb) == 2048.0 ]] && awk '"'"'$1 == "box_lo" { split($0, lo) } $1 == "box_hi" { split($0, hi) } END { exit !(hi[2] - lo[2] > 1 && hi[3] - lo[3] > 1 && hi[4] - lo[4] > 1) }'"'"' "$tmp/stat"'
check "frames refused is the sum of the reasons" \
  '[[ $(val frames_refused) == $(awk '"'"'$1 == "refused" { s += $2 } END { print s + 0 }'"'"' "$tmp/stat") ]]'

kill "$simpid"; wait "$simpid"; simpid=
sleep 0.5
# The trainer shares the counts between its steps, and a sanitizer build's
# step can take seconds: the last counts are those of a share made after
# the sim stopped (two shares on from here).
"$shm" stat $p-m >"$tmp/stat"
u0=$(val status_updates)
wait_until 600 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null && (( $(val status_updates) >= u0 + 2 ))'
"$shm" stat $p-m >"$tmp/last"
stop_node
"$shm" stat $p-m >"$tmp/stat"
check "after the stop the segment keeps the node's last counts" \
  '[[ $(val frames_in) == $(awk '"'"'$1 == "frames_in" { print $2 }'"'"' "$tmp/last") && $(val iterations) -ge $(awk '"'"'$1 == "iterations" { print $2 }'"'"' "$tmp/last") && $(val writer_alive) == no ]]'
echo "$passes passed, $fails failed"
(( fails == 0 )) || { echo "--- stat"; cat "$tmp/stat"; echo "--- node log"; tail -30 "$tmp/log"; }
(( fails == 0 ))
