# Sourced by the node's shell tests: the check counter, a poll (wait_until),
# a scratch directory ($tmp), segments named /<prefix>-$$-* ($p), a cleanup
# on exit that stops $simpid and $nodepid when set and removes both, and
# verdict, which prints the counts (and the tail of $tmp/log on a failure)
# and is the script's last command. Usage: . sh_kit.sh PREFIX
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
verdict() {
  echo "$passes passed, $fails failed"
  (( fails == 0 )) || { echo "--- node log"; tail -30 "$tmp/log"; }
  (( fails == 0 ))
}
