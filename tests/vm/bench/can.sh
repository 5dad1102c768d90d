# Run by tests/bench/can.sh through tests/vm/run: heartbeat jitter and status
# frames/s capacity on vcan.
# vm-bins: can_vm_bench
# vm-timeout: 180
set -e
ip link add dev vbench0 type vcan
ip link set vbench0 up
can_vm_bench vbench0
