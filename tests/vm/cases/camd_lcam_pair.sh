# vlff-camd pairing a libcamera colour camera with an Aravis range camera:
# vimc free-runs, Aravis' fake GigE camera (127.0.0.1, Mono16) is fired by
# gpio-sim edges (gpio.mode input) that also stamp vimc's next frame; every
# edge must give one RGB-D record in the ring, at the configured 240x180,
# stamped with the edge's kernel time (or with vimc's own time when its
# frame began just before the edge, within the pair tolerance), and no range
# frame unmatched.
# vm-bins: vlff-camd vlff-camd-vmtest
# vm-tools: arv-fake-gv-camera-0.8 media-ctl v4l2-ctl
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so.sign
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/vimc_ipa_proxy /usr/share/libcamera/ipa/vimc
# vm-files: tests/vm/cases/camd.inc
# vm-timeout: 180
# vm-stream: cameras
set -e
. "$VLFF_SRC/tests/vm/cases/camd.inc"
ip link set lo up
vimc_ready
camd_gpio_run vlff-camd-lpair lcam-pair 127.0.0.1
