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
# Hostile actors (issue 51) act beside the kills, each at least once
# (VLFF_CHAOS_HOSTILE_ROUNDS rounds of all four, spread over the kills):
#   fifo      a FIFO planted at the frame and feature rings' names while the
#             node starts and waits for them (open() of a FIFO blocks)
#   mailbox   the prompt mailbox's state word flipped to "abandoned" by a
#             4-byte write; a post must still be accepted
#   shmfull   /dev/shm filled to the brim while the simulator recreates its
#             rings; it must say so and back off, not spin
#   pose      a forged future pose line on vlff-pose's UDP socket; the
#             tracker's lines that follow must still reach the pose ring
# Each case ends with a SIGTERM to the node, timed (sigterm_p99_s over the
# cases; one that takes over 5 s fails the run). The run happens in a private
# mount namespace with a tmpfs of its own at /dev/shm (as root; otherwise
# the shmfull case is left out and said so), so filling it touches nothing else.
#   hostile_cases     cases run
#   hostile_failures  cases whose product did not hold (the post refused, no
#                     "no space" message or a spinning creator, legitimate
#                     poses lost after the forged one)
# Baseline in the same run: the node's cold start (start -> first map version),
# recovery_vs_cold_start. Exits non-zero if anything but kills, quality_checked
# and times is not 0, or if quality_checked is 0.
# Env: VLFF_BUILD (build dir, set by scripts/bench), VLFF_CHAOS_KILLS (default
# 100), VLFF_CHAOS_GAP_S (mean seconds between kills, default 1.2),
# VLFF_CHAOS_SEED (random seed, default the pid), VLFF_CHAOS_HOSTILE_ROUNDS
# (default 1 for fewer than 50 kills, else 2; 0 for none).
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
# A private /dev/shm: the shmfull case fills it, and nothing of another run or
# program lives there. unshare -m needs root; without it /dev/shm is the host's.
if [[ -z ${VLFF_CHAOS_NS:-} ]] && ((EUID == 0)) && unshare -m --propagation private true 2>/dev/null; then
  export VLFF_CHAOS_NS=1
  exec unshare -m --propagation private bash -c \
    'mount -t tmpfs -o size=256m,mode=1777 vlff-chaos /dev/shm || export VLFF_CHAOS_NS=0; exec bash "$0" "$@"' "$0" "$@"
fi
private_shm=0
[[ ${VLFF_CHAOS_NS:-} == 1 ]] && private_shm=1
build=${VLFF_BUILD:-$here/../../build/release}
node=$build/node/vlff-node
sim=$build/node/sim/vlff-sim
shm=$build/shm/vlff-shm
reader=$build/bench/chaos_reader
for x in "$node" "$sim" "$shm" "$reader" "$build/drivers/pose/vlff-pose"; do [[ -x $x ]] || { echo "chaos.sh: $x not built" >&2; exit 1; }; done
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

# The 3D mIoU a node log shows for the map its last checkpoint holds (empty:
# none yet): the newest status line's whose map version is at most the one the
# checkpoint line names, since the field is written a pass after the grid and
# a map published meanwhile is not in the checkpoint.
ckpt_q() {
  tr '\r' '\n' <"$1" | awk '/map v[0-9]+ (flips [0-9]+ )?mIoU/ {
      for (i = 1; i <= NF; i++) if ($i ~ /^v[0-9]+$/) v = substr($i, 2) + 0
      for (i = 1; i <= NF; i++) if ($i == "3D" && $(i + 1) != "-") { n++; sv[n] = v; sq[n] = $(i + 1) }
    }
    / I node: checkpoint .* map v[0-9]+$/ {
      saved = substr($NF, 2) + 0; at = ""
      for (j = n; j >= 1; j--) if (sv[j] <= saved) { at = sq[j]; break }
    } END { print at }'
}
# The first 3D mIoU a node log shows on a map newer than version $2 (empty: none yet).
resumed_q() {
  tr '\r' '\n' <"$1" | awk -v vb="$2" '/map v[0-9]+ (flips [0-9]+ )?mIoU/ {
      for (i = 1; i <= NF; i++) if ($i ~ /^v[0-9]+$/) v = substr($i, 2) + 0
      for (i = 1; i <= NF; i++) if ($i == "3D" && $(i + 1) != "-") { if (v > vb) { print $(i + 1); exit } }
    }'
}
# The configured segment names of one kind (ring, feature_ring, pose_ring...).
seg_name() { awk -v k="$1:" '/^shm:/ { s = 1; next } /^[a-z]/ { s = 0 } s && $1 == k { print $2 }' "$out/chaos.yaml"; }
gone() { local p; for p in "$@"; do [[ -z $p ]] && continue; while kill -0 "$p" 2>/dev/null; do sleep 0.01; done; done; }
sigterm_times=() hostile_failures=0 hostile_cases=0
declare -A hostile=([fifo]=0 [mailbox]=0 [shmfull]=0 [pose]=0)
hostile_fail() { echo "chaos: hostile $1: $2"; hostile_failures=$((hostile_failures + 1)); }
# SIGTERM to the node, timed; one still there after 10 s is killed (and fails the run).
term_node() {
  local t0 i
  v_before=$(map_version); v_before=${v_before:-0}
  t0=$(now)
  kill -TERM "$nodepid" 2>/dev/null
  for ((i = 0; i < 1000 && $(alive "$nodepid" && echo 1 || echo 0); i++)); do sleep 0.01; done
  if alive "$nodepid"; then
    hostile_fail "$1" "the node did not stop within 10 s of SIGTERM"
    kill -9 "$nodepid"; gone "$nodepid"
  fi
  sigterm_times+=("$(awk -v a="$t0" -v b="$(now)" 'BEGIN { printf "%.3f", b - a }')")
}
# A FIFO at the rings' names while the node starts: open() on a FIFO blocks
# until a writer comes, so a reader that does not refuse it hangs (and its
# thread with it, the node's stop included).
hostile_fifo() {
  local n
  kill -9 "$simpid" "$nodepid" 2>/dev/null; gone "$simpid" "$nodepid"
  for n in $(seg_name ring) $(seg_name feature_ring); do rm -f "/dev/shm$n"; mkfifo -m 600 "/dev/shm$n"; done
  start_node
  sleep 2
  term_node fifo
  for n in $(seg_name ring) $(seg_name feature_ring); do rm -f "/dev/shm$n"; done
}
# The mailbox's segment header keeps its state word at byte 80 (shm_internal.h,
# struct seg_hdr; a fixed ABI): 2 is "abandoned by its writer". Any member of the
# mailbox's group can write it.
hostile_mailbox() {
  local r
  gone "$posterpid"
  printf '\002\000\000\000' | dd of="/dev/shm$prompts" bs=1 seek=80 conv=notrunc status=none
  r=$("$shm" set-prompts -t 5 "$prompts" -i 0 2>&1)
  [[ $r == accepted* ]] || hostile_fail mailbox "a post after the state word was flipped: $r"
  term_node mailbox
}
# /dev/shm filled to the brim, twice: while the simulator starts (it must say so
# and stop with the reason), and while it runs when a process with write access
# truncates its frame ring (it must say so, keep running and retry at a growing
# interval; before, it replaced its rings about 15 times a second, the node
# reattached as often and no frames flowed), then frames flow again once there
# is room, without a restart.
fill_shm() { # tops the filler up until /dev/shm has stayed full for a second
  local i avail full=0
  for ((i = 0; i < 100 && full < 5; i++)); do
    avail=$(df -B1 --output=avail /dev/shm | tail -1)
    if ((avail > 0)); then
      full=0
      fallocate -l "$avail" "/dev/shm/$tag-filler.$RANDOM$i" 2>/dev/null || break
    else
      full=$((full + 1))
    fi
    sleep 0.2
  done
}
ring_head() { "$shm" stat "$(seg_name ring)" 2>/dev/null | awk '$1 == "head" { print $2 }'; }
hostile_shmfull() {
  local n lines0 lines at0 at h0 h i
  # 1. At start: the removed rings' pages come back once the node lets go of its
  # mappings, which fill_shm waits for.
  kill -9 "$simpid" 2>/dev/null; gone "$simpid"
  for n in $(seg_name ring) $(seg_name feature_ring); do rm -f "/dev/shm$n"; done
  fill_shm
  lines0=$(wc -l <"$out/sim.log")
  start_sim
  for ((i = 0; i < 50; i++)); do alive "$simpid" || break; sleep 0.1; done
  tail -n "+$((lines0 + 1))" "$out/sim.log" | grep -q 'no space left in /dev/shm' ||
    hostile_fail shmfull "the simulator started on a full /dev/shm and did not say so; its log: $(tail -n "+$((lines0 + 1))" "$out/sim.log" | head -3)"
  rm -f "/dev/shm/$tag-filler".*
  # 2. Running: the frame ring truncated while /dev/shm is full.
  start_sim
  for ((i = 0; i < 100; i++)); do h0=$(ring_head); ((${h0:-0} >= 2)) && break; sleep 0.1; done
  fill_shm
  lines0=$(wc -l <"$out/sim.log") at0=$(grep -c 'attached to ring' "$out/node.$inc.log")
  truncate -s 4096 "/dev/shm$(seg_name ring)"
  fill_shm # the truncation gave its pages back
  sleep 2
  lines=$(($(wc -l <"$out/sim.log") - lines0))
  at=$(($(grep -c 'attached to ring' "$out/node.$inc.log") - at0))
  alive "$simpid" || hostile_fail shmfull "the simulator stopped when /dev/shm was full"
  tail -n "+$((lines0 + 1))" "$out/sim.log" | grep -q 'no space left in /dev/shm' ||
    hostile_fail shmfull "the simulator did not say /dev/shm is full when its ring could not be replaced; its log: $(tail -n "+$((lines0 + 1))" "$out/sim.log" | head -3)"
  ((lines <= 10)) || hostile_fail shmfull "the simulator logged $lines lines in about 3 s of a full /dev/shm"
  ((at <= 3)) || hostile_fail shmfull "the node attached to the frame ring $at times in about 3 s of a full /dev/shm"
  rm -f "/dev/shm/$tag-filler".*
  h0=$(ring_head)
  for ((i = 0; i < 150; i++)); do h=$(ring_head); ((${h:-0} > ${h0:-0} + 1)) && break; sleep 0.1; done
  ((${h:-0} > ${h0:-0} + 1)) || hostile_fail shmfull "no frames flowed within 15 s of /dev/shm having room again"
  term_node shmfull
}
# A forged pose line stamped a day ahead on vlff-pose's UDP socket, between the
# tracker's lines (UNIX time, as a VIO SDK sends them): before, every line after
# it was refused as out of order for good.
pose=$build/drivers/pose/vlff-pose
hostile_pose() {
  local port=$((20000 + $$ % 20000)) pid i head0 head sent=0
  "$pose" -c "$out/chaos.yaml" --udp "127.0.0.1:$port" --clock realtime 2>>"$out/pose.log" &
  pid=$!
  for ((i = 0; i < 50; i++)); do grep -q "127.0.0.1:$port" "$out/pose.log" 2>/dev/null && break; sleep 0.1; done
  head0=$("$shm" stat "$(seg_name pose_ring)" 2>/dev/null | awk '$1 == "head" { print $2 }')
  for ((i = 0; i < 30; i++)); do
    if ((i == 5)); then
      echo "$(awk -v t="$(now)" 'BEGIN { printf "%.6f", t + 86400 }') 0 0 0 0 0 0 1" >"/dev/udp/127.0.0.1/$port"
    fi
    echo "$(now) 0.$i 0 0 0 0 0 1" >"/dev/udp/127.0.0.1/$port"
    sent=$((sent + 1))
    sleep 0.02
  done
  sleep 0.3
  head=$("$shm" stat "$(seg_name pose_ring)" 2>/dev/null | awk '$1 == "head" { print $2 }')
  kill -TERM "$pid" 2>/dev/null; gone "$pid"
  ((${head:-0} - ${head0:-0} >= sent)) ||
    hostile_fail pose "$((${head:-0} - ${head0:-0})) poses reached the ring of $sent legitimate lines; vlff-pose: $(tail -2 "$out/pose.log" | tr '\n' ' ')"
  term_node pose
}
hostile_case() {
  hostile_cases=$((hostile_cases + 1))
  hostile[$1]=$((hostile[$1] + 1))
  echo "chaos: hostile $1 (after $kills kills)"
  "hostile_$1"
}
rounds=${VLFF_CHAOS_HOSTILE_ROUNDS:-$((target < 50 ? 1 : 2))}
plan=()
for ((r = 0; r < rounds; r++)); do
  plan+=(fifo mailbox pose)
  ((private_shm)) && plan+=(shmfull)
done
((rounds > 0 && !private_shm)) && echo "chaos: no private /dev/shm (needs root and unshare -m): the shmfull case is left out"
next_hostile=0

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
  # The hostile cases, spread evenly over the kills, each once the node has
  # recovered from whatever came before.
  if ((next_hostile < ${#plan[@]} && !pending && kills >= target * (next_hostile + 1) / (${#plan[@]} + 1))); then
    hostile_case "${plan[next_hostile]}"
    next_hostile=$((next_hostile + 1))
    next_kill=$(later "$(now)")
    continue
  fi
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
for ((i = 0; i < 600; i++)); do grep -q "waiting for ring\|attached to ring" "$out/node.$inc.log" 2>/dev/null && break; sleep 0.1; done
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
sig_p99=$(printf '%s\n' "${sigterm_times[@]}" | sort -g | awk '{ a[NR] = $1 } END { if (!NR) { print "nan"; exit }
  i = int(0.99 * NR + 0.999999); if (i < 1) i = 1; print a[i] }')
echo "chaos: hostile fifo ${hostile[fifo]}, mailbox ${hostile[mailbox]}, shmfull ${hostile[shmfull]}, pose ${hostile[pose]}; SIGTERM to exit: ${sigterm_times[*]:-none} s"
echo "RESULT kills=$kills torn_reads=$torn lost_versions=$lost leaked_files=$leaked recovery_p99_s=$p99 quality_drops=$quality_drops quality_checked=$quality_checked cold_start_s=$cold recovery_vs_cold_start=$ratio hostile_cases=$hostile_cases hostile_failures=$hostile_failures sigterm_p99_s=$sig_p99"
((next_hostile == ${#plan[@]})) || { echo "chaos.sh: only $next_hostile of ${#plan[@]} hostile cases ran" >&2; exit 1; }
((hostile_failures == 0)) || { echo "chaos.sh: $hostile_failures hostile cases broke the node or its inputs" >&2; exit 1; }
awk -v p="$sig_p99" 'BEGIN { exit !(p == "nan" || p <= 5) }' || { echo "chaos.sh: SIGTERM took $sig_p99 s at p99 (over 5 s)" >&2; exit 1; }
[[ $final_post == accepted* ]] || { echo "chaos.sh: the mailbox did not answer after the chaos" >&2; exit 1; }
((quality_checked > 0)) || { echo "chaos.sh: no restart's quality was compared with its checkpoint's" >&2; exit 1; }
((torn == 0 && lost == 0 && leaked == 0 && quality_drops == 0 && unrecovered == 0 && kills >= target))
