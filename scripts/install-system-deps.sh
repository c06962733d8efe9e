#!/usr/bin/env bash
# Debian packages the project needs: libusb for Open3D, SUMO's netconvert as an independent
# OpenDRIVE reader in the tests, headless Chromium to render the build report in its test.
# Installs only what is missing.
set -euo pipefail
pkgs=(libusb-1.0-0 sumo chromium)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
SUDO=""
[ "$(id -u)" -ne 0 ] && SUDO="sudo"
echo "installing Debian packages: ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
