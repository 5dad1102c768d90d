#!/usr/bin/env bash
# Soak: does vlff-node's memory stay flat over hours of keyframes?
#
# The real vlff-sim and vlff-node binaries run the demo room with the stream
# and keyframe rate raised from 5 to 20 Hz (the sim renders what it can; on
# 2 cores about 12 Hz), so each minute admits keyframes as two to four
# minutes of the 5 Hz demo would: keyframe churn (admit, evict, free) of
# hours, with a checkpoint every 30 s. The hours printed are counted from the
# keyframes the node admitted. The store's byte budget is set below what
# max_keyframes would hold, so eviction by bytes is what bounds it.
#
# Baseline in the same run: the node's RSS once the store is full (the
# highest sample in the window after the warm-up). The result is the highest
# RSS in the last quarter of the run against it; flat memory gives a ratio
# of 1.00. The store's own bytes are in the node's status, its budget in the
# config; both are printed.
# Env: VLFF_BUILD (release build dir, set by scripts/bench), VLFF_SOAK_SECONDS
# (default 900), VLFF_SOAK_WARMUP_S (default 120).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${VLFF_BUILD:-$here/../../build/release}
node=$build/node/vlff-node
sim=$build/node/sim/vlff-sim
for x in "$node" "$sim"; do [[ -x $x ]] || { echo "soak.sh: $x not built" >&2; exit 1; }; done
secs=${VLFF_SOAK_SECONDS:-900}
warm=${VLFF_SOAK_WARMUP_S:-120}
budget_mb=512
(( secs >= 2 * warm )) || { echo "soak.sh: VLFF_SOAK_SECONDS must be at least twice the warm-up ($warm s)" >&2; exit 1; }

out=$(mktemp -d "${TMPDIR:-/tmp}/vlff-bench-soak.XXXXXX")
tag=soak$$
cleanup() {
  kill "${simpid:-}" "${nodepid:-}" 2>/dev/null || true
  wait 2>/dev/null || true
  rm -rf "$out" /dev/shm/"$tag"-*
}
trap cleanup EXIT

# The demo config with this run's own segments, state directory and rates.
awk -v tag="$tag" -v out="$out" -v secs="$secs" -v budget="$budget_mb" '
  /^[a-z]/ { sec = $1 }
  sec == "node:" && /state_dir:/ { print "  state_dir: " out "/state"; next }
  sec == "node:" && /checkpoint_period_s:/ { print "  checkpoint_period_s: 30"; print "  run_seconds: " secs; next }
  sec == "sim:" && /rate_hz:/ { print "  rate_hz: 20"; next }
  sec == "shm:" && /: \/vlff-demo-/ { sub(/\/vlff-demo-/, "/" tag "-") }
  { print }
  END { print "keyframes:"; print "  rate_hz: 20"; print "  memory_mb: " budget }
' "$here/../../configs/demo-sim.yaml" >"$out/soak.yaml"
"$node" --check-config "$out/soak.yaml" >/dev/null 2>"$out/check.log" || { cat "$out/check.log" >&2; exit 1; }

"$sim" --config "$out/soak.yaml" --quiet 2>"$out/sim.log" &
simpid=$!
"$node" --config "$out/soak.yaml" 2>"$out/node.log" &
nodepid=$!
echo "soak: ${secs} s at up to 20 Hz keyframes, store budget ${budget_mb} MB"

rss_kb() { awk '/^VmRSS:/ { print $2 }' /proc/"$1"/status 2>/dev/null; }
t0=$SECONDS
samples=()
while kill -0 "$nodepid" 2>/dev/null; do
  r=$(rss_kb "$nodepid")
  [[ -n $r ]] && samples+=("$((SECONDS - t0)) $r")
  if (( ${#samples[@]} % 12 == 1 )) && [[ -n $r ]]; then
    printf 't=%4d s  rss %4d MB\n' "$((SECONDS - t0))" "$((r / 1024))"
  fi
  sleep 5
done
wait "$nodepid" || { echo "soak.sh: vlff-node failed; its log:" >&2; tail -20 "$out/node.log" >&2; exit 1; }
stopped=$(grep -E ' node: stopped' "$out/node.log")
echo "  $stopped"
# Keyframes admitted = held + evicted; at the demo's 5 Hz that many take this long.
admitted=$(sed -n 's/.* \([0-9]*\) keyframes (\([0-9]*\) evicted[,)].*/\1 \2/p' <<<"$stopped" | awk '{ print $1 + $2 }')
[[ -n $admitted ]] || { echo "soak.sh: no keyframe count in the node's stop line" >&2; exit 1; }
checkpoints=$(grep -c ' I node: checkpoint ' "$out/node.log" || true)
errors=$(grep -c '^\[[^]]*\] E ' "$out/node.log" || true)

printf '%s\n' "${samples[@]}" | awk -v warm="$warm" -v secs="$secs" -v budget="$budget_mb" \
  -v ckpt="$checkpoints" -v errs="$errors" -v admitted="$admitted" '
  { t = $1; kb = $2; if (kb > peak) peak = kb
    if (t >= warm && t < 2 * warm && kb > base) base = kb
    if (t >= 0.75 * secs && kb > last) last = kb }
  END {
    if (base == 0 || last == 0) { print "soak.sh: too few RSS samples" > "/dev/stderr"; exit 1 }
    printf "RSS after warm-up %.0f MB, last quarter %.0f MB, peak %.0f MB; %d keyframes admitted, %d checkpoints, %d error lines\n",
           base / 1024, last / 1024, peak / 1024, admitted, ckpt, errs
    printf "RESULT soak_rss_end_mb=%.0f soak_rss_warm_mb=%.0f soak_rss_growth_mb=%.0f soak_end_over_warm=%.3f soak_kf_budget_mb=%d soak_hours_equiv=%.2f\n",
           last / 1024, base / 1024, (last - base) / 1024, last / base, budget, admitted / 5 / 3600
  }'
