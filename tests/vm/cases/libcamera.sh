# libcamera against the vimc virtual camera: vlff-camd (camera.kind
# libcamera) streams into a frame ring, checked by vlff-camd-vmtest (size,
# format, monotonic sensor timestamps, colour bar content, clean shutdown).
# vm-bins: vlff-camd vlff-camd-vmtest
# vm-tools: media-ctl v4l2-ctl
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so /usr/lib/x86_64-linux-gnu/libcamera/ipa_vimc.so.sign
# vm-host-files: /usr/lib/x86_64-linux-gnu/libcamera/vimc_ipa_proxy /usr/share/libcamera/ipa/vimc
# vm-files: tests/vm/cases/camd.inc
# vm-timeout: 150
# vm-stream: cameras
set -e
. "$VLFF_SRC/tests/vm/cases/camd.inc"
vimc_ready
vlff-camd-vmtest libcamera 8
