#!/usr/bin/python3
"""The node's watchdog goes unfed while one of its threads makes no progress.

Runs vlff-node as systemd runs a Type=notify service (a notify socket of our
own, WATCHDOG_USEC), waits for WATCHDOG=1, then freezes one named thread
(vlff-trainer or vlff-ingest) alone with ptrace (PTRACE_SEIZE + INTERRUPT:
the other threads and the main loop go on, as they do when a thread hangs in
a deadlock or a driver call), and checks that WATCHDOG=1 stops while it is
frozen, that the log names the quiet thread, and that feeding resumes once it
is let go.

Usage: watchdog_stall.py NODE CONFIG THREAD WORKDIR [EMULATOR...]
Exit 0 pass, 1 fail, 77 when ptrace is not permitted here.
"""
import ctypes
import os
import re
import signal
import socket
import subprocess
import sys
import time

PTRACE_DETACH, PTRACE_SEIZE, PTRACE_INTERRUPT = 17, 0x4206, 0x4207
WALL = 0x40000000
PERIOD_S = 1.0  # WATCHDOG_USEC: a thread counts as quiet after half of it

node, config, thread, work = sys.argv[1:5]
libc = ctypes.CDLL(None, use_errno=True)
libc.ptrace.argtypes = [ctypes.c_long, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p]
libc.ptrace.restype = ctypes.c_long

sock_path = os.path.join(work, "wd-%s.sock" % thread)
sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
sock.bind(sock_path)
sock.settimeout(0.05)
msgs = []  # (time, message)


def collect(until):
    while time.monotonic() < until:
        try:
            m = sock.recv(4096).decode()
        except socket.timeout:
            continue
        msgs.append((time.monotonic(), m))


def fail(why):
    print("FAIL: watchdog with %s frozen: %s" % (thread, why))
    print("messages: %s" % [(round(t - t0, 2), m) for t, m in msgs])
    sys.stdout.write(open(log_path).read()[-3000:])
    sys.exit(1)


log_path = os.path.join(work, "wd-%s.log" % thread)
env = dict(os.environ, NOTIFY_SOCKET=sock_path, WATCHDOG_USEC=str(int(PERIOD_S * 1e6)))
t0 = time.monotonic()
proc = subprocess.Popen([node, "--config", config], env=env, stderr=open(log_path, "w"))
tid = None
try:
    # Ready, and fed while both threads loop (slow to start under sanitizers).
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and sum(m == "WATCHDOG=1" for _, m in msgs) < 2:
        collect(time.monotonic() + 0.2)
    if not any(m == "READY=1" for _, m in msgs):
        fail("no READY=1")
    if sum(m == "WATCHDOG=1" for _, m in msgs) < 2:
        fail("no WATCHDOG=1 while both threads loop")
    for t in os.listdir("/proc/%d/task" % proc.pid):
        if open("/proc/%d/task/%s/comm" % (proc.pid, t)).read().strip() == thread:
            tid = int(t)
    if tid is None:
        fail("no thread named %s" % thread)
    if libc.ptrace(PTRACE_SEIZE, tid, None, None) != 0:
        err = ctypes.get_errno()
        print("SKIP: ptrace not permitted here (%s): the stall is not checked" % os.strerror(err))
        proc.kill()
        proc.wait()
        sys.exit(77)
    if libc.ptrace(PTRACE_INTERRUPT, tid, None, None) != 0:
        fail("PTRACE_INTERRUPT: %s" % os.strerror(ctypes.get_errno()))
    os.waitpid(tid, WALL)  # the thread is stopped from here on
    frozen = time.monotonic()
    collect(frozen + 3 * PERIOD_S)
    libc.ptrace(PTRACE_DETACH, tid, None, None)
    thawed = time.monotonic()
    tid = None
    collect(thawed + 2 * PERIOD_S)
    proc.send_signal(signal.SIGTERM)
    rc = proc.wait(timeout=60)
    collect(time.monotonic() + 0.3)
finally:
    if tid is not None:
        libc.ptrace(PTRACE_DETACH, tid, None, None)
    if proc.poll() is None:
        proc.kill()
        proc.wait()

# Half a period for the beat to go stale, a quarter for the next check.
quiet_from = frozen + 0.75 * PERIOD_S
fed_frozen = [t for t, m in msgs if m == "WATCHDOG=1" and quiet_from <= t <= thawed]
if fed_frozen:
    fail("WATCHDOG=1 sent %.2f s after the freeze" % (fed_frozen[0] - frozen))
if not any(m == "WATCHDOG=1" and t > thawed for t, m in msgs):
    fail("no WATCHDOG=1 once the thread runs again")
short = thread.replace("vlff-", "")
quiet = [float(x) for x in re.findall(r"watchdog not fed: .*?\b%s ([0-9.]+) s" % short, open(log_path).read())]
if not quiet or max(quiet) < PERIOD_S:
    fail("the log does not name the quiet %s thread (%s)" % (short, quiet))
if rc != 0 or not any(m == "STOPPING=1" for _, m in msgs):
    fail("SIGTERM: rc %d, STOPPING=1 %s" % (rc, any(m == "STOPPING=1" for _, m in msgs)))
print("ok: %s frozen %.1f s: no WATCHDOG=1 from %.2f s on, fed again after" % (thread, thawed - frozen, 0.75 * PERIOD_S))
