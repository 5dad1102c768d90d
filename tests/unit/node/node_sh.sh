# Sourced by the node's shell tests (test_node_mailbox.sh, test_node_status.sh,
# test_node_rings.sh): the check counter, a poll (wait_until), a scratch
# directory, segments named /<prefix>-$$-*, and a vlff-node started on the
# simulator source in the background ($nodepid), all removed on exit.
# stop_node stops the node with SIGTERM and checks that it exits 0; verdict
# prints the counts (and the node log's tail on a failure) and is the
# script's last command. Usage: . node_sh.sh PREFIX NODE SHM SIM
node=$2 shm=$3 sim=$4
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
# wait_until N COND: evaluates COND every 0.1 s, N times at most, until it holds.
wait_until() { local k; for ((k = 0; k < $1; k++)); do eval "$2" && return 0; sleep 0.1; done; return 1; }
tmp=$(mktemp -d)
p=/$1-$$
cleanup() {
  [[ -n ${simpid:-} ]] && kill "$simpid" 2>/dev/null
  [[ -n ${nodepid:-} ]] && kill -9 "$nodepid" 2>/dev/null
  rm -rf "$tmp"
  rm -f /dev/shm$p-*
}
trap cleanup EXIT
stop_node() {
  local rc
  kill -TERM "$nodepid"; wait "$nodepid"; rc=$?; nodepid=
  check "node exits 0 on SIGTERM (rc=$rc)" "[[ $rc == 0 ]]"
}
verdict() {
  echo "$passes passed, $fails failed"
  (( fails == 0 )) || { echo "--- node log"; tail -30 "$tmp/log"; }
  (( fails == 0 ))
}
printf 'node:\n  state_dir: %s\nsource:\n  kind: sim\nsim:\n  frames: 20\n  rate_hz: 10\nshm:\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\n  feature_ring: %s-f\n' \
  "$tmp" $p $p $p $p >"$tmp/n.yaml"
"$node" --config "$tmp/n.yaml" 2>"$tmp/log" &
nodepid=$!
