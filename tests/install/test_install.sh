#!/usr/bin/env bash
# Install the build tree into a temporary prefix and use it as a user would:
# a controller built with pkg-config alone (PKG_CONFIG_PATH into the prefix),
# in C and C++, run against a segment; the installed programs answer
# --version; a /usr install (DESTDIR) puts configs in /etc/vlff, the library
# in the multiarch directory and the units' paths under /usr.
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
  'LD_LIBRARY_PATH="$run_lib" ldd "$tmp/ctl_c" | grep -q "libvlff-shm.so.1 => $run_lib"'
# A copy of the prefix elsewhere still tells the truth (.pc relocatable).
cp -a "$tmp/p" "$tmp/moved"
check "moved prefix: pkg-config follows" \
  '[[ "$(readlink -f "$(PKG_CONFIG_PATH="$tmp/moved/$libdir/pkgconfig" pkg-config --variable=libdir vlff-shm)")" == "$(readlink -f "$tmp/moved/$libdir")" ]]'
for prog in "$tmp"/p/bin/vlff-*; do
  check "$(basename "$prog") --version" '"$prog" --version | grep -qE "^$(basename "$prog") [0-9]+\.[0-9]+\.[0-9]+$"'
done
check "configs under the prefix" '[[ -f "$tmp/p/etc/vlff/vlff.yaml" && -f "$tmp/p/etc/vlff/vlff.dbc" ]]'
check "unit follows the prefix" \
  'grep -qx "ExecStart=$tmp/p/bin/vlff-node --config $tmp/p/etc/vlff/vlff.yaml" "$tmp/p/lib/systemd/system/vlff-node.service"'
check "installed vlff.yaml is a valid config" '"$tmp/p/bin/vlff-node" --check-config "$tmp/p/etc/vlff/vlff.yaml" >/dev/null 2>&1'

# prefix /usr, staged with DESTDIR as a packager does
DESTDIR="$tmp/stage" cmake --install "$build" --prefix /usr >"$tmp/install2.log" 2>&1 || { cat "$tmp/install2.log"; exit 1; }
check "/usr: configs in /etc/vlff" '[[ -f "$tmp/stage/etc/vlff/vlff.yaml" && ! -e "$tmp/stage/usr/etc" ]]'
check "/usr: library in /usr/$libdir" '[[ -f "$tmp/stage/usr/$libdir/libvlff-shm.so.1" ]]'
check "/usr: unit runs /usr/bin/vlff-node with /etc/vlff/vlff.yaml" \
  'grep -qx "ExecStart=/usr/bin/vlff-node --config /etc/vlff/vlff.yaml" "$tmp/stage/usr/lib/systemd/system/vlff-node.service"'
check "/usr: sysusers file" '[[ -f "$tmp/stage/usr/lib/sysusers.d/vlff.conf" ]]'
echo "$passes passed, $fails failed"
rm -f /dev/shm/vlff-install-*-$$
(( fails == 0 ))
