#!/usr/bin/env bash
# Prints the path of am335x-boneblack.dtb from Debian's armhf armmp kernel package (trixie),
# fetched once through the machine's configured Debian mirror with a private apt state.
set -euo pipefail
cache=${EXOLINK_DTB_CACHE:-$HOME/.cache/exolink-dtb}
found=$(find "$cache/x" -name am335x-boneblack.dtb 2>/dev/null | head -1 || true)
if [ -n "$found" ]; then echo "$found"; exit 0; fi
A=$cache/apt; mkdir -p "$A/lists/partial" "$A/cache/archives/partial" "$cache/x"
mirror=$(awk '/^URIs:/{print $2; exit} /^deb /{print $2; exit}' /etc/apt/sources.list.d/debian.sources /etc/apt/sources.list 2>/dev/null | head -1)
echo "deb [arch=armhf signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] $mirror ${DTB_SUITE:-trixie} main" > "$A/sources.list"
APTO=(-o Dir::Etc::sourcelist="$A/sources.list" -o Dir::Etc::sourceparts=/nonexistent -o Dir::State::Lists="$A/lists"
      -o Dir::Cache="$A/cache" -o Debug::NoLocking=1 -o APT::Architecture=armhf -o APT::Architectures=armhf
      -o APT::Sandbox::User=root)
apt-get "${APTO[@]}" -qq update >&2
img=$(apt-cache "${APTO[@]}" depends linux-image-armmp | awk '/Depends: linux-image-[0-9]/{print $2; exit}')
(cd "$cache" && apt-get "${APTO[@]}" -qq download "$img:armhf" >&2)
dpkg-deb --fsys-tarfile "$cache"/linux-image-*.deb | tar -x -C "$cache/x" --wildcards '*am335x-boneblack.dtb'
rm -f "$cache"/linux-image-*.deb; rm -rf "$A/cache"
find "$cache/x" -name am335x-boneblack.dtb | head -1
