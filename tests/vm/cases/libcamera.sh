# libcamera against the vimc virtual camera: vlff-camd (camera.kind
# libcamera) streams into a frame ring, checked by vlff-camd-vmtest (size,
# format, monotonic sensor timestamps, colour bar content, clean shutdown).
# vm-bins: vlff-camd vlff-camd-vmtest
# vm-tools: media-ctl v4l2-ctl
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so.sign
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/vimc_ipa_proxy /usr/share/libcamera/ipa/vimc
# vm-timeout: 150
set -e
export LIBCAMERA_LOG_LEVELS='*:ERROR'

# libcamera enumerates through libudev only. Without udevd, udev's database
# must say each device is initialised (I:1), and /dev/char/M:m must resolve.
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
# A known starting state (libcamera's vimc handler then sets the formats it
# needs itself), and no text overlay on the sensors' colour bars: the content
# check wants plain bars.
for s in "Sensor A" "Sensor B"; do
  media-ctl -d "$media" -V "\"$s\":0[fmt:SBGGR8_1X8/640x480]"
  v4l2-ctl -d "$(media-ctl -d "$media" -e "$s")" --set-ctrl show_information=2
done
media-ctl -d "$media" -V '"Debayer A":0[fmt:SBGGR8_1X8/640x480]'
media-ctl -d "$media" -V '"Debayer B":0[fmt:SBGGR8_1X8/640x480]'
vlff-camd-vmtest libcamera 8
