#!/usr/bin/env bash
# node.cpu_budget (issue 49): the node keeps its CPU use with its own threads.
# A node given 4 threads and a budget of 1.5 cores starts a pool of 2 (one
# vlff-pool worker beside the trainer); one given 0.5 starts none, shows the
# budget and its measured use in the map's status and on --status, and while it learns from
# vlff-sim its process uses at most 1.3 x the budget (its own CPU time from
# /proc, over a few seconds of training; generous, not timed: a loaded host
# only makes the node use less).
# Usage: test_node_budget.sh NODE SHM SIM
set -u
node=$1 shm=$2 sim=$3
. "$(dirname "$0")/sh_kit.sh" nbg
val() { awk -v k="$1" '$1 == k { print $2 }' "$tmp/stat"; }
pool_threads() { grep -lx vlff-pool /proc/"$1"/task/*/comm 2>/dev/null | wc -l; }
cfg() {  # cfg BUDGET
  printf 'node:\n  state_dir: %s\n  threads: 4\n  cpu_budget: %s\n  checkpoint_period_s: 0\nsource:\n  kind: sim\n' "$tmp" "$1"
  printf 'sim:\n  frames: 20\n  rate_hz: 10\nshm:\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\n  feature_ring: %s-f\n' $p $p $p $p
}

# 1.5 cores: the pool is ceil(1.5) = 2 threads, not node.threads' 4. The pool
# exists once the map segment does (the field is made first).
cfg 1.5 >"$tmp/a.yaml"
: >"$tmp/log"  # now: the background redirection may come after the first wait reads it
"$node" --config "$tmp/a.yaml" 2>"$tmp/log" &
nodepid=$!
wait_until 300 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null && [[ -n $(val cpu_budget) ]]'
check "budget 1.5, threads 4: one pool worker ($(pool_threads $nodepid))" '[[ $(pool_threads $nodepid) == 1 ]]'
check "budget 1.5 on the map's status ($(val cpu_budget))" '[[ $(val cpu_budget) == 1.500 ]]'
kill -TERM $nodepid; wait $nodepid; nodepid=
rm -f /dev/shm$p-*

cfg 0.5 >"$tmp/b.yaml"
: >"$tmp/log"  # now: the background redirection may come after the first wait reads it
"$node" --config "$tmp/b.yaml" --status 2>"$tmp/log" &
nodepid=$!
wait_until 300 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null && [[ -n $(val cpu_budget) ]]'
check "budget 0.5, threads 4: no pool worker ($(pool_threads $nodepid))" '[[ $(pool_threads $nodepid) == 0 ]]'
"$sim" --config "$tmp/b.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 1200 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null; [[ $(val iterations) -gt 0 ]] 2>/dev/null'
check "the node learns under its budget ($(val iterations) iterations)" '[[ $(val iterations) -gt 0 ]]'
# The process's own CPU time (utime + stime, the clock ticks getrusage reports
# at exit) over 4 s of learning.
ticks() { awk '{ print $14 + $15 }' /proc/"$nodepid"/stat; }
hz=$(getconf CLK_TCK)
c0=$(ticks) t0=$(date +%s.%N)
sleep 4
c1=$(ticks) t1=$(date +%s.%N)
used=$(awk -v c="$((c1 - c0))" -v hz="$hz" -v a="$t0" -v b="$t1" 'BEGIN { printf "%.3f", c / hz / (b - a) }')
check "process CPU over 4 s: $used cores, at most 1.3 x 0.5" "awk -v u=$used 'BEGIN { exit !(u <= 0.65) }'"
check "--status shows the use against the budget" 'grep -aq "| cpu [0-9]*\.[0-9]* of 0.50 |" "$tmp/log"'
check "--status shows the memory against its limits" 'grep -aq "| mem kf [0-9]*/1024 ev [0-9]*/64 rss [0-9]* MiB |" "$tmp/log"'
"$shm" stat $p-m >"$tmp/stat"
check "the map's status: budget $(val cpu_budget), use $(val cpu_used) in (0, 1.3 x budget]" \
  "[[ \$(val cpu_budget) == 0.500 ]] && awk -v u=\$(val cpu_used) 'BEGIN { exit !(u > 0 && u <= 0.65) }'"
kill "$simpid"; wait "$simpid"; simpid=
kill -TERM $nodepid; wait $nodepid; rc=$?; nodepid=
check "node exits 0 on SIGTERM (rc=$rc)" "[[ $rc == 0 ]]"
verdict
