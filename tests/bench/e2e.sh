#!/usr/bin/env bash
# scripts/bench e2e: the same room through the simulator source and through
# the camera rig (two Aravis fake GigE cameras, vlff-camd, vlff-pose, the
# feature ring): bench_e2e. The depth registration figure is
# bench_register's, measured in the same run; the no-GPU feature source's
# cost per frame is bench_feature_source.py's (the shipped extractor with a
# numpy model at D=512, 60x80 and 120x160, and the bare frame read as its
# baseline). One RESULT line of all three.
set -uo pipefail
B=${VLFF_BUILD:-build/release}
for b in "$B/bench/bench_e2e" "$B/bench/bench_register"; do
  [[ -x $b ]] || { echo "e2e: $b not built (needs Aravis, vlff-camd, vlff-pose)" >&2; exit 1; }
done
e2e=$("$B/bench/bench_e2e" | tee /dev/stderr | grep '^RESULT ') || { echo "e2e: bench_e2e failed" >&2; exit 1; }
reg=$("$B/bench/bench_register" | grep '^RESULT ') || { echo "e2e: bench_register failed" >&2; exit 1; }
ms=$(sed -n 's/.* register_ms_vga=\([0-9.]*\).*/\1/p' <<<"$reg")
fs=$(/usr/bin/python3 "$(dirname "$0")/bench_feature_source.py" --lib "$B/shm/libvlff-shm.so.2") ||
  { echo "e2e: bench_feature_source.py failed" >&2; exit 1; }
echo "${e2e} register_ms_vga=${ms} ${fs}"
