#!/usr/bin/env bash
# CAN benchmark (scripts/bench can): boots the test VM and runs can_vm_bench
# on vcan there. Heartbeat lateness is measured against the ideal period grid
# (the baseline), idle and with every core busy; status capacity against a
# constant-frame send loop in the same run. Last line: RESULT ...
set -uo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
build=${VLFF_BUILD:-$root/build/release}
echo "host load: $(cut -d' ' -f1-3 /proc/loadavg) on $(nproc) cores (the VM's timing depends on it)"
"$root/tests/vm/run" "$build" "$root/tests/vm/bench/can.sh"
rc=$?
if (( rc == 77 )); then echo "bench can: SKIPPED (no VM)"; exit 77; fi
grep -aE '^(timer|heartbeat|send capacity)' "$build/vm/console.log"
line=$(grep -aE '^RESULT ' "$build/vm/console.log" | tail -1)
[[ -n "$line" ]] || { echo "bench can: no RESULT line"; exit 1; }
echo "$line"
exit $rc
