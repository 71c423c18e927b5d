"""The commands that only describe or read (`--help`, `fields`, `status`, `query`) import neither torch nor Ray.

Each runs in a fresh interpreter, which then lists the torch and Ray modules it holds: the list must be
empty. What keeps it so: a domain's card (asp_dist/domains/<name>/__init__.py) describes the domain
without torch and imports its torch half (game.py) when a method first needs it; the row schema
(asp_dist/training/row.py), the store and the ledger import no torch at the top. bench/bench_cli.py
measures what this buys in wall time.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from asp_dist.results import store
from asp_dist.spec import CellSpec
from asp_dist.sweep import ledger

HEAVY = ("torch", "ray")
MARK = "HEAVY-MODULES:"
PROBE = f"""
import json, sys
from asp_dist.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as e:  # argparse's --help exits
    code = e.code
heavy = sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r})
print({MARK!r} + json.dumps({{"code": code, "heavy": heavy}}))
"""


def heavy_modules(argv: list[str], cwd: Path) -> tuple[int, list[str]]:
    """Run `asp-dist ARGV` in a fresh interpreter; its exit code and the torch and Ray modules it imported."""
    out = subprocess.run([sys.executable, "-c", PROBE, *argv], cwd=cwd, capture_output=True, text=True, timeout=120)
    lines = [line for line in out.stdout.splitlines() if line.startswith(MARK)]
    assert lines, f"the probe printed no result:\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}"
    result = json.loads(lines[-1].removeprefix(MARK))
    return result["code"], result["heavy"]


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    """A results root holding sweep `tiny`: a manifest of three signaling cells and a row for one of them
    (a row by hand, with the pinned schema: no training, so the test needs no torch either)."""
    root = tmp_path_factory.mktemp("results")
    specs = [CellSpec(domain="signaling", method=m, paired=1).resolved() for m in ("pc", "osp", "asp")]
    sweep_dir = root / "tiny"
    store.write_manifest(sweep_dir, ledger.new_manifest("tiny", "smoke", specs))
    from harness import finished_row

    row = finished_row(specs[0], eval_mixed=0.75)
    assert store.write_row(sweep_dir, row, sweep_id="tiny")
    return root


COMMANDS = {
    "help": ["--help"],
    "fields": ["fields"],
    "fields-vae": ["fields", "--domain", "vae"],
    "status": ["status", "tiny", "--results", "{results}"],
    "query": ["query", "tiny", "--results", "{results}", "--sql", "SELECT count(*) FROM cells"],
}


@pytest.mark.parametrize("command", COMMANDS)
def test_command_imports_neither_torch_nor_ray(command, results, tmp_path):
    argv = [a.format(results=results) for a in COMMANDS[command]]
    code, heavy = heavy_modules(argv, tmp_path)
    assert code == 0, f"asp-dist {' '.join(argv)} exited {code}"
    assert heavy == [], f"asp-dist {' '.join(argv)} imported {len(heavy)} torch/Ray modules, e.g. {heavy[:5]}"


def test_a_domain_card_loads_its_game_on_first_use(tmp_path):
    """Resolving specs of every domain stays light; the first torch method of a domain imports its game."""
    probe = f"""
import sys
from asp_dist.core.registry import DOMAINS
from asp_dist.spec import CellSpec
ids = [CellSpec(domain=d, method='asp', paired=2).resolved().cell_id for d in DOMAINS]
light = sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r})
agents = DOMAINS['signaling'].new_agents(CellSpec(domain='signaling').resolved(), 0)
print(len(ids) == len(DOMAINS) >= 4, light, 'torch' in sys.modules, type(agents).__module__)
"""
    out = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["True", "[]", "True", "asp_dist.domains.signaling.game"]


def top_level_modules_after(code: str, **env: str) -> set[str]:
    """Run `code` in a fresh interpreter (with `env` added to this one's); the top-level names of the modules it
    then holds."""
    probe = code + f"\nimport sys\nprint({MARK!r} + ','.join(sorted({{m.split('.')[0] for m in sys.modules}})))\n"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120,
                         env={**os.environ, **env})
    lines = [line for line in out.stdout.splitlines() if line.startswith(MARK)]
    assert lines, f"the probe printed no result:\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}"
    return set(lines[-1].removeprefix(MARK).split(","))


TAG_PROBE = """
from ray import tune
from ray.air._internal import usage as air_usage
from asp_dist.sweep.tune import _no_callback_tag_without_usage_stats
with _no_callback_tag_without_usage_stats():
    air_usage.tag_callbacks([tune.Callback()])
"""


@pytest.mark.parametrize("enabled, imported", [("0", False), ("1", True)])
def test_a_sweep_driver_imports_no_tracker_library_for_ray_usage_tags_it_never_sends(enabled, imported):
    """With Ray's usage stats off (asp-dist's default), Tune's callback tag is skipped: it imports MLflow and
    W&B just to name the run's callbacks (~3 s of a driver's CPU). With them on, Tune records it as usual."""
    assert ("mlflow" in top_level_modules_after(TAG_PROBE, RAY_USAGE_STATS_ENABLED=enabled)) is imported


def test_the_sweep_driver_imports_no_torch():
    """The driver hands train_cell to Tune and names trials; only the workers that train need torch (~2 s of
    CPU per sweep run: asp_dist/sweep/trial.py imports it in the functions a worker runs)."""
    assert "torch" not in top_level_modules_after("import asp_dist.sweep.tune")
