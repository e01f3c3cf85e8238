#!/bin/sh
# exolink-boot-update [KERNEL_VERSION]: puts the kernel, initrd and merged dtb where the boot script
# (image/boot.cmd) loads them: /boot/exolink/ of this root slot. Each A/B slot carries its own, so an
# update bundle brings its kernel with its root and a fallback boots the old pair.
# Runs in the image build and, as /etc/kernel/postinst.d/zz-exolink-boot, after every kernel update
# on the board. The overlay is merged into the dtb here (fdtoverlay) rather than applied by U-Boot:
# U-Boot skips a failing overlay silently and its overlay address clobbers large initrds.
set -eu
DEST=${DEST:-/boot/exolink}
kver=${1:-$(ls /lib/modules | sort -V | tail -1)}
dtb=$(find "/usr/lib/linux-image-$kver" -name am335x-boneblack.dtb | head -1)
dtbo=/usr/lib/exolink/exolink-dcan1.dtbo
[ -f "/boot/vmlinuz-$kver" ] && [ -f "/boot/initrd.img-$kver" ] && [ -n "$dtb" ] || {
  echo "exolink-boot-update: kernel $kver incomplete (vmlinuz, initrd or dtb missing)" >&2
  exit 1
}
mkdir -p "$DEST"
put() { cp "$1" "$DEST/$2.new" && sync && mv "$DEST/$2.new" "$DEST/$2"; }
put "/boot/vmlinuz-$kver" vmlinuz
put "/boot/initrd.img-$kver" initrd.img
fdtoverlay -i "$dtb" -o "$DEST/board.dtb.new" "$dtbo"
mv "$DEST/board.dtb.new" "$DEST/board.dtb"
echo "$kver" > "$DEST/kernel-version"
sync
echo "exolink-boot-update: $DEST has kernel $kver and the merged dtb"
