#!/usr/bin/env bash
# Install everything tesseract4d needs on a fresh Debian 12 machine (idempotent).
#   1. Debian packages (Vulkan loader, libusb for Open3D, Chromium for browser tests, ffmpeg)
#   2. Mesa 25 software Vulkan (lavapipe) from bookworm-backports into .deps/mesa (system Mesa untouched)
#   3. Python venv in .venv with torch==2.13.0 (CPU) first, then the project and its extras
# Usage: scripts/setup.sh [--dev]     (--dev adds the test tools)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
EXTRAS="[dev]"
[[ "${1:-}" == "--no-dev" ]] && EXTRAS=""
SUDO=""; [[ $(id -u) -ne 0 ]] && SUDO="sudo"

APT_PACKAGES="libvulkan1 mesa-vulkan-drivers libusb-1.0-0 libgl1 libglib2.0-0 chromium chromium-driver"
missing=""
for p in $APT_PACKAGES; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [[ -n "$missing" ]]; then
  echo "[setup] apt-get install$missing"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing
fi

# --- Mesa 25 lavapipe from bookworm-backports, unpacked into a project-local folder ---------
MESA_DIR="$ROOT/.deps/mesa"
ICD_JSON="$MESA_DIR/lvp_icd.json"
if [[ ! -f "$ICD_JSON" ]]; then
  echo "[setup] fetching mesa-vulkan-drivers from bookworm-backports into $MESA_DIR"
  WORK="$(mktemp -d)"; trap 'rm -rf "$WORK"' EXIT
  mkdir -p "$WORK/lists/partial" "$WORK/archives/partial"
  # Mirror URI from the system's own apt sources (deb822 or one-line format).
  URI="$(grep -hoE '^URIs:\s*\S+' /etc/apt/sources.list.d/*.sources 2>/dev/null | grep -v security | head -n1 | awk '{print $2}' || true)"
  [[ -z "$URI" ]] && URI="$(grep -hoE '^deb\s+(\[[^]]*\]\s+)?\S+' /etc/apt/sources.list 2>/dev/null | grep -v security | head -n1 | awk '{print $NF}' || true)"
  [[ -z "$URI" ]] && { echo "[setup] no Debian mirror found in /etc/apt sources" >&2; exit 1; }
  cat > "$WORK/backports.sources" <<SRC
Types: deb
URIs: $URI
Suites: bookworm-backports
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
SRC
  APT_OPTS=(-o Dir::Etc::sourcelist="$WORK/backports.sources" -o Dir::Etc::sourceparts=- \
            -o Dir::State::Lists="$WORK/lists" -o Dir::Cache::Archives="$WORK/archives" \
            -o APT::Get::List-Cleanup=0)
  apt-get "${APT_OPTS[@]}" update -qq
  (cd "$WORK" && apt-get "${APT_OPTS[@]}" download mesa-vulkan-drivers/bookworm-backports)
  mkdir -p "$MESA_DIR"
  dpkg-deb -x "$WORK"/mesa-vulkan-drivers_*.deb "$MESA_DIR/root"
  LVP="$(find "$MESA_DIR/root" -name libvulkan_lvp.so | head -n1)"
  [[ -z "$LVP" ]] && { echo "[setup] libvulkan_lvp.so not found in the backports package" >&2; exit 1; }
  cat > "$ICD_JSON.tmp" <<JSON
{"file_format_version": "1.0.0", "ICD": {"library_path": "$LVP", "api_version": "1.3.0"}}
JSON
  mv "$ICD_JSON.tmp" "$ICD_JSON"
fi

# --- Python environment ------------------------------------------------------------------
PY="${PYTHON:-python3.11}"
command -v "$PY" >/dev/null || PY=python3
[[ -x .venv/bin/python ]] || "$PY" -m venv .venv
# No wheel cache: it would keep a second copy of every download (torch, Open3D, Ray, SAPIEN)
# on a machine whose disk may be nearly full.
export PIP_NO_CACHE_DIR=1
# torch first, pinned to the CPU build, or a dependency pulls a multi-GB CUDA build.
.venv/bin/pip install -q --upgrade pip
.venv/bin/pip install -q torch==2.13.0
.venv/bin/pip install -q -c scripts/constraints.txt -e ".${EXTRAS}"
.venv/bin/pip check
echo "[setup] done: software Vulkan at $ICD_JSON, venv at .venv"
