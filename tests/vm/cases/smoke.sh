# The VM itself: SocketCAN (vcan) comes up and gpio-sim lines appear, so the
# CAN and GPIO cases can trust the kernel side.
set -e
ip link add dev vsmoke0 type vcan
ip link set vsmoke0 up
[ "$(cat /sys/class/net/vsmoke0/type)" = 280 ]   # ARPHRD_CAN
ip link show vsmoke0 | grep -q 'UP'
ip link del vsmoke0
echo "smoke: vcan ok"

g=/sys/kernel/config/gpio-sim/smoke
mkdir "$g" "$g/bank0"
echo 4 >"$g/bank0/num_lines"
mkdir "$g/bank0/line2"
echo smoke-line >"$g/bank0/line2/name"
echo 1 >"$g/live"
chip=$(cat "$g/bank0/chip_name")
[ -c "/dev/$chip" ]
dev=$(ls -d /sys/devices/platform/gpio-sim.*/"$chip")
lines=$(ls -d "$dev"/sim_gpio* | wc -l)
[ "$lines" -eq 4 ]
echo pull-up >"$dev/sim_gpio2/pull"
[ "$(cat "$dev/sim_gpio2/value")" = 1 ]
echo "smoke: gpio-sim $chip has $lines lines"
echo 0 >"$g/live"
rmdir "$g/bank0/line2" "$g/bank0" "$g"

[ -e /dev/media0 ] || ls /sys/bus/platform/drivers/vimc >/dev/null
echo "smoke: vimc loaded"
