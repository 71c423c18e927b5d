#!/usr/bin/env bash
# Installs asp-dist with the CPU build of PyTorch. Installing torch==2.13.0 first keeps pip
# from pulling a CUDA build (several GB); the project itself accepts any torch>=2.3.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
"$PY" -m pip install --quiet --disable-pip-version-check "torch==2.13.0"
"$PY" -m pip install --quiet --disable-pip-version-check -e ".[test]"
