#!/usr/bin/env bash
# Online benchmark (issue 55): the live node on a recorded scene, as a robot
# gets it. The flat of tests/bench/eval-flat.yaml (80 frames at 5 Hz, D = 512)
# is written as a scene directory by vlff-sim, then `vlff-eval --online` fits
# it offline for 60 s (the offline score and fusion's) and plays it with
# vlff-replay at its recorded rate into a vlff-node, scoring the published map
# every 10 s until 60 s after the replay's end. Prints the curve and a last
# line: RESULT online_miou3d_60s=... offline_miou3d=... fusion_miou3d=...
# online_coverage_60s=... publish_interval_s=...
# Targets (docs/eval.md): online >= offline - 2 and >= fusion + 5; coverage
# >= 99 %; publish interval within 10 % of 1 / publish.rate_hz.
# Environment: VLFF_BUILD (default build/release), VLFF_ONLINE_SEED (default 4:
# a flat the eval bench does not use), VLFF_ONLINE_AFTER (default 60).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${VLFF_BUILD:-$here/../../build/release}
for p in node/sim/vlff-sim node/eval/vlff-eval node/vlff-node node/dataset/vlff-replay; do
  [[ -x $build/$p ]] || { echo "online.sh: $build/$p not built" >&2; exit 1; }
done
seed=${VLFF_ONLINE_SEED:-4} after=${VLFF_ONLINE_AFTER:-60}
out=$(mktemp -d "${TMPDIR:-/tmp}/vlff-bench-online.XXXXXX")
trap 'rm -rf "$out"' EXIT
"$build/node/sim/vlff-sim" --config "$here/eval-flat.yaml" --seed "$seed" --quiet --write-dataset "$out/scene"
"$build/node/eval/vlff-eval" --config "$here/eval-flat.yaml" --dataset "$out/scene" --fit-seconds 60 --quiet \
  --online --online-after "$after" --out "$out/eval" | tee "$out/log"
grep -q '^RESULT online_' "$out/log"
