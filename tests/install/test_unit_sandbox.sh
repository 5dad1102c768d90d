#!/usr/bin/env bash
# The installed programs under their units' sandbox, as far as it can be had
# without a running systemd: each does a short real job (the node trains on
# the simulator with its CAN thread on, camd streams Aravis' fake GigE camera
# into its ring, vlff-pose takes a pose over UDP, vlff-view serves its page on lo)
# under strace and with the kernel's memory-deny-write-execute set
# (PR_SET_MDWE, what MemoryDenyWriteExecute= asks of the kernel since systemd
# 253; 252 refuses the same mappings with seccomp). Every system call each
# made must pass its installed unit's SystemCallFilter= and every socket
# family be in its RestrictAddressFamilies= (sandbox_check.py), and each must
# do its job and exit 0 on SIGTERM (vlff-view: SIGINT).
# Not covered: journald's and sd_notify's AF_UNIX sockets (no systemd here;
# they are in every list), cameras other than GigE (no V4L2, USB or libcamera
# device on the host).
# Usage: test_unit_sandbox.sh BUILD_DIR SOURCE_DIR
set -u
build=$1 src=$2
for t in strace systemd-analyze; do
  command -v $t >/dev/null || { echo "SKIP: $t not installed (scripts/setup --test)"; exit 77; }
done
py=/usr/bin/python3
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
wait_until() { local k; for ((k = 0; k < $1; k++)); do eval "$2" && return 0; sleep 0.1; done; return 1; }
tmp=$(mktemp -d)
p=/vlff-sbx-$$
pids=()
cleanup() {
  local x
  for x in "${pids[@]}"; do kill -9 "$x" 2>/dev/null; done
  rm -rf "$tmp"
  rm -f /dev/shm$p-*
}
trap cleanup EXIT
cmake --install "$build" --prefix "$tmp/p" >"$tmp/install.log" 2>&1 || { cat "$tmp/install.log"; exit 1; }
bin="$tmp/p/bin" units="$tmp/p/lib/systemd/system"

# "${mdwe[@]}" CMD...: runs CMD with PR_SET_MDWE (refuse writable+executable
# memory), which children and exec'd programs inherit.
mdwe=("$py" -c 'import ctypes, os, sys
libc = ctypes.CDLL(None, use_errno=True)
if libc.prctl(65, 1, 0, 0, 0):  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN
    sys.exit("PR_SET_MDWE: " + os.strerror(ctypes.get_errno()))
os.execvp(sys.argv[1], sys.argv[1:])')
wx='import mmap; mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)'
if ! "${mdwe[@]}" true 2>"$tmp/mdwe.log"; then
  echo "note: $(cat "$tmp/mdwe.log") (kernel before 6.3): the programs run without it"
  mdwe=(env)
else
  check "MDWE holds under strace (a writable executable mapping is refused)" \
    '"$py" -c "$wx" && ! "${mdwe[@]}" strace -f -qq -o /dev/null "$py" -c "$wx" 2>/dev/null'
fi
# sandboxed NAME CMD...: runs CMD (the program) in the background under MDWE
# and strace (log $tmp/NAME.st); $traced is the program's pid (the first
# line of strace's log: its execve), $tracer strace's.
sandboxed() {
  local name=$1
  shift
  "${mdwe[@]}" strace -f -qq -o "$tmp/$name.st" "$@" >"$tmp/$name.log" 2>&1 &
  tracer=$!
  pids+=("$tracer")
  traced=""
  wait_until 100 'traced=$(sed -n "1s/^\([0-9][0-9]*\) .*/\1/p" "$tmp/$name.st" 2>/dev/null); [[ -n "$traced" ]]'
  [[ -n "$traced" ]] && pids+=("$traced")
}
# stopped SIGNAL: signals the program, waits for strace, which exits with the
# program's status.
stopped() {
  [[ -n "$traced" ]] || { echo "no traced program to stop"; return 1; }
  kill "-$1" "$traced" && wait "$tracer"
}
# rules NAME [FAMILY...]: NAME's calls and families within its unit; the
# families named are the program's own tries that the unit refuses on purpose.
rules() {
  local u=$1
  shift
  "$py" "$src/tests/install/sandbox_check.py" "$units/$u.service" "$tmp/$u.st" "$@" >"$tmp/$u.check" || { cat "$tmp/$u.check"; false; }
}
# stat_of SEGMENT [KEY]: KEY (head) of vlff-shm stat SEGMENT, empty while there is none
stat_of() { "$bin/vlff-shm" stat "$1" 2>/dev/null | sed -n "s/^${2:-head} //p"; }

# The node: trains on the simulator's rings; its CAN thread opens AF_CAN
# sockets (the host has no SocketCAN: refused, retried) and asks for SCHED_FIFO.
printf 'node:\n  state_dir: %s\nsource:\n  kind: sim\nsim:\n  frames: 20\n  rate_hz: 10\nshm:\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\n  feature_ring: %s-f\ncan:\n  enabled: true\n  interface: vlffsbx0\n' \
  "$tmp" $p $p $p $p >"$tmp/n.yaml"
"$bin/vlff-sim" --config "$tmp/n.yaml" --quiet 2>"$tmp/sim.log" &
sim=$!
pids+=("$sim")
sandboxed vlff-node "$bin/vlff-node" --config "$tmp/n.yaml"
wait_until 300 'it=$(stat_of $p-m iterations); [[ -n "$it" ]] && (( it > 0 )) && grep -q "vlffsbx0: cannot open" "$tmp/vlff-node.log"'
stopped TERM
node_rc=$?
check "node exits 0 on SIGTERM (rc=$node_rc)" '(( node_rc == 0 )) || { tail -5 "$tmp/vlff-node.log"; false; }'
kill "$sim" 2>/dev/null
wait "$sim" 2>/dev/null
check "node trained (iterations in its last line)" 'grep -qE "I node: stopped: [1-9][0-9]* iterations" "$tmp/vlff-node.log"'
check "node: its CAN thread asked for AF_CAN" 'grep -q "socket(AF_CAN" "$tmp/vlff-node.st"'
check "node: system calls and socket families within vlff-node.service" 'rules vlff-node'
# The check itself: the same calls under a filter without @resources (the
# CAN thread's sched_setscheduler), or a family list without AF_CAN, fail.
cp "$units/vlff-node.service" "$tmp/narrow.service"
echo "SystemCallFilter=~@resources" >>"$tmp/narrow.service"
check "sandbox_check refuses a call outside the filter" \
  '"$py" "$src/tests/install/sandbox_check.py" "$tmp/narrow.service" "$tmp/vlff-node.st" >"$tmp/narrow.out";
   grep -q "system call sched_setscheduler is outside" "$tmp/narrow.out"'
sed 's/^RestrictAddressFamilies=.*/RestrictAddressFamilies=AF_UNIX/' "$units/vlff-node.service" >"$tmp/narrow.service"
check "sandbox_check refuses a family outside the list" \
  '"$py" "$src/tests/install/sandbox_check.py" "$tmp/narrow.service" "$tmp/vlff-node.st" >"$tmp/narrow.out";
   grep -q "family AF_CAN is outside" "$tmp/narrow.out"'

# camd: Aravis' fake GigE camera on loopback (one at a time on the machine:
# test_camd's lock) into the frame ring.
if [[ -x "$bin/vlff-camd" ]] && command -v arv-fake-gv-camera-0.8 >/dev/null; then
  exec 9>/tmp/vlff-fake-gv-camera.lock
  flock 9
  arv-fake-gv-camera-0.8 -i 127.0.0.1 >/dev/null 2>&1 &
  cam=$!
  pids+=("$cam")
  printf 'shm:\n  ring: %s-c\n  pose_ring: %s-cp\n  max_width: 640\n  max_height: 480\ncamera:\n  kind: aravis\n  device: 127.0.0.1\n  pixel_format: RGB8\n  width: 320\n  height: 240\n  frame_rate: 20\n  intrinsics: [500, 500, 160, 120]\n' \
    $p $p >"$tmp/c.yaml"
  sleep 1
  sandboxed vlff-camd "$bin/vlff-camd" --config "$tmp/c.yaml"
  wait_until 300 'h=$(stat_of $p-c); [[ -n "$h" ]] && (( h >= 5 ))'
  h=$(stat_of $p-c)
  stopped TERM
  camd_rc=$?
  kill -9 "$cam" 2>/dev/null
  wait "$cam" 2>/dev/null
  flock -u 9
  check "camd streamed the fake camera into its ring (head ${h:-none})" '[[ -n "$h" ]] && (( h >= 5 )) || { tail -5 "$tmp/vlff-camd.log"; false; }'
  check "camd exits 0 on SIGTERM (rc=$camd_rc)" '(( camd_rc == 0 )) || { tail -5 "$tmp/vlff-camd.log"; false; }'
  # Aravis first tries a packet socket for the stream (it needs CAP_NET_RAW,
  # which the unit does not give) and streams over UDP when refused.
  check "camd: system calls and socket families within vlff-camd.service" 'rules vlff-camd AF_PACKET'
else
  echo "note: vlff-camd or arv-fake-gv-camera-0.8 missing: camd not run"
fi

# vlff-pose: one TUM line over UDP into the pose ring.
if [[ -x "$bin/vlff-pose" ]]; then
  port=$((20000 + $$ % 20000))
  printf 'shm:\n  pose_ring: %s-pose\npose:\n  udp: "127.0.0.1:%d"\n' $p $port >"$tmp/p.yaml"
  sandboxed vlff-pose "$bin/vlff-pose" --config "$tmp/p.yaml"
  wait_until 100 '[[ -n "$(stat_of $p-pose)" ]]'
  for _ in 1 2 3; do echo "1.0 0 0 0 0 0 0 1" >"/dev/udp/127.0.0.1/$port"; sleep 0.2; done
  wait_until 50 '[[ "$(stat_of $p-pose)" -ge 1 ]]'
  h=$(stat_of $p-pose)
  stopped TERM
  pose_rc=$?
  check "vlff-pose wrote the pose it received (head ${h:-none})" '[[ -n "$h" ]] && (( h >= 1 ))'
  check "vlff-pose exits 0 on SIGTERM (rc=$pose_rc)" '(( pose_rc == 0 ))'
  check "vlff-pose: system calls and socket families within vlff-pose.service" 'rules vlff-pose'
fi

# vlff-view: serves its page, listening on an interface by name (lo: the
# interface list comes over netlink).
if [[ -x "$bin/vlff-view" ]]; then
  sandboxed vlff-view "$bin/vlff-view" --port 0 --listen lo --map $p-m --frames ""
  port=""
  wait_until 100 'port=$(sed -n "s|^vlff-view: serving http://lo:\([0-9]*\)/.*|\1|p" "$tmp/vlff-view.log"); [[ -n "$port" ]]'
  got=""
  if [[ -n "$port" ]] && exec 3<>"/dev/tcp/127.0.0.1/$port"; then
    printf 'GET /index.html HTTP/1.1\r\nHost: 127.0.0.1:%s\r\n\r\n' "$port" >&3
    got=$(timeout 10 head -1 <&3)
    exec 3<&-
  fi
  stopped INT
  view_rc=$?
  check "vlff-view served its page (${got:-no answer})" '[[ "$got" == "HTTP/1.1 200"* ]]'
  check "vlff-view exits 0 on SIGINT (rc=$view_rc)" '(( view_rc == 0 ))'
  check "vlff-view: system calls and socket families within vlff-view.service" 'rules vlff-view'
fi
# vlff-dds: joins DDS (multicast discovery on lo, the interface list over
# netlink), publishes the map and status of the node's segment from above.
if [[ -x "$bin/vlff-dds" ]]; then
  dom=$((($$ % 200) + 1))
  printf 'shm:\n  ring: %s-r\n  map: %s-m\n  prompts: %s-p\ndds:\n  domain_id: %d\n  namespace: /sbx\n  status_hz: 10\n' \
    $p $p $p $dom >"$tmp/d.yaml"
  sandboxed vlff-dds env CYCLONEDDS_URI='<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface name="lo"/></Interfaces></General></Domain></CycloneDDS>' \
    "$bin/vlff-dds" --config "$tmp/d.yaml" -v
  wait_until 100 'grep -q "map version" "$tmp/vlff-dds.log"'
  stopped TERM
  dds_rc=$?
  check "vlff-dds sent the segment's map (log: $(tail -1 "$tmp/vlff-dds.log"))" 'grep -q "map version" "$tmp/vlff-dds.log"'
  check "vlff-dds exits 0 on SIGTERM (rc=$dds_rc)" '(( dds_rc == 0 ))'
  check "vlff-dds: system calls and socket families within vlff-dds.service" 'rules vlff-dds'
fi
echo "$passes passed, $fails failed"
(( fails == 0 ))
