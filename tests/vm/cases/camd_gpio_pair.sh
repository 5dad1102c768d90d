# vlff-camd's RGB-D pair fired by GPIO: gpio.mode input on a gpio-sim line
# fires software triggers on two Aravis fake GigE cameras in the VM
# (colour on 127.0.0.1, Mono16 range on 127.0.0.2, an address put on the
# VM's loopback); every edge must give one record holding both frames,
# stamped with the edge's kernel timestamp, and nothing unmatched.
# vm-bins: vlff-camd vlff-camd-vmtest
# vm-tools: arv-fake-gv-camera-0.8
# vm-files: tests/vm/cases/camd.inc
# vm-timeout: 120
# vm-stream: cameras
set -e
. "$VLFF_SRC/tests/vm/cases/camd.inc"
ip link set lo up
ip addr add 127.0.0.2/8 dev lo 2>/dev/null || true
camd_gpio_run vlff-camd-pair gpio-pair 127.0.0.1 127.0.0.2
