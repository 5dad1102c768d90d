# vlff-camd + GPIO end to end: gpio.mode input on a gpio-sim line fires
# software triggers on Aravis' fake GigE camera (running in the VM on
# 127.0.0.1); edges driven through the sim's pull attribute must give one
# frame each, stamped with the edge's kernel timestamp.
# vm-bins: vlff-camd vlff-camd-vmtest
# vm-tools: arv-fake-gv-camera-0.8
# vm-files: tests/vm/cases/camd.inc
# vm-timeout: 90
# vm-stream: cameras
set -e
. "$VLFF_SRC/tests/vm/cases/camd.inc"
camd_gpio_run vlff-camd gpio-trigger 127.0.0.1
