#!/usr/bin/env bash
# vlff-eval --online on a tiny recorded scene (issue 55): the scene written by
# vlff-sim at 5 Hz is played by vlff-replay into a vlff-node, the published
# map is sampled every second and scored at the labelled points; the curve
# has rows with map versions, frames and keyframes rising, the last row is
# the sample after the replay's end, the RESULT line carries the online,
# offline and fusion scores, and no segment of the run is left behind.
# Usage: test_eval_online.sh SIM EVAL
set -u
sim=$1 eval=$2
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
printf 'sim:\n  frames: 20\n  width: 160\n  height: 120\n  rate_hz: 5\nfield:\n  feature_dim: 16\n' >"$tmp/c.yaml"
"$sim" --config "$tmp/c.yaml" --quiet --write-dataset "$tmp/scene" 2>"$tmp/sim.log" || { cat "$tmp/sim.log"; exit 1; }
"$eval" -c "$tmp/c.yaml" --dataset "$tmp/scene" --iters 50 --online --online-interval 1 --online-after 3 --quiet \
  --out "$tmp/out" >"$tmp/out.log" 2>"$tmp/err.log" &
pid=$!
wait $pid; rc=$?
check "vlff-eval --online exits 0 (rc=$rc)" '[[ $rc == 0 ]]'
rows=$(awk '$1 ~ /^[0-9.]+$/ && NF >= 7' "$tmp/out.log")
last=$(grep -- "<- end of replay + after" "$tmp/out.log")
check "the curve has a row per second and a last one past the replay ($(wc -l <<<"$rows") rows)" \
  '(( $(wc -l <<<"$rows") >= 5 )) && [[ -n $last ]]'
check "the last row: a published map (version > 0), every one of the 20 frames read, keyframes" \
  'read -r t v f k m a c _ <<<"$last"; (( v > 0 && f == 20 && k > 0 ))'
check "the map labels most labelled points the training frames saw" \
  'read -r t v f k m a c _ <<<"$last"; awk -v c="$c" "BEGIN { exit !(c > 50) }"'
res=$(grep '^RESULT online_' "$tmp/out.log")
check "RESULT carries online, offline, fusion, coverage and the publish interval ($res)" \
  '[[ $res =~ ^RESULT\ online_miou3d_3s=[0-9.]+\ offline_miou3d=[0-9.]+\ fusion_miou3d=[0-9.]+\ online_coverage_3s=[0-9.]+\ publish_interval_s=[0-9.]+$ ]]'
check "the online score is a real one (3D mIoU above 10)" \
  '[[ $res =~ online_miou3d_3s=([0-9.]+) ]] && awk -v m="${BASH_REMATCH[1]}" "BEGIN { exit !(m > 10) }"'
check "the node ran fresh, with the scene's prompts in their order" \
  'grep -q "fresh start" "$tmp/out/online/node.log" && grep -q "prompts: the 20 of the embeddings file" "$tmp/out/online/node.log"'
check "the curve is written as TSV" '(( $(wc -l <"$tmp/out/online/curve.tsv") >= 6 ))'
check "no segment of the run is left" '! ls /dev/shm/vlff-eval-$pid-* 2>/dev/null'
out=$("$eval" --online 2>&1); rc=$?
check "--online without --dataset is a usage error ($rc)" '[[ $rc == 2 && $out == *"--dataset"* ]]'
echo "$passes passed, $fails failed"
(( fails == 0 )) || { cat "$tmp/out.log" "$tmp/err.log"; tail -20 "$tmp/out/online/node.log"; }
(( fails == 0 ))
