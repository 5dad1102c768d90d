# vlff-camd's RGB-D pair fired by GPIO: gpio.mode input on a gpio-sim line
# fires software triggers on two Aravis fake GigE cameras in the VM
# (colour on 127.0.0.1, Mono16 range on 127.0.0.2, an address put on the
# VM's loopback); every edge must give one record holding both frames,
# stamped with the edge's kernel timestamp, and nothing unmatched.
# vm-bins: vlff-camd vlff-camd-vmtest
# vm-tools: arv-fake-gv-camera-0.8
# vm-timeout: 120
set -e
ip link set lo up
ip addr add 127.0.0.2/8 dev lo 2>/dev/null || true
g=/sys/kernel/config/gpio-sim/vlff-camd-pair
mkdir "$g" "$g/bank0"
echo 2 >"$g/bank0/num_lines"
echo 1 >"$g/live"
chip=$(cat "$g/bank0/chip_name")
dev=$(ls -d /sys/devices/platform/gpio-sim.*/"$chip")
arv-fake-gv-camera-0.8 -i 127.0.0.1 >/tmp/fakecam1.log 2>&1 &
c1=$!
arv-fake-gv-camera-0.8 -i 127.0.0.2 >/tmp/fakecam2.log 2>&1 &
c2=$!
rc=0
vlff-camd-vmtest gpio-pair "$chip" "$dev" || rc=$?
kill "$c1" "$c2"
wait "$c1" "$c2" 2>/dev/null || true
echo 0 >"$g/live"
rmdir "$g/bank0" "$g"
exit $rc
