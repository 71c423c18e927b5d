"""bench/peers.py refuses in one line (exit 2) what it cannot run: a Python without the peers' venv
(bench/peers-venv.sh; the core install never pulls BenchMARL or JaxMARL), and bad flags, before measuring anything."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

PEERS = Path(__file__).resolve().parents[1] / "bench" / "peers.py"


def run(*flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(PEERS), *flags], capture_output=True, text=True, timeout=60)


@pytest.mark.skipif(importlib.util.find_spec("benchmarl") is not None, reason="the peers' venv is this Python")
def test_without_the_peers_venv_it_is_one_line_and_exit_2():
    out = run("--quick")
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.count("\n") == 1 and "not installed" in out.stderr and "bash bench/peers-venv.sh" in out.stderr


@pytest.mark.parametrize("flags,needle", [(["--peers", "bogus"], "--peers: unknown bogus"),
                                          (["--pack-teams", "0"], "--pack-teams must be >= 1"),
                                          (["--budget-cpu-s", "-1"], "--budget-cpu-s must be > 0"),
                                          (["--batches", "1,x"], "--batches: comma-separated integers")])
def test_bad_flags_are_one_line_and_exit_2(flags, needle):
    out = run(*flags)
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and needle in out.stderr, out.stderr
