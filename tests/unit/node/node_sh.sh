# Sourced by the node's shell tests that run the default node (test_node_mailbox.sh,
# test_node_status.sh, test_node_rings.sh, ...): sh_kit.sh's helpers and a
# vlff-node started on the simulator source in the background ($nodepid).
# stop_node stops the node with SIGTERM and checks that it exits 0.
# Usage: . node_sh.sh PREFIX NODE SHM SIM
node=$2 shm=$3 sim=$4
. "$(dirname "${BASH_SOURCE[0]}")/sh_kit.sh" "$1"
stop_node() {
  local rc
  kill -TERM "$nodepid"; wait "$nodepid"; rc=$?; nodepid=
  check "node exits 0 on SIGTERM (rc=$rc)" "[[ $rc == 0 ]]"
}
# More keys under shm: from the sourcing test (node_shm_extra, indented).
printf 'node:\n  state_dir: %s\nsource:\n  kind: sim\nsim:\n  frames: 20\n  rate_hz: 10\nshm:\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\n  feature_ring: %s-f\n%s' \
  "$tmp" $p $p $p $p "${node_shm_extra:+$node_shm_extra$'\n'}" >"$tmp/n.yaml"
# A light field (64-dim features, a 2^16 table) unless the test names its own
# (node_field; empty for the default field): these tests check the node's
# plumbing, not what it learns, and a sanitizer build trains and publishes the
# default 512 dimensions slowly.
printf '%s\n' "${node_field-$'field:\n  feature_dim: 64\n  hash_log2_size: 16'}" >>"$tmp/n.yaml"
# More top-level YAML from the sourcing test, before the node starts; and
# more options (node_args, e.g. --status).
[[ -n ${node_yaml_extra:-} ]] && printf '%s\n' "$node_yaml_extra" >>"$tmp/n.yaml"
"$node" --config "$tmp/n.yaml" ${node_args:-} 2>"$tmp/log" &
nodepid=$!
