# Frames captured with candump from the node's CAN code (vlff_can on a real
# vcan, served by can_vm_test) and the DBC `vlff-can dbc` writes for that
# node's config, both printed for the host check: Debian's python3-canmatrix
# (an outside parser, not in the VM) decodes every captured frame with that DBC
# to the values the node sent (tests/unit/can/test_dbc_canmatrix.py --candump).
# vm-bins: can_vm_test vlff-can
# vm-tools: candump
# vm-files: configs/default.yaml
# vm-host-check: /usr/bin/python3 tests/unit/can/test_dbc_canmatrix.py --candump
# vm-timeout: 60
set -e
ip link add dev vdump0 type vcan
ip link set vdump0 up
vlff-can dbc --config /vlff/src/configs/default.yaml >/tmp/node.dbc
candump -L vdump0 >/tmp/cap.log &
dump=$!
sleep 0.3
can_vm_test --serve vdump0 2 >/tmp/serve.log 2>&1
sleep 0.2
kill $dump
wait $dump || true
echo "DBC-BEGIN"; cat /tmp/node.dbc; echo "DBC-END"
echo "CANDUMP-BEGIN"; cat /tmp/cap.log; echo "CANDUMP-END"
[ "$(grep -c . /tmp/cap.log)" -gt 20 ]
ip link del vdump0
echo "can_candump: ok"
