#!/usr/bin/env bash
# mmdebstrap essential hook ($1 = root): settings that must exist before the kernel package
# installs and builds its initramfs.
set -euo pipefail
R=$1
mkdir -p "$R/etc/initramfs-tools/conf.d" "$R/etc/initramfs-tools/hooks"
# The default (MODULES=most) gave a 24 MB initramfs; list what booting needs instead.
cat > "$R/etc/initramfs-tools/conf.d/exolink.conf" <<'CONF'
MODULES=list
COMPRESS=zstd
CONF
install -m 0755 /dev/stdin "$R/etc/initramfs-tools/hooks/exolink" <<'HOOK'
#!/bin/sh
# exolink: drivers to find and mount the root on the BeagleBone's SD card (and on qemu's virt
# machine for the boot smoke test), plus the AM335x watchdog so systemd can arm it at once.
case "$1" in prereqs) exit 0 ;; esac
. /usr/share/initramfs-tools/hook-functions
for m in ext4 mmc_block sdhci-omap omap_hsmmc omap_wdt virtio_blk virtio_mmio virtio_pci; do
  manual_add_modules "$m"
done
force_load ext4
HOOK
