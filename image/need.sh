#!/usr/bin/env bash
# Installs the Debian package behind each missing host command: need.sh cmd:package ...
set -euo pipefail
missing=()
for t in "$@"; do
  command -v "${t%%:*}" >/dev/null || missing+=("${t#*:}")
done
if [ ${#missing[@]} -gt 0 ]; then
  # Wait for a dpkg/apt lock held by another apt run (up to 10 min) instead of failing at once.
  apt-get -o DPkg::Lock::Timeout=600 update -qq
  DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq "${missing[@]}"
fi
