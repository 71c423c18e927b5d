#!/usr/bin/env bash
# Install, then run the whole test suite (the README's second command; CI runs this too).
#   bash scripts/test.sh                 everything, two workers (pytest-xdist), the 25 slowest listed
#   bash scripts/test.sh -m "not slow"   the fast tier, for iterating (no Ray sweeps)
#   bash scripts/test.sh -n 0 tests/test_spec.py   one file, in this process
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export OMP_NUM_THREADS=1 RAY_USAGE_STATS_ENABLED=0
# Tests that share a module fixture (one smoke sweep read by several tests) stay on one worker: loadgroup.
exec "${PYTHON:-python3}" -m pytest -q -n "${ASP_TEST_WORKERS:-2}" --dist loadgroup --durations=25 "$@"
