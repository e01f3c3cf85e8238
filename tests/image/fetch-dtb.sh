#!/usr/bin/env bash
# Prints the path of am335x-boneblack.dtb from Debian's armhf armmp kernel package, fetched once
# through the machine's configured Debian mirror with a private apt state (signatures checked).
# Suites are tried in order (DTB_SUITES, default "trixie bookworm"): a mirror whose armhf index does
# not match its signed Release (seen Nov 2026: a stale trixie Packages.xz) falls through to the next
# suite, named on stderr, rather than failing the overlay check on someone else's mirror.
set -euo pipefail
cache=${EXOLINK_DTB_CACHE:-$HOME/.cache/exolink-dtb}
found=$(find "$cache/x" -name am335x-boneblack.dtb 2>/dev/null | head -1 || true)
if [ -n "$found" ]; then echo "$found"; exit 0; fi
mirror=$(awk '/^URIs:/{print $2; exit} /^deb /{print $2; exit}' /etc/apt/sources.list.d/debian.sources /etc/apt/sources.list 2>/dev/null | head -1)
for suite in ${DTB_SUITES:-${DTB_SUITE:-trixie bookworm}}; do
  A=$cache/apt-$suite; rm -rf "$A"; mkdir -p "$A/lists/partial" "$A/cache/archives/partial" "$cache/x"
  echo "deb [arch=armhf signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] $mirror $suite main" > "$A/sources.list"
  APTO=(-o Dir::Etc::sourcelist="$A/sources.list" -o Dir::Etc::sourceparts=/nonexistent -o Dir::State::Lists="$A/lists"
        -o Dir::Cache="$A/cache" -o Debug::NoLocking=1 -o APT::Architecture=armhf -o APT::Architectures=armhf
        -o APT::Sandbox::User=root)
  if ! apt-get "${APTO[@]}" -qq update >&2; then
    echo "fetch-dtb: $mirror $suite armhf index unusable (above); trying the next suite" >&2; continue
  fi
  img=$(apt-cache "${APTO[@]}" depends linux-image-armmp | awk '/Depends: linux-image-[0-9]/{print $2; exit}')
  (cd "$cache" && apt-get "${APTO[@]}" -qq download "$img:armhf" >&2)
  dpkg-deb --fsys-tarfile "$cache"/linux-image-*.deb | tar -x -C "$cache/x" --wildcards '*am335x-boneblack.dtb'
  rm -f "$cache"/linux-image-*.deb; rm -rf "$A"
  echo "fetch-dtb: using $img ($suite)" >&2
  find "$cache/x" -name am335x-boneblack.dtb | head -1
  exit 0
done
echo "fetch-dtb: no suite of $mirror gave a usable armhf index (tried: ${DTB_SUITES:-${DTB_SUITE:-trixie bookworm}})" >&2
exit 1
