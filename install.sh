#!/usr/bin/env bash
# Installs l1flow-rl into ./.venv on a fresh Debian/Ubuntu machine with Python 3.11.
# Usage: ./install.sh [EXTRAS]      EXTRAS is a comma list from: maniskill, robosuite, pusht, launchers, dev, all
#                                   (default: maniskill, which the main job needs)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"
extras="${1:-maniskill}"
py="${PYTHON:-python3.11}"
command -v "$py" >/dev/null 2>&1 || py=python3

as_root() { if [[ $(id -u) -eq 0 ]]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else
  echo "install.sh: '$*' needs root; run it by hand or as root" >&2; return 1; fi; }

wants() { [[ ",$extras," == *",$1,"* || ",$extras," == *",all,"* ]]; }

# --- system packages ------------------------------------------------------------------------
if command -v apt-get >/dev/null 2>&1; then
  apt_pkgs=()
  "$py" -m venv --help >/dev/null 2>&1 || apt_pkgs+=(python3-venv)
  if wants maniskill; then
    # SAPIEN needs a Vulkan device. With no GPU driver, Mesa lavapipe >= 24.3 is the CPU device;
    # Debian bookworm's 22.3 fails with 'Failed to find a supported physical device "cpu"'.
    if ! ls /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json >/dev/null 2>&1; then
      mesa=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true)
      if [[ -z $mesa ]] || dpkg --compare-versions "$mesa" lt 24.3; then
        if grep -q 'VERSION_CODENAME=bookworm' /etc/os-release; then
          printf 'Types: deb\nURIs: http://deb.debian.org/debian\nSuites: bookworm-backports\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' \
            | as_root tee /etc/apt/sources.list.d/bookworm-backports.sources >/dev/null
          as_root apt-get update -qq
          as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -t bookworm-backports \
            mesa-vulkan-drivers libegl-mesa0 libgl1-mesa-dri libosmesa6
        else
          apt_pkgs+=(mesa-vulkan-drivers)
        fi
      fi
    fi
    apt_pkgs+=(libvulkan1 libegl1 libgl1)
  fi
  if wants robosuite; then apt_pkgs+=(libegl1 libgl1 libosmesa6); fi
  missing=()
  for p in "${apt_pkgs[@]}"; do dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'ok installed' || missing+=("$p"); done
  if (( ${#missing[@]} )); then
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}"
  fi
fi

# --- python packages ------------------------------------------------------------------------
[[ -x .venv/bin/python ]] || "$py" -m venv .venv
pip=(.venv/bin/python -m pip install -q --disable-pip-version-check)
# torch first: 2.13.0 is the CPU build on CPU-only machines; any other spec pulls CUDA wheels.
"${pip[@]}" torch==2.13.0
"${pip[@]}" -c constraints.txt -e ".[${extras}]"
echo "install.sh: installed l1flow-rl[${extras}] into $(pwd)/.venv"
