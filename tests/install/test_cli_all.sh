#!/usr/bin/env bash
# Every program of the build follows one command-line convention (cli.h):
# --help: the usage on stdout, nothing on stderr, exit 0; --version: "<prog>
# <project version>" on stdout, exit 0; an unknown option: nothing on stdout,
# one line "<prog>: unknown option '--bogus'" then the usage on stderr, exit 2.
# Usage: test_cli_all.sh VERSION PROGRAM...
set -u
version=$1; shift
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
for path in "$@"; do
  p=$(basename "$path")
  # VLFF_EMULATOR: qemu-user in a cross-built tree (word-split on purpose)
  # shellcheck disable=SC2206
  prog=(${VLFF_EMULATOR:-} "$path")
  "${prog[@]}" --help >"$tmp/h.out" 2>"$tmp/h.err"; rc=$?
  check "$p --help exits 0 (rc=$rc)" '[[ $rc == 0 ]]'
  check "$p --help: usage on stdout" 'head -1 "$tmp/h.out" | grep -q "^Usage: $p "'
  check "$p --help: stderr empty" '[[ ! -s "$tmp/h.err" ]]'
  "${prog[@]}" --version >"$tmp/v.out" 2>"$tmp/v.err"; rc=$?
  check "$p --version exits 0 (rc=$rc)" '[[ $rc == 0 ]]'
  check "$p --version prints '$p $version'" '[[ "$(cat "$tmp/v.out")" == "$p $version" ]]'
  check "$p --version: stderr empty" '[[ ! -s "$tmp/v.err" ]]'
  "${prog[@]}" --bogus >"$tmp/b.out" 2>"$tmp/b.err"; rc=$?
  check "$p --bogus exits 2 (rc=$rc)" '[[ $rc == 2 ]]'
  check "$p --bogus: stdout empty" '[[ ! -s "$tmp/b.out" ]]'
  check "$p --bogus: one line naming the option" '[[ "$(head -1 "$tmp/b.err")" == "$p: unknown option '"'"'--bogus'"'"'" ]]'
  check "$p --bogus: then the usage" 'diff <(tail -n +2 "$tmp/b.err") "$tmp/h.out" >/dev/null'
  "${prog[@]}" -V >"$tmp/v2.out" 2>&1
  check "$p -V is --version" 'diff "$tmp/v.out" "$tmp/v2.out" >/dev/null'
done
echo "$passes passed, $fails failed over $# programs"
(( fails == 0 ))
