# GPIO camera triggering against gpio-sim: pulse train read back on the sim
# side, edges driven through the sim's pull attribute, debounce, busy line,
# missing chip/line (drivers/gpio, run by vlff-gpio-vmtest).
# vm-bins: vlff-gpio-vmtest
set -e
g=/sys/kernel/config/gpio-sim/vlff-gpio
mkdir "$g" "$g/bank0"
echo 4 >"$g/bank0/num_lines"
mkdir "$g/bank0/line3"
echo vlff-trigger >"$g/bank0/line3/name"
echo 1 >"$g/live"
chip=$(cat "$g/bank0/chip_name")
dev=$(ls -d /sys/devices/platform/gpio-sim.*/"$chip")
vlff-gpio-vmtest "$chip" "$dev"
echo 0 >"$g/live"
rmdir "$g/bank0/line3" "$g/bank0" "$g"
