#!/usr/bin/env bash
# Install, then run the whole test suite (the README's second command; CI runs this too).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export OMP_NUM_THREADS=1 RAY_USAGE_STATS_ENABLED=0
exec "${PYTHON:-python3}" -m pytest -q "$@"
