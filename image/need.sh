#!/usr/bin/env bash
# Installs the Debian package behind each missing host command: need.sh cmd:package ...
set -euo pipefail
missing=()
for t in "$@"; do
  command -v "${t%%:*}" >/dev/null || missing+=("${t#*:}")
done
if [ ${#missing[@]} -gt 0 ]; then
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}"
fi
