#!/usr/bin/env bash
# Evidence paging through the real node (publish.evidence_page_mb;
# docs/field.md, "Evidence paging"): with an evidence budget far smaller than
# the simulated room's surfaces, what the full budget gives up goes to
# node.state_dir's evidence.pages while the node runs (said once in its log,
# counted in its stop line, none given up for good), the file goes when the
# node stops, and the checkpoint holds every voxel's evidence: the node
# started again pages out what is beyond its budget instead of dropping it.
# The keyframe store, kept to 6 keyframes (fewer than the walk's places),
# says when it is full, pages what it evicts out to keyframes.pages
# (keyframes.page_mb; a newer view of a paged place overwrites it) and
# counts it in the stop line and on --status, none dropped; that file goes
# with the node too. The map's status (vlff-shm stat) shows the keyframes'
# page file against keyframes.page_mb, and after the stop the counts of the
# stop lines.
set -u
node_field=  # the default field: its evidence records (D = 512) fill the 1 MiB budget
node_args=--status
node_yaml_extra=$'publish:\n  evidence_max_mb: 1\n  evidence_page_mb: 64\nkeyframes:\n  max_keyframes: 6\n  page_mb: 128'
. "$(dirname "$0")/node_sh.sh" nep "$@"
"$sim" --config "$tmp/n.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 1200 'grep -q "page theirs out" "$tmp/log"'
check "a full evidence budget pages out to the state directory: said ($(grep -o 'publish.evidence_max_mb[^;]*' "$tmp/log" | head -1)), and the file is there" \
  'grep -q "evidence: publish.evidence_max_mb (1 MB, [0-9]* voxels) is full; from now on the least-observed voxels page theirs out" "$tmp/log" && [[ -s $tmp/evidence.pages ]]'
# Keyframes past the first fill: views of what was paged out come round
# again; and past the keyframe store's.
sleep 3
wait_until 600 'grep -q "keyframes: the store is full" "$tmp/log"'
# --status is redrawn every half second: the first paged keyframe shows on a later line.
wait_until 300 'grep -aEq "rss [0-9]* MiB( box [^|]*)? kf paged [1-9]" "$tmp/log"'
check "evicted keyframes go to the state directory's keyframes.pages ($(stat -c %s "$tmp/keyframes.pages" 2>&1) bytes), said on --status ($(grep -aEo 'rss [0-9]* MiB( box [^|]*)? kf paged [0-9]*' "$tmp/log" | tail -1))" \
  '[[ -s $tmp/keyframes.pages ]] && grep -aEq "\| mem kf [0-9]*/[0-9]* ev [0-9]*/1 rss [0-9]* MiB( box [0-9]+x[0-9]+x[0-9]+ m)? kf paged [1-9][0-9]* \|" "$tmp/log"'
# The map's status has the page file's use against keyframes.page_mb (the
# trainer shares its status a tenth of a second at most after --status saw
# it, or after a step that a sanitizer build makes long: poll).
val() { awk -v k="$1" '$1 == k { print $2 }' "$tmp/stat"; }
kf_page_ok() {
  awk -v u="$(val keyframes_page_mb)" "BEGIN { exit !(u > 0 && u <= 128) }" && [[ $(val keyframes_page_limit_mb) == 128.0 ]] &&
    (( $(val keyframes_paged_out) > 0 ))
}
wait_until 300 '"$shm" stat $p-m >"$tmp/stat" && kf_page_ok'
check "vlff-shm stat: the keyframes' page file $(val keyframes_page_mb) of $(val keyframes_page_limit_mb) MiB, $(val keyframes_paged_out) keyframes written to it" kf_page_ok
kill "$simpid"; wait "$simpid"; simpid=
stop_node
# A stopped node's segment keeps the counts it stopped with: those of its
# stop lines, for any controller (vlff-shm stat; the viewer and DDS show
# the same block).
"$shm" stat $p-m >"$tmp/stat"
line=$(grep "evidence beyond publish.evidence_max_mb" "$tmp/log")
kline=$(grep "keyframes beyond keyframes.memory_mb" "$tmp/log")
check "vlff-shm stat after the stop: keyframes paged $(val keyframes_paged) (out $(val keyframes_paged_out), in $(val keyframes_paged_in), dropped $(val keyframes_dropped)), evidence paged $(val evidence_paged) (out $(val evidence_paged_out), in $(val evidence_paged_in), dropped $(val evidence_dropped)): the stop lines' counts" \
  '[[ "$kline" == *": $(val keyframes_paged) in the page file ($(val keyframes_paged_out) paged out, $(val keyframes_paged_in) brought back), $(val keyframes_dropped) dropped"* && "$line" == *": $(val evidence_paged) voxels in the page file ($(val evidence_paged_out) paged out, $(val evidence_paged_in) brought back), $(val evidence_dropped) given up"* ]]'
check "the stop line counts what was paged ($line), nothing given up for good" \
  '[[ $line =~ ([0-9]+)\ voxels\ in\ the\ page\ file\ \(([0-9]+)\ paged\ out,\ ([0-9]+)\ brought\ back\),\ 0\ given\ up ]] && (( BASH_REMATCH[1] > 0 && BASH_REMATCH[2] >= BASH_REMATCH[1] ))'
check "the page file goes with the node" '[[ ! -e $tmp/evidence.pages ]]'
stopped=$(grep "stopped: " "$tmp/log")
check "a full keyframe store is said once ($(grep -o 'keyframes: the store is full[^;]*' "$tmp/log")), and what it evicted counted at the stop ($stopped)" \
  '(( $(grep -c "keyframes: the store is full at 6 keyframes (keyframes.memory_mb [0-9]* MiB, max_keyframes 6); from now on each new one replaces the most redundant" "$tmp/log") == 1 )) && [[ $stopped =~ [0-9]+\ keyframes\ \(([0-9]+)\ evicted ]] && (( BASH_REMATCH[1] > 0 ))'
check "the keyframes' page file is said ($(grep -o 'which goes to keyframes.pages[^;]*' "$tmp/log")) and counted at the stop ($kline), none dropped, and goes with the node" \
  'grep -q "counted as evicted, which goes to keyframes.pages (keyframes.page_mb) and comes back when the camera returns near it" "$tmp/log" && [[ $kline =~ ([0-9]+)\ in\ the\ page\ file\ \(([0-9]+)\ paged\ out,\ ([0-9]+)\ brought\ back\),\ 0\ dropped ]] && (( BASH_REMATCH[1] > 0 && BASH_REMATCH[2] >= BASH_REMATCH[1] + BASH_REMATCH[3] )) && [[ ! -e $tmp/keyframes.pages ]]'
check "no page file error" '! grep -q "evidence: page file" "$tmp/log"'
# Started again on its checkpoint: the evidence beyond the budget is paged,
# not given up (the load would say how many it gave up). A file a killed
# run left is not read as this run's.
head -c 100000 /dev/urandom >"$tmp/evidence.pages"
"$node" --config "$tmp/n.yaml" 2>"$tmp/log2" &
nodepid=$!
wait_until 600 'grep -q "resumed\|restored\|checkpoint" "$tmp/log2" && [[ -s $tmp/evidence.pages ]]'
# Records of 2 + 2 D bytes (D = 512 here): the junk's 100000 bytes are not.
check "restarted on its checkpoint, the evidence beyond the budget is paged again ($(stat -c %s "$tmp/evidence.pages") bytes), none given up" \
  '[[ -s $tmp/evidence.pages ]] && (( $(stat -c %s "$tmp/evidence.pages") % 1026 == 0 )) && ! grep -q "were given up" "$tmp/log2"'
stop_node
echo "$passes passed, $fails failed"
(( fails == 0 )) || { echo "--- node log"; tail -30 "$tmp/log"; echo "--- restarted"; tail -30 "$tmp/log2"; }
(( fails == 0 ))
