# Shared by the scripts: configure and build one tree.
# vlff_build DIR BUILD_TYPE [cmake args...]
VLFF_ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VLFF_JOBS=${VLFF_JOBS:-$(nproc)}

vlff_build() {
  local dir=$1 type=$2
  shift 2
  cmake -S "$VLFF_ROOT" -B "$dir" -DCMAKE_BUILD_TYPE="$type" "$@" >"$dir.configure.log" 2>&1 \
    || { cat "$dir.configure.log"; return 1; }
  grep -m1 'vlff parts' "$dir.configure.log" || true
  local rc=0
  # VLFF_TARGET: one target (and what it needs) in place of everything
  cmake --build "$dir" -j "$VLFF_JOBS" ${VLFF_TARGET:+--target "$VLFF_TARGET"} >"$dir.build.log" 2>&1 || rc=$?
  grep -vE '^\[ *[0-9]+%\]|^Consolidate|^-- ' "$dir.build.log" || true   # warnings and errors only
  return $rc
}
