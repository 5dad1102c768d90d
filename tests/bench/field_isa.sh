#!/usr/bin/env bash
# Training speed per kernel ISA on this CPU (scripts/bench field_isa): the
# kernels the CPU picks by default, VLFF_GEMM=avx2 (what a CPU with AVX2
# but not AVX-512 runs: most x86 robot computers) and VLFF_GEMM=generic (the
# portable code, here compiled for x86-64's SSE2 baseline). Each run
# measures its own ISA's FMA peak in the same process; two interleaved
# rounds, the better of each kept; the last line gives each ISA's samples/s
# and fraction of its peak, and samples/s as a ratio to the default's.
# Caveat: the small compiler-cloned loops (VLFF_HOT, a few % of a step) keep
# this CPU's widest clone in every run.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${VLFF_BUILD:-$here/../../build/release}
exe=$build/bench/bench_field
[[ -x $exe ]] || { echo "field_isa.sh: $exe not built" >&2; exit 1; }
declare -A sps frac name
for round in 1 2; do
  for isa in default avx2 generic; do
    if [[ $isa == default ]]; then out=$(env -u VLFF_GEMM "$exe" --train-only); else out=$(VLFF_GEMM=$isa "$exe" --train-only); fi
    echo "round $round, VLFF_GEMM=$isa: $(grep -v '^RESULT' <<<"$out")"
    res=$(grep '^RESULT' <<<"$out")
    s=$(sed -n 's/.*train_samples_per_s=\([0-9.]*\).*/\1/p' <<<"$res")
    f=$(sed -n 's/.*train_peak_frac=\([0-9.]*\).*/\1/p' <<<"$res")
    name[$isa]=$(sed -n 's/.*isa=\([^ ]*\).*/\1/p' <<<"$res")
    if [[ -z ${sps[$isa]:-} ]] || awk -v a="$s" -v b="${sps[$isa]}" 'BEGIN { exit !(a > b) }'; then
      sps[$isa]=$s frac[$isa]=$f
    fi
  done
done
line="RESULT default_isa=${name[default]}"
for isa in default avx2 generic; do
  ratio=$(awk -v a="${sps[$isa]}" -v b="${sps[default]}" 'BEGIN { printf "%.2f", a / b }')
  line+=" ${isa}_samples_per_s=${sps[$isa]} ${isa}_peak_frac=${frac[$isa]} ${isa}_vs_default=$ratio"
done
echo "$line"
