# vlff_can on real SocketCAN (vcan): heartbeat under load, commands, malformed
# frames, DBC decoding of live frames (classic and FD), error frames, full tx
# queue (plug qdisc), interface down/up and re-creation.
# vm-bins: can_vm_test
# vm-tools: tc
# vm-files: configs/vlff.dbc
# vm-timeout: 150
exec can_vm_test
