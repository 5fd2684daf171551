#!/usr/bin/env bash
# System libraries the Python wheels need: Open3D loads libusb-1.0, diagram pictures use
# Graphviz's `dot`, headless Open3D/Meshcat rendering wants libGL and libgomp.
# Installs them with apt-get when running as root; otherwise says what to install.
set -euo pipefail
packages=(libusb-1.0-0 graphviz libgl1 libgomp1)
missing=()
for p in "${packages[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi
if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "Installing system packages: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
else
  echo "drake-rus needs these system packages: ${missing[*]}" >&2
  echo "Install them with your package manager, for example:" >&2
  echo "  sudo apt-get install ${missing[*]}" >&2
  exit 1
fi
