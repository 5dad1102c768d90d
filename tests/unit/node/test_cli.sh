#!/usr/bin/env bash
# vlff-node's command line: version, help, config checking, clean exit on signals.
set -u
# VLFF_EMULATOR: qemu-user in a cross-built tree (word-split on purpose)
# shellcheck disable=SC2206
node=(${VLFF_EMULATOR:-} "$1")
src=$2
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT

check "--version" '"${node[@]}" --version | grep -qE "^vlff-node [0-9]+\.[0-9]+\.[0-9]+$"'
check "--help lists --check-config" '"${node[@]}" --help | grep -q -- "--check-config"'
check "bad option exits 2" '"${node[@]}" --bogus >/dev/null 2>&1; [[ $? == 2 ]]'
check "default.yaml checks" '"${node[@]}" --check-config "$src/configs/default.yaml" >/dev/null 2>&1'
# The defaults describe a rig: without a text encoder for the prompts the
# node refuses to start, saying so, before it makes any segment.
sed -e "s#\"/var/lib/vlff\"#\"$tmp/state\"#; s#\"/vlff-#\"/cli-$$-#" "$src/configs/default.yaml" >"$tmp/rig.yaml"
check "the rig defaults need a text encoder" \
  '! timeout 20 "${node[@]}" --config "$tmp/rig.yaml" >/dev/null 2>"$tmp/rig.err" && grep -q "no text encoder for the prompts" "$tmp/rig.err" && ! ls /dev/shm/cli-$$-* >/dev/null 2>&1'
printf 'source:\n  kind: ring\n  features: sim\n' >"$tmp/simfeat.yaml"
check "sim features with a camera ring are a config error" \
  '! "${node[@]}" --check-config "$tmp/simfeat.yaml" >/dev/null 2>"$tmp/sf.err" && grep -q "simfeat.yaml:3:13: key .source.features.: sim features" "$tmp/sf.err"'
printf 'node:\n  name: x\ntrain:\n  lr: fast\n' >"$tmp/bad.yaml"
check "bad config exits 1 with file:line:col" \
  '! "${node[@]}" --check-config "$tmp/bad.yaml" >/dev/null 2>"$tmp/err" && grep -q "bad.yaml:4:7: key .train.lr.: expected number" "$tmp/err"'
check "bad --config refuses to start" '! "${node[@]}" --config "$tmp/bad.yaml" >/dev/null 2>&1'
for sig in INT TERM; do
  printf 'node:\n  state_dir: %s\nsource:\n  kind: sim\nsim:\n  frames: 20\nshm:\n  ring: /cli-%s-r\n  map: /cli-%s-m\n  prompts: /cli-%s-p\n' "$tmp" $$ $$ $$ >"$tmp/ok.yaml"
  "${node[@]}" --config "$tmp/ok.yaml" 2>"$tmp/log.$sig" &
  pid=$!
  for ((i = 0; i < 100; i++)); do grep -q "waiting for ring" "$tmp/log.$sig" && break; sleep 0.1; done
  kill -$sig $pid
  wait $pid
  rc=$?
  check "SIG$sig exits 0 (rc=$rc)" '[[ $rc == 0 ]]'
  check "SIG$sig logged" 'grep -q "stopping (SIG$sig)" "$tmp/log.$sig"'
done
JOURNAL_STREAM=1:2 timeout 20 "${node[@]}" --config "$tmp/ok.yaml" 2>"$tmp/j" & p=$!
for ((i = 0; i < 100; i++)); do grep -q "waiting for ring" "$tmp/j" && break; sleep 0.1; done
kill -TERM $p; wait $p
check "journald lines start with <6>" 'head -1 "$tmp/j" | grep -q "^<6>node: "'
echo "$passes passed, $fails failed"
rm -f /dev/shm/cli-$$-*
(( fails == 0 ))
