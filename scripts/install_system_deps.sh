#!/usr/bin/env bash
# Debian packages ermrl needs beyond Python: Mesa's headless OpenGL, so that MuJoCo renders
# offscreen without a display (`ermrl video`, tests/test_video.py).
#   EGL:    libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri   (MUJOCO_GL=egl, tried first)
#   OSMesa: libosmesa6                                    (MUJOCO_GL=osmesa, the fallback)
# and a headless browser, which opens `ermrl report`'s report.html in tests/test_report_browser.py:
#   chromium, with fonts-dejavu-core for its text
# Idempotent: installs only what is missing, and runs apt-get update only then.
# Usage: bash scripts/install_system_deps.sh   (as root, or with sudo available)
set -euo pipefail

PACKAGES=(libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libosmesa6 chromium fonts-dejavu-core)

missing=()
for pkg in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$pkg")
  fi
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "install_system_deps: all present (${PACKAGES[*]})"
  exit 0
fi

if ! command -v apt-get >/dev/null 2>&1; then
  echo "install_system_deps: apt-get not found; install these yourself: ${missing[*]}" >&2
  exit 1
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1; then
    SUDO="sudo"
  else
    echo "install_system_deps: need root (or sudo) to install: ${missing[*]}" >&2
    exit 1
  fi
fi

echo "install_system_deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
echo "install_system_deps: done"
