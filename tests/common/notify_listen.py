#!/usr/bin/python3
"""A notify socket as systemd gives a Type=notify service, for the tests.

Usage: notify_listen.py SOCKET LOG SECONDS [PATH]
Binds the datagram socket SOCKET and writes each message received to LOG, a
line each, until STOPPING=1 or SECONDS pass. With PATH, a READY=1 is written
as "READY=1 (exists)" when PATH exists at that moment, so a test can check
that readiness came only once what the service promised was there.
"""
import os
import socket
import sys
import time

sock_path, log_path, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
ready_path = sys.argv[4] if len(sys.argv) > 4 else None
s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
s.bind(sock_path)
s.settimeout(0.5)
end = time.time() + seconds
with open(log_path, "w") as out:
    while time.time() < end:
        try:
            msg = s.recv(4096).decode()
        except socket.timeout:
            continue
        if msg == "READY=1" and ready_path and os.path.exists(ready_path):
            msg += " (exists)"
        out.write(msg + "\n")
        out.flush()
        if "STOPPING=1" in msg:
            break
