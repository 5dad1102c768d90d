# A live vlff-node on a real vcan: its own heartbeat and status frames (classic
# and FD, non-default ids), captured with candump while it trains on a small
# simulated room, then stopped over CAN (`vlff-can send stop`, acked). The
# host check (tests/unit/can/test_dbc_canmatrix.py --node) decodes the capture
# with the DBC `vlff-can dbc` wrote for that config, using Debian's
# python3-canmatrix, and compares the stopped node's last frames with its
# status as `vlff-shm stat` read it from the map segment.
# vm-bins: vlff-node vlff-sim vlff-can vlff-shm
# vm-tools: candump
# vm-files: tests/vm/cases/can_node.yaml
# vm-host-check: /usr/bin/python3 tests/unit/can/test_dbc_canmatrix.py --node
# vm-timeout: 150
set -e
cfg=/vlff/src/tests/vm/cases/can_node.yaml
ip link add dev vnode0 type vcan
ip link set vnode0 mtu 72
ip link set vnode0 up
mkdir -p /tmp/vmcan
vlff-can dbc --config $cfg >/tmp/node.dbc
candump -L vnode0 >/tmp/cap.log &
dump=$!
vlff-node --config $cfg >/tmp/node.log 2>&1 &
node=$!
vlff-sim --config $cfg --quiet >/tmp/sim.log 2>&1 &
sim=$!
# Polls `vlff-shm stat` until grep ARGS match, at most TRIES times NAP s;
# the node's log and a failure if they never do.
stat_until() { # tries nap grep-args...
  tries=$1 nap=$2 i=0
  shift 2
  until vlff-shm stat /vmcan-map 2>/dev/null | grep -q "$@"; do
    i=$((i + 1))
    if [ $i -gt "$tries" ]; then cat /tmp/node.log; exit 1; fi
    sleep "$nap"
  done
}
# Training under the VM's emulated CPU: wait for keyframes and steps.
stat_until 200 0.5 '^iterations [1-9]'
vlff-can -f $cfg vnode0 send stop -t 5
# The ack says the command was queued; the trainer applies it after the step
# it is in, which under the VM's emulated CPU on a loaded host can take a
# while: wait until the node says it stopped, then for status frames of the
# stopped node (can.status_ms).
stat_until 120 0.25 -x 'state stopped'
sleep 1.5
echo "STAT-BEGIN"; vlff-shm stat /vmcan-map; echo "STAT-END"
sleep 0.5
kill $sim
kill $node
wait $node || true
kill $dump
wait $dump || true
echo "DBC-BEGIN"; cat /tmp/node.dbc; echo "DBC-END"
echo "CANDUMP-BEGIN"; cat /tmp/cap.log; echo "CANDUMP-END"
ip link del vnode0
echo "can_node: ok"
