#!/usr/bin/env bash
# Every program of the build follows one command-line convention (cli.h):
# --help: the usage on stdout, nothing on stderr, exit 0; --version: "<prog>
# <project version>" on stdout, exit 0; an unknown option: nothing on stdout,
# one line "<prog>: unknown option '--bogus'" then the usage on stderr, exit 2;
# -c is --config; and the subcommands of vlff-shm and vlff-can likewise.
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

# In every program that reads a config (vlff-shm and vlff-view read none):
# -c is --config, a known option taking a value, so "-c FILE --help" is the
# help; and a config that cannot run gives the parser's "file:line:col: key
# ...: what" first on stderr, with no program name before the file, and exit
# 1 (with the operands each program needs to get as far as reading it).
printf 'node:\n  bogus_key: 1\n' >"$tmp/bad.yaml"
for path in "$@"; do
  p=$(basename "$path")
  [[ $p == vlff-shm || $p == vlff-view ]] && continue
  # shellcheck disable=SC2206
  prog=(${VLFF_EMULATOR:-} "$path")
  check "$p: -c is --config" \
    '"${prog[@]}" -c "$tmp/absent.yaml" --help >"$tmp/c.out" 2>&1 && grep -q -- "-c, --config" "$tmp/c.out"'
  args=()
  [[ $p == vlff-can ]] && args=(dbc)
  [[ $p == vlff-replay ]] && args=("$tmp/no-scene")
  [[ $p == vlff-record ]] && args=("$tmp/no-recording.mcap")
  "${prog[@]}" -c "$tmp/bad.yaml" "${args[@]}" </dev/null >/dev/null 2>"$tmp/cfg.err"; rc=$?
  check "$p: a bad config exits 1 (rc=$rc)" '[[ $rc == 1 ]]'
  check "$p: a bad config's error starts with file:line:col" \
    'head -1 "$tmp/cfg.err" | grep -q "^$tmp/bad.yaml:2:3: key .node.bogus_key.: unknown key" || { cat "$tmp/cfg.err"; false; }'
done

# Subcommands follow the same convention with their own usage: --help to
# stdout (exit 0), a usage error (a bad number included) one line and the
# subcommand's usage on stderr (exit 2), a runtime failure one line (exit 1).
# usage_error NAME EXPECTED_FIRST_LINE_PART USAGE_FILE ARGS...
usage_error() {
  local name=$1 want=$2 usage=$3; shift 3
  "${prog[@]}" "$@" >"$tmp/u.out" 2>"$tmp/u.err"; local rc=$?
  check "$name: exit 2 (rc=$rc)" '[[ $rc == 2 ]]'
  check "$name: one line naming '$want'" 'head -1 "$tmp/u.err" | grep -qF -- "$want"'
  check "$name: then the usage, nothing on stdout" 'diff <(tail -n +2 "$tmp/u.err") "$usage" >/dev/null && [[ ! -s "$tmp/u.out" ]]'
}
# runtime_error NAME ARGS...
runtime_error() {
  local name=$1; shift
  "${prog[@]}" "$@" >"$tmp/r.out" 2>"$tmp/r.err"; local rc=$?
  check "$name: exit 1 (rc=$rc)" '[[ $rc == 1 ]]'
  check "$name: a message and no usage" '[[ -s "$tmp/r.err" ]] && ! grep -q "^Usage:" "$tmp/r.err"'
}
for path in "$@"; do
  p=$(basename "$path")
  # shellcheck disable=SC2206
  prog=(${VLFF_EMULATOR:-} "$path")
  if [[ $p == vlff-shm ]]; then
    for sub in list stat dump-frame label set-prompts watch; do
      "${prog[@]}" $sub --help >"$tmp/$sub.help" 2>"$tmp/s.err"; rc=$?
      check "vlff-shm $sub --help: exit 0, usage on stdout (rc=$rc)" \
        '[[ $rc == 0 && ! -s "$tmp/s.err" ]] && head -1 "$tmp/$sub.help" | grep -q "^Usage: vlff-shm $sub"'
      usage_error "vlff-shm $sub --bogus" "unknown option '--bogus'" "$tmp/$sub.help" $sub --bogus
    done
    usage_error "vlff-shm stat (no NAME)" "stat: expected 1 argument" "$tmp/stat.help" stat
    usage_error "vlff-shm list extra" "unexpected argument 'extra'" "$tmp/list.help" list extra
    usage_error "vlff-shm watch NAME abc" "'abc'" "$tmp/watch.help" watch /vlff-cli-all-$$ abc
    usage_error "vlff-shm watch NAME 1 2" "unexpected argument '2'" "$tmp/watch.help" watch /vlff-cli-all-$$ 1 2
    usage_error "vlff-shm label NAME 1 2 x" "'x'" "$tmp/label.help" label /vlff-cli-all-$$ 1 2 x
    usage_error "vlff-shm set-prompts -t abc" "'abc'" "$tmp/set-prompts.help" set-prompts -t abc /vlff-cli-all-$$ a
    usage_error "vlff-shm set-prompts -t 0" "'0'" "$tmp/set-prompts.help" set-prompts -t 0 /vlff-cli-all-$$ a
    usage_error "vlff-shm set-prompts -i x" "'x'" "$tmp/set-prompts.help" set-prompts /vlff-cli-all-$$ -i x
    usage_error "vlff-shm set-prompts NAME (no prompts)" "no prompts" "$tmp/set-prompts.help" set-prompts /vlff-cli-all-$$
    "${prog[@]}" --help >"$tmp/top.help"
    usage_error "vlff-shm frob" "unknown command 'frob'" "$tmp/top.help" frob
    runtime_error "vlff-shm stat MISSING" stat /vlff-cli-all-missing-$$
    runtime_error "vlff-shm label MISSING -0.5 (a negative coordinate is no option)" label /vlff-cli-all-missing-$$ 1 2 -0.5
  elif [[ $p == vlff-can ]]; then
    "${prog[@]}" --help >"$tmp/can.help"
    printf 'can:\n  node_id: 17\n' >"$tmp/can17.yaml"
    for o in -c -f --config; do
      "${prog[@]}" $o "$tmp/can17.yaml" dbc >"$tmp/dbc$o" 2>"$tmp/dbc.err"; rc=$?
      check "vlff-can $o FILE dbc: the DBC of node 17 (rc=$rc)" '[[ $rc == 0 ]] && grep -q "^BO_ 1809 " "$tmp/dbc$o"'
    done
    check "vlff-can dbc --help: the usage on stdout" '"${prog[@]}" dbc --help | diff - "$tmp/can.help" >/dev/null'
    check "vlff-can can0 send --help: the usage on stdout" '"${prog[@]}" can0 send --help | diff - "$tmp/can.help" >/dev/null'
    c=(-c "$tmp/can17.yaml")
    usage_error "vlff-can send frob" "unknown command 'frob'" "$tmp/can.help" "${c[@]}" can0 send frob
    usage_error "vlff-can send (nothing)" "send needs a command" "$tmp/can.help" "${c[@]}" can0 send
    usage_error "vlff-can send save extra" "unexpected argument 'extra'" "$tmp/can.help" "${c[@]}" can0 send save extra
    usage_error "vlff-can send prompt-set 999" "'999'" "$tmp/can.help" "${c[@]}" can0 send prompt-set 999
    usage_error "vlff-can send prompt-set x" "'x'" "$tmp/can.help" "${c[@]}" can0 send prompt-set x
    usage_error "vlff-can --seq 300" "'300'" "$tmp/can.help" "${c[@]}" --seq 300 can0 send save
    usage_error "vlff-can --count abc" "'abc'" "$tmp/can.help" "${c[@]}" --count abc can0 dump
    usage_error "vlff-can --node-id 200" "'200'" "$tmp/can.help" "${c[@]}" --node-id 200 can0 dump
    usage_error "vlff-can --command-id 0x800" "'0x800'" "$tmp/can.help" "${c[@]}" --command-id 0x800 can0 dump
    usage_error "vlff-can --seconds -1" "'-1'" "$tmp/can.help" "${c[@]}" --seconds=-1 can0 dump
    usage_error "vlff-can can0 frob" "unknown command 'frob'" "$tmp/can.help" "${c[@]}" can0 frob
    usage_error "vlff-can dump extra" "unexpected argument 'extra'" "$tmp/can.help" "${c[@]}" can0 dump extra
    # No such interface (or no PF_CAN at all here): a runtime failure.
    runtime_error "vlff-can on a missing interface, dump" "${c[@]}" -t 0.1 vlff-none-$$ dump
    runtime_error "vlff-can on a missing interface, send" "${c[@]}" -t 0.1 vlff-none-$$ send save
  fi
done
echo "$passes passed, $fails failed over $# programs"
(( fails == 0 ))
