#!/usr/bin/env bash
# Create or update .venv with everything BRAVE-6D needs, on a fresh Linux machine (CPU).
# Idempotent: a second run with an unchanged pyproject.toml only checks and returns.
set -euo pipefail
cd "$(dirname "$0")/.."

# open3d needs libusb-1.0 (ImportError: libusb-1.0.so.0 otherwise)
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "setup: installing the Debian package libusb-1.0-0 (needed by open3d)" >&2
  $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

PYTHON="${PYTHON:-python3}"
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv

stamp=".venv/.brave6d-installed"
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
echo "setup: installing into .venv (about 3 GB; a few minutes the first time)" >&2
.venv/bin/python -m pip install -q --upgrade pip
# The CPU wheel of torch first, pinned: an unpinned torch would pull the multi-GB CUDA build.
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[test]"
echo "$want" > "$stamp"
