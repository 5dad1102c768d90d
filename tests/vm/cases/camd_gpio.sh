# vlff-camd + GPIO end to end: gpio.mode input on a gpio-sim line fires
# software triggers on Aravis' fake GigE camera (running in the VM on
# 127.0.0.1); edges driven through the sim's pull attribute must give one
# frame each, stamped with the edge's kernel timestamp.
# vm-bins: vlff-camd vlff-camd-vmtest
# vm-tools: arv-fake-gv-camera-0.8
# vm-timeout: 90
set -e
g=/sys/kernel/config/gpio-sim/vlff-camd
mkdir "$g" "$g/bank0"
echo 2 >"$g/bank0/num_lines"
echo 1 >"$g/live"
chip=$(cat "$g/bank0/chip_name")
dev=$(ls -d /sys/devices/platform/gpio-sim.*/"$chip")
arv-fake-gv-camera-0.8 -i 127.0.0.1 >/tmp/fakecam.log 2>&1 &
cam=$!
rc=0
vlff-camd-vmtest gpio-trigger "$chip" "$dev" || rc=$?
kill "$cam"
wait "$cam" 2>/dev/null || true
echo 0 >"$g/live"
rmdir "$g/bank0" "$g"
exit $rc
