#!/usr/bin/env bash
# Evaluation benchmark: vlff-eval on fixed scenes, D = 512, the field fitted
# for a wall-clock budget (--fit-seconds) on the machine's cores. Scenes:
# three seeds of the flat (tests/bench/eval-flat.yaml: rooms joined by
# doorways, small and thin objects, per-object feature bias) and today's
# single room (eval.yaml), and the building (eval-building.yaml: three flats
# off a corridor, 240 frames, every 6th held out for 2D). Prints each
# scene's table (per-class 3D IoU beside fusion's), a summary table, and a
# final RESULT line: means over the flat scenes (scene-averaged, as the
# reference code averages), the worst class ratio over them, the room's 3D
# figures as room_*, and the building's figures as bldg_*. The baselines
# (raw per-frame features in 2D, multi-view fusion in 3D) are computed in
# the same run on the same frames and points.
# Env: VLFF_BUILD (release build dir, set by scripts/bench),
# VLFF_EVAL_SECONDS (fit budget per scene, default 60), VLFF_EVAL_ITERS
# (a step count instead: deterministic, for comparing ideas on a loaded
# machine), VLFF_EVAL_SCENES (default "flat:1 flat:2 flat:3 room:1 bldg:1").
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=${VLFF_BUILD:-$here/../../build/release}
exe=$build/node/eval/vlff-eval
[[ -x $exe ]] || { echo "eval.sh: $exe not built" >&2; exit 1; }
scenes=${VLFF_EVAL_SCENES:-"flat:1 flat:2 flat:3 room:1 bldg:1"}
if [[ -n ${VLFF_EVAL_ITERS:-} ]]; then budget=(--iters "$VLFF_EVAL_ITERS"); what="$VLFF_EVAL_ITERS steps"
else budget=(--fit-seconds "${VLFF_EVAL_SECONDS:-60}"); what="${VLFF_EVAL_SECONDS:-60} s"; fi
out=$(mktemp -d "${TMPDIR:-/tmp}/vlff-bench-eval.XXXXXX")
trap 'rm -rf "$out"' EXIT
rows=()
for sc in $scenes; do
  layout=${sc%%:*} seed=${sc#*:}
  extra=()
  case $layout in flat) cfg=$here/eval-flat.yaml ;; room) cfg=$here/eval.yaml ;;
    bldg) cfg=$here/eval-building.yaml; extra=(--holdout 6) ;;
    *) echo "eval.sh: unknown layout '$layout' in '$sc'" >&2; exit 1 ;; esac
  echo "--- $layout seed $seed ($what)"
  "$exe" --config "$cfg" --seed "$seed" "${budget[@]}" "${extra[@]}" --quiet --out "$out/$layout$seed" |
    tee "$out/$layout$seed.log"
  rows+=("$layout:$seed $(grep '^RESULT ' "$out/$layout$seed.log" | sed 's/^RESULT //')")
done
echo
printf '%s\n' "${rows[@]}" | awk '
  function val(k) { return (k in v) ? v[k] : "n/a" }
  BEGIN {
    nk = split("miou3d miou3d_fusion miou2d miou2d_raw macc2d macc2d_raw worst_class_vs_fusion fit_seconds steps miou3d_field_alone miou2d_field_alone macc2d_field_alone", key, " ")
    hdr = sprintf("%-9s", "scene"); for (i = 1; i <= nk; i++) hdr = hdr sprintf(" %13s", key[i]); print hdr
    worst = ""
  }
  {
    delete v
    for (i = 2; i <= NF; i++) { split($i, kv, "="); v[kv[1]] = kv[2] }
    line = sprintf("%-9s", $1); for (i = 1; i <= nk; i++) line = line sprintf(" %13s", val(key[i])); print line
    if ($1 ~ /^flat:/) {
      nf++
      for (i = 1; i <= nk; i++) if (val(key[i]) != "n/a") { s[key[i]] += v[key[i]]; c[key[i]]++ }
      w = val("worst_class_vs_fusion")
      if (w != "n/a" && (worst == "" || w + 0 < worst + 0)) worst = w
    } else if ($1 ~ /^room:/) { room3 = val("miou3d"); roomf = val("miou3d_fusion") }
    else if ($1 ~ /^bldg:/ && bldg == "") {
      nb = split("miou3d miou3d_fusion miou3d_field_alone miou2d miou2d_raw macc2d macc2d_raw worst_class_vs_fusion", bk, " ")
      for (i = 1; i <= nb; i++) bldg = bldg " bldg_" bk[i] "=" val(bk[i])
    }
  }
  END {
    res = "RESULT"; line = sprintf("%-9s", "flat mean")
    for (i = 1; i <= nk; i++) {
      k = key[i]
      m = (k == "worst_class_vs_fusion") ? (worst == "" ? "n/a" : worst) : (c[k] ? sprintf("%.1f", s[k] / c[k]) : "n/a")
      line = line sprintf(" %13s", m); res = res " " k "=" m
    }
    print line
    if (room3 != "") res = res " room_miou3d=" room3 " room_miou3d_fusion=" roomf
    print res bldg
  }'
