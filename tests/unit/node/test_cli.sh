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
# --check-config refuses what start-up refuses (the shipped configs: test_configs).
check "--check-config: the rig defaults need a text encoder" \
  '! "${node[@]}" --check-config "$src/configs/default.yaml" >/dev/null 2>"$tmp/dc.err" && grep -q "default.yaml: no text encoder for the prompts: set prompts.embeddings" "$tmp/dc.err"'
# The defaults describe a rig: without a text encoder for the prompts the
# node refuses to start, saying so, before it makes any segment.
sed -e "s#\"/var/lib/vlff\"#\"$tmp/state\"#; s#\"/vlff-#\"/cli-$$-#" "$src/configs/default.yaml" >"$tmp/rig.yaml"
check "the rig defaults need a text encoder" \
  '! timeout 20 "${node[@]}" --config "$tmp/rig.yaml" >/dev/null 2>"$tmp/rig.err" && grep -q "no text encoder for the prompts" "$tmp/rig.err" && ! ls /dev/shm/cli-$$-* >/dev/null 2>&1'
printf 'source:\n  kind: ring\n  features: sim\n' >"$tmp/simfeat.yaml"
check "sim features with a camera ring are a config error" \
  '! "${node[@]}" --check-config "$tmp/simfeat.yaml" >/dev/null 2>"$tmp/sf.err" && grep -q "simfeat.yaml:3:13: key .source.features.: sim features" "$tmp/sf.err"'
printf 'node:\n  log_level: info\ntrain:\n  lr: fast\n' >"$tmp/bad.yaml"
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
# A field larger than the machine: create wrote every byte of it (48 GiB for
# these tables alone, terabytes for the step buffers) and the OOM killer
# ended the node, or a neighbour. Refused before anything is allocated.
printf 'field:\n  hash_levels: 32\n  hash_log2_size: 24\n  hash_features: 8\ntrain:\n  rays_per_step: 1048576\n  samples_per_ray: 4096\nshm:\n  ring: /cli-%s-hr\n  map: /cli-%s-hm\n  prompts: /cli-%s-hp\n' $$ $$ $$ >"$tmp/huge.yaml"
check "a field larger than memory refused by --check-config, naming the keys" \
  'timeout 20 "${node[@]}" --check-config "$tmp/huge.yaml" >/dev/null 2>"$tmp/err"; [[ $? == 1 ]] && grep -q "huge.yaml: field: the model and its step buffers need [0-9.]* GiB (field.hash_levels 32 .*train.rays_per_step 1048576 x train.samples_per_ray 4096 .*more than this machine" "$tmp/err"'
check "a field larger than memory refused at start, before any segment" \
  'timeout 20 "${node[@]}" --config "$tmp/huge.yaml" >/dev/null 2>"$tmp/err"; [[ $? == 1 ]] && grep -q "more than this machine" "$tmp/err" && ! ls /dev/shm/cli-$$-h* >/dev/null 2>&1'
# --snapshot DIR is checked at start: a file there, or a missing parent, was
# found only when the run ended (the node here would wait for its ring).
touch "$tmp/snapfile"
check "--snapshot on a file refused at start" \
  'timeout 20 "${node[@]}" --config "$tmp/ok.yaml" --snapshot "$tmp/snapfile" >/dev/null 2>"$tmp/err"; [[ $? == 2 ]] && grep -q -- "--snapshot .*snapfile.: exists and is not a directory" "$tmp/err"'
check "--snapshot under a missing directory refused at start" \
  'timeout 20 "${node[@]}" --config "$tmp/ok.yaml" --snapshot "$tmp/no/such" >/dev/null 2>"$tmp/err"; [[ $? == 2 ]] && grep -q "its parent .*/no is not a directory" "$tmp/err"'
mkfifo "$tmp/fifo.yaml"
check "a FIFO as config refused, not waited on" \
  'timeout 20 "${node[@]}" --check-config "$tmp/fifo.yaml" >/dev/null 2>"$tmp/err"; [[ $? == 1 ]] && grep -q "fifo.yaml: is a FIFO, expected a regular file" "$tmp/err"'
printf 'prompts:\n  embeddings: %s/none.txt\n' "$tmp" >"$tmp/emb.yaml"
check "--check-config loads prompts.embeddings" \
  '! "${node[@]}" --check-config "$tmp/emb.yaml" >/dev/null 2>"$tmp/err" && grep -q "emb.yaml: key .prompts.embeddings.: .*none.txt: cannot open" "$tmp/err"'
printf 'shm:\n  group: vlff-no-such-group\n' >"$tmp/grp.yaml"
check "--check-config checks that shm.group exists" \
  '! "${node[@]}" --check-config "$tmp/grp.yaml" >/dev/null 2>"$tmp/err" && grep -q "grp.yaml: key .shm.group.: no group .vlff-no-such-group." "$tmp/err"'
printf 'source:\n  kind: sim\nshm:\n  group: "0"\n' >"$tmp/gid.yaml"
check "--check-config takes a numeric shm.group" '"${node[@]}" --check-config "$tmp/gid.yaml" >/dev/null 2>&1'
# Every prompt of every set must be in the embeddings file, as start-up
# needs the active set's and a controller may select another.
{ printf 'vlff-embeddings 1\ndim 8\n'; for p in wall floor; do printf '%s\t1 0 0 0 0 0 0 0\n' "$p"; done; } >"$tmp/emb8.txt"
printf 'field:\n  feature_dim: 8\nprompts:\n  embeddings: %s/emb8.txt\n  sets:\n    - name: a\n      prompts: [wall, floor]\n    - name: b\n      prompts: [floor, sofa]\n' "$tmp" >"$tmp/emb8.yaml"
check "--check-config: a prompt of another set not in prompts.embeddings" \
  '! "${node[@]}" --check-config "$tmp/emb8.yaml" >/dev/null 2>"$tmp/err" && grep -q "emb8.yaml: key .prompts.embeddings.: prompt .sofa. of set .b. is not in .*emb8.txt" "$tmp/err"'
sed -i 's/\[floor, sofa\]/[floor]/' "$tmp/emb8.yaml"
check "--check-config: every prompt in prompts.embeddings" '"${node[@]}" --check-config "$tmp/emb8.yaml" >/dev/null 2>"$tmp/err" || { cat "$tmp/err"; false; }'
# Without prompts.sets the file defines the prompts (start-up adopts its
# records), so the default sets' prompts need not be in it.
printf 'field:\n  feature_dim: 8\nprompts:\n  embeddings: %s/emb8.txt\n' "$tmp" >"$tmp/emb8only.yaml"
check "--check-config: prompts.embeddings without prompts.sets defines the prompts" \
  '"${node[@]}" --check-config "$tmp/emb8only.yaml" >/dev/null 2>"$tmp/err" || { cat "$tmp/err"; false; }'
# The text encoder's files are named by their keys.
printf 'vlm:\n  text_model: %s/none.onnx\n' "$tmp" >"$tmp/tm.yaml"
check "--check-config: a missing vlm.text_model" \
  '! "${node[@]}" --check-config "$tmp/tm.yaml" >/dev/null 2>"$tmp/err" && grep -qE "tm.yaml: (key .vlm.text_model.: .*none.onnx: cannot open|vlm.text_model: this vlff-node was built without OpenCV)" "$tmp/err"'
mkdir -p "$tmp/fstate"
mkfifo "$tmp/fstate/field.1.ckpt"
(exit 0) & dead=$!; wait $dead
: >"$tmp/fstate/field.0.ckpt.tmp.$dead"
: >"$tmp/fstate/map.1.obs.tmp.$dead"
printf 'node:\n  state_dir: %s/fstate\nsource:\n  kind: sim\nsim:\n  frames: 20\nshm:\n  ring: /cli-%s-r\n  map: /cli-%s-m\n  prompts: /cli-%s-p\n' "$tmp" $$ $$ $$ >"$tmp/fifo-state.yaml"
timeout 60 "${node[@]}" --config "$tmp/fifo-state.yaml" 2>"$tmp/log.fifo" & pid=$!
for ((i = 0; i < 200; i++)); do grep -q "waiting for ring" "$tmp/log.fifo" && break; sleep 0.1; done
check "a FIFO checkpoint does not block start-up" 'grep -q "waiting for ring" "$tmp/log.fifo"'
check "the FIFO checkpoint is refused and named" 'grep -q "field.1.ckpt: is a FIFO, expected a regular file" "$tmp/log.fifo"'
check "a dead writer's checkpoint temporaries are removed" \
  '[[ ! -e "$tmp/fstate/field.0.ckpt.tmp.$dead" && ! -e "$tmp/fstate/map.1.obs.tmp.$dead" ]]'
kill -TERM $pid; wait $pid; rc=$?
check "and it stops on SIGTERM (rc=$rc)" '[[ $rc == 0 ]]'
# A hang-up stops it as cleanly (its default action killed the node with no
# log line and no checkpoint: status 129). Where this shell was started with
# SIGHUP ignored (nohup), the node keeps it ignored, as it should, and the
# case cannot be run.
if (( 0x$(sed -n 's/^SigIgn:[[:space:]]*//p' /proc/$$/status) & 1 )); then
  echo "skip: SIGHUP is ignored in this environment (nohup): the hang-up case is not run"
else
  timeout 60 "${node[@]}" --config "$tmp/fifo-state.yaml" 2>"$tmp/log.hup" & pid=$!
  for ((i = 0; i < 200; i++)); do grep -q "waiting for ring" "$tmp/log.hup" && break; sleep 0.1; done
  kill -HUP $pid; wait $pid; rc=$?
  check "it stops on SIGHUP, exit 0, said (rc=$rc)" '[[ $rc == 0 ]] && grep -q "stopping (SIGHUP)" "$tmp/log.hup"'
fi
# No silent defaults: without --config, $VLFF_CONFIG is used, and with neither
# (and no installed vlff.yaml) the node refuses to start.
def=$("${node[@]}" --help | sed -n 's/.*then \(.*vlff\.yaml\); none found.*/\1/p')
if [[ -n "$def" && ! -e "$def" ]]; then
  check "no config: exits 1 naming the search path" \
    'env -u VLFF_CONFIG "${node[@]}" >/dev/null 2>"$tmp/nocfg"; [[ $? == 1 ]] && grep -q "no config: .*VLFF_CONFIG.*$def" "$tmp/nocfg"'
else
  echo "note: $def exists here; the no-config refusal is not checked"
fi
VLFF_CONFIG="$tmp/ok.yaml" timeout 20 "${node[@]}" 2>"$tmp/env" & p=$!
for ((i = 0; i < 100; i++)); do grep -qs "waiting for ring" "$tmp/env" && break; sleep 0.1; done
# The segments' group reads the map and posts prompts: map 0640, mailbox 0660.
check "map segment is 0640" '[[ "$(stat -c %a /dev/shm/cli-$$-m)" == 640 ]]'
check "prompt mailbox is 0660 (group posts prompts)" '[[ "$(stat -c %a /dev/shm/cli-$$-p)" == 660 ]]'
kill -TERM $p; wait $p
check "\$VLFF_CONFIG is the config" 'grep -q "config $tmp/ok.yaml" "$tmp/env"'

# An idle node (no frames, nothing learned) writes no checkpoint, however
# often its period comes round, nor on exit.
mkdir -p "$tmp/state"
sed "s|state_dir: $tmp|state_dir: $tmp/state\n  checkpoint_period_s: 0.2|" "$tmp/ok.yaml" >"$tmp/idle.yaml"
"${node[@]}" --config "$tmp/idle.yaml" 2>"$tmp/idle" & p=$!
for ((i = 0; i < 100; i++)); do grep -qs "waiting for ring" "$tmp/idle" && break; sleep 0.1; done
sleep 1.5
kill -TERM $p; wait $p
check "idle node wrote no checkpoint" '[[ -z "$(ls -A "$tmp/state")" ]]'

# Under systemd (Type=notify): READY=1, WATCHDOG=1 while both threads loop,
# STOPPING=1; received on a notify socket of our own.
if "${node[@]}" --help >/dev/null && [[ -z "${VLFF_EMULATOR:-}" ]] && command -v /usr/bin/python3 >/dev/null &&
   grep -q "sd_notify" "$(command -v "${node[-1]}")" 2>/dev/null; then
  /usr/bin/python3 "$src/tests/common/notify_listen.py" "$tmp/notify.sock" "$tmp/notify.log" 15 & listener=$!
  for ((i = 0; i < 50; i++)); do [[ -S "$tmp/notify.sock" ]] && break; sleep 0.1; done
  NOTIFY_SOCKET="$tmp/notify.sock" WATCHDOG_USEC=2000000 "${node[@]}" --config "$tmp/ok.yaml" 2>"$tmp/sd" & p=$!
  # the main loop starts after the node is up (slow under sanitizers), then
  # feeds the watchdog every quarter period
  for ((i = 0; i < 300; i++)); do grep -qs "waiting for ring" "$tmp/sd" && break; sleep 0.1; done
  sleep 1.5
  kill -TERM $p; wait $p
  wait $listener
  check "sd_notify READY=1" 'grep -qx "READY=1" "$tmp/notify.log"'
  check "sd_notify WATCHDOG=1 while the threads loop" 'grep -qx "WATCHDOG=1" "$tmp/notify.log"'
  check "sd_notify STOPPING=1" 'grep -qx "STOPPING=1" "$tmp/notify.log"'
  # A thread that makes no progress stops the feeding while the main loop
  # goes on: each thread in turn is frozen alone with ptrace, as a deadlock or
  # a driver call that never returns would leave it (watchdog_stall.py). The
  # node has no blocking wait to stall it with: every wait it makes has a
  # timeout, FIFOs are refused, the mailbox lock is never waited for.
  for t in vlff-trainer vlff-ingest; do
    /usr/bin/python3 "$src/tests/unit/node/watchdog_stall.py" "${node[-1]}" "$tmp/ok.yaml" $t "$tmp" >"$tmp/stall.$t" 2>&1
    rc=$?
    if [[ $rc == 77 ]]; then
      cat "$tmp/stall.$t"
    else
      check "watchdog not fed while $t is frozen, fed again after" '[[ $rc == 0 ]] || { cat "$tmp/stall.$t"; false; }'
    fi
  done
else
  echo "note: this vlff-node has no sd_notify (built without libsystemd) or runs emulated; notify not checked"
fi
echo "$passes passed, $fails failed"
rm -f /dev/shm/cli-$$-*
(( fails == 0 ))
