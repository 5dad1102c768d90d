"""Checks one program's strace log against its installed unit's sandbox: every
system call it made must pass the unit's SystemCallFilter= (systemd's sets
expanded by `systemd-analyze syscall-filter`), every socket family it asked
for must be in RestrictAddressFamilies=. Prints what broke the rules.
Usage: sandbox_check.py UNIT_FILE STRACE_LOG [FAMILY...] (strace -f -qq -o LOG)
       sandbox_check.py --vm UNIT_FILE [FAMILY...] CONSOLE_OUTPUT
The FAMILYs named are let pass: tries of the program that the unit refuses on
purpose (the caller says why)."""
import re
import subprocess
import sys

if sys.argv[1] == "--vm":
    # tests/vm/cases/camd_sandbox.sh's host check: the log lies between
    # STRACE-BEGIN and STRACE-END in the case's console output (last argument).
    import tempfile
    lines = open(sys.argv[-1], errors="replace").read().splitlines()
    try:
        part = lines[lines.index("STRACE-BEGIN") + 1:lines.index("STRACE-END")]
    except ValueError:
        sys.exit("sandbox_check: no STRACE-BEGIN/END in the console output")
    tmpf = tempfile.NamedTemporaryFile("w", suffix=".st", delete=False)
    tmpf.write("\n".join(part) + "\n")
    tmpf.close()
    sys.argv = [sys.argv[0], sys.argv[2], tmpf.name] + sys.argv[3:-1]
unit, log = sys.argv[1:3]
refused_on_purpose = set(sys.argv[3:])


def sets():
    """systemd's named sets: '@name' -> members (names and '@sets')."""
    out = subprocess.run(["systemd-analyze", "syscall-filter", "--no-pager"], capture_output=True,
                         text=True, check=True).stdout
    groups, cur = {}, None
    for line in out.splitlines():
        if re.match(r"^@[\w-]+$", line):
            cur = groups.setdefault(line, set())
        elif not line.strip():
            cur = None
        elif cur is not None and not line.strip().startswith("#"):
            cur.add(line.strip())
    return groups


def expand(name, groups, seen=()):
    if not name.startswith("@"):
        return {name}
    if name not in groups:
        sys.exit(f"sandbox_check: systemd-analyze knows no set {name}")
    out = set()
    for m in groups[name]:
        if m not in seen:
            out |= expand(m, groups, seen + (name,))
    return out


allow, deny, families = None, set(), None
groups = sets()
for line in open(unit):
    key, _, val = line.strip().partition("=")
    if key == "SystemCallFilter" and val:
        neg = val.startswith("~")
        names = set().union(*(expand(n, groups) for n in val.lstrip("~").split()))
        if neg:
            deny |= names
        else:
            allow = names if allow is None else allow | names
    elif key == "RestrictAddressFamilies" and val:
        families = set(val.split())
if allow is None or families is None:
    sys.exit(f"sandbox_check: {unit} has no SystemCallFilter= allow list or no RestrictAddressFamilies=")

calls, fams = set(), set()
for line in open(log, errors="replace"):
    m = re.match(r"^\d+\s+([a-z0-9_]+)\((AF_\w+)?", line)
    if m:
        calls.add(m.group(1))
        if m.group(1) in ("socket", "socketpair") and m.group(2):
            fams.add(m.group(2))
bad_calls = sorted(c for c in calls if c not in allow or c in deny)
bad_fams = sorted(fams - families - refused_on_purpose)
for c in bad_calls:
    print(f"FAIL: system call {c} is outside {unit}'s SystemCallFilter")
for f in bad_fams:
    print(f"FAIL: socket family {f} is outside {unit}'s RestrictAddressFamilies")
if not calls:
    print(f"FAIL: no system calls in {log}")
print(f"{len(calls)} system calls, families {sorted(fams)}: {len(bad_calls) + len(bad_fams)} outside the unit")
sys.exit(1 if bad_calls or bad_fams or not calls else 0)
