#!/usr/bin/env bash
# vlff-pose's command line: help, version, usage errors, refusals reported
# with their line numbers, and the records it writes (read back with vlff-shm).
set -u
# VLFF_EMULATOR: qemu-user in a cross-built tree (word-split on purpose)
# shellcheck disable=SC2206
pose=(${VLFF_EMULATOR:-} "$1")
shm=(${VLFF_EMULATOR:-} "$2")
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
tmp=$(mktemp -d); ring=/pcli-$$; trap 'rm -rf "$tmp"; rm -f /dev/shm${ring}' EXIT

check "--help to stdout, exit 0" '"${pose[@]}" --help >"$tmp/h" 2>/dev/null && grep -q -- "--udp ADDR:PORT" "$tmp/h"'
check "--version" '"${pose[@]}" --version | grep -qE "^vlff-pose [0-9]+\.[0-9]+\.[0-9]+$"'
"${pose[@]}" --bogus >"$tmp/o" 2>"$tmp/e"; rc=$?
check "unknown option exits 2 (rc=$rc)" '[[ $rc == 2 ]]'
check "unknown option: one line, then the usage, on stderr" \
  'head -1 "$tmp/e" | grep -q "bogus" && sed -n 2p "$tmp/e" | grep -q "^Usage: vlff-pose" && [[ ! -s "$tmp/o" ]]'
check "bad --extrinsic exits 2" '"${pose[@]}" --extrinsic "0 0 0 0 0 0 3" </dev/null >/dev/null 2>&1; [[ $? == 2 ]]'
check "bad --udp exits 1" '"${pose[@]}" --ring "$ring-u" --udp nowhere </dev/null >/dev/null 2>&1; [[ $? == 1 ]]'
check "missing file exits 1" '"${pose[@]}" --ring "$ring-m" "$tmp/none.txt" >/dev/null 2>&1; [[ $? == 1 ]]'
printf '# timestamp tx ty tz qx qy qz qw\n10.0 1 2 3 0 0 0 1\n10.0 1 2 3 0 0 0 1\n9.0 1 2 3 0 0 0 1\n10.5 1 2 3 0 0 0 2\n10.6 1 2 nan 0 0 0 1\n10.7 1 2 3\n11.0 4 5 6 0 0 0.7071068 0.7071068\n' >"$tmp/t.txt"
"${pose[@]}" --ring "$ring" <"$tmp/t.txt" >/dev/null 2>"$tmp/log"; rc=$?
check "stdin: exit 0 with refusals (rc=$rc)" '[[ $rc == 0 ]]'
check "duplicate named with its line" 'grep -q "stdin:3: refused, duplicate stamp" "$tmp/log"'
check "out of order named with its line" 'grep -q "stdin:4: refused, out of order" "$tmp/log"'
check "non-unit quaternion named with its line" 'grep -q "stdin:5: refused, non-unit quaternion" "$tmp/log"'
check "NaN named with its line" 'grep -q "stdin:6: refused, not finite: tz is nan" "$tmp/log"'
check "malformed named with its line" 'grep -q "stdin:7: refused, malformed: 4 fields, expected 8" "$tmp/log"'
check "summary" 'grep -q "2 poses written to $ring, 5 lines refused (malformed 1, not finite 1, non-unit quaternion 1, duplicate stamp 1, out of order 1)" "$tmp/log"'
check "the ring holds both records" '"${shm[@]}" stat "$ring" | grep -qx "head 2"'
echo "$passes passed, $fails failed"
(( fails == 0 ))
