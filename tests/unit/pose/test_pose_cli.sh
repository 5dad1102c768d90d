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
tmp=$(mktemp -d); ring=/pcli-$$; trap 'rm -rf "$tmp"; rm -f /dev/shm${ring}*' EXIT
printf 'shm:\n  pose_ring: %s\n' "$ring" >"$tmp/c.yaml"

check "--help to stdout, exit 0" '"${pose[@]}" --help >"$tmp/h" 2>/dev/null && grep -q -- "--udp ADDR:PORT" "$tmp/h"'
check "--version" '"${pose[@]}" --version | grep -qE "^vlff-pose [0-9]+\.[0-9]+\.[0-9]+$"'
"${pose[@]}" --bogus >"$tmp/o" 2>"$tmp/e"; rc=$?
check "unknown option exits 2 (rc=$rc)" '[[ $rc == 2 ]]'
check "unknown option: one line, then the usage, on stderr" \
  'head -1 "$tmp/e" | grep -q "bogus" && sed -n 2p "$tmp/e" | grep -q "^Usage: vlff-pose" && [[ ! -s "$tmp/o" ]]'
check "bad --extrinsic exits 2" '"${pose[@]}" --extrinsic "0 0 0 0 0 0 3" </dev/null >/dev/null 2>&1; [[ $? == 2 ]]'
check "bad --udp exits 1" '"${pose[@]}" -c "$tmp/c.yaml" --ring "$ring-u" --udp nowhere </dev/null >/dev/null 2>&1; [[ $? == 1 ]]'
# getaddrinfo binds port 99999 modulo 65536 while the log said 99999; 0 binds a random one
for p in 99999 0 +80 ""; do
  check "--udp port '$p' refused, exit 1" '"${pose[@]}" -c "$tmp/c.yaml" --ring "$ring-u" --udp "127.0.0.1:$p" </dev/null >/dev/null 2>"$tmp/pe"; [[ $? == 1 ]]'
done
check "--udp port named" 'grep -q "port .99999. is not 1..65535" <("${pose[@]}" -c "$tmp/c.yaml" --ring "$ring-u" --udp 127.0.0.1:99999 </dev/null 2>&1)'
check "--udp-peer port 99999 refused" '! "${pose[@]}" -c "$tmp/c.yaml" --ring "$ring-u" --udp 127.0.0.1:47999 --udp-peer 127.0.0.1:99999 </dev/null >/dev/null 2>&1'
check "--extrinsic beyond 1e4 m exits 2" '"${pose[@]}" --extrinsic "1e308 0 0 0 0 0 1" </dev/null >/dev/null 2>&1; [[ $? == 2 ]]'
check "missing file exits 1" '"${pose[@]}" -c "$tmp/c.yaml" --ring "$ring-m" "$tmp/none.txt" >/dev/null 2>&1; [[ $? == 1 ]]'
check "no config found exits 1" 'VLFF_CONFIG="$tmp/absent.yaml" "${pose[@]}" </dev/null >/dev/null 2>&1; [[ $? == 1 ]]'
printf '# timestamp tx ty tz qx qy qz qw\n10.0 1 2 3 0 0 0 1\n10.0 1 2 3 0 0 0 1\n9.0 1 2 3 0 0 0 1\n10.5 1 2 3 0 0 0 2\n10.6 1 2 nan 0 0 0 1\n10.7 1 2 3\n11.0 4 5 6 0 0 0.7071068 0.7071068\n11.5 1e300 0 0 0 0 0 1\n' >"$tmp/t.txt"
"${pose[@]}" --config "$tmp/c.yaml" <"$tmp/t.txt" >/dev/null 2>"$tmp/log"; rc=$?
check "stdin: exit 0 with refusals (rc=$rc)" '[[ $rc == 0 ]]'
check "duplicate named with its line" 'grep -q "stdin:3: refused, duplicate stamp" "$tmp/log"'
check "out of order named with its line" 'grep -q "stdin:4: refused, out of order" "$tmp/log"'
check "non-unit quaternion named with its line" 'grep -q "stdin:5: refused, non-unit quaternion" "$tmp/log"'
check "NaN named with its line" 'grep -q "stdin:6: refused, not finite: tz is nan" "$tmp/log"'
check "malformed named with its line" 'grep -q "stdin:7: refused, malformed: 4 fields, expected 8" "$tmp/log"'
check "out of range named with its line" 'grep -q "stdin:9: refused, position out of range: tx is 1e+300 m, beyond 1e+07 m" "$tmp/log"'
check "summary" 'grep -q "2 poses written to $ring, 6 lines refused (malformed 1, not finite 1, non-unit quaternion 1, duplicate stamp 1, out of order 1, position out of range 1)" "$tmp/log"'
check "the ring holds both records" '"${shm[@]}" stat "$ring" | grep -qx "head 2"'
# The service's way: pose.udp in the config makes it listen (no FILE, no --udp).
port=$((20000 + $$ % 20000))
printf 'shm:\n  pose_ring: %s-s\npose:\n  udp: "127.0.0.1:%d"\n  clock_offset_s: 100\n' "$ring" "$port" >"$tmp/s.yaml"
"${pose[@]}" --config "$tmp/s.yaml" </dev/null >/dev/null 2>"$tmp/slog" & spid=$!
for ((i = 0; i < 100; i++)); do grep -q "pose ring" "$tmp/slog" && break; sleep 0.05; done
printf '1.5 0 0 0 0 0 0 1\n2.5 0 0 0 0 0 0 1\n' >"/dev/udp/127.0.0.1/$port"
for ((i = 0; i < 100; i++)); do "${shm[@]}" stat "$ring-s" 2>/dev/null | grep -qx "head 2" && break; sleep 0.05; done
check "pose.udp: listening, two records" '"${shm[@]}" stat "$ring-s" | grep -qx "head 2"'
kill -TERM $spid; wait $spid; rc=$?
check "SIGTERM ends it with 0 (rc=$rc)" '[[ $rc == 0 ]]'
check "pose.udp: the summary" 'grep -q "2 poses written to $ring-s, 0 lines refused" "$tmp/slog"'
check "a FILE wins over pose.udp" \
  'printf "5 0 0 0 0 0 0 1\n" | "${pose[@]}" --config "$tmp/s.yaml" - 2>"$tmp/flog" && grep -q "stdin -> pose ring" "$tmp/flog"'
check "a config error names file:line:col" \
  'printf "pose:\n  extrinsic: [0, 0, 0, 0, 0, 0, 2]\n" >"$tmp/e.yaml"; ! "${pose[@]}" -c "$tmp/e.yaml" </dev/null 2>"$tmp/ee" >/dev/null && grep -q "e.yaml:2:14: key .pose.extrinsic.: expected tx ty tz qx qy qz qw with a unit quaternion" "$tmp/ee"'
# Type=notify (built with libsystemd), on a notify socket of our own as systemd
# gives one: READY=1 once the pose ring exists, WATCHDOG=1 from the input loop
# while a tracker's pipe stays quiet, STOPPING=1 at the end of the input.
if [[ -z "${VLFF_EMULATOR:-}" ]] && grep -q "sd_notify" "$1" && command -v /usr/bin/python3 >/dev/null; then
  /usr/bin/python3 "$(dirname "$0")/../../common/notify_listen.py" "$tmp/notify.sock" "$tmp/notify.log" 20 "/dev/shm$ring-n" &
  listener=$!
  for ((i = 0; i < 50; i++)); do [[ -S "$tmp/notify.sock" ]] && break; sleep 0.1; done
  printf 'shm:\n  pose_ring: %s-n\n' "$ring" >"$tmp/n.yaml"
  # A tracker that says nothing for 1.5 s (a quarter period is 0.1 s), then
  # one line, then ends.
  { sleep 1.5; printf '1.0 0 0 0 0 0 0 1\n'; } |
    NOTIFY_SOCKET="$tmp/notify.sock" WATCHDOG_USEC=400000 "${pose[@]}" --config "$tmp/n.yaml" - 2>"$tmp/nlog"; rc=$?
  wait $listener
  check "notify: exit 0 at the end of the input (rc=$rc)" '[[ $rc == 0 ]] && grep -q "1 poses written to $ring-n" "$tmp/nlog"'
  check "notify: READY=1 once the pose ring exists" 'grep -qx "READY=1 (exists)" "$tmp/notify.log"'
  check "notify: WATCHDOG=1 while the pipe is quiet ($(grep -cx "WATCHDOG=1" "$tmp/notify.log") of them)" \
    '(( $(grep -cx "WATCHDOG=1" "$tmp/notify.log") >= 5 ))'
  check "notify: STOPPING=1 last" '[[ "$(tail -1 "$tmp/notify.log")" == "STOPPING=1" ]]'
else
  echo "note: this vlff-pose has no sd_notify (built without libsystemd) or runs emulated; notify not checked"
fi
# A stream without newlines is refused as one overlong line, not held in memory.
head -c 200000 /dev/zero | tr '\0' 'x' >"$tmp/long.txt"
printf '\n2.0 0 0 0 0 0 0 1\n' >>"$tmp/long.txt"
"${pose[@]}" --config "$tmp/c.yaml" --ring "$ring-l" "$tmp/long.txt" >/dev/null 2>"$tmp/llog"; rc=$?
check "an overlong line is refused once, counted, and the next line taken (rc=$rc)" \
  '[[ $rc == 0 ]] && [[ $(grep -c "a line of 65536 bytes or more" "$tmp/llog") == 1 ]] && grep -q "long.txt:1: refused, too long: a line of 65536 bytes or more" "$tmp/llog" && grep -q "1 poses written to $ring-l, 1 lines refused (too long 1)" "$tmp/llog"'
echo "$passes passed, $fails failed"
(( fails == 0 ))
