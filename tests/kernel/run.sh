#!/usr/bin/env bash
# make test-kernel: the kernel-facing tests on real kernels, in throwaway guests.
#   SocketCAN tests (vcan, broadcast manager, netlink, the whole appliance) and the power-cut
#   safety of the board's writes to the card's FAT partition, in User-Mode Linux.
#   libgpiod tests (gpio-sim) in a qemu guest (Debian's UML has no GPIO support).
# Inside a guest a missing kernel feature fails the run (EXOLINK_REQUIRE_KERNEL); on the plain host
# the same tests skip with the reason. Guests and kernels: tests/kernel/vmtest.sh (cached in VMDIR).
set -euo pipefail
repo=$(cd "$(dirname "$0")/../.." && pwd)
export VMDIR=${VMDIR:-$HOME/.cache/exolink-vmtest}
vm="$repo/tests/kernel/vmtest.sh"
work="$repo/.vmtest"
rm -rf "$work/tmp" "$work/pt"; mkdir -p "$work/tmp" "$work/cache"
t0=$(date +%s)
bash "$vm" setup
t1=$(date +%s)
pytest="cd $repo && export PYTHONDONTWRITEBYTECODE=1 TMPDIR=$work/tmp EXOLINK_CACHE=$work/cache \
EXOLINK_KERNEL_RESULTS=$work EXOLINK_LOG_JSON=1; $repo/.venv/bin/python -m pytest -p no:cacheprovider \
--basetemp=$work/pt -q -rs -s"
rc=0
echo "== SocketCAN tests and FAT card writes in User-Mode Linux"
card="$work/fat-card.img"; rm -f "$card"; truncate -s 64M "$card"   # /dev/ubdb in the guest
VM_UML_DISK=$card bash "$vm" uml "$repo" "export EXOLINK_REQUIRE_KERNEL=can,fat,clock EXOLINK_FAT_CARD=$card; \
$pytest tests/kernel/test_socketcan.py tests/kernel/test_fat_writes.py \
tests/kernel/test_wall_clock.py tests/kernel/test_lease.py" || rc=$?
t2=$(date +%s)
echo "== gpio-sim tests in qemu (software emulation)"
bash "$vm" qemu "$repo" "export EXOLINK_REQUIRE_KERNEL=gpio; $pytest tests/kernel/test_gpio.py" || rc=$((rc ? rc : $?))
t3=$(date +%s)
echo "kernel tests: setup $((t1 - t0)) s, uml $((t2 - t1)) s, qemu $((t3 - t2)) s, rc=$rc"
exit $rc
