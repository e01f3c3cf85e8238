#!/usr/bin/env bash
# mmdebstrap setup hook ($1 = root, before apt resolves anything; $2 = image/debian.lock, or
# /dev/null for none): pin every package in the lock to its locked version, so dependencies are
# pinned too, not only the packages named in debian-packages.txt. A locked version the mirror no
# longer has is not an error here: build.sh compares the installed set with the lock afterwards
# and stops on any difference.
# customize.sh removes the pins: the board's own `apt upgrade` must follow Debian's fixes.
set -euo pipefail
R=$1
LOCK=$2
[ -s "$LOCK" ] || exit 0
mkdir -p "$R/etc/apt/preferences.d"
awk -F= 'NF >= 2 && $1 !~ /^#/ {
  name = $1; version = substr($0, length(name) + 2)
  printf "Package: %s\nPin: version %s\nPin-Priority: 1001\n\n", name, version
}' "$LOCK" > "$R/etc/apt/preferences.d/exolink-lock"
echo "pinned $(grep -c '^Package:' "$R/etc/apt/preferences.d/exolink-lock") packages to $LOCK"
