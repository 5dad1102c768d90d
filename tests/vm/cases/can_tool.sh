# The vlff-can tool against a live node on vcan: dump decodes heartbeat and
# status frames, send gets the right ack and exit status.
# vm-bins: can_vm_test vlff-can
# vm-files: configs/vlff.dbc
# vm-timeout: 60
set -e
ip link add dev vtool0 type vcan
ip link set vtool0 up
can_vm_test --serve vtool0 6 >/tmp/serve.log 2>&1 &
sleep 1.5
vlff-can -t 1 vtool0 dump >/tmp/dump.txt
cat /tmp/dump.txt | head -16
grep -q '72A heartbeat node=42 state=operational' /tmp/dump.txt
grep -q '180 TRAIN iteration=123456789 keyframes=77 prompt_set=1 state=operational' /tmp/dump.txt
grep -q '181 LOSS total=2.5000 color=0.0421 depth=0.1370 feature=0.9000' /tmp/dump.txt
grep -q '182 MAP version=31 age_ms=never fps_in=29.97' /tmp/dump.txt
grep -q '183 HEALTH flags=0x02\[pose-stale\] fps_dropped=0.50 cmd_rejected=0 tx_dropped=0' /tmp/dump.txt
grep -q '185 INGEST refused=193 last_reason=6 ' /tmp/dump.txt
grep -q '186 MEMORY rss=1435MiB keyframes=60/2048MiB evidence=9/16MiB' /tmp/dump.txt
grep -q '187 PAGING keyframes_paged=128 keyframes_dropped=3 evidence_dropped=65535 box_growths=12 box_refused=2' /tmp/dump.txt
vlff-can -s 7 vtool0 send save | tee /tmp/ack.txt
grep -q '580 ACK node=42 cmd=save seq=7 result=ok' /tmp/ack.txt
vlff-can vtool0 send prompt-set 2
rc=0; vlff-can vtool0 send prompt-set 9 || rc=$?
[ "$rc" = 1 ]   # out-of-range: a NAK
rc=0; vlff-can -n 5 -t 0.3 vtool0 send save || rc=$?
[ "$rc" = 1 ]   # nobody at node 5: no ack (a runtime failure)
rc=0; vlff-can vtool0 send launch 2>/dev/null || rc=$?
[ "$rc" = 2 ]   # not a command: a usage error
wait
cat /tmp/serve.log
grep -q 'served: 1 saves, 2 prompt set' /tmp/serve.log
ip link del vtool0
echo "can_tool: ok"
