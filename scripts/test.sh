#!/usr/bin/env bash
# Install (if needed) and run the BRAVE-6D test suite (unit, property-based, miniature end-to-end).
# Extra arguments go to pytest (e.g. -k transforms, -x).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --with-ros2  # .venv, and .venv-ros2 for the rclpy tests
exec .venv/bin/python -m pytest "$@"
