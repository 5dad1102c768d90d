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
# Hostile configs and state (issue 29): refused with file:line, never waited on.
printf 'shm:\n  map: /x\n  prompts: /x\n' >"$tmp/same.yaml"
check "shm.map == shm.prompts refused with file:line" \
  '! "${node[@]}" --check-config "$tmp/same.yaml" >/dev/null 2>"$tmp/err" && grep -q "same.yaml:3:12: key .shm.prompts.: expected a segment name distinct from shm.map" "$tmp/err"'
printf 'shm:\n  ring: no-slash\n' >"$tmp/slash.yaml"
check "ring without a slash refused with file:line" \
  '! "${node[@]}" --check-config "$tmp/slash.yaml" >/dev/null 2>"$tmp/err" && grep -q "slash.yaml:2:9: key .shm.ring.: expected a POSIX shared-memory name" "$tmp/err"'
python3 -c "print('node: '+'['*100000+']'*100000)" >"$tmp/deep.yaml"
check "100000-deep YAML refused at once" \
  'timeout 20 "${node[@]}" --check-config "$tmp/deep.yaml" >/dev/null 2>"$tmp/err"; [[ $? == 1 ]] && grep -q "deep.yaml:1:38: nesting deeper than 32 levels" "$tmp/err"'
mkfifo "$tmp/fifo.yaml"
check "a FIFO as config refused, not waited on" \
  'timeout 20 "${node[@]}" --check-config "$tmp/fifo.yaml" >/dev/null 2>"$tmp/err"; [[ $? == 1 ]] && grep -q "fifo.yaml: is a FIFO, expected a regular file" "$tmp/err"'
mkdir -p "$tmp/state"
mkfifo "$tmp/state/field.1.ckpt"
(exit 0) & dead=$!; wait $dead
: >"$tmp/state/field.0.ckpt.tmp.$dead"
: >"$tmp/state/map.1.obs.tmp.$dead"
printf 'node:\n  state_dir: %s/state\nsource:\n  kind: sim\nsim:\n  frames: 20\nshm:\n  ring: /cli-%s-r\n  map: /cli-%s-m\n  prompts: /cli-%s-p\n' "$tmp" $$ $$ $$ >"$tmp/fifo-state.yaml"
timeout 60 "${node[@]}" --config "$tmp/fifo-state.yaml" 2>"$tmp/log.fifo" & pid=$!
for ((i = 0; i < 200; i++)); do grep -q "waiting for ring" "$tmp/log.fifo" && break; sleep 0.1; done
check "a FIFO checkpoint does not block start-up" 'grep -q "waiting for ring" "$tmp/log.fifo"'
check "the FIFO checkpoint is refused and named" 'grep -q "field.1.ckpt: is a FIFO, expected a regular file" "$tmp/log.fifo"'
check "a dead writer's checkpoint temporaries are removed" \
  '[[ ! -e "$tmp/state/field.0.ckpt.tmp.$dead" && ! -e "$tmp/state/map.1.obs.tmp.$dead" ]]'
kill -TERM $pid; wait $pid; rc=$?
check "and it stops on SIGTERM (rc=$rc)" '[[ $rc == 0 ]]'
echo "$passes passed, $fails failed"
rm -f /dev/shm/cli-$$-*
(( fails == 0 ))
