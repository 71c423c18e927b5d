#!/usr/bin/env bash
# bench/peers.py's own virtual environment, .venv-peers/ at the repository root: BenchMARL, JaxMARL (CPU jax),
# VMAS and asp-dist itself (editable, with its vmas extra only), pinned in bench/peers-requirements.txt. The
# core install (scripts/install.sh) never pulls any of it.
#
#   bash bench/peers-venv.sh                        # create it, or bring it to the pins (PYTHON=... picks Python)
#   .venv-peers/bin/python bench/peers.py --quick
#
# PEERS_VENV=DIR puts it elsewhere. Everything comes from PyPI: the PyTorch wheel index is not needed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${PEERS_VENV:-.venv-peers}
if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
  echo "peers-venv.sh: error: needs Python >= 3.11, $PY is not (PYTHON=... to choose another)" >&2
  exit 2
fi
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
pip_install() { "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check "$@"; }
# torch first and alone, as scripts/install.sh: torch==2.13.0 from PyPI is the CPU build, and nothing resolved
# later then asks pip for another torch (which could pull CUDA wheels of several GB)
pip_install "torch==2.13.0"
pip_install -r bench/peers-requirements.txt
# BenchMARL without its dependencies: it also asks for torchvision and av<14, which it never imports on this path
# (VMAS tasks, MLPs, no video logging), and PyPI's torchvision 0.28.0, the one for torch 2.13.0, fails to load
# its operators beside the CPU torch ("operator torchvision::nms does not exist"). pip check names the two.
pip_install --no-deps "benchmarl==1.5.2"
pip_install -e ".[vmas]"
"$VENV/bin/python" - <<'PYEOF'
import importlib.metadata as md

import asp_dist.domains.vmas.game, benchmarl.experiment, jax, jaxmarl, tensordict, torchrl, vmas  # noqa: F401
names = ("torch", "torchrl", "tensordict", "benchmarl", "vmas", "jax", "jaxlib", "jaxmarl", "asp-dist")
print("peers-venv.sh: ready:", ", ".join(f"{n} {md.version(n)}" for n in names))
PYEOF
