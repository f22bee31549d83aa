#!/usr/bin/env bash
# Installs everything imtune and its tests need on a fresh Debian machine with Python 3.11:
# system packages (Chromium + driver for the dashboard test, PostgreSQL for multi-worker tests),
# a virtualenv in .venv with the CPU build of torch and the project in editable mode.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
need=()
for pkg in chromium chromium-driver postgresql; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# torch first, pinned: the CPU build of 2.13.0 is what this machine kind provides (any other spec
# pulls a multi-GB CUDA build); the project's own `torch>=2.2` is then already satisfied.
.venv/bin/python -m pip install -q torch==2.13.0
.venv/bin/python -m pip install -q -e '.[test]'
echo "imtune installed in $(pwd)/.venv"
