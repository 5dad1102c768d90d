#!/usr/bin/env bash
# scripts/bench e2e: the same room through the simulator source and through
# the camera rig (two Aravis fake GigE cameras, vlff-camd, vlff-pose, the
# feature ring): bench_e2e. The depth registration figure is
# bench_register's, measured in the same run. One RESULT line of both.
set -uo pipefail
B=${VLFF_BUILD:-build/release}
for b in "$B/bench/bench_e2e" "$B/bench/bench_register"; do
  [[ -x $b ]] || { echo "e2e: $b not built (needs Aravis, vlff-camd, vlff-pose)" >&2; exit 1; }
done
e2e=$("$B/bench/bench_e2e" | tee /dev/stderr | grep '^RESULT ') || { echo "e2e: bench_e2e failed" >&2; exit 1; }
reg=$("$B/bench/bench_register" | grep '^RESULT ') || { echo "e2e: bench_register failed" >&2; exit 1; }
ms=$(sed -n 's/.* register_ms_vga=\([0-9.]*\).*/\1/p' <<<"$reg")
echo "${e2e} register_ms_vga=${ms}"
