"""The DBC that `vlff-can dbc` writes for a node with non-default ids, read by
an outside parser (Debian's python3-canmatrix), decodes frames encoded by the
project's CAN code (can_dbc_frames) to the values that were encoded.
Usage: test_dbc_canmatrix.py VLFF_CAN CAN_DBC_FRAMES TMPDIR
       test_dbc_canmatrix.py --candump CONSOLE_OUTPUT
       test_dbc_canmatrix.py --node CONSOLE_OUTPUT
The second form is the host check of tests/vm/cases/can_candump.sh: the DBC
that case's `vlff-can dbc` wrote and the frames candump captured from the
node's CAN code on vcan (can_vm_test --serve: frozen status), both cut from
the case's console output; the newest frame of each message must decode to
the served values. The third is the host check of tests/vm/cases/can_node.sh:
frames of a live vlff-node, stopped over CAN; its last status frames must
decode to the status `vlff-shm stat` read from its map segment."""
import subprocess
import sys
import warnings

warnings.simplefilter("ignore")
try:
    import canmatrix
    import canmatrix.formats
except ImportError:
    print("SKIP: python3-canmatrix not installed (apt install python3-canmatrix)")
    sys.exit(77)

def section(lines, name):
    a, b = lines.index(name + "-BEGIN"), lines.index(name + "-END")
    return lines[a + 1:b]


def load_capture(path):
    """The case's DBC, read by canmatrix, and its candump -L frames as
    (id, payload) in capture order (FD frames are written "ID##<flags><data>")."""
    import os
    import tempfile
    lines = open(path, errors="replace").read().splitlines()
    dbc_text, dump = section(lines, "DBC"), section(lines, "CANDUMP")
    with tempfile.TemporaryDirectory() as d:
        with open(os.path.join(d, "node.dbc"), "w") as f:
            f.write("\n".join(dbc_text) + "\n")
        db = canmatrix.formats.loadp_flat(os.path.join(d, "node.dbc"))
    frames = []
    for line in dump:
        # candump -L: "(1700000000.123456) vdump0 180#0123456789ABCDEF"
        parts = line.split()
        if len(parts) != 3 or "#" not in parts[2]:
            continue
        fid, data = parts[2].split("#", 1)
        if data.startswith("#"):
            data = data[2:]
        frames.append((int(fid, 16), bytes.fromhex(data)))
    return lines, db, frames


def node_check(path):
    lines, db, frames = load_capture(path)
    stat = {}
    for line in section(lines, "STAT"):
        k, _, v = line.partition(" ")
        stat.setdefault(k, v)
    fails = []
    decoded = []
    for fid, data in frames:
        frame = db.frame_by_id(canmatrix.ArbitrationId(fid))
        if frame is not None:
            decoded.append((frame.name, {k: float(v.phys_value) for k, v in frame.decode(data).items()}))
    names = {n for n, _ in decoded}
    # With can.fd (the case's config) one STATUS_FD frame carries what the
    # classic TRAIN, LOSS, MAP, HEALTH, INGEST, MEMORY and PAGING frames would.
    fd = "VLFF_STATUS_FD" in names
    train, mapm, ingest, mem, paging = (("VLFF_STATUS_FD",) * 5 if fd
                                        else ("VLFF_TRAIN", "VLFF_MAP", "VLFF_INGEST", "VLFF_MEMORY", "VLFF_PAGING"))
    for want in ("VLFF_HEARTBEAT", "VLFF_ACK", train, mapm, ingest, mem, paging):
        if want not in names:
            fails.append(f"no {want} frame captured")
    states = [d["NmtState"] for n, d in decoded if n == "VLFF_HEARTBEAT"]
    if 5 not in states or states[-1] != 4:
        fails.append(f"heartbeat states {sorted(set(states))}, last {states[-1] if states else None}: "
                     "want operational, then stopped last")
    its = [d["Iteration"] for n, d in decoded if n == train]
    if its != sorted(its):
        fails.append(f"{train} iterations went backwards")
    acks = [d for n, d in decoded if n == "VLFF_ACK"]
    if acks and acks[-1]["Result"] != 0:
        fails.append(f"stop command acked with {acks[-1]}")
    newest = {}
    for n, d in decoded:
        newest[n] = d
    want = {"Iteration": int(stat["iterations"]), "Keyframes": int(stat["keyframes"]),
            "NmtState": int(stat["state_code"])}
    for sig, v in want.items():
        got = newest.get(train, {}).get(sig)
        if got != v:
            fails.append(f"{train}.{sig}: last frame {got}, vlff-shm stat {v}")
    got = newest.get(ingest, {}).get("FramesRefused")
    if got != int(stat["frames_refused"]):
        fails.append(f"{ingest}.FramesRefused: {got}, vlff-shm stat {stat['frames_refused']}")
    # The limits are the config's, in the signals' steps; the resident set
    # moves between the frame and the stat, so only its scale is checked.
    last = newest.get(mem, {})
    for sig, key, step in (("MemKeyframesLimit", "mem_keyframes_limit_mb", 4),
                           ("MemEvidenceLimit", "mem_evidence_limit_mb", 1)):
        want_mb = step * int(float(stat[key]) / step + 0.5)
        if last.get(sig) != want_mb:
            fails.append(f"{mem}.{sig}: {last.get(sig)}, vlff-shm stat {stat[key]}")
    rss = float(stat["mem_rss_mb"])
    if not (rss / 2 <= last.get("MemRss", -1) <= rss * 2):
        fails.append(f"{mem}.MemRss: {last.get('MemRss')}, vlff-shm stat {rss}")
    if not 0 <= last.get("MemKeyframes", -1) <= last.get("MemKeyframesLimit", -1):
        fails.append(f"{mem}.MemKeyframes: {last.get('MemKeyframes')} of {last.get('MemKeyframesLimit')}")
    # The stopped node's paging counts and box growths: vlff-shm stat's,
    # saturated to the signals' width. Its box grew from a first box in a
    # corner of the room (can_node.yaml), so one of them is a count that moved.
    if int(stat["box_growths"]) < 1:
        fails.append(f"vlff-shm stat box_growths {stat['box_growths']}: the node's box never grew")
    last = newest.get(paging, {})
    for sig, key, top in (("KeyframesPaged", "keyframes_paged", 65535), ("KeyframesDropped", "keyframes_dropped", 65535),
                          ("EvidenceDropped", "evidence_dropped", 65535), ("BoxGrowths", "box_growths", 255),
                          ("BoxRefused", "box_refused", 255)):
        if last.get(sig) != min(int(stat[key]), top):
            fails.append(f"{paging}.{sig}: {last.get(sig)}, vlff-shm stat {stat[key]}")
    if not any(d["FpsIn"] > 0 for n, d in decoded if n == mapm):
        fails.append(f"no {mapm} frame with frames coming in")
    for f in fails:
        print("FAIL:", f)
    print(f"{len(frames)} captured frames, {len(decoded)} decoded, iterations {want['Iteration']}, "
          f"{len(fails)} failures")
    sys.exit(1 if fails else 0)


def candump_check(path):
    lines, db, frames = load_capture(path)
    served = {  # can_vm_test's fixed_status(), node 42, operational
        "VLFF_HEARTBEAT": {"NmtState": 5},
        "VLFF_TRAIN": {"Iteration": 123456789, "Keyframes": 77, "PromptSet": 1, "NmtState": 5},
        "VLFF_LOSS": {"LossTotal": 2.5, "LossColor": 0.0421, "LossDepth": 0.137, "LossFeature": 0.9},
        "VLFF_MAP": {"MapVersion": 31, "MapAge": 65535, "FpsIn": 29.97},
        "VLFF_HEALTH": {"ErrPoseStale": 1, "ErrCameraLost": 0, "FpsDropped": 0.5},
        "VLFF_MEMORY": {"MemRss": 1435, "MemKeyframes": 60, "MemKeyframesLimit": 2048, "MemEvidence": 9,
                        "MemEvidenceLimit": 16},
        "VLFF_PAGING": {"KeyframesPaged": 128, "KeyframesDropped": 3, "EvidenceDropped": 65535, "BoxGrowths": 12,
                        "BoxRefused": 2},
    }
    newest = {}
    for fid, data in frames:
        frame = db.frame_by_id(canmatrix.ArbitrationId(fid))
        if frame is not None:
            newest[frame.name] = data
    fails = 0
    for name, want in served.items():
        if name not in newest:
            print(f"FAIL: no {name} frame captured")
            fails += 1
            continue
        decoded = db.frame_by_name(name).decode(newest[name])
        for sig, v in want.items():
            got = float(decoded[sig].phys_value)
            if abs(got - v) > 1e-9 + 1e-6 * abs(v):
                print(f"FAIL: {name}.{sig}: decoded {got}, served {v}")
                fails += 1
    print(f"{len(frames)} captured frames, {len(newest)} messages decoded, {fails} failures")
    sys.exit(1 if fails else 0)


if sys.argv[1] == "--candump":
    candump_check(sys.argv[2])
if sys.argv[1] == "--node":
    node_check(sys.argv[2])

vlff_can, frames_prog, tmp = sys.argv[1:4]
cfg = f"{tmp}/node17.yaml"
with open(cfg, "w") as f:
    f.write("can:\n  node_id: 17\n  status_base_id: 0x200\n  command_id: 0x611\n  ack_id: 0x591\n"
            "  heartbeat_ms: 50\n  status_ms: 100\n")
dbc = f"{tmp}/node17.dbc"
with open(dbc, "w") as f:
    subprocess.run([vlff_can, "dbc", "--config", cfg], stdout=f, check=True)
db = canmatrix.formats.loadp_flat(dbc)

expect = {
    "VLFF_TRAIN": {"Iteration": 123456, "Keyframes": 41, "PromptSet": 2, "NmtState": 5},
    "VLFF_LOSS": {"LossTotal": 1.234, "LossColor": 0.0123, "LossDepth": 0.0456, "LossFeature": 0.789},
    "VLFF_MAP": {"MapVersion": 77, "MapAge": 1500, "FpsIn": 29.97},
    "VLFF_HEALTH": {"ErrCameraLost": 1, "ErrPoseStale": 0, "ErrCmdRejected": 1, "FpsDropped": 1.5,
                    "CmdRejected": 3, "TxDropped": 4, "BusOff": 1, "BusPassive": 0},
    "VLFF_INGEST": {"FramesRefused": 193, "LastRefusal": 6, "RefusedNoPose": 1, "RefusedNoDepth": 0,
                    "RefusedPeriod": 15},
    "VLFF_MEMORY": {"MemRss": 1435, "MemKeyframes": 60, "MemKeyframesLimit": 2048, "MemEvidence": 9,
                    "MemEvidenceLimit": 16},
    # can_dbc_frames' 70000 voxels given up saturate
    "VLFF_PAGING": {"KeyframesPaged": 128, "KeyframesDropped": 3, "EvidenceDropped": 65535, "BoxGrowths": 12,
                    "BoxRefused": 2},
    "VLFF_HEARTBEAT": {"NmtState": 5},
    "VLFF_COMMAND": {"Target": 17, "Command": 5, "Argument": 2, "Sequence": 17},
    "VLFF_ACK": {"Node": 17, "Command": 5, "Result": 2, "Sequence": 17},
}
CLASSIC = ("VLFF_TRAIN", "VLFF_LOSS", "VLFF_MAP", "VLFF_HEALTH", "VLFF_INGEST", "VLFF_MEMORY", "VLFF_PAGING")
expect["VLFF_STATUS_FD"] = {k: v for m in CLASSIC for k, v in expect[m].items()}
ids = {"VLFF_HEARTBEAT": 0x700 + 17, "VLFF_TRAIN": 0x200, "VLFF_HEALTH": 0x203, "VLFF_STATUS_FD": 0x204,
       "VLFF_INGEST": 0x205, "VLFF_MEMORY": 0x206, "VLFF_PAGING": 0x207,
       "VLFF_COMMAND": 0x611, "VLFF_ACK": 0x591}

fails = 0
out = subprocess.run([frames_prog, cfg], capture_output=True, text=True, check=True).stdout
seen = set()
for line in out.splitlines():
    name, fid, hexdata = line.split()
    frame = db.frame_by_id(canmatrix.ArbitrationId(int(fid)))
    if frame is None or frame.name != name:
        print(f"FAIL: id {int(fid):#x}: the DBC has {frame.name if frame else 'nothing'}, expected {name}")
        fails += 1
        continue
    seen.add(name)
    decoded = frame.decode(bytes.fromhex(hexdata))
    for sig, want in expect[name].items():
        got = float(decoded[sig].phys_value)
        if abs(got - want) > 1e-9 + 1e-6 * abs(want):
            print(f"FAIL: {name}.{sig}: decoded {got}, encoded {want}")
            fails += 1
for name, fid in ids.items():
    frame = db.frame_by_id(canmatrix.ArbitrationId(fid))
    if frame is None or frame.name != name:
        print(f"FAIL: {name} not at {fid:#x} in the DBC")
        fails += 1
if seen != set(expect):
    print(f"FAIL: decoded {sorted(seen)}, expected {sorted(expect)}")
    fails += 1
cycle = {f.name: f.cycle_time for f in db.frames}
if cycle.get("VLFF_HEARTBEAT") != 50 or cycle.get("VLFF_TRAIN") != 100:
    print(f"FAIL: cycle times {cycle}")
    fails += 1
if cycle.get("VLFF_STATUS_FD"):
    print(f"FAIL: classic DBC gives VLFF_STATUS_FD, never sent, a cycle time: {cycle}")
    fails += 1

# With can.fd the node sends the heartbeat, STATUS_FD and acks, nothing else:
# the DBC lists those (and the command), STATUS_FD cyclic with NmtState's
# value table, and none of the classic status frames.
nmt = {0: "BootUp", 4: "Stopped", 5: "Operational", 127: "PreOperational", 143: "Error"}
cfg_fd = f"{tmp}/node17fd.yaml"
with open(cfg_fd, "w") as f:
    f.write(open(cfg).read() + "  fd: true\n")
dbc_fd = f"{tmp}/node17fd.dbc"
with open(dbc_fd, "w") as f:
    subprocess.run([vlff_can, "dbc", "--config", cfg_fd], stdout=f, check=True)
dbfd = canmatrix.formats.loadp_flat(dbc_fd)
fd_names = {fr.name for fr in dbfd.frames}
if fd_names != {"VLFF_HEARTBEAT", "VLFF_STATUS_FD", "VLFF_COMMAND", "VLFF_ACK"}:
    print(f"FAIL: can.fd DBC lists {sorted(fd_names)}")
    fails += 1
fdcycle = {fr.name: fr.cycle_time for fr in dbfd.frames}
if fdcycle.get("VLFF_STATUS_FD") != 100 or fdcycle.get("VLFF_HEARTBEAT") != 50:
    print(f"FAIL: can.fd DBC cycle times {fdcycle}")
    fails += 1
for d, what in ((dbfd, "can.fd"), (db, "classic")):
    fr = d.frame_by_name("VLFF_STATUS_FD")
    vals = {int(k): v for k, v in fr.signal_by_name("NmtState").values.items()} if fr else {}
    if vals != nmt:
        print(f"FAIL: {what} DBC: VLFF_STATUS_FD.NmtState value table {vals}")
        fails += 1
out_fd = subprocess.run([frames_prog, cfg_fd], capture_output=True, text=True, check=True).stdout
for line in out_fd.splitlines():
    name, fid, hexdata = line.split()
    frame = dbfd.frame_by_id(canmatrix.ArbitrationId(int(fid)))
    if name in CLASSIC:
        if frame is not None:
            print(f"FAIL: can.fd DBC has {frame.name} at {int(fid):#x}, a classic status id")
            fails += 1
        continue
    if frame is None or frame.name != name:
        print(f"FAIL: can.fd DBC: id {int(fid):#x} is {frame.name if frame else 'nothing'}, expected {name}")
        fails += 1
        continue
    decoded = frame.decode(bytes.fromhex(hexdata))
    for sig, want in expect[name].items():
        got = float(decoded[sig].phys_value)
        if abs(got - want) > 1e-9 + 1e-6 * abs(want):
            print(f"FAIL: can.fd DBC {name}.{sig}: decoded {got}, encoded {want}")
            fails += 1
    if "NmtState" in decoded and decoded["NmtState"].named_value != "Operational":
        print(f"FAIL: can.fd DBC {name}.NmtState names {decoded['NmtState'].named_value}")
        fails += 1
print(f"{len(seen)} messages decoded, {fails} failures")
sys.exit(1 if fails else 0)
