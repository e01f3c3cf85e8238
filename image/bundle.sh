#!/usr/bin/env bash
# bundle.sh ROOTFS OUT.raucb: a RAUC bundle (verity format) of a root slot's content, signed with
# RAUC_KEY / RAUC_CERT (build.sh makes a development pair in build/rauc/ when none is given).
# The slot image is sized to its content (RAUC writes it and grows it to the slot: resize=true).
# BUNDLE_VERSION (default: the package version + the commit) is what `exolink status` shows.
set -euo pipefail
cd "$(dirname "$0")/.."
. image/image.conf
R=$1 OUT=$2
VERSION=$(sed -n 's/^version = "\(.*\)"/\1/p' pyproject.toml)
BUNDLE_VERSION=${BUNDLE_VERSION:-$VERSION+$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}
T=$(dirname "$OUT")/bundle-parts && rm -rf "$T" && mkdir -p "$T/content"
used_mib=$(du -sm --apparent-size "$R" | cut -f1)
root_mib=$((used_mib * 115 / 100 + 64))
if [ "$root_mib" -gt "$ROOT_SLOT_MIB" ]; then
  echo "bundle.sh: the root needs ${root_mib} MiB, a slot holds ${ROOT_SLOT_MIB} MiB (image.conf)" >&2
  exit 1
fi
mkfs.ext4 -q -F -L exolink-root -E root_owner=0:0 -d "$R" "$T/content/rootfs.ext4" "${root_mib}M"
cat > "$T/content/manifest.raucm" <<MANIFEST
[update]
compatible=$RAUC_COMPATIBLE
version=$BUNDLE_VERSION
description=exolink $BUNDLE_VERSION root file system (image/build.sh bundle)
build=$(date -u +%Y-%m-%dT%H:%M:%SZ)

[bundle]
format=verity

[image.rootfs]
filename=rootfs.ext4
MANIFEST
rm -f "$OUT"
rauc bundle --cert="$RAUC_CERT" --key="$RAUC_KEY" "$T/content" "$OUT"
rm -rf "$T"
(cd "$(dirname "$OUT")" && sha256sum "$(basename "$OUT")" > "$(basename "$OUT").sha256")
rauc info --keyring="$RAUC_KEYRING" "$OUT" | sed 's/^/    /'
ls -l "$OUT"
