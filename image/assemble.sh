#!/usr/bin/env bash
# assemble.sh ROOTFS DATA IMG: the SD-card layout the AM335x boot chain and A/B updates need,
# without loop devices (each partition is made as a file and placed with dd).
#   sector 0      MBR (disk id $DISK_ID; partition N has PARTUUID ${DISK_ID#0x}-0N)
#   128 KiB       MLO (the boot ROM's raw-mode offset; also tried at 0/256/384 KiB)
#   384 KiB       u-boot.img (SPL's CONFIG_SYS_MMCSD_RAW_MODE_U_BOOT_SECTOR=0x300)
#   4 MiB         p1 FAT32 "EXOLINK", bootable: boot.scr (image/boot.cmd: A/B selection with a
#                 boot counter), exolink-boot.env (its state), exolink-settings.yaml (the file
#                 users edit on a laptop)
#   after p1      p2 ext4 root slot A "exolink-a" (this build; kernel, initrd, dtb in /boot/exolink)
#                 p3 root slot B (empty: the first update goes there), each ROOT_SLOT_MIB
#                 p4 ext4 data "exolink-data" (/data: exolink's state and recordings, RAUC's
#                 status; grown to the card on first boot)
set -euo pipefail
cd "$(dirname "$0")/.."
. image/image.conf
R=$1 D=$2 IMG=$3
T=$(dirname "$IMG")/parts && rm -rf "$T" && mkdir -p "$T"

# p1: FAT from the root's /boot/firmware (the mount point stays, empty, in the root) + boot script.
boot_sectors=$((BOOT_SIZE_MIB * 2048))
mkimage -A arm -O linux -T script -C none -n "exolink A/B boot" -d image/boot.cmd \
  "$R/boot/firmware/boot.scr" >/dev/null
printf 'BOOT_ORDER=A B\nBOOT_A_LEFT=%s\nBOOT_B_LEFT=%s\n' "$BOOT_TRIES" "$BOOT_TRIES" \
  > "$R/boot/firmware/exolink-boot.env"
mkfs.vfat -F 32 -n EXOLINK -i "${DISK_ID#0x}" -C "$T/boot.vfat" $((BOOT_SIZE_MIB * 1024)) >/dev/null
mcopy -s -i "$T/boot.vfat" "$R"/boot/firmware/* ::/
find "$R/boot/firmware" -mindepth 1 -delete

# p2: slot A, the whole slot (free blocks are holes in the image, zeros in the .xz).
used_mib=$(du -sm --apparent-size "$R" | cut -f1)
if [ $((used_mib * 115 / 100)) -gt "$ROOT_SLOT_MIB" ]; then
  echo "assemble.sh: the root needs ${used_mib} MiB + 15%, a slot holds ${ROOT_SLOT_MIB} MiB" >&2
  exit 1
fi
mkfs.ext4 -q -F -L exolink-a -E root_owner=0:0 -d "$R" "$T/root.ext4" "${ROOT_SLOT_MIB}M"
# p4: data.
mkfs.ext4 -q -F -L exolink-data -E root_owner=0:0 -d "$D" "$T/data.ext4" "${DATA_MIB}M"

slot=$((ROOT_SLOT_MIB * 2048))
p1=$((BOOT_START_MIB * 2048)) p2=$((BOOT_START_MIB * 2048 + boot_sectors))
p3=$((p2 + slot)) p4=$((p2 + 2 * slot))
total_mib=$((BOOT_START_MIB + BOOT_SIZE_MIB + 2 * ROOT_SLOT_MIB + DATA_MIB + 1))
rm -f "$IMG" && truncate -s "${total_mib}M" "$IMG"
sfdisk -q "$IMG" <<TABLE
label: dos
label-id: $DISK_ID
unit: sectors
start=$p1, size=$boot_sectors, type=c, bootable
start=$p2, size=$slot, type=83
start=$p3, size=$slot, type=83
start=$p4, size=$((DATA_MIB * 2048)), type=83
TABLE
U=$R/usr/lib/exolink/u-boot
dd if="$U/MLO" of="$IMG" bs=128k seek=1 conv=notrunc status=none
dd if="$U/u-boot.img" of="$IMG" bs=384k seek=1 conv=notrunc status=none
dd if="$T/boot.vfat" of="$IMG" bs=1M seek="$BOOT_START_MIB" conv=notrunc,sparse status=none
dd if="$T/root.ext4" of="$IMG" bs=1M seek=$((p2 / 2048)) conv=notrunc,sparse status=none
dd if="$T/data.ext4" of="$IMG" bs=1M seek=$((p4 / 2048)) conv=notrunc,sparse status=none
rm -rf "$T"
sfdisk -l "$IMG"
