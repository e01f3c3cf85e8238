#!/bin/sh
# exolink-boot-update [KERNEL_VERSION]: fills the card's FAT boot partition from /boot.
# Runs in the image build and, as /etc/kernel/postinst.d/zz-exolink-boot, after every kernel
# update on the board. The overlay is merged into the dtb here (fdtoverlay) rather than applied by
# U-Boot: U-Boot skips a failing overlay silently and its overlay address clobbers large initrds.
set -eu
BOOT=${BOOT:-/boot/firmware}
. /usr/lib/exolink/image.conf
kver=${1:-$(ls /lib/modules | sort -V | tail -1)}
dtb=$(find "/usr/lib/linux-image-$kver" -name am335x-boneblack.dtb | head -1)
dtbo=/usr/lib/exolink/exolink-dcan1.dtbo
[ -f "/boot/vmlinuz-$kver" ] && [ -f "/boot/initrd.img-$kver" ] && [ -n "$dtb" ] || {
  echo "exolink-boot-update: kernel $kver incomplete (vmlinuz, initrd or dtb missing)" >&2
  exit 1
}
mkdir -p "$BOOT/extlinux" "$BOOT/overlays"
put() { cp "$1" "$BOOT/$2.new" && sync && mv "$BOOT/$2.new" "$BOOT/$2"; }
put "/boot/vmlinuz-$kver" vmlinuz
put "/boot/initrd.img-$kver" initrd.img
fdtoverlay -i "$dtb" -o "$BOOT/am335x-boneblack-exolink.dtb.new" "$dtbo"
mv "$BOOT/am335x-boneblack-exolink.dtb.new" "$BOOT/am335x-boneblack-exolink.dtb"
put "$dtbo" overlays/exolink-dcan1.dtbo
cat > "$BOOT/extlinux/extlinux.conf.new" <<CONF
# Written by exolink-boot-update for kernel $kver; U-Boot's distro boot reads this file.
default exolink
timeout 10
label exolink
  menu label exolink (Debian $kver, DCAN1 + trigger overlay merged)
  kernel /vmlinuz
  initrd /initrd.img
  fdt /am335x-boneblack-exolink.dtb
  append root=PARTUUID=$ROOT_PARTUUID rootwait ro console=ttyO0,115200n8
CONF
mv "$BOOT/extlinux/extlinux.conf.new" "$BOOT/extlinux/extlinux.conf"
sync
echo "exolink-boot-update: $BOOT has kernel $kver and the merged dtb"
