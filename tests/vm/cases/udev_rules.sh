# The udev rules (configs/udev/60-vlff.rules) as udev itself applies them:
# Debian's udevadm test on a gpio-sim chip gives /dev/gpiochipN the group
# vlff, mode 0660, and reports no fault anywhere in the file (the USB3 Vision
# rule is parsed too; no USB device exists here to match it). The same file
# with a misspelt key on the USB3 Vision line must report a fault there, or
# the fault check proves nothing.
# vm-tools: udevadm
# vm-files: configs/udev/60-vlff.rules
set -e
mkdir -p /etc/udev/rules.d /run/udev
grep -q '^vlff:' /etc/group 2>/dev/null || echo 'vlff:x:990:' >>/etc/group
g=/sys/kernel/config/gpio-sim/vlff-udev
mkdir "$g" "$g/bank0"
echo 1 >"$g/bank0/num_lines"
echo 1 >"$g/live"
chip=$(cat "$g/bank0/chip_name")
rules=/etc/udev/rules.d/60-vlff.rules
# utest LOG: udevadm test on the chip with the rules in place, log in LOG
utest() { udevadm test --action=add "/sys/bus/gpio/devices/$chip" >"$1" 2>&1; }
# faults LOG: the lines where udev finds fault with the rules file
faults() { grep '60-vlff\.rules' "$1" | grep -iE 'invalid|unknown|ignor|error|fail|warn' || true; }
fails=0
cp "$VLFF_SRC/configs/udev/60-vlff.rules" "$rules"
rc=0
utest /tmp/udev.log || rc=$?
grep '60-vlff' /tmp/udev.log
if [ $rc != 0 ]; then echo "FAIL: udevadm test exits $rc"; fails=1; fi
if ! grep -q "Setting permissions /dev/$chip, uid=0, gid=990, mode=0660" /tmp/udev.log; then
  echo "FAIL: /dev/$chip not given group vlff (990), mode 0660"; fails=1
fi
if [ -n "$(faults /tmp/udev.log)" ]; then echo "FAIL: udev finds fault with the rules:"; faults /tmp/udev.log; fails=1; fi
sed 's/^\(SUBSYSTEM=="usb".*\)GROUP=/\1GRUOP=/' "$VLFF_SRC/configs/udev/60-vlff.rules" >"$rules"
utest /tmp/udev-bad.log || true
if [ -z "$(faults /tmp/udev-bad.log)" ]; then echo "FAIL: a misspelt key on the USB3 Vision line goes unreported"; fails=1; fi
faults /tmp/udev-bad.log
rm -f "$rules"
echo 0 >"$g/live"
rmdir "$g/bank0" "$g"
[ $fails = 0 ] || { tail -30 /tmp/udev.log; exit 1; }
echo "udev rules: $chip to vlff 0660, no fault; a misspelt key reported"
