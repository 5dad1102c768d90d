#!/usr/bin/env bash
# The systemd units and the sysusers file as installed, checked by systemd's
# own tools: systemd-analyze verify (syntax, directives, the ExecStart binary
# exists and is executable) and systemd-sysusers --dry-run. verify exits 0 on
# an unknown or unparsable directive (it only warns), so a unit passes only
# when verify says nothing at all.
# Units of programs built with libsystemd are Type=notify with a watchdog, of
# a build without it Type=simple with none; both kinds are installed here from
# this one tree (VLFF_I_NOTIFY) and verified.
# Usage: test_units.sh BUILD_DIR notify|simple (the build's: VLFF_WITH_SYSTEMD)
set -u
build=$1 kind=$2
if ! command -v systemd-analyze >/dev/null; then
  echo "SKIP: systemd-analyze not installed (apt install systemd)"; exit 77
fi
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
cmake --install "$build" --prefix "$tmp/p" >"$tmp/install.log" 2>&1 || { cat "$tmp/install.log"; exit 1; }
units="$tmp/p/lib/systemd/system"
quiet_verify() {
  systemd-analyze verify "$1" >"$tmp/verify.log" 2>&1 && [[ ! -s "$tmp/verify.log" ]] || { cat "$tmp/verify.log"; false; }
}
# verify needs no running systemd; if it cannot work in this container at all
# (a unit known to be fine fails), say so and skip rather than pass blindly.
printf '[Service]\nType=oneshot\nExecStart=/bin/true\n' >"$tmp/probe.service"
if ! systemd-analyze verify "$tmp/probe.service" >"$tmp/probe.log" 2>&1; then
  echo "SKIP: systemd-analyze verify cannot run here:"; cat "$tmp/probe.log"; exit 77
fi
for u in vlff-node vlff-camd vlff-pose vlff-view vlff-dds; do
  if [[ ($u == vlff-pose || $u == vlff-view || $u == vlff-dds) && ! -x "$tmp/p/bin/$u" ]]; then
    echo "note: $u is not built in this tree; its unit is checked without its binary"
    sed "s|^ExecStart=[^ ]*|ExecStart=/bin/true|" "$units/$u.service" >"$tmp/$u.service"
    check "$u.service verifies" 'quiet_verify "$tmp/$u.service"'
    continue
  fi
  check "$u.service verifies" 'quiet_verify "$units/$u.service"'
  check "$u.service runs as vlff" 'grep -qx "User=vlff" "$units/$u.service" && grep -qx "Group=vlff" "$units/$u.service"'
done
check "vlff-view.service listens on loopback only (no --listen without a drop-in)" \
  '! grep -q "^ExecStart=.*--listen" "$units/vlff-view.service"'
check "vlff-view.service comes after the node and wants it" \
  'grep -qx "Wants=vlff-node.service" "$units/vlff-view.service" && grep -qx "After=vlff-node.service" "$units/vlff-view.service"'
check "vlff-dds.service comes after the node and wants it, runs vlff-dds with the installed vlff.yaml" \
  'grep -qx "Wants=vlff-node.service" "$units/vlff-dds.service" && grep -q "^After=vlff-node.service" "$units/vlff-dds.service" &&
   grep -qx "ExecStart=$tmp/p/bin/vlff-dds --config $tmp/p/etc/vlff/vlff.yaml" "$units/vlff-dds.service"'
check "vlff-dds.service allows the socket families DDS needs" \
  'grep -qx "RestrictAddressFamilies=AF_UNIX AF_NETLINK AF_INET AF_INET6" "$units/vlff-dds.service"'
# The notifying programs' units: Type=notify with a watchdog exactly when the
# build has libsystemd, Type=simple without one otherwise.
notify_units="vlff-node vlff-camd vlff-pose"
is_notify() { grep -qx "Type=notify" "$1" && grep -qx "NotifyAccess=main" "$1" && grep -q "^WatchdogSec=[1-9]" "$1"; }
is_simple() { grep -qx "Type=simple" "$1" && ! grep -q "^WatchdogSec=\|^NotifyAccess=\|^Type=notify" "$1"; }
for u in $notify_units; do
  check "$u.service is Type=$kind as the build's libsystemd says" 'is_$kind "$units/$u.service"'
  check "$u.service runs $u with the installed vlff.yaml" \
    'grep -qx "ExecStart=$tmp/p/bin/$u --config $tmp/p/etc/vlff/vlff.yaml" "$units/$u.service"'
done
for k in notify simple; do
  on=OFF; [[ $k == notify ]] && on=ON
  cmake -DCMAKE_INSTALL_PREFIX="$tmp/$k" -DVLFF_I_NOTIFY=$on -P "$build/cmake_install.cmake" >"$tmp/install-$k.log" 2>&1 \
    || { cat "$tmp/install-$k.log"; exit 1; }
  for u in $notify_units; do
    f="$tmp/$k/lib/systemd/system/$u.service"
    check "$u.service installed as Type=$k (VLFF_I_NOTIFY=$on)" 'is_$k "$f"'
    if [[ -x "$tmp/$k/bin/$u" ]]; then check "$u.service (Type=$k) verifies" 'quiet_verify "$f"'; fi
  done
done
check "vlff-node.service has its StateDirectory" 'grep -qx "StateDirectory=vlff" "$units/vlff-node.service"'
# The CAN drop-in: installed inert (not under a unit directory), and verified
# with the node's unit as it is once linked into vlff-node.service.d/.
canconf="$tmp/p/share/vlff/systemd/vlff-node.service.d/can.conf"
check "CAN drop-in installed under share/vlff/systemd" '[[ -f "$canconf" ]]'
check "CAN drop-in inert: no vlff-node.service.d in the unit directory" '[[ ! -e "$units/vlff-node.service.d" ]]'
mkdir -p "$tmp/can/vlff-node.service.d"
cp "$units/vlff-node.service" "$tmp/can/"
cp "$canconf" "$tmp/can/vlff-node.service.d/can.conf"
check "vlff-node.service with the CAN drop-in verifies" 'quiet_verify "$tmp/can/vlff-node.service"'
check "CAN drop-in binds to and orders after can0" \
  'grep -qx "BindsTo=sys-subsystem-net-devices-can0.device" "$canconf" && grep -qx "After=sys-subsystem-net-devices-can0.device" "$canconf"'
rtprio=$(sed -n 's/^ *rt_priority: *\([0-9]*\).*/\1/p' "$tmp/p/etc/vlff/default.yaml")
check "CAN drop-in's LimitRTPRIO allows can.rt_priority's default ($rtprio)" \
  '[[ -n "$rtprio" ]] && (( $(sed -n "s/^LimitRTPRIO=//p" "$canconf") >= rtprio ))'
sed -i 's/^LimitRTPRIO=/LimitRTPIRO=/' "$tmp/can/vlff-node.service.d/can.conf"
check "verify reads the drop-in (a misspelt directive there fails)" '! quiet_verify "$tmp/can/vlff-node.service" >/dev/null'
# The sandbox: systemd-analyze security, offline from the unit files, rates
# every unit (the node's also with the CAN drop-in) at 4.0 ("OK") or below;
# the same units without their sandbox lines must rate above it, or the bound
# proves nothing. What each program really does under these options is
# test_unit_sandbox's.
if systemd-analyze security --help 2>/dev/null | grep -q -- '--offline'; then
  # exposure UNIT: systemd-analyze's overall rating of UNIT (e.g. 2.1)
  exposure() { systemd-analyze security --offline=true "$1" 2>&1 | sed -n 's/^→ Overall exposure level for .*: \([0-9.]*\) .*/\1/p'; }
  security_ok() {
    systemd-analyze security --offline=true --threshold=40 "$1" >"$tmp/security.log" 2>&1 ||
      { grep -E '^✗|Overall' "$tmp/security.log"; false; }
  }
  for u in vlff-node vlff-camd vlff-pose vlff-view vlff-dds; do
    f="$units/$u.service"
    [[ -f "$tmp/$u.service" ]] && f="$tmp/$u.service"   # the unit with its command replaced, above
    check "$u.service: systemd-analyze security at most 4.0 (rated $(exposure "$f"))" 'security_ok "$f"'
    sed '/^CapabilityBoundingSet=/,/^RestrictRealtime=/d' "$f" >"$tmp/open-$u.service"
    check "$u.service without its sandbox rates above 4.0 ($(exposure "$tmp/open-$u.service"))" \
      '! security_ok "$tmp/open-$u.service" >/dev/null'
    check "$u.service: native system calls of @system-service only" \
      'grep -qx "SystemCallArchitectures=native" "$f" && grep -qx "SystemCallFilter=@system-service" "$f" &&
       grep -qx "SystemCallErrorNumber=EPERM" "$f" && grep -qx "MemoryDenyWriteExecute=yes" "$f" && grep -qx "CapabilityBoundingSet=" "$f"'
  done
  mkdir -p "$tmp/can2/vlff-node.service.d"
  cp "$units/vlff-node.service" "$tmp/can2/"
  cp "$canconf" "$tmp/can2/vlff-node.service.d/can.conf"
  check "vlff-node.service with the CAN drop-in: security at most 4.0" 'security_ok "$tmp/can2/vlff-node.service"'
  check "CAN drop-in lets the CAN thread take SCHED_FIFO (RestrictRealtime=no)" \
    'grep -qx "RestrictRealtime=yes" "$units/vlff-node.service" && grep -qx "RestrictRealtime=no" "$canconf"'
else
  echo "note: systemd-analyze security has no --offline here (systemd < 250): exposure not rated"
fi
# A mistyped directive must fail verify, or the checks above prove nothing.
sed 's/^Type=notify/Tpye=notify/' "$units/vlff-node.service" >"$tmp/bad.service"
check "a misspelt directive fails the check" '! quiet_verify "$tmp/bad.service" >/dev/null'
# The udev rules that give camd (as vlff) the GPIO chips and USB3 Vision
# cameras: installed where udev reads them, naming the sysusers group. No
# udevd runs here; systemd 253's udevadm verify checks their syntax.
rules="$tmp/p/lib/udev/rules.d/60-vlff.rules"
check "udev rules in <prefix>/lib/udev/rules.d" '[[ -f "$rules" ]]'
check "udev rules: GPIO chips to group vlff" \
  'grep -qx "SUBSYSTEM==\"gpio\", KERNEL==\"gpiochip\[0-9\]\*\", GROUP=\"vlff\", MODE=\"0660\"" "$rules"'
check "udev rules: USB3 Vision devices (interface class ef/05/00) to group vlff" \
  'grep -q "^SUBSYSTEM==\"usb\", ENV{DEVTYPE}==\"usb_device\", ENV{ID_USB_INTERFACES}==\"\*:ef0500:\*\", GROUP=\"vlff\", MODE=\"0660\"$" "$rules"'
check "udev rules' group is the sysusers file's" \
  'grep -q "^u vlff " "$tmp/p/lib/sysusers.d/vlff.conf" && ! grep -v "^#" "$rules" | grep -o "GROUP=\"[^\"]*\"" | grep -vqx "GROUP=\"vlff\""'
if udevadm verify --help >/dev/null 2>&1; then
  check "udev rules verify" 'udevadm verify "$rules" >"$tmp/udev.log" 2>&1 || { cat "$tmp/udev.log"; false; }'
fi
if command -v systemd-sysusers >/dev/null; then
  check "sysusers file parses" \
    'systemd-sysusers --dry-run "$tmp/p/lib/sysusers.d/vlff.conf" >"$tmp/su.log" 2>&1 || { cat "$tmp/su.log"; false; }'
fi
echo "$passes passed, $fails failed"
(( fails == 0 ))
