#!/usr/bin/env bash
# Installs the Debian packages the project needs, only those missing (idempotent).
set -euo pipefail
pkgs=(libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libopengl0 pkg-config fonts-dejavu-core g++ chromium)
# socat makes the pseudo-terminal pairs the Robotiq gripper tests talk Modbus RTU over;
# pyrealsense2 (the camera host) links libusb-1.0.
pkgs+=(socat libusb-1.0-0)
if ! python3 -m venv --help >/dev/null 2>&1; then pkgs+=(python3-venv); fi
if ! command -v python3 >/dev/null 2>&1; then pkgs+=(python3 python3-venv); fi
# systemd-analyze, systemd-sysusers and systemd-tmpfiles check deploy/ (tests/tests/service.rs).
if ! command -v systemd-analyze >/dev/null 2>&1; then pkgs+=(systemd); fi
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "installing Debian packages: ${missing[*]}"
  sudo_cmd=""
  if [ "$(id -u)" != 0 ]; then sudo_cmd="sudo"; fi
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi
command -v cargo >/dev/null || { echo "error: cargo not found; install Rust (rustup) first" >&2; exit 1; }
