#!/usr/bin/env bash
# Install the build tree into a temporary prefix and use it as a user would:
# a controller built with pkg-config alone (PKG_CONFIG_PATH into the prefix),
# in C and C++, run against a segment; the installed programs answer
# --version; the installed vlff-view serves the installed page (index.html and
# three.js over HTTP); the default config's vlm.bpe_vocab is installed; a
# prefix moved after the install keeps its programs finding its files; the
# feature extractor (share/vlff/extractor) runs from the prefix, also moved,
# and loads the library installed beside it; a /usr install (DESTDIR) puts
# configs in /etc/vlff, the library in the multiarch directory, the units'
# paths under /usr and no run path in the .pc file; a prefix moved after the
# install still serves controllers built with pkg-config and with
# find_package(vlff-shm), which then start with no LD_LIBRARY_PATH.
# Usage: test_install.sh BUILD_DIR SOURCE_DIR LIBDIR
set -u
build=$1 src=$2 libdir=$3
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
cc=${CC:-cc} cxx=${CXX:-c++}

cmake --install "$build" --prefix "$tmp/p" >"$tmp/install.log" 2>&1 || { cat "$tmp/install.log"; exit 1; }
export PKG_CONFIG_PATH="$tmp/p/$libdir/pkgconfig"
unset PKG_CONFIG_LIBDIR
check "vlff-shm.pc in the multiarch libdir" '[[ -f "$PKG_CONFIG_PATH/vlff-shm.pc" ]]'
check "pkg-config finds the prefix it was installed to" \
  '[[ "$(readlink -f "$(pkg-config --variable=includedir vlff-shm)")" == "$(readlink -f "$tmp/p/include")" ]]'
cflags=$(pkg-config --cflags vlff-shm) libs=$(pkg-config --libs vlff-shm)
check "no /usr/local in the flags" '[[ "$cflags $libs" != */usr/local* ]]'
# shellcheck disable=SC2086
check "C controller builds" \
  '$cc -std=c17 -Wall -Wextra -Werror -D_GNU_SOURCE $cflags "$src/tests/install/controller.c" -o "$tmp/ctl_c" $libs 2>"$tmp/cc.log" || { cat "$tmp/cc.log"; false; }'
# shellcheck disable=SC2086
check "C++ controller builds (the header compiles as C++)" \
  '$cxx -std=c++17 -Wall -Wextra -Werror -x c++ $cflags "$src/tests/install/controller.c" -o "$tmp/ctl_cxx" $libs 2>"$tmp/cxx.log" || { cat "$tmp/cxx.log"; false; }'
run_lib="$(pkg-config --variable=libdir vlff-shm)"
check "C controller runs against a segment" 'LD_LIBRARY_PATH="$run_lib" "$tmp/ctl_c" /vlff-install-c-$$ | grep -q "^ok /vlff-install-c-$$ seq 0$"'
check "C++ controller runs against a segment" 'LD_LIBRARY_PATH="$run_lib" "$tmp/ctl_cxx" /vlff-install-cxx-$$ | grep -q "^ok "'
check "the C controller links the installed shared library" \
  'LD_LIBRARY_PATH="$run_lib" ldd "$tmp/ctl_c" | grep -q "libvlff-shm.so.2 => $run_lib"'
# A copy of the prefix elsewhere still tells the truth (.pc relocatable).
cp -a "$tmp/p" "$tmp/moved"
check "moved prefix: pkg-config follows" \
  '[[ "$(readlink -f "$(PKG_CONFIG_PATH="$tmp/moved/$libdir/pkgconfig" pkg-config --variable=libdir vlff-shm)")" == "$(readlink -f "$tmp/moved/$libdir")" ]]'
# The extractor: its help, and the library it loads by default is the
# prefix's (in place and in the moved copy).
ext=share/vlff/extractor/vlff_extractor.py
check "extractor installed, executable" '[[ -x "$tmp/p/$ext" ]]'
check "installed extractor --help" '/usr/bin/python3 "$tmp/p/$ext" --help | grep -q -- "--frames"'
for pre in p moved; do
  check "$pre: the extractor loads the prefix's libvlff-shm" \
    '[[ "$(cd / && PYTHONPATH="$tmp/$pre/share/vlff/extractor" /usr/bin/python3 -c \
        "import vlff_extractor as e; print(e.load_library()._name)")" == "$(readlink -f "$tmp/$pre/$libdir")/libvlff-shm.so.2" ]]'
done
for prog in "$tmp"/p/bin/vlff-*; do
  check "$(basename "$prog") --version" '"$prog" --version | grep -qE "^$(basename "$prog") [0-9]+\.[0-9]+\.[0-9]+$"'
done
# The installed viewer finds the installed page (share/vlff/view) by itself and
# serves its files over HTTP, byte for byte, with the page's security policy.
if [[ -x "$tmp/p/bin/vlff-view" ]]; then
  "$tmp/p/bin/vlff-view" --port 0 --map /vlff-install-view-$$ --frames "" >"$tmp/view.out" 2>"$tmp/view.err" &
  view_pid=$! port=""
  for _ in $(seq 100); do
    port=$(sed -n 's|^vlff-view: serving http://127\.0\.0\.1:\([0-9]*\)/.*|\1|p' "$tmp/view.out")
    [[ -n "$port" ]] && break
    sleep 0.1
  done
  # fetch PATH OUT: the whole answer to GET PATH (the viewer closes after it)
  fetch() {
    exec 3<>"/dev/tcp/127.0.0.1/$port" || return 1
    # the viewer answers requests naming it with its port only (Host check)
    printf 'GET %s HTTP/1.1\r\nHost: 127.0.0.1:%s\r\n\r\n' "$1" "$port" >&3
    timeout 10 cat <&3 >"$2"
    local rc=$?
    exec 3<&-
    return $rc
  }
  for f in index.html three/three.module.js three/addons/OrbitControls.js; do
    file="$tmp/p/share/vlff/view/$f"
    check "installed vlff-view serves the installed $f" \
      '[[ -n "$port" && -f "$file" ]] && fetch "/$f" "$tmp/answer" && head -1 "$tmp/answer" | grep -q "^HTTP/1.1 200" &&
       grep -qi "^content-security-policy: default-src" "$tmp/answer" &&
       tail -c "$(stat -c %s "$file")" "$tmp/answer" | cmp -s - "$file"'
  done
  kill -INT "$view_pid"
  wait "$view_pid"
  view_rc=$?
  check "installed vlff-view exits 0 on SIGINT" '(( view_rc == 0 )) || { cat "$tmp/view.err"; false; }'
fi
check "configs under the prefix" '[[ -f "$tmp/p/etc/vlff/vlff.yaml" && -f "$tmp/p/etc/vlff/vlff.dbc" ]]'
check "unit follows the prefix" \
  'grep -qx "ExecStart=$tmp/p/bin/vlff-node --config $tmp/p/etc/vlff/vlff.yaml" "$tmp/p/lib/systemd/system/vlff-node.service"'
# The installed vlff.yaml is valid and needs only what its comment says the
# user adds (a text encoder for the prompts; test_configs checks them all).
check "installed vlff.yaml: --check-config asks only for a text encoder" \
  '! "$tmp/p/bin/vlff-node" --check-config "$tmp/p/etc/vlff/vlff.yaml" >/dev/null 2>"$tmp/vc.err" && grep -q "vlff.yaml: no text encoder for the prompts" "$tmp/vc.err"'
# vlm.bpe_vocab's default as the installed configs leave it (unset, or ""),
# in a config --check-config accepts (the simulator embeds its prompts).
printf 'source:\n  kind: sim\nvlm:\n  bpe_vocab: ""\n' >"$tmp/vocab.yaml"
check "the installed configs leave vlm.bpe_vocab to its default" \
  '! grep -q "^ *bpe_vocab: *[^ \"#]" "$tmp/p/etc/vlff/vlff.yaml" "$tmp/p/etc/vlff/default.yaml" && grep -q "^  bpe_vocab: \"\"" "$tmp/p/etc/vlff/default.yaml"'
# A program outside an install (the build tree's) takes the defaults of the
# configured prefix (the config search path, vlm.bpe_vocab): an install with
# that prefix, staged with DESTDIR, must put CLIP's vocabulary where the
# installed configs' vlm.bpe_vocab then looks.
DESTDIR="$tmp/conf" cmake --install "$build" >"$tmp/install3.log" 2>&1 || { cat "$tmp/install3.log"; exit 1; }
vocab=$("$build/node/vlff-node" --check-config "$tmp/vocab.yaml" 2>/dev/null | sed -n 's/^vlm\.bpe_vocab: "\(.*\)"$/\1/p')
check "vlm.bpe_vocab's default ($vocab) is installed there" '[[ "$vocab" == /* && -f "$tmp/conf$vocab" ]] && gzip -t "$tmp/conf$vocab"'

# Installed to one prefix, then moved: the programs find the install's files
# (the config search path's vlff.yaml, vlm.bpe_vocab's default) from where
# they run, not at the prefix configured or installed to.
cmake --install "$build" --prefix "$tmp/q" >"$tmp/install4.log" 2>&1 || { cat "$tmp/install4.log"; exit 1; }
mv "$tmp/q" "$tmp/r"
vocab=$("$tmp/r/bin/vlff-node" --check-config "$tmp/vocab.yaml" 2>/dev/null | sed -n 's/^vlm\.bpe_vocab: "\(.*\)"$/\1/p')
check "moved prefix: vlm.bpe_vocab ($vocab) is the moved install's" \
  '[[ "$vocab" == "$tmp/r/share/vlff/bpe_simple_vocab_16e6.txt.gz" ]] && gzip -t "$vocab"'
printf 'vlff_moved_probe: 1\n' >"$tmp/r/etc/vlff/vlff.yaml"
check "moved prefix: without --config, vlff-pose reads the moved install's vlff.yaml" \
  'env -u VLFF_CONFIG "$tmp/r/bin/vlff-pose" </dev/null >/dev/null 2>"$tmp/moved.err"; [[ $? == 1 ]] &&
   grep -q "^$tmp/r/etc/vlff/vlff.yaml:1:1: .*unknown key" "$tmp/moved.err" || { cat "$tmp/moved.err"; false; }'

# prefix /usr, staged with DESTDIR as a packager does
DESTDIR="$tmp/stage" cmake --install "$build" --prefix /usr >"$tmp/install2.log" 2>&1 || { cat "$tmp/install2.log"; exit 1; }
check "/usr: configs in /etc/vlff" '[[ -f "$tmp/stage/etc/vlff/vlff.yaml" && ! -e "$tmp/stage/usr/etc" ]]'
check "/usr: library in /usr/$libdir" '[[ -f "$tmp/stage/usr/$libdir/libvlff-shm.so.2" ]]'
check "/usr: unit runs /usr/bin/vlff-node with /etc/vlff/vlff.yaml" \
  'grep -qx "ExecStart=/usr/bin/vlff-node --config /etc/vlff/vlff.yaml" "$tmp/stage/usr/lib/systemd/system/vlff-node.service"'
check "/usr: sysusers file" '[[ -f "$tmp/stage/usr/lib/sysusers.d/vlff.conf" ]]'
check "/usr: the extractor in /usr/share/vlff/extractor" '[[ -x "$tmp/stage/usr/$ext" ]]'
check "/usr: udev rules in /usr/lib/udev/rules.d" '[[ -f "$tmp/stage/usr/lib/udev/rules.d/60-vlff.rules" ]]'
check "/usr: vlff-shm.pc gives no run path (the linker's own directory)" \
  '[[ -f "$tmp/stage/usr/$libdir/pkgconfig/vlff-shm.pc" ]] && ! grep -q rpath "$tmp/stage/usr/$libdir/pkgconfig/vlff-shm.pc"'
check "/usr: CMake package in /usr/$libdir/cmake/vlff-shm" \
  '[[ -f "$tmp/stage/usr/$libdir/cmake/vlff-shm/vlff-shmConfig.cmake" && -f "$tmp/stage/usr/$libdir/cmake/vlff-shm/vlff-shmConfigVersion.cmake" ]]'

# The prefix moved after the install (P to Q, P gone): a controller built
# against Q with pkg-config alone, and one built by its own CMake project with
# find_package(vlff-shm), start without LD_LIBRARY_PATH and load Q's library.
mv "$tmp/p" "$tmp/q"
unset LD_LIBRARY_PATH
q_so=$(readlink -f "$tmp/q/$libdir/libvlff-shm.so.2")
# loads_q EXE: the libvlff-shm.so.2 EXE loads is Q's
loads_q() {
  local got
  got=$(ldd "$1" | sed -n 's/^[[:space:]]*libvlff-shm\.so\.2 => \(.*\) (0x[0-9a-f]*)$/\1/p')
  [[ -n "$got" && "$(readlink -f "$got")" == "$q_so" ]] || { echo "ldd $1:"; ldd "$1"; false; }
}
export PKG_CONFIG_PATH="$tmp/q/$libdir/pkgconfig"
cflags=$(pkg-config --cflags vlff-shm) libs=$(pkg-config --libs vlff-shm)
# shellcheck disable=SC2086
check "moved prefix: C controller builds with pkg-config" \
  '$cc -std=c17 -Wall -Wextra -Werror -D_GNU_SOURCE $cflags "$src/tests/install/controller.c" -o "$tmp/ctl_q" $libs 2>"$tmp/cc.log" || { cat "$tmp/cc.log"; false; }'
check "moved prefix: the pkg-config controller starts by itself" \
  '"$tmp/ctl_q" /vlff-install-q-$$ 2>&1 | grep -q "^ok /vlff-install-q-$$ seq 0$"'
check "moved prefix: the pkg-config controller loads the moved library" 'loads_q "$tmp/ctl_q"'
check "moved prefix: find_package(vlff-shm) configures and builds the controller" \
  'cmake -S "$src/tests/install/cmake-consumer" -B "$tmp/cmake-ctl" -DCMAKE_PREFIX_PATH="$tmp/q" -DCMAKE_C_COMPILER="$cc" \
     >"$tmp/cmake-ctl.log" 2>&1 && cmake --build "$tmp/cmake-ctl" >>"$tmp/cmake-ctl.log" 2>&1 || { cat "$tmp/cmake-ctl.log"; false; }'
check "moved prefix: the CMake controller starts by itself" \
  '"$tmp/cmake-ctl/controller" /vlff-install-cm-$$ 2>&1 | grep -q "^ok /vlff-install-cm-$$ seq 0$"'
check "moved prefix: the CMake controller loads the moved library" 'loads_q "$tmp/cmake-ctl/controller"'
echo "$passes passed, $fails failed"
rm -f /dev/shm/vlff-install-*-$$
(( fails == 0 ))
