# vlff-camd pairing a libcamera colour camera with an Aravis range camera:
# vimc free-runs, Aravis' fake GigE camera (127.0.0.1, Mono16) is fired by
# gpio-sim edges (gpio.mode input) that also stamp vimc's next frame; every
# edge must give one RGB-D record in the ring, at the configured 240x180,
# stamped with the edge's kernel time, and no range frame unmatched.
# vm-bins: vlff-camd vlff-camd-vmtest
# vm-tools: arv-fake-gv-camera-0.8 media-ctl v4l2-ctl
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so.sign
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/vimc_ipa_proxy /usr/share/libcamera/ipa/vimc
# vm-timeout: 180
set -e
export LIBCAMERA_LOG_LEVELS='*:ERROR'
ip link set lo up

# libcamera enumerates through libudev only (as in libcamera.sh).
mkdir -p /run/udev/data /dev/char
for d in /sys/dev/char/*; do
  mm=$(basename "$d")
  echo "I:1" >"/run/udev/data/c$mm"
  name=$(sed -n 's/^DEVNAME=//p' "$d/uevent")
  [ -n "$name" ] && ln -sf "../$name" "/dev/char/$mm"
done
media=
for m in /dev/media*; do
  media-ctl -d "$m" -p 2>/dev/null | grep -q 'driver *vimc' && media=$m
done
[ -n "$media" ] || { echo "no vimc media device"; exit 1; }
for s in "Sensor A" "Sensor B"; do
  media-ctl -d "$media" -V "\"$s\":0[fmt:SBGGR8_1X8/640x480]"
  v4l2-ctl -d "$(media-ctl -d "$media" -e "$s")" --set-ctrl show_information=2
done
media-ctl -d "$media" -V '"Debayer A":0[fmt:SBGGR8_1X8/640x480]'
media-ctl -d "$media" -V '"Debayer B":0[fmt:SBGGR8_1X8/640x480]'

g=/sys/kernel/config/gpio-sim/vlff-camd-lpair
mkdir "$g" "$g/bank0"
echo 2 >"$g/bank0/num_lines"
echo 1 >"$g/live"
chip=$(cat "$g/bank0/chip_name")
dev=$(ls -d /sys/devices/platform/gpio-sim.*/"$chip")
arv-fake-gv-camera-0.8 -i 127.0.0.1 >/tmp/fakecam.log 2>&1 &
cam=$!
rc=0
vlff-camd-vmtest lcam-pair "$chip" "$dev" || rc=$?
kill "$cam"
wait "$cam" 2>/dev/null || true
echo 0 >"$g/live"
rmdir "$g/bank0" "$g"
exit $rc
