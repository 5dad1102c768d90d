# GPIO pulse jitter for scripts/bench drivers, on a gpio-sim line inside the
# VM (qemu TCG: emulated CPU and timers, so an upper bound). Not a test case:
# tests/bench/drivers.sh runs it and reads the RESULT line from the console.
# vm-bins: bench_drivers
# vm-timeout: 60
set -e
g=/sys/kernel/config/gpio-sim/vlff-bench
mkdir "$g" "$g/bank0"
echo 1 >"$g/bank0/num_lines"
echo 1 >"$g/live"
bench_drivers --gpio-jitter "$(cat "$g/bank0/chip_name")" 0
echo 0 >"$g/live"
rmdir "$g/bank0" "$g"
