#!/usr/bin/env bash
# A node waiting for its frame ring says why, at warning level, once for each
# new reason (issue 29): no segment yet, not a vlff segment, a mode wider than
# shm.mode, a ring of other records, a file shorter than its header says; then
# it attaches to the simulator's ring once that is there. The same for the
# feature ring. Rings removed from /dev/shm under it are followed too.
set -u
. "$(dirname "$0")/node_sh.sh" rng "$@"
seeds=$VLFF_SOURCE_DIR/tests/fuzz/seeds/shm_header
r=/dev/shm$p-r
# why N TEXT: the log holds exactly N warnings about the ring that contain TEXT.
why() { [[ $(grep -c " W node: waiting for ring $p-r: .*$2" "$tmp/log") == "$1" ]]; }
# put TEXT: waits until the node logged TEXT once, then a while more (retries
# happen every 0.1 s): a reason is not repeated while it holds.
put() { wait_until 100 "why 1 '$1'" && sleep 0.5; }

# place MODE: the file built in $r.new takes the ring's name at once, with MODE.
place() { chmod "$1" "$r.new" && mv "$r.new" "$r"; }

put "no such segment"
check "missing ring: logged once" 'why 1 "no such segment"'
head -c 4096 /dev/zero | tr '\0' 'x' >"$r.new"; place 600
put "is not a vlff segment"
check "not a vlff segment: logged once" 'why 1 "is not a vlff segment"'
chmod 644 "$r"
put "mode 0644 has bits beyond 0640"
check "a mode wider than shm.mode: logged once" 'why 1 "mode 0644 has bits beyond 0640"'
cp "$seeds/ring_pose" "$r.new"; place 600
put "ring of record kind 4, expected 2"
check "a pose ring where frames are expected: logged once" 'why 1 "ring of record kind 4, expected 2"'
head -c 1000 "$seeds/ring_frame" >"$r.new"; place 600
put "1000 bytes, header says"
check "a frame ring shorter than its header says: logged once" 'why 1 "1000 bytes, header says"'
check "every reason at warning level, none twice" \
  '[[ $(grep -c "waiting for ring" "$tmp/log") == 5 && $(grep -c " W node: waiting for ring" "$tmp/log") == 5 ]]'
# A frame ring to read (the seed's, whose producer is gone): the node attaches
# and then says why the feature ring beside it is refused.
f=/dev/shm$p-f
cp "$seeds/ring_pose" "$f.new" && chmod 600 "$f.new" && mv "$f.new" "$f"
cp "$seeds/ring_frame" "$r.new"; place 600
wait_until 100 'grep -q "waiting for feature ring $p-f: .*record kind 4, expected 3" "$tmp/log"' && sleep 0.5
check "a pose ring as feature ring: logged once" \
  '[[ $(grep -c " W node: waiting for feature ring $p-f: .*record kind 4, expected 3" "$tmp/log") == 1 ]]'
# The simulator replaces both (their creator is gone); the node follows.
"$sim" --config "$tmp/n.yaml" --quiet 2>"$tmp/simlog" &
simpid=$!
wait_until 300 '[[ $(grep -c "attached to ring $p-r" "$tmp/log") -ge 2 ]] && grep -q "attached to feature ring $p-f" "$tmp/log"'
check "node attached to the simulator's frame ring" '[[ $(grep -c "attached to ring $p-r" "$tmp/log") -ge 2 ]]'
check "node attached to the simulator's feature ring" 'grep -q "attached to feature ring $p-f" "$tmp/log"'
# The simulator dies and its rings are removed by hand before it is started
# again: the node, left mapped to files no name leads to, attaches to the new
# ones (the frame ring's read and the feature ring's poll say EPIPE).
kill -9 "$simpid"; wait "$simpid" 2>/dev/null
rm -f "$r" "$f"
"$sim" --config "$tmp/n.yaml" --quiet 2>"$tmp/simlog2" &
simpid=$!
wait_until 300 '[[ $(grep -c "attached to ring $p-r" "$tmp/log") -ge 3 && $(grep -c "attached to feature ring $p-f" "$tmp/log") -ge 2 ]]'
check "node attached to the new frame ring after the old one was removed" '[[ $(grep -c "attached to ring $p-r" "$tmp/log") -ge 3 ]]'
check "node attached to the new feature ring after the old one was removed" \
  '[[ $(grep -c "attached to feature ring $p-f" "$tmp/log") -ge 2 ]]'
kill "$simpid"; wait "$simpid"; simpid=
stop_node
verdict
