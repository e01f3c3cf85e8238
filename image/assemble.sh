#!/usr/bin/env bash
# assemble.sh ROOTFS IMG: the SD-card layout the AM335x boot chain needs, without loop devices.
#   sector 0      MBR (disk id $DISK_ID)
#   128 KiB       MLO (the boot ROM's raw-mode offset; also tried at 0/256/384 KiB)
#   384 KiB       u-boot.img (SPL's CONFIG_SYS_MMCSD_RAW_MODE_U_BOOT_SECTOR=0x300)
#   4 MiB         p1 FAT32 "EXOLINK", bootable: extlinux.conf, kernel, initrd, merged dtb,
#                 exolink-settings.yaml (the file users edit on a laptop)
#   after p1      p2 ext4 root "exolink-root" (grown to the card on first boot)
set -euo pipefail
cd "$(dirname "$0")/.."
. image/image.conf
R=$1 IMG=$2
T=$(dirname "$IMG")/parts && rm -rf "$T" && mkdir -p "$T"

# p1: FAT from the root's /boot/firmware (the mount point stays, empty, in the root).
boot_sectors=$((BOOT_SIZE_MIB * 2048))
mkfs.vfat -F 32 -n EXOLINK -i "${DISK_ID#0x}" -C "$T/boot.vfat" $((BOOT_SIZE_MIB * 1024)) >/dev/null
mcopy -s -i "$T/boot.vfat" "$R"/boot/firmware/* ::/
find "$R/boot/firmware" -mindepth 1 -delete

# p2: ext4 sized to the content plus headroom.
used_mib=$(du -sm --apparent-size "$R" | cut -f1)
root_mib=$((used_mib * 115 / 100 + ROOT_FREE_MIB))
mkfs.ext4 -q -F -L exolink-root -E root_owner=0:0 -d "$R" "$T/root.ext4" "${root_mib}M"

boot_start=$((BOOT_START_MIB * 2048))
root_start=$((boot_start + boot_sectors))
total_mib=$((BOOT_START_MIB + BOOT_SIZE_MIB + root_mib + 1))
rm -f "$IMG" && truncate -s "${total_mib}M" "$IMG"
sfdisk -q "$IMG" <<TABLE
label: dos
label-id: $DISK_ID
unit: sectors
start=$boot_start, size=$boot_sectors, type=c, bootable
start=$root_start, size=$((root_mib * 2048)), type=83
TABLE
U=$R/usr/lib/exolink/u-boot
dd if="$U/MLO" of="$IMG" bs=128k seek=1 conv=notrunc status=none
dd if="$U/u-boot.img" of="$IMG" bs=384k seek=1 conv=notrunc status=none
dd if="$T/boot.vfat" of="$IMG" bs=1M seek="$BOOT_START_MIB" conv=notrunc,sparse status=none
dd if="$T/root.ext4" of="$IMG" bs=1M seek=$((BOOT_START_MIB + BOOT_SIZE_MIB)) conv=notrunc,sparse status=none
rm -rf "$T"
sfdisk -l "$IMG"
