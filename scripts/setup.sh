#!/usr/bin/env bash
# Idempotent set-up on a fresh Debian 12 machine (as root, or with sudo): Debian packages, .venv/, the project
# installed editable with its extras, every Python package at the version pinned in constraints.txt. A second run
# with nothing changed (pyproject.toml, constraints.txt, this script) returns in well under a second.
# SYGRID_VENV and SYGRID_CONSTRAINTS (default .venv and constraints.txt) are for scripts/lock.sh, which runs this
# into a scratch venv with no constraints (/dev/null) to resolve fresh versions from pyproject.toml.
set -euo pipefail
cd "$(dirname "$0")/.."

# libusb: `import open3d`; EGL/OSMesa: MuJoCo offscreen rendering on CPU; libLLVM 19: Mitsuba's llvm_ad_rgb
# (Debian 12's default LLVM 14/15 aborts in drjit); libgomp: coacd/open3d.
APT_PACKAGES="libusb-1.0-0 libegl1 libgl1 libosmesa6 libllvm19 libgomp1 python3-venv"
VENV=${SYGRID_VENV:-.venv}
CONSTRAINTS=${SYGRID_CONSTRAINTS:-constraints.txt}
STAMP=$VENV/.sygrid-setup
FINGERPRINT=$(cat pyproject.toml "$CONSTRAINTS" scripts/setup.sh | sha256sum | cut -d' ' -f1)

if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$FINGERPRINT" ]; then
    exit 0
fi

missing=""
for pkg in $APT_PACKAGES; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing="$missing $pkg"
done
if [ -n "$missing" ]; then
    echo "setup: installing Debian packages:$missing"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing
fi

PYTHON=${PYTHON:-python3}
if [ ! -x "$VENV/bin/python" ]; then
    echo "setup: creating $VENV with $($PYTHON --version)"
    "$PYTHON" -m venv "$VENV"
fi
PIP=("$VENV/bin/python" -m pip install --disable-pip-version-check -q -c "$CONSTRAINTS")
"${PIP[@]}" --upgrade pip setuptools wheel

# Torch: a CPU wheel lies on these machines; installing it first stops the `train` extra from pulling the
# registry's CUDA build (several GB). Elsewhere the registry's torch is used.
TORCH_WHEEL=$(ls /opt/wheels/torch-*+cpu-*.whl 2>/dev/null | sort -V | tail -n 1 || true)
if [ -n "$TORCH_WHEEL" ] && ! "$VENV/bin/python" -c "import torch" 2>/dev/null; then
    echo "setup: installing the local CPU torch wheel $(basename "$TORCH_WHEEL")"
    "${PIP[@]}" "$TORCH_WHEEL"
fi

echo "setup: installing the project and its extras into $VENV (first time: several minutes)"
"${PIP[@]}" -e ".[train,dist,dev]"
echo "$FINGERPRINT" > "$STAMP"
echo "setup: done"
