#!/usr/bin/env bash
# Install (if needed) and run the whole BRAVE-6D pipeline on the embedded demo scene.
# Extra arguments go to `brave6d demo` (e.g. --workdir DIR, --quick, --device cuda).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/brave6d demo "$@"
