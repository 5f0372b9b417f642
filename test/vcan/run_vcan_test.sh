#!/usr/bin/env bash
# ctest entry for the SocketCAN test: runs test_can_vcan inside a throwaway VM with a real vcan0
# (test/vcan/vcan-vm.sh, a copy of the team tool so CI needs nothing outside the clone).
# Exit 0: passed in the VM. Exit 77 (ctest SKIP_RETURN_CODE): the VM could not start, with the reason printed.
# Anything else: the test failed inside the VM.
set -uo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
BIN="${1:?usage: run_vcan_test.sh <test_can_vcan binary> [work dir]}"
WORK="${2:-$(pwd)/vcan_vm_work}"
skip() { echo "SKIPPED: vcan VM test: $*"; exit 77; }

[ -x "$BIN" ] || { echo "FAILED: test binary $BIN not built"; exit 1; }
[ "$(id -u)" = 0 ] || skip "needs root (9p passthrough and apt in vcan-vm.sh)"
command -v qemu-system-x86_64 >/dev/null || command -v apt-get >/dev/null || skip "no qemu-system-x86_64 and no apt-get to install it"
command -v cansend >/dev/null && command -v candump >/dev/null || skip "can-utils (cansend/candump) not installed"

rm -rf "$WORK" && mkdir -p "$WORK" && cd "$WORK" || exit 1
# The marker proves the VM booted and ran our command; without it a failure is the VM's, not the test's.
export VCAN_VM_TIMEOUT="${VCAN_VM_TIMEOUT:-240}"
start=$(date +%s)
"$HERE/vcan-vm.sh" -- sh -c "touch vm_started; ip -details link show vcan0 >/dev/null && exec '$BIN' --gtest_color=no" 2>&1 | tee vm.log
rc=${PIPESTATUS[0]}
echo "vcan VM test: exit $rc after $(( $(date +%s) - start )) s"
if [ ! -f vm_started ]; then
  reason=$(grep -m1 -E "vcan-vm:|qemu|Could not|failed" vm.log || true)
  skip "the VM did not start (vcan-vm.sh exit $rc${reason:+: $reason})"
fi
exit "$rc"
