#!/usr/bin/env bash
# `make image`: the flashable SD-card image for the BeagleBone Black, built on an x86_64 host.
# `make bundle` (build.sh bundle): the same root, as a signed RAUC update bundle instead.
#   Debian trixie armhf root (mmdebstrap + qemu-user binfmt) with Debian's armmp kernel, the
#   BeagleBone dtb merged with our overlay, U-Boot (u-boot-omap), exolink in /opt/exolink,
#   the units from services/. No loop devices: the partitions are made as files and placed with dd.
# Output: build/image/exolink-bbb-<version>.img.xz (+ .packages / .python manifests, .sha256);
#   bundle: build/image/exolink-bbb-<version>.raucb (and its rootfs, .sha256).
# Needs root (mmdebstrap --mode=root, binfmt_misc, a tmpfs); CI-able, no kernel CAN/GPIO needed.
set -euo pipefail
cd "$(dirname "$0")/.."
. image/image.conf

VERSION=$(sed -n 's/^version = "\(.*\)"/\1/p' pyproject.toml)
OUT=${OUT:-$PWD/build/image}
WORK=$OUT/work
NAME=exolink-bbb-$VERSION
WHAT=${1:-image}
case "$WHAT" in image|bundle) ;; *) echo "build.sh: image or bundle, not '$WHAT'" >&2; exit 2 ;; esac
T0=$(date +%s)
step() { printf '\n==> [%4ds] %s\n' $(($(date +%s) - T0)) "$*"; }

step "host tools"
bash image/need.sh mmdebstrap:mmdebstrap qemu-arm-static:qemu-user-static \
  update-binfmts:binfmt-support arch-test:arch-test fdtoverlay:device-tree-compiler mcopy:mtools \
  mkfs.vfat:dosfstools sfdisk:fdisk mkfs.ext4:e2fsprogs xz:xz-utils mkimage:u-boot-tools \
  rauc:rauc mksquashfs:squashfs-tools openssl:openssl
mountpoint -q /proc/sys/fs/binfmt_misc || mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc
update-binfmts --enable qemu-arm 2>/dev/null || true
arch-test armhf >/dev/null || { echo "armhf binaries do not run here (qemu-user binfmt)" >&2; exit 1; }

# Everything in a tmpfs: initramfs tools under qemu-user miss the block drivers when readdir runs
# on the host's ext4 (32-bit readdir overflow), and the build is faster there.
mkdir -p "$WORK"
cleanup() { umount -R "$WORK" 2>/dev/null || true; }
trap cleanup EXIT
cleanup
mount -t tmpfs -o size=${TMPFS_SIZE} tmpfs "$WORK"
export TMPDIR=$WORK/tmp && mkdir -p "$TMPDIR"

step "bundle signing key"
# RAUC_KEY / RAUC_CERT: the lab's signing key and certificate; RAUC_KEYRING: the CA the boards
# trust (the image carries it as /etc/rauc/ca.cert.pem). Without them a development key is made
# once in build/rauc/ (never committed: build/ is ignored) and its self-signed certificate is the
# keyring, so bundles from this checkout install on images from this checkout only.
if [ -z "${RAUC_KEY:-}" ]; then
  RAUC_KEY=$PWD/build/rauc/dev.key.pem RAUC_CERT=$PWD/build/rauc/dev.cert.pem
  if [ ! -f "$RAUC_KEY" ]; then
    mkdir -p build/rauc && chmod 0700 build/rauc
    openssl req -x509 -newkey rsa:4096 -nodes -days 3650 -keyout "$RAUC_KEY" -out "$RAUC_CERT" \
      -subj "/O=exolink/CN=exolink development bundle signing $(hostname)" \
      -addext "basicConstraints=critical,CA:TRUE" 2>/dev/null
    echo "made a development signing key: $RAUC_KEY (a lab sets RAUC_KEY, RAUC_CERT, RAUC_KEYRING)"
  fi
fi
export RAUC_KEY RAUC_CERT RAUC_KEYRING=${RAUC_KEYRING:-$RAUC_CERT}
for f in "$RAUC_KEY" "$RAUC_CERT" "$RAUC_KEYRING"; do
  [ -r "$f" ] || { echo "build.sh: cannot read $f (RAUC_KEY, RAUC_CERT, RAUC_KEYRING)" >&2; exit 1; }
done
openssl verify -CAfile "$RAUC_KEYRING" "$RAUC_CERT" >/dev/null || {
  echo "build.sh: $RAUC_CERT is not signed by the keyring $RAUC_KEYRING: boards would refuse" \
    "every bundle" >&2
  exit 1
}

step "overlay and wheels (host side: the armhf root lacks the host's CA)"
make -s overlays
W=$WORK/wheels && mkdir -p "$W"
PIP=${PIP:-.venv/bin/python -m pip}
$PIP wheel -q --no-deps -w "$W" .
$PIP download -q --no-deps --only-binary=:all: --python-version "$PY_VERSION" \
  --implementation cp --abi "cp${PY_VERSION/./}" --abi abi3 \
  --platform manylinux_2_17_armv7l --platform manylinux2014_armv7l \
  -r <(grep -v -E '^(msgspec|msgpack)==' image/python-requirements.txt) -d "$W"
$PIP download -q --no-deps --no-binary=:all: -d "$W" \
  $(grep -E '^(msgspec|msgpack)==' image/python-requirements.txt)
$PIP download -q --no-deps --only-binary=:all: -r image/build-requirements.txt -d "$W"
ls "$W"

step "Debian $SUITE armhf base root (mmdebstrap under qemu-user; the long step, cached)"
# With image/debian.lock (from `make image-lock`) every package is pinned to its locked version
# (hooks/setup.sh; dependencies too), and the build stops if the installed set differs from it.
# ACCEPT_LOCK_DRIFT=1 builds from the mirror's current versions instead, to make a new lock.
LOCK=image/debian.lock
[ "${ACCEPT_LOCK_DRIFT:-}" = 1 ] || [ ! -f "$LOCK" ] && LOCK=/dev/null
pkgs=$(grep -v -E '^\s*(#|$)' image/debian-packages.txt | while read -r p; do
  v=$(sed -n "s/^$p=//p" "$LOCK" 2>/dev/null || true); echo "$p${v:+=$v}"; done | paste -sd,)
key=$(cat image/debian-packages.txt image/hooks/setup.sh image/hooks/essential.sh image/image.conf \
  "$LOCK" | sha256sum | cut -c1-16)
BASE=$OUT/cache/base-$key.tar
if [ -f "$BASE" ]; then
  echo "reusing $BASE"
else
  mkdir -p "$OUT/cache" && rm -f "$OUT"/cache/base-*.tar
  mmdebstrap --mode=root --arch=armhf --variant=apt --components=main --include="$pkgs" \
    --aptopt='Acquire::Retries "3"' --dpkgopt='path-exclude=/usr/share/man/*' \
    --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-exclude=/usr/share/doc/*' \
    --dpkgopt='path-include=/usr/share/doc/*/copyright' \
    --setup-hook="image/hooks/setup.sh \"\$1\" $LOCK" \
    --essential-hook="image/hooks/essential.sh \"\$1\"" \
    "$SUITE" "$WORK/base.tar" "deb $MIRROR $SUITE main" \
    ${SECURITY_MIRROR:+"deb $SECURITY_MIRROR $SUITE-security main"}
  mv "$WORK/base.tar" "$BASE"
fi

step "exolink, units, users, boot files (image/hooks/customize.sh in the armhf root)"
R=$WORK/rootfs && mkdir -p "$R"
tar -C "$R" --xattrs --xattrs-include='*' -xpf "$BASE"
mount -t proc proc "$R/proc" && mount -t sysfs sys "$R/sys" && mount --rbind /dev "$R/dev"
EXOLINK_SRC=$PWD image/hooks/customize.sh "$R" "$W" "$VERSION"
umount -R "$R/proc" "$R/sys" "$R/dev" 2>/dev/null || umount -lR "$R/dev"

step "manifests"
chroot "$R" dpkg-query -W -f '${Package}=${Version}\n' | sort > "$OUT/$NAME.packages"
chroot "$R" /opt/exolink/bin/python -m pip list --format=freeze > "$OUT/$NAME.python"
wc -l "$OUT/$NAME.packages" "$OUT/$NAME.python"
if [ -f image/debian.lock ]; then
  if diff -u image/debian.lock "$OUT/$NAME.packages" > "$OUT/$NAME.lockdiff"; then
    echo "all $(wc -l < image/debian.lock) Debian packages match image/debian.lock"
  else
    echo "installed packages differ from image/debian.lock (- locked, + installed):" >&2
    grep '^[-+][^-+]' "$OUT/$NAME.lockdiff" | head -40 >&2
    if [ "$LOCK" != /dev/null ]; then
      echo "stopping: the build does not match its lock. Review the list; to move to the mirror's" \
        "versions, rebuild with ACCEPT_LOCK_DRIFT=1 and run 'make image-lock'." >&2
      exit 1
    fi
  fi
fi

# What survives an update lives on the data partition, not in the root slot: exolink's state
# (the mount point /var/lib/exolink stays, empty) and RAUC's slot status.
D=$WORK/data && mkdir -p "$D/rauc"
if [ -d "$R/var/lib/exolink" ]; then mv "$R/var/lib/exolink" "$D/exolink"; else mkdir "$D/exolink"; fi
install -d -m 0750 "$R/var/lib/exolink"
chown "$(chroot "$R" id -u exolink):$(chroot "$R" id -g exolink)" "$D/exolink"
chmod 0750 "$D/exolink"

if [ "$WHAT" = bundle ]; then
  step "RAUC bundle (the root slot's content, signed)"
  image/bundle.sh "$R" "$OUT/$NAME.raucb"
  step "done: $OUT/$NAME.raucb in $(($(date +%s) - T0)) s"
  exit 0
fi

step "disk image (partition table, U-Boot raw at 128 KiB / 384 KiB, FAT boot, A/B root slots, data)"
image/assemble.sh "$R" "$D" "$OUT/$NAME.img"

step "compress"
rm -f "$OUT/$NAME.img.xz"
xz -T0 -6 -k -f "$OUT/$NAME.img"
(cd "$OUT" && sha256sum "$NAME.img.xz" > "$NAME.img.xz.sha256")
step "done: $OUT/$NAME.img.xz"
ls -l "$OUT/$NAME.img" "$OUT/$NAME.img.xz"
printf 'image %s: %s raw (%s used), %s compressed, built in %ds\n' "$NAME" \
  "$(du -h --apparent-size "$OUT/$NAME.img" | cut -f1)" "$(du -h "$OUT/$NAME.img" | cut -f1)" \
  "$(du -h "$OUT/$NAME.img.xz" | cut -f1)" $(($(date +%s) - T0))
