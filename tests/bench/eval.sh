#!/usr/bin/env bash
# Evaluation benchmark: vlff-eval on three fixed seeds of the synthetic room
# at the default difficulty. Prints each seed's table, then a summary table
# and a final RESULT line with the means over scenes (scene-averaged, as the
# reference code averages). The baselines are computed in the same run on the
# same features, so the field's numbers are always read against them.
# Env: VLFF_BUILD (release build dir, set by scripts/bench), VLFF_EVAL_ITERS
# (training steps, default 600), VLFF_EVAL_SEEDS (default "1 2 3").
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${VLFF_BUILD:-$here/../../build/release}
exe=$build/node/eval/vlff-eval
[[ -x $exe ]] || { echo "eval.sh: $exe not built" >&2; exit 1; }
iters=${VLFF_EVAL_ITERS:-600}
seeds=${VLFF_EVAL_SEEDS:-"1 2 3"}
out=$(mktemp -d "${TMPDIR:-/tmp}/vlff-bench-eval.XXXXXX")
trap 'rm -rf "$out"' EXIT
rows=()
for s in $seeds; do
  echo "--- seed $s ($iters steps)"
  "$exe" --config "$here/eval.yaml" --seed "$s" --iters "$iters" --quiet --out "$out/seed$s" | tee "$out/seed$s.log"
  rows+=("$s $(grep '^RESULT ' "$out/seed$s.log" | sed 's/^RESULT //')")
done
echo
printf '%-6s %10s %12s %10s %15s %10s %10s\n' seed miou2d miou2d_raw miou3d miou3d_fusion macc2d macc3d
for r in "${rows[@]}"; do
  set -- $r
  seed=$1; shift
  vals=()
  for kv in "$@"; do vals+=("${kv#*=}"); done
  printf '%-6s %10s %12s %10s %15s %10s %10s\n' "$seed" "${vals[@]}"
done
printf '%s\n' "${rows[@]}" | awk '
  { for (i = 2; i <= NF; i++) { split($i, kv, "="); k[i] = kv[1]; if (kv[2] == "n/a") na[i] = 1; else s[i] += kv[2] } n++ }
  END {
    split("10 12 10 15 10 10", w, " ")
    line = "mean  "; res = "RESULT"
    for (i = 2; i <= NF; i++) {
      v = na[i] ? "n/a" : sprintf("%.1f", s[i] / n)
      line = line sprintf(" %" w[i - 1] "s", v); res = res " " k[i] "=" v
    }
    print line; print res
  }'
