#!/usr/bin/env bash
# vlff-node --fresh (node.resume: false) for evaluations (issue 55: every run
# resumed the previous run's checkpoint from the shared state_dir). A node
# learns and checkpoints on SIGTERM; restarted with --fresh it removes that
# checkpoint and starts from step 0; restarted without it, it resumes this
# run's own checkpoint, never the removed one.
set -u
. "$(dirname "$0")/node_sh.sh" nfr "$@"
val() { awk -v k="$1" '$1 == k { print $2 }' "$tmp/stat"; }
learn() {  # sim frames until the node has trained, then both stop
  "$sim" --config "$tmp/n.yaml" --quiet 2>>"$tmp/simlog" &
  simpid=$!
  wait_until 1200 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null; [[ $(val iterations) -gt 0 ]] 2>/dev/null'
  kill "$simpid"; wait "$simpid"; simpid=
  stop_node
}
learn
first=$(ls "$tmp"/field.*.ckpt 2>/dev/null)
check "the first run checkpointed ($first)" '[[ -n $first ]]'
touch -d '2001-01-01' $first  # recognisable: a resume of it would log its name

: >"$tmp/log"  # now: the background redirection may come after the first wait reads it
"$node" --config "$tmp/n.yaml" --fresh 2>"$tmp/log" &
nodepid=$!
wait_until 300 'grep -q "fresh start" "$tmp/log"'
check "--fresh says so, naming state_dir" 'grep -q "fresh start (node.resume false): 1 checkpoint(s) in $tmp removed, not resumed" "$tmp/log"'
check "--fresh does not resume" '! grep -q "resumed from" "$tmp/log"'
check "the old checkpoint is gone" '[[ -z $(find "$tmp" -name "field.*.ckpt" ! -newermt 2002-01-01) ]]'
learn
check "the fresh run checkpointed at its own step count" 'grep -q "I node: checkpoint .* at step" "$tmp/log"'

: >"$tmp/log"  # now: the background redirection may come after the first wait reads it
"$node" --config "$tmp/n.yaml" 2>"$tmp/log" &
nodepid=$!
wait_until 300 'grep -q "resumed from\|waiting for ring" "$tmp/log"'
new=$(ls "$tmp"/field.*.ckpt)
check "without --fresh the node resumes the fresh run's checkpoint ($new)" 'grep -q "resumed from $new" "$tmp/log"'
stop_node
verdict
