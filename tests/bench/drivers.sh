#!/usr/bin/env bash
# scripts/bench drivers: GPIO pulse jitter measured on gpio-sim inside the
# qemu VM (this host has no GPIO chips), then bench_drivers on the host
# (vlff-camd vs a bare Aravis grab loop), which reports the VM jitter in its
# RESULT line marked gpio_jitter_measured_on=qemu_tcg.
set -uo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
build=${VLFF_BUILD:?VLFF_BUILD (the Release tree) must be set}
jitter=
if [[ -z "${VLFF_BENCH_GPIO_CHIP:-}" ]]; then
  echo "gpio: measuring pulse jitter in the qemu VM (TCG emulation, not real hardware timing)"
  "$root/tests/vm/run" "$build" "$root/tests/vm/bench/gpio_jitter.sh" | sed 's/^/  /'
  if (( PIPESTATUS[0] == 0 )); then
    grep -a '^gpio: ' "$build/vm/console.log" | sed 's/^/  vm /'
    jitter=$(sed -nE 's/^RESULT gpio_pulse_jitter_us_p99=([0-9.]+)$/\1/p' "$build/vm/console.log" | tail -1)
  fi
  [[ -n "$jitter" ]] || echo "!!! gpio: no jitter from the VM (see above): reported as NA"
fi
VLFF_BENCH_GPIO_JITTER_VM_US=$jitter exec "$build/bench/bench_drivers"
