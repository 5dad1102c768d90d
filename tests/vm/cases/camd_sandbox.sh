# vlff-camd under strace, streaming vimc through libcamera (the camera path
# the host cannot run): the host checks every system call and socket family
# it made against vlff-camd.service's SystemCallFilter= and
# RestrictAddressFamilies= (tests/install/sandbox_check.py --vm).
# vm-bins: vlff-camd vlff-shm
# vm-tools: media-ctl v4l2-ctl strace
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so.sign
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/vimc_ipa_proxy /usr/share/libcamera/ipa/vimc
# vm-files: tests/vm/cases/camd.inc
# vm-timeout: 150
# vm-stream: cameras
# vm-host-check: /usr/bin/python3 tests/install/sandbox_check.py --vm configs/systemd/vlff-camd.service.in
set -e
. "$VLFF_SRC/tests/vm/cases/camd.inc"
vimc_ready
printf 'shm:\n  ring: /sbx-c\n  pose_ring: /sbx-cp\n  max_width: 640\n  max_height: 480\ncamera:\n  kind: libcamera\n  device: "0"\n  pixel_format: RGB8\n  width: 480\n  height: 360\n  frame_rate: 30\n  intrinsics: [500, 500, 240, 180]\n' >/tmp/sbx.yaml
strace -f -qq -o /tmp/camd.st vlff-camd --config /tmp/sbx.yaml >/tmp/camd.log 2>&1 &
tracer=$!
# the traced camd: strace's child
camd=
i=0
while [ -z "$camd" ] && [ $i -lt 100 ]; do
  for s in /proc/[0-9]*/stat; do
    set -- $(cat "$s" 2>/dev/null)
    [ "${4:-}" = "$tracer" ] && camd=$1
  done
  sleep 0.1
  i=$((i + 1))
done
head=0
i=0
while [ $i -lt 900 ]; do
  head=$(vlff-shm stat /sbx-c 2>/dev/null | sed -n 's/^head //p')
  [ -n "$head" ] && [ "$head" -ge 5 ] && break
  sleep 0.1
  i=$((i + 1))
done
rc=0
kill -TERM "$camd"
wait "$tracer" || rc=$?
echo "camd under strace: ring head ${head:-none}, exit $rc"
[ -n "$head" ] && [ "$head" -ge 5 ] && [ "$rc" = 0 ] || { tail -20 /tmp/camd.log; exit 1; }
# One line per system call name and socket family, as sandbox_check.py reads them.
echo STRACE-BEGIN
sed -n 's/^[0-9][0-9]* *\([a-z0-9_]*(\(AF_[A-Z0-9_]*\)\{0,1\}\).*/1 \1/p' /tmp/camd.st | sort -u
echo STRACE-END
