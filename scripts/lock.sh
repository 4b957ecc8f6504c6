#!/usr/bin/env bash
# Refreshes constraints.txt (run by `make lock`): scripts/setup.sh into a scratch venv with no constraints, so pip
# resolves the newest versions pyproject.toml allows (the project with its train, dist and dev extras; torch from
# the local CPU wheel where /opt/wheels has one), then every installed distribution frozen with an exact pin.
# Local version labels are dropped (torch 2.13.0+cpu is pinned as torch==2.13.0, which that wheel satisfies and
# a registry can serve). Review the diff and run the tests (`make test`) before committing a new lock.
set -euo pipefail
cd "$(dirname "$0")/.."

SCRATCH=$(mktemp -d "${TMPDIR:-/tmp}/sygrid-lock.XXXXXX")
trap 'rm -rf "$SCRATCH"' EXIT
SYGRID_VENV="$SCRATCH/venv" SYGRID_CONSTRAINTS=/dev/null bash scripts/setup.sh
PY="$SCRATCH/venv/bin/python"
PLATFORM='import platform, sys; print(f"CPython {sys.version.split()[0]}, {platform.system()} {platform.machine()}")'

{
    echo "# Exact versions of every Python package scripts/setup.sh installs into .venv (it runs pip install -c this"
    echo "# file). Made by \`make lock\` (scripts/lock.sh) on $("$PY" -c "$PLATFORM"): scripts/setup.sh into a"
    echo "# scratch venv with no constraints (newest versions pyproject.toml allows), then \`pip list --format=freeze"
    echo "# --exclude-editable\`, local version labels dropped (e.g. torch 2.13.0+cpu -> torch==2.13.0)."
    echo "# The upper bound on opencv-contrib-python-headless is pyproject.toml's (<5; why: robot/hand_eye.py)."
    "$PY" -m pip list --disable-pip-version-check --format=freeze --exclude-editable | sed -E 's/\+[A-Za-z0-9.]+$//'
} > "$SCRATCH/constraints.txt"
mv "$SCRATCH/constraints.txt" constraints.txt
echo "lock: wrote constraints.txt ($(grep -cv '^#' constraints.txt) packages)"
