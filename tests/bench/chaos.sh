#!/usr/bin/env bash
# Chaos: kill -9, at random moments, the simulator (frame and feature ring
# producer), the node (ring consumer, map writer, mailbox owner), a controller
# reading the map (tests/bench/chaos_reader.c) and a prompt poster (vlff-shm
# set-prompts), restarting each at once, until VLFF_CHAOS_KILLS kills are done.
# The node is not killed again before it has published a new map version, and
# at least 2 of the kills (all, for a target below 2) are the node's, the last
# ones if chance did not pick it before: a short run then still has restarts
# whose quality can be compared.
#
# Counted (issue 29):
#   kills           kill -9 delivered
#   torn_reads      snapshots of one map version with different contents
#   lost_versions   map versions lower than one a reader had already seen
#   leaked_files    after a clean stop: segments of this run other than the
#                   configured ones, and temporary files in the state directory
#   recovery_p99_s  node restart -> its first new map version, 99th percentile
#   quality_drops   restarts whose first 3D mIoU after resuming is more than 5
#                   points below the mIoU when the killed node last checkpointed
#   quality_checked restarts whose quality was compared so (left out: those
#                   before any killed node had checkpointed with a 3D mIoU, and
#                   those whose node logged none after resuming); 0 fails the
#                   run, which would otherwise pass having compared nothing.
#                   So that a short run compares one, the node is spared until
#                   a node has checkpointed with a 3D mIoU, and a restarted one
#                   until it logs its resumed map's (5 s at most)
# Baseline in the same run: the node's cold start (start -> first map version),
# recovery_vs_cold_start. Exits non-zero if anything but kills, quality_checked
# and times is not 0, or if quality_checked is 0.
# Env: VLFF_BUILD (build dir, set by scripts/bench), VLFF_CHAOS_KILLS (default
# 100), VLFF_CHAOS_GAP_S (mean seconds between kills, default 1.2),
# VLFF_CHAOS_SEED (random seed, default the pid).
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${VLFF_BUILD:-$here/../../build/release}
node=$build/node/vlff-node
sim=$build/node/sim/vlff-sim
shm=$build/shm/vlff-shm
reader=$build/bench/chaos_reader
for x in "$node" "$sim" "$shm" "$reader"; do [[ -x $x ]] || { echo "chaos.sh: $x not built" >&2; exit 1; }; done
target=${VLFF_CHAOS_KILLS:-100}
min_node_kills=$((target < 2 ? target : 2))
gap=${VLFF_CHAOS_GAP_S:-1.2}
RANDOM=${VLFF_CHAOS_SEED:-$$}

out=$(mktemp -d "${TMPDIR:-/tmp}/vlff-chaos.XXXXXX")
tag=chaos$$
map=/$tag-map prompts=/$tag-prompts
simpid= nodepid= readerpid= posterpid=
cleanup() {
  for p in $simpid $nodepid $readerpid $posterpid; do kill -9 "$p" 2>/dev/null; done
  if [[ -n ${VLFF_CHAOS_KEEP:-} ]]; then echo "chaos: logs kept in $out"; else rm -rf "$out"; fi
  rm -f /dev/shm/"$tag"-*
}
trap cleanup EXIT

awk -v tag="$tag" -v out="$out" '
  /^[a-z]/ { sec = $1 }
  sec == "node:" && /state_dir:/ { print "  state_dir: " out "/state"; next }
  sec == "node:" && /checkpoint_period_s:/ { print "  checkpoint_period_s: 3"; next }
  sec == "publish:" && /rate_hz:/ { print "  rate_hz: 2"; next }
  sec == "shm:" && /: \/vlff-demo-/ { sub(/\/vlff-demo-/, "/" tag "-") }
  { print }
' "$here/../../configs/demo-sim.yaml" >"$out/chaos.yaml"
mkdir -p "$out/state"
"$node" --check-config "$out/chaos.yaml" >/dev/null 2>"$out/check.log" || { cat "$out/check.log" >&2; exit 1; }

now() { echo "${EPOCHREALTIME/,/.}"; }
later() { awk -v t="$1" -v g="$gap" -v r="$RANDOM" 'BEGIN { printf "%.3f", t + g * 2 * r / 32767 }'; }
before() { awk -v a="$1" -v b="$2" 'BEGIN { exit !(a < b) }'; }
map_version() { "$shm" stat "$map" 2>/dev/null | awk '$1 == "version" { print $2 }'; }

inc=0
start_node() {
  inc=$((inc + 1))
  "$node" --config "$out/chaos.yaml" --status 2>"$out/node.$inc.log" &
  nodepid=$!
  disown
}
# Disowned, so that the shell does not report each kill; liveness is kill -0.
start_sim() { "$sim" --config "$out/chaos.yaml" --quiet 2>>"$out/sim.log" & simpid=$!; disown; }
start_reader() { "$reader" "$map" "$out/reader.state" 2>>"$out/reader.log" & readerpid=$!; disown; }
start_poster() { "$shm" set-prompts -t 5 "$prompts" -i 0 >>"$out/poster.log" 2>&1 & posterpid=$!; disown; }
alive() { [[ -n $1 ]] && kill -0 "$1" 2>/dev/null; }
stop() { # SIGTERM, then wait for the process to be gone
  local p
  kill -TERM "$@" 2>/dev/null
  for p in "$@"; do while kill -0 "$p" 2>/dev/null; do sleep 0.1; done; done
}

t_cold=$(now)
start_node
start_sim
start_reader
v=
for ((i = 0; i < 1200; i++)); do
  v=$(map_version)
  [[ -n $v && $v -ge 1 ]] && break
  sleep 0.1
done
[[ -n $v && $v -ge 1 ]] || { echo "chaos.sh: the node never published; its log:" >&2; tail -5 "$out/node.1.log" >&2; exit 1; }
cold=$(awk -v a="$t_cold" -v b="$(now)" 'BEGIN { printf "%.3f", b - a }')
echo "chaos: node published map v$v after a cold start of ${cold} s; $target kills follow"

# The 3D mIoU a node log shows at its last checkpoint (empty: none yet).
ckpt_q() {
  tr '\r' '\n' <"$1" | awk '/map v[0-9]+ mIoU/ { for (i = 1; i <= NF; i++) if ($i == "3D" && $(i + 1) != "-") last = $(i + 1) }
                              / I node: checkpoint / { at = last } END { print at }'
}
# The first 3D mIoU a node log shows on a map newer than version $2 (empty: none yet).
resumed_q() {
  tr '\r' '\n' <"$1" | awk -v vb="$2" '/map v[0-9]+ mIoU/ {
      for (i = 1; i <= NF; i++) if ($i ~ /^v[0-9]+$/) v = substr($i, 2) + 0
      for (i = 1; i <= NF; i++) if ($i == "3D" && $(i + 1) != "-") { if (v > vb) { print $(i + 1); exit } }
    }'
}
kills=0 pending=0 v_before=0 t_restart=0 t_recovered= comparable=0
declare -A killed=([sim]=0 [node]=0 [reader]=0 [poster]=0)
recoveries=()
next_kill=$(later "$(now)")
# Restarts whatever is dead; notes the node's recovery (a map newer than v_before).
tend() {
  alive "$simpid" || start_sim
  alive "$readerpid" || start_reader
  [[ $1 == poster ]] && ! alive "$posterpid" && start_poster
  if ! alive "$nodepid"; then
    start_node
    pending=1 t_restart=$(now)
  fi
  if ((pending)); then
    local v
    v=$(map_version)
    if [[ -z $t_recovered && -n $v ]] && ((v > v_before)); then
      t_recovered=$(now)
      recoveries+=("$(awk -v a="$t_restart" -v b="$t_recovered" 'BEGIN { printf "%.3f", b - a }')")
      echo "node.$inc v_before=$v_before" >>"$out/restarts"
    fi
    # Recovered once its log shows the resumed map's 3D mIoU (what the
    # quality check reads), or 5 s after the new map if it never does.
    if [[ -n $t_recovered ]] && { [[ -n $(resumed_q "$out/node.$inc.log" "$v_before") ]] ||
         before "$(awk -v t="$t_recovered" 'BEGIN { printf "%.3f", t + 5 }')" "$(now)"; }; then
      pending=0 t_recovered=
    fi
  fi
}
while ((kills < target)); do
  sleep 0.05
  tend poster
  before "$(now)" "$next_kill" && continue
  victims=(sim reader poster)
  # Until one node has been killed after checkpointing with a 3D mIoU, the
  # node waits for that, so that a quick run still compares one restart.
  ((comparable)) || { [[ -n $(ckpt_q "$out/node.$inc.log") ]] && comparable=1; }
  ((pending || !comparable)) || victims+=(node)
  owed=$((min_node_kills - killed[node]))
  if ((owed > 0 && target - kills <= owed)); then
    ((pending || !comparable)) && continue # the node's kill waits for its recovery
    victims=(node)
  fi
  victim=${victims[RANDOM % ${#victims[@]}]}
  case $victim in
    sim) pid=$simpid ;;
    reader) pid=$readerpid ;;
    poster) pid=$posterpid ;;
    node) pid=$nodepid; v_before=$(map_version); v_before=${v_before:-0} ;;
  esac
  if alive "$pid" && kill -9 "$pid" 2>/dev/null; then
    while alive "$pid"; do sleep 0.01; done
    kills=$((kills + 1))
    killed[$victim]=$((killed[$victim] + 1))
  fi
  next_kill=$(later "$(now)")
done
# Restart the last victims and let the node recover before stopping.
tend none
for ((i = 0; i < 1200 && pending; i++)); do
  sleep 0.1
  tend none
done
unrecovered=$pending
# A last prompt post must still be answered after all this.
while alive "$posterpid"; do sleep 0.1; done
final_post=$("$shm" set-prompts -t 10 "$prompts" -i 0 2>&1)

kill -9 "$readerpid" 2>/dev/null
stop "$simpid" "$nodepid"
readerpid= simpid= nodepid= posterpid=
# One more clean start and stop: whatever a killed writer left must be gone then.
start_node
for ((i = 0; i < 600; i++)); do grep -q "waiting for ring\|attached to ring" "$out/node.$inc.log" && break; sleep 0.1; done
stop "$nodepid"; nodepid=

configured=$(awk '/^shm:/ { s = 1; next } /^[a-z]/ { s = 0 } s && /: \// { print $2 }' "$out/chaos.yaml")
leaked_segments=$(for f in /dev/shm/"$tag"-*; do
  [[ -e $f ]] || continue
  n=/${f#/dev/shm/}
  grep -qxF "$n" <<<"$configured" || echo "$n"
done)
leaked_tmp=$(find "$out/state" -name '*.tmp*' 2>/dev/null)
leaked=$( (printf '%s\n' "$leaked_segments" "$leaked_tmp" | grep -c .) || true)
torn=$(grep -c '^torn' "$out/reader.state.events" 2>/dev/null); torn=${torn:-0}
lost=$(grep -c '^backwards' "$out/reader.state.events" 2>/dev/null); lost=${lost:-0}

# Quality: for each restart, the killed node's 3D mIoU at its last checkpoint
# (inherited from its own resume if it never checkpointed) against the restarted
# node's first 3D mIoU on a map newer than v_before.
quality_drops=0 quality_checked=0
prev_q=
for ((k = 1; k <= inc; k++)); do
  log=$out/node.$k.log
  [[ -f $log ]] || continue
  if ((k > 1)) && [[ -n $prev_q ]]; then
    vb=$(awk -v n="node.$k" '$1 == n { sub("v_before=", "", $2); print $2 }' "$out/restarts" 2>/dev/null)
    if [[ -n $vb ]]; then
      q=$(resumed_q "$log" "$vb")
      [[ -n $q ]] && quality_checked=$((quality_checked + 1))
      if [[ -n $q ]] && awk -v a="$q" -v b="$prev_q" 'BEGIN { exit !(a < b - 5) }'; then
        quality_drops=$((quality_drops + 1))
        echo "chaos: node.$k resumed at 3D mIoU $q, its checkpoint held $prev_q"
      fi
    fi
  fi
  q=$(ckpt_q "$log")
  [[ -n $q ]] && prev_q=$q
done

p99=$(printf '%s\n' "${recoveries[@]}" | sort -g | awk '{ a[NR] = $1 } END { if (!NR) { print "nan"; exit }
  i = int(0.99 * NR + 0.999999); if (i < 1) i = 1; print a[i] }')
echo "chaos: killed sim ${killed[sim]}, node ${killed[node]} (${#recoveries[@]} recoveries), reader ${killed[reader]}, poster ${killed[poster]}"
echo "chaos: last post after the chaos: $final_post"
[[ -n $leaked_segments ]] && echo "chaos: leaked segments: $leaked_segments"
[[ -n $leaked_tmp ]] && echo "chaos: leaked temporary files: $leaked_tmp"
[[ -s $out/reader.state.events ]] && head -5 "$out/reader.state.events"
ratio=$(awk -v a="$p99" -v b="$cold" 'BEGIN { if (a == "nan" || b <= 0) print "nan"; else printf "%.2f", a / b }')
echo "RESULT kills=$kills torn_reads=$torn lost_versions=$lost leaked_files=$leaked recovery_p99_s=$p99 quality_drops=$quality_drops quality_checked=$quality_checked cold_start_s=$cold recovery_vs_cold_start=$ratio"
[[ $final_post == accepted* ]] || { echo "chaos.sh: the mailbox did not answer after the chaos" >&2; exit 1; }
((quality_checked > 0)) || { echo "chaos.sh: no restart's quality was compared with its checkpoint's" >&2; exit 1; }
((torn == 0 && lost == 0 && leaked == 0 && quality_drops == 0 && unrecovered == 0 && kills >= target))
