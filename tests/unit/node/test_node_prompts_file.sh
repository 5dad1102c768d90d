#!/usr/bin/env bash
# An embeddings file given without prompts.sets defines the prompts, in its
# order, and the log says so (issue 55: the node took scannet20's names and
# looked each up in the file, so the map's label k matched the file's record
# k only by luck, and a file without "floor" could not start the node). With
# prompts.sets named the set applies and the log says that instead.
# Usage: test_node_prompts_file.sh NODE SHM SIM
set -u
node=$1 shm=$2 sim=$3
. "$(dirname "$0")/sh_kit.sh" npf
# three prompts, not in scannet20's order, one not in scannet20 at all
awk 'BEGIN { print "vlff-embeddings 1"; print "dim 16"; n = split("chair lamp wall", t, " ")
  for (k = 1; k <= n; k++) { v = ""; for (i = 1; i <= 16; i++) v = v (i > 1 ? " " : "") (i == k ? 1 : 0); print t[k] "\t" v } }' >"$tmp/emb.txt"
base() {
  printf 'node:\n  state_dir: %s\nsource:\n  kind: sim\nsim:\n  rate_hz: 10\n  width: 160\n  height: 120\nfield:\n  feature_dim: 16\n' "$tmp"
  printf 'shm:\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\n  feature_ring: %s-f\n' $p $p $p $p
  printf 'prompts:\n  embeddings: %s/emb.txt\n' "$tmp"
}
run_node() {
  : >"$tmp/log"  # now: the background redirection may come after the first wait reads it
  "$node" --config "$1" 2>"$tmp/log" &
  nodepid=$!
  "$sim" --config "$1" --quiet 2>"$tmp/simlog" &
  simpid=$!
  wait_until 900 '"$shm" stat $p-m >"$tmp/stat" 2>/dev/null && grep -q "^prompt 0 " "$tmp/stat"'
}
stop_node() {
  kill "$simpid"; wait "$simpid"; simpid=
  kill -TERM "$nodepid"; wait "$nodepid"; nodepid=
  rm -f /dev/shm$p-*
}

base >"$tmp/file.yaml"
run_node "$tmp/file.yaml"
check "the node starts on a file without scannet20's prompts" 'kill -0 $nodepid'
check "the map's prompts are the file's, in its order" \
  '[[ $(grep "^prompt " "$tmp/stat" | tr "\n" ,) == "prompt 0 chair,prompt 1 lamp,prompt 2 wall," ]]'
check "the log says the file defines the prompts" \
  'grep -q "prompts: the 3 of the embeddings file .*emb.txt, in its order (no prompts.sets" "$tmp/log"'
stop_node

{ base; printf '  sets:\n    - name: mine\n      prompts: [wall, chair]\n'; } >"$tmp/set.yaml"
run_node "$tmp/set.yaml"
check "with prompts.sets the set applies, in its order" \
  '[[ $(grep "^prompt " "$tmp/stat" | tr "\n" ,) == "prompt 0 wall,prompt 1 chair," ]]'
check "the log names the set and the file" "grep -q \"prompts: set 'mine' of prompts.sets (prompts.active 0); vectors from .*emb.txt\" \"\$tmp/log\""
stop_node

verdict
