#!/usr/bin/env bash
# Customizes the base root (run by build.sh with proc, sys, dev mounted): $1 = root, $2 = host folder of wheels/sdists, $3 = exolink version.
# Installs exolink and the units, creates the users, fills the boot partition, cleans up.
set -euo pipefail
R=$1 W=$2 VERSION=$3
ch() { chroot "$R" env -i PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LANG=C.UTF-8 "$@"; }
cd "$EXOLINK_SRC"
say() { printf '    customize: %s\n' "$*"; }

say "exolink $VERSION into /opt/exolink (venv over Debian's site-packages)"
mkdir -p "$R/tmp/wheels" && cp "$W"/* "$R/tmp/wheels/"
ch python3 -m venv --system-site-packages /opt/exolink
# --no-index: everything comes from the host-downloaded folder or Debian; a missing piece fails here.
ch env PIP_NO_CACHE_DIR=1 /opt/exolink/bin/pip install -q --no-index --find-links /tmp/wheels \
  -r /dev/stdin "exolink==$VERSION" < image/python-requirements.txt
ch /opt/exolink/bin/pip check || echo "    customize: WARNING: pip check found the conflicts above (Debian metadata?)"
ch /opt/exolink/bin/python -c 'import gpiod, zenoh, can, msgspec, exolink.supervisor.core
from importlib.metadata import version as v
print("    customize: imports ok; gpiod", v("gpiod"), "zenoh", v("eclipse-zenoh"), "can", v("python-can"))'
ln -sf /opt/exolink/bin/exolink "$R/usr/local/bin/exolink"
rm -rf "$R/tmp/wheels"

say "users: exolink (the service), exo (the lab's login; locked until a key or password is set)"
ch groupadd --system gpio
ch useradd --system --user-group --groups gpio --home-dir /var/lib/exolink --shell /usr/sbin/nologin exolink
ch useradd --create-home --shell /bin/bash --groups sudo,adm,systemd-journal,exolink exo
ch passwd --lock exo >/dev/null

say "configuration and units (services/)"
cp -a services/etc/. "$R/etc/"
install -d -m 0750 "$R/etc/exolink"
sed 's|^  # config_file: /etc/exolink/zenoh.json5 .*|  config_file: /etc/exolink/zenoh.json5   # written by exolink-setup from the card|' \
  appliance/exolink/configs/board.yaml > "$R/etc/exolink/appliance.yaml"
grep -q '^  config_file: /etc/exolink/zenoh.json5' "$R/etc/exolink/appliance.yaml"
echo '{}' > "$R/etc/exolink/zenoh.json5"
ch chown -R root:exolink /etc/exolink && ch chmod 0640 /etc/exolink/appliance.yaml /etc/exolink/zenoh.json5
install -d "$R/usr/lib/exolink" "$R/boot/firmware"
cp image/image.conf build/overlays/exolink-dcan1.dtbo "$R/usr/lib/exolink/"
install -m 0755 image/boot-update.sh "$R/usr/local/sbin/exolink-boot-update"
install -D -m 0755 /dev/stdin "$R/etc/kernel/postinst.d/zz-exolink-boot" <<'HOOK'
#!/bin/sh
exec /usr/local/sbin/exolink-boot-update "$1"
HOOK
cp services/boot/* "$R/boot/firmware/"
. image/image.conf
# The root is whichever slot U-Boot chose (root=PARTUUID=... from image/boot.cmd): /dev/root here.
# What must survive an update lives on the data partition: exolink's state and recordings
# (/var/lib/exolink, bound from /data/exolink) and RAUC's slot status (/data/rauc).
install -d "$R/data"
cat > "$R/etc/fstab" <<FSTAB
# <device>                  <mount>           <type> <options>                          <dump> <pass>
/dev/root                 /                 ext4   defaults,noatime,commit=5          0      1
PARTUUID=$BOOT_PARTUUID  /boot/firmware    vfat   defaults,noatime,fmask=0177,dmask=0077 0   2
PARTUUID=$DATA_PARTUUID  /data             ext4   defaults,noatime,commit=5          0      2
/data/exolink             /var/lib/exolink  none   bind,x-systemd.requires-mounts-for=/data 0 0
FSTAB
ch exolink config /etc/exolink/appliance.yaml > /dev/null
ch systemctl enable exolink.service exolink-setup.service systemd-networkd.service \
  systemd-resolved.service systemd-timesyncd.service ssh.service \
  exolink-boot-check.service exolink-update.path exolink-mark-good.path
# Wi-Fi starts when a USB adapter's wlan0 appears (also plugged in later), never at boot: enabled
# for multi-user.target it made boot wait 90 s for a device the BeagleBone Black does not have.
install -d "$R/etc/systemd/system/sys-subsystem-net-devices-wlan0.device.wants"
ln -sfn /usr/lib/systemd/system/wpa_supplicant@.service \
  "$R/etc/systemd/system/sys-subsystem-net-devices-wlan0.device.wants/wpa_supplicant@wlan0.service"
ch systemctl mask getty@tty1.service  # no display; the serial console (ttyO0) keeps its getty

say "identity: new machine-id and SSH host keys on each card's first boot"
rm -f "$R"/etc/ssh/ssh_host_*
echo uninitialized > "$R/etc/machine-id"
rm -f "$R/var/lib/dbus/machine-id"
echo exolink > "$R/etc/hostname"

say "RAUC: two root slots, bundles signed by $(openssl x509 -noout -subject -in "$RAUC_KEYRING")"
install -d "$R/etc/rauc"
sed -e "s/@RAUC_COMPATIBLE@/$RAUC_COMPATIBLE/" -e "s/@ROOT_A_PARTUUID@/$ROOT_A_PARTUUID/" \
  -e "s/@ROOT_B_PARTUUID@/$ROOT_B_PARTUUID/" image/rauc/system.conf.in > "$R/etc/rauc/system.conf"
install -m 0644 "$RAUC_KEYRING" "$R/etc/rauc/ca.cert.pem"
install -m 0755 image/rauc/rauc-boot-backend image/rauc/rauc-post-install "$R/usr/lib/exolink/"
install -m 0644 image/boot.cmd "$R/usr/lib/exolink/"

say "kernel, initrd and merged dtb into this slot's /boot/exolink (image/boot.cmd loads them)"
ch exolink-boot-update
ls -l "$R/boot/exolink" | sed 's/^/    /'
install -d "$R/usr/lib/exolink/u-boot"
cp "$R"/usr/lib/u-boot/am335x_boneblack/{MLO,u-boot.img} "$R/usr/lib/exolink/u-boot/"

say "cleanup: build tools, caches"
ch env DEBIAN_FRONTEND=noninteractive apt-get purge -y -qq build-essential python3-dev >/dev/null
ch env DEBIAN_FRONTEND=noninteractive apt-get autoremove --purge -y -qq >/dev/null
ch apt-get clean
rm -rf "$R"/var/lib/apt/lists/* "$R"/var/cache/* "$R"/tmp/* "$R"/root/.cache
# The build's pins (hooks/setup.sh) would hold the board back from Debian's security fixes.
rm -f "$R/etc/apt/preferences.d/exolink-lock"
