#!/usr/bin/env bash
# Debian packages the project needs: libusb for Open3D, python3-venv to make the virtual
# environments, chromium for the headless-browser test of the report. SUMO is not among them:
# netconvert and its data come from the PyPI package eclipse-sumo in the lock (Debian's sumo
# without sumo-tools has no data and fails). Installs only what is missing.
set -euo pipefail
pkgs=(libusb-1.0-0 python3-venv chromium)
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
