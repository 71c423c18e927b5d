"""Domains are plugins found through the `asp_dist.domains` entry-point group.

Each case installs a real (tiny) distribution in a temporary site directory — a package and its
``*.dist-info`` with ``entry_points.txt``, what pip leaves — and runs `asp-dist` in a fresh interpreter
with that directory on PYTHONPATH: discovery goes through importlib.metadata exactly as for a pip-installed
plugin. A broken plugin is named in one line and never takes the other domains down."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from harness import env

GOOD = '''
from asp_dist.core.contract import GameDomain, MetricInfo, PaperFacts
from asp_dist.knobs import Knob


class ToyDomain(GameDomain):
    name = "toy"
    channels = ("message",)
    paper = PaperFacts(metric_label="toy score", claim="none")
    metrics = {m: MetricInfo(True, m) for m in ("mixed", "self_play_new", "self_play_base")}
    knobs = (Knob("toy_size", int, 7, "Size of the toy world."),
             Knob("toy_mode", str, "a", "Mode of the toy world.", choices=("a", "b")))
    defaults = dict(train_steps=3, batch_size=4, lr=0.01, lambda_paired=1.0, lambda_unpaired=0.1,
                    unpaired_size=16, disc_hidden=8, disc_layers=1, disc_lr=0.01, base_train_steps=1,
                    eval_episodes=4)

    def channel_dims(self, spec):
        return {"message": spec.toy_size}
'''


def install(site: Path, dist: str, module: str, source: str, entry: str) -> None:
    """A distribution `dist` with one module and one entry point `entry` (``name = module:attr``)."""
    (site / f"{module}.py").write_text(textwrap.dedent(source))
    info = site / f"{dist}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[asp_dist.domains]\n{entry}\n")


def asp(site: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "asp_dist", *args], capture_output=True, text=True,
                          env=env(PYTHONPATH=str(site)), cwd=site)


def python(site: Path, code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env(PYTHONPATH=str(site)), cwd=site)


ROW_COLUMNS = "from asp_dist.training.row import schema; print(' '.join(schema('vae').names))"
SMOKE_IDS = "from asp_dist.sweep.spaces import expand; import json; print(json.dumps([s.cell_id for s in expand('smoke')]))"


@pytest.fixture
def site(tmp_path):
    path = tmp_path / "site"
    path.mkdir()
    return path


def test_a_plugin_domain_is_found_and_its_knobs_are_cell_fields_and_move_no_other_cell(site, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    before = json.loads(python(empty, SMOKE_IDS).stdout)
    vae_columns = python(empty, ROW_COLUMNS).stdout
    install(site, "asp-toy", "asp_toy", GOOD, "toy = asp_toy:ToyDomain")

    out = asp(site, "fields", "--domain", "toy")
    assert out.returncode == 0, out.stderr
    assert "toy_size" in out.stdout and "Size of the toy world." in out.stdout and "vae_latent_dim" not in out.stdout
    listed = {line.split()[0]: line.split()[1] for line in out.stdout.splitlines()}
    assert listed["toy_size"] == "7" and listed["toy_mode"] == "a" and listed["train_steps"] == "3"
    assert "toy_size" not in asp(site, "fields", "--domain", "vae").stdout

    spec = python(site, "from asp_dist.spec import CellSpec\n"
                        "s = CellSpec(domain='toy', method='pc').resolved()\n"
                        "print(s.toy_size, s.toy_mode, s.train_steps, s.cell_id)")
    assert spec.returncode == 0, spec.stderr
    assert spec.stdout.split()[:3] == ["7", "a", "3"]
    bad = python(site, "from asp_dist.spec import CellSpec\nCellSpec(domain='toy', toy_mode='c').resolved()")
    assert "toy_mode must be one of a, b" in bad.stderr
    assert json.loads(python(site, SMOKE_IDS).stdout) == before, "installing a domain moved built-in cell ids"
    assert python(site, ROW_COLUMNS).stdout == vae_columns, "installing a domain changed a built-in row's shape"
    toy_columns = python(site, ROW_COLUMNS.replace("'vae'", "'toy'")).stdout.split()
    assert {"toy_size", "toy_mode"} <= set(toy_columns) and "vae_latent_dim" in toy_columns


@pytest.mark.parametrize("case, source, entry, expected", [
    ("import-error", "import not_a_module_anywhere\n", "broken = asp_broken:Domain",
     "domain plugin 'broken' (asp_broken:Domain, from asp-broken 0.1) cannot be loaded: ModuleNotFoundError"),
    ("not-a-domain", "class NotADomain:\n    pass\n", "broken = asp_broken:NotADomain",
     "it is a NotADomain, not an asp_dist.core.contract.Domain"),
    ("knob-twice", GOOD.replace('"toy"', '"broken"').replace("toy_", "broken_").replace(
        'Knob("broken_mode", str, "a", "Mode of the toy world.", choices=("a", "b"))',
        'Knob("broken_size", int, 1, "Again.")'), "broken = asp_broken:ToyDomain",
     "knob 'broken_size' is declared twice"),
    ("wrong-prefix", GOOD.replace('"toy"', '"broken"').replace("toy_", "broken_").replace('"broken_mode"', '"mode"'),
     "broken = asp_broken:ToyDomain",
     "knob 'mode' must be named broken_<knob>"),
    ("wrong-name", GOOD, "broken = asp_broken:ToyDomain",
     "it is registered as 'broken' but its Domain.name is 'toy'"),
    ("core-collision", GOOD.replace('"toy"', '"base"').replace('"toy_size"', '"base_train_steps"').replace(
        "toy_", "base_"), "base = asp_broken:ToyDomain",
     "its knob 'base_train_steps' collides with a common CellSpec field"),
    ("taken-name", GOOD.replace('"toy"', '"vae"').replace("toy_", "vae_"), "vae = asp_broken:ToyDomain",
     "domain 'vae' is registered by 2 plugins: 'vae' (asp_broken:ToyDomain, from asp-broken 0.1); 'vae' "
     "(asp_dist.domains.vae:VAEDomain, from asp-dist"),
])
def test_a_broken_plugin_is_named_in_one_line_and_the_other_domains_work(site, case, source, entry, expected):
    install(site, "asp-broken", "asp_broken", source, entry)
    name = entry.split(" = ")[0]

    listing = asp(site, "fields")
    assert listing.returncode == 0, listing.stderr
    warnings = [line for line in listing.stderr.splitlines() if line.startswith("asp-dist: warning:")]
    assert len(warnings) == 1 and expected in warnings[0], listing.stderr
    assert "levers_hidden" in listing.stdout and "particles_hidden" in listing.stdout
    assert asp(site, "fields", "--domain", "particles").returncode == 0

    # Asking for it (a space, --domain) is refused in one line; with two packages registering `vae`, neither
    # runs: which one would is an accident of installation.
    asked = asp(site, "fields", "--domain", name)
    assert asked.returncode == 2 and asked.stdout == ""
    lines = asked.stderr.strip().splitlines()
    assert lines[-1].startswith("asp-dist: error: ") and expected in lines[-1], asked.stderr


METHOD = '''
from asp_dist.method_registry import Method

SP = Method("sp", "self-play only: the convention the pair invents, no base data", self_play=True, paired=False)
NOT_A_METHOD = object()
'''

RUN_SP = ("from asp_dist.spec import CellSpec\n"
          "from asp_dist.training.cell import run_cell\n"
          "from asp_dist.training.methods import method_weights\n"
          "spec = CellSpec(domain='signaling', method='sp', paired=4, train_steps=30, batch_size=16, unpaired_size=64)\n"
          "row = run_cell(spec)\n"
          "print(row['method'], row['loss_paired'], row['loss_unpaired'], row['lambda_unpaired'], method_weights(spec))")


def test_a_plugin_method_trains_a_cell_and_a_broken_one_is_named(site):
    install(site, "asp-sp", "asp_sp", METHOD, "sp = asp_sp:SP\nbroken = asp_sp:NOT_A_METHOD")
    (site / "asp-sp-0.1.dist-info" / "entry_points.txt").write_text(
        "[asp_dist.methods]\nsp = asp_sp:SP\nbroken = asp_sp:NOT_A_METHOD\n")
    out = python(site, RUN_SP)
    assert out.returncode == 0, out.stderr
    method, paired, unpaired, lam, weights = out.stdout.split(maxsplit=4)
    assert (method, paired, unpaired, lam) == ("sp", "None", "None", "0.0"), out.stdout
    assert "self_play=1.0, paired=0.0, unpaired=0.0" in weights

    listing = asp(site, "fields")
    assert listing.returncode == 0 and "it is a object, not an asp_dist.method_registry.Method" in listing.stderr
    refused = asp(site, "cell", "--domain", "signaling", "--method", "broken", "--paired", "0")
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines()[-1].startswith("asp-dist: error: method plugin 'broken'"), refused.stderr
    assert asp(site, "cell", "--domain", "signaling", "--method", "nope", "--paired", "0").stderr.strip().endswith(
        "choose one of asp, osp, pc, sp")
