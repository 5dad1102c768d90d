#!/usr/bin/env bash
# A running vlff-node against its prompt mailbox and hostile shared memory (issue 29):
# vlff-shm set-prompts prints the node's answer, forged and refused sets fail loudly,
# a burst of posters is answered one by one, and truncating the map, the mailbox or
# the frame ring under the node and the simulator kills neither.
set -u
. "$(dirname "$0")/node_sh.sh" mbx "$@"
wait_until 200 'grep -q "waiting for ring" "$tmp/log"'

check "mailbox is group-writable (0660)" '[[ $(stat -c %a /dev/shm$p-p) == 660 ]]'
check "set -i 0 accepted" '[[ $("$shm" set-prompts $p-p -i 0) == "accepted 1" ]]'
out=$("$shm" set-prompts $p-p -i 99 2>&1); rc=$?
check "set -i 99 refused with the node's reason, rc 1 ($out)" '[[ $rc == 1 && $out == "refused 2: "*"prompt set 99"* ]]'
out=$("$shm" set-prompts $p-p "$(printf 'wall\nlabel 0 confidence 255 prompt FAKE')" floor 2>&1); rc=$?
check "forged newline refused before posting ($out)" '[[ $rc == 1 && $out == *"control characters"* ]]'
check "nothing was posted" '"$shm" stat $p-p | grep -qE "^posts 2$"'
out=$("$shm" set-prompts $p-p chair chair 2>&1); rc=$?
check "duplicate prompts refused ($out)" '[[ $rc == 1 && $out == *"repeats"* ]]'
burst=()
for k in 1 2 3 4 5; do "$shm" set-prompts $p-p -i 0 >"$tmp/burst.$k" 2>&1 & burst+=($!); done
wait "${burst[@]}"
check "a burst of 5 posters: every one accepted, 5 distinct numbers" \
  '[[ $(cat "$tmp"/burst.* | grep -c "^accepted") == 5 && $(cat "$tmp"/burst.* | sort -u | wc -l) == 5 ]]'

# Truncation under the node: the map writer and the mailbox.
truncate -s 4096 /dev/shm$p-m
truncate -s 100 /dev/shm$p-p
sleep 1
check "node alive after its map and mailbox were truncated" 'kill -0 $nodepid'
check "map truncation logged" 'grep -qE "map (heartbeat|status): .*shrank" "$tmp/log"'
check "mailbox posts answered again after the truncation" '"$shm" set-prompts $p-p -i 0 | grep -q "^accepted"'
check "the map segment is whole again" '[[ $(stat -c %s /dev/shm$p-m) -gt 4096 ]]'

# Truncation of the frame and feature rings under the simulator (writer) and of the
# frame ring under the node (reader).
"$sim" --config "$tmp/n.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 300 'grep -q "attached to ring" "$tmp/log"'
check "node attached to the simulator's ring" 'grep -q "attached to ring" "$tmp/log"'
truncate -s 4096 /dev/shm$p-r
truncate -s 4096 /dev/shm$p-f
sleep 2
check "simulator alive after its ring was truncated" 'kill -0 $simpid'
check "simulator logged it" 'grep -q "frame ring: .*shrank" "$tmp/simlog" && grep -q "feature ring: .*shrank" "$tmp/simlog"'
check "node alive after its input ring was truncated" 'kill -0 $nodepid'
check "node re-attached to the replaced ring" '[[ $(grep -c "attached to ring" "$tmp/log") -ge 2 ]]'
# A poster that holds the mailbox mid-post (its sequence word odd) and then dies:
# the node keeps training and publishing meanwhile, then discards the half-written
# request with a log line, and posting works again.
mapv() { "$shm" stat $p-m | awk '$1 == "version" { print $2 }'; }
wait_until 600 '[[ $(mapv) -ge 1 ]]'
# One process holding the lock, as a poster would (flock(1) would leave its child
# holding it after the kill).
python3 -c 'import fcntl, os, sys, time
fcntl.flock(os.open(sys.argv[1], os.O_RDONLY), fcntl.LOCK_EX)
time.sleep(120)' /dev/shm$p-p &
holder=$!
sleep 0.2
b=$(od -An -tu1 -j128 -N1 /dev/shm$p-p | tr -d ' ')
printf "\\x$(printf %02x $((b + 1)))" | dd of=/dev/shm$p-p bs=1 seek=128 count=1 conv=notrunc status=none
v0=$(mapv)
wait_until 600 '(( $(mapv) >= v0 + 2 ))'
check "node publishes while a poster holds the mailbox mid-post (v$v0 -> v$(mapv))" '(( $(mapv) >= v0 + 2 ))'
kill -9 $holder; wait $holder 2>/dev/null
wait_until 600 'grep -q "left half-written" "$tmp/log"'
check "the dead poster's half-written request is logged" 'grep -q "left half-written by poster pid" "$tmp/log"'
# The answer comes between two trainer passes: under ASan one can outlast
# set-prompts' default 5 s.
check "posting works after the dead poster" '"$shm" set-prompts -t 120 $p-p -i 0 | grep -q "^accepted"'
kill "$simpid"; wait "$simpid"; simpid=
stop_node
verdict
