#!/usr/bin/env bash
# Every shipped config (configs/*.yaml) through --check-config of each
# program that reads it. A config that runs as shipped is accepted; one that
# needs the user's files says so in a comment line
#   # Before use (PROGRAM): ... `key` ... `key` ...
# and PROGRAM's --check-config must refuse it naming one of those keys.
# Shipped configs name their files where the install puts them (/etc/vlff/);
# here those are the source tree's configs/.
# Usage: test_configs.sh SOURCE_DIR VLFF_NODE [VLFF_CAMD]
set -u
src=$1 node=$2 camd=${3:-}
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT

# The programs each config is for. rgbd-calibration.yaml is no config: the
# calibration aravis-rgbd.yaml names, checked through vlff-camd's check of it.
declare -A programs=(
  [vlff.yaml]="vlff-node vlff-camd"
  [default.yaml]="vlff-node"
  [demo-sim.yaml]="vlff-node"
  [aravis-gige.yaml]="vlff-node vlff-camd"
  [aravis-rgbd.yaml]="vlff-node vlff-camd"
  [libcamera.yaml]="vlff-node vlff-camd"
  [rgbd-calibration.yaml]=""
)
declare -A path=([vlff-node]=$node [vlff-camd]=$camd)

for f in "$src"/configs/*.yaml; do
  c=$(basename "$f")
  check "$c: the test knows which programs read it" '[[ -v "programs[$c]" ]]'
  [[ -v "programs[$c]" ]] || continue
  sed "s#/etc/vlff/#$src/configs/#g" "$f" >"$tmp/$c"
  for p in ${programs[$c]}; do
    if [[ -z "${path[$p]}" ]]; then
      echo "note: $p not built; $c not checked with it"
      continue
    fi
    # VLFF_EMULATOR: qemu-user in a cross-built tree (word-split on purpose)
    # shellcheck disable=SC2206
    prog=(${VLFF_EMULATOR:-} "${path[$p]}")
    "${prog[@]}" --check-config "$tmp/$c" >/dev/null 2>"$tmp/err"; rc=$?
    if grep -qE "this build has no|was built without" "$tmp/err"; then
      echo "note: $p: $(cat "$tmp/err")"
      continue
    fi
    note=$(grep "^# Before use ($p):" "$f")
    if [[ -z "$note" ]]; then
      check "$p --check-config $c: accepted (rc=$rc)" '[[ $rc == 0 ]] || { cat "$tmp/err"; false; }'
      continue
    fi
    mapfile -t keys < <(grep -o '`[a-z_.]*`' <<<"$note" | tr -d '`')
    named=0
    for k in "${keys[@]}"; do grep -qF "$k" "$tmp/err" && named=1; done
    check "$p --check-config $c: refused (rc=$rc), naming one of '${keys[*]}' as its comment says" \
      '[[ $rc == 1 && ${#keys[@]} -gt 0 && $named == 1 ]] || { cat "$tmp/err"; false; }'
  done
done
echo "$passes passed, $fails failed"
(( fails == 0 ))
