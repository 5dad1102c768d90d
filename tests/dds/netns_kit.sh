#!/usr/bin/env bash
# Sourced by the vlff-dds network tests: two network namespaces A and B
# joined by a veth pair (10.213.0.1 and .2), each side's Cyclone DDS on its
# veth end only, so that DDS discovery and data cross the link. Sets nsa,
# nsb, va, vb, the command prefixes in_a and in_b (ip netns exec and env exec
# the program: $! is the program's own pid), tmp (a scratch directory) and
# p (a prefix for segment names); defines check, wait_until and a cleanup
# that kills the pids in $pids, removes the namespaces, tmp and the
# segments. Exits 77 (skipped) without root or ip netns.
if [[ $(id -u) != 0 ]] || ! command -v ip >/dev/null; then
  echo "skipped: ip netns needs root and iproute2"; exit 77
fi
fails=0 passes=0
check() { if eval "$2"; then passes=$((passes + 1)); else echo "FAIL: $1"; fails=$((fails + 1)); fi; }
wait_until() { local k; for ((k = 0; k < $1; k++)); do eval "$2" && return 0; sleep 0.1; done; return 1; }
tmp=$(mktemp -d)
p=/dds-$$
nsa=vlffdds-a-$$ nsb=vlffdds-b-$$ va=vdda$$ vb=vddb$$
pids=()
cleanup() {
  local x
  for x in "${pids[@]}"; do kill -9 "$x" 2>/dev/null; done
  ip netns del "$nsa" 2>/dev/null
  ip netns del "$nsb" 2>/dev/null
  rm -rf "$tmp"
  rm -f /dev/shm$p-*
}
trap cleanup EXIT
if ! ip netns add "$nsa" || ! ip netns add "$nsb"; then
  echo "skipped: cannot create network namespaces here"; exit 77
fi
ip link add "$va" netns "$nsa" type veth peer name "$vb" netns "$nsb" || { echo "FAIL: veth pair"; exit 1; }
ip -n "$nsa" addr add 10.213.0.1/24 dev "$va"
ip -n "$nsb" addr add 10.213.0.2/24 dev "$vb"
for n in "$nsa" "$nsb"; do ip -n "$n" link set lo up; done
ip -n "$nsa" link set "$va" up
ip -n "$nsb" link set "$vb" up
# Loopback would also work inside one namespace; the point is the link.
# ${DDS_DISCOVERY:-} is extra Cyclone <Discovery> settings.
uri() {
  echo "<CycloneDDS><Domain Id=\"any\"><General><Interfaces><NetworkInterface name=\"$1\"/></Interfaces></General>${DDS_DISCOVERY:+<Discovery>$DDS_DISCOVERY</Discovery>}</Domain></CycloneDDS>"
}
ua=$(uri "$va") ub=$(uri "$vb")
in_a=(ip netns exec "$nsa" env CYCLONEDDS_URI="$ua")
in_b=(ip netns exec "$nsb" env CYCLONEDDS_URI="$ub")
