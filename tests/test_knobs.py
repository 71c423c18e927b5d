"""The reproduction study's knobs: neutral values change nothing, other values do what they say."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import pandas as pd
import pytest
import torch

from asp_dist.core.registry import DOMAINS, get_domain
from asp_dist.errors import SpecError
from asp_dist.hashing import stable_hash
from asp_dist.spec import COMMON_DEFAULTS, HASH_NEUTRAL, CellSpec
from asp_dist.study.decide_plan import DecidePlan
from asp_dist.study.decide_run import cells_through
from asp_dist.sweep.ledger import DECIDE_FILE
from asp_dist.sweep.spaces import expand, grid_hash
from asp_dist.training import bases
from asp_dist.training.cell import run_cell
from asp_dist.training.methods import lambda_factor
from asp_dist.training.row import comparable


@pytest.mark.parametrize("knob", sorted(HASH_NEUTRAL))
def test_a_knob_at_its_neutral_value_keeps_every_id(knob):
    """At its neutral value a knob is left out of the hash material, so ids, seeds and base keys are
    what they were before the knob existed: the hash of the spec without it. Off it, they change."""
    # Particles default to a λ1 warm-up and a growing base budget; start from the neutral values.
    spec = CellSpec(domain="particles", trial=7, lambda_unpaired_schedule="constant", base_steps_growth=1.0).resolved()
    before = {k: v for k, v in spec.to_dict().items() if k not in HASH_NEUTRAL}  # as a spec without the knobs
    assert spec.identity_dict() == before
    assert spec.cell_id.endswith(stable_hash(before)[:10])
    other = {str: "x", bool: not HASH_NEUTRAL[knob], int: 2, float: 0.25}[type(HASH_NEUTRAL[knob])]
    changed = dataclasses.replace(spec, **{knob: other})  # not validated: any other value will do
    assert changed.identity_dict() == {**before, knob: other}
    assert stable_hash(changed.identity_dict()) != stable_hash(before)


def test_new_agent_knobs_share_the_base_and_base_knobs_do_not():
    spec = CellSpec(domain="vae", trial=7).resolved()
    assert spec.replace(vae_adversary_input="z").base_key == spec.base_key
    assert spec.replace(vae_paired_reduction="mean").base_key == spec.base_key
    assert spec.replace(vae_recon_loss="mse").base_key != spec.base_key
    assert spec.replace(base_steps_growth=1.5).base_key != spec.base_key
    p = CellSpec(domain="particles", trial=7).resolved()
    assert p.replace(particles_replay_size=1000, particles_paired_listener=False).base_key == p.base_key
    assert p.replace(particles_replay_size=1000).cell_id != p.cell_id


BUILT_IN = sorted(d for d in DOMAINS if DOMAINS[d].legacy_identity)  # the study's choices; a plugin makes its own


@pytest.mark.parametrize("domain", BUILT_IN)
def test_domain_defaults_of_the_common_knobs(domain):
    """Particles and the VAE take the reproduction study's settings
    (docs/decisions/0021-domain-defaults-from-reproduction-study.md); the rest keep COMMON_DEFAULTS; PC
    and OSP never carry a λ1 schedule (they have no adversary)."""
    chosen = {"particles": dict(lambda_unpaired_schedule="warmup", lambda_schedule_frac=0.5,
                                base_steps_growth=1.5, base_max_attempts=10)}
    asp = CellSpec(domain=domain, method="asp").resolved()
    expected = {**COMMON_DEFAULTS, **chosen.get(domain, {})}
    assert {k: getattr(asp, k) for k in expected} == expected
    if domain == "vae":
        assert asp.lambda_unpaired == 10.0
    for method in ("pc", "osp"):
        other = CellSpec(domain=domain, method=method, lambda_unpaired_schedule="anneal",
                         lambda_schedule_frac=0.3).resolved()
        assert (other.lambda_unpaired_schedule, other.lambda_schedule_frac, other.lambda_unpaired or 0.0) == \
            ("constant", 0.5, 0.0)
        assert other.cell_id == CellSpec(domain=domain, method=method).cell_id
    explicit = CellSpec(domain=domain, method="asp", lambda_unpaired_schedule="anneal", base_max_attempts=3).resolved()
    assert (explicit.lambda_unpaired_schedule, explicit.base_max_attempts) == ("anneal", 3), "a set knob beats the default"


EXAMPLES = Path(__file__).resolve().parents[1] / "results" / "examples"
EXAMPLE_MANIFESTS = sorted(EXAMPLES.glob("*/manifest.json"))


def space_path(name: str) -> str:
    """A recorded space's file: tune_spaces/<name>.toml, or a plugin's beside it (examples/*/<name>.toml)."""
    root = EXAMPLES.parents[1]
    found = [p for p in [root / "tune_spaces" / f"{name}.toml", *sorted(root.glob(f"examples/*/{name}.toml"))]
             if p.is_file()]
    return str(found[0]) if found else name


@pytest.mark.parametrize("manifest", EXAMPLE_MANIFESTS, ids=lambda p: p.parent.name)
def test_spaces_that_ran_still_resolve_to_their_cells(manifest):
    """A changed default must not change what a committed sweep's space means: its space file still
    expands to the recorded cells, and every recorded spec still resolves to its recorded id."""
    recorded = json.loads(manifest.read_text())
    specs = expand(space_path(recorded["space"]))
    decided = manifest.parent / DECIDE_FILE
    if decided.is_file():
        # A decided sweep records the stages it reached, each training the treatments still open when it
        # started; the grid and registration behind its looks must be the ones it ran under.
        plan = DecidePlan.from_space(space_path(recorded["space"]))
        record = json.loads(decided.read_text())
        assert plan.fingerprint() == record["fingerprint"]
        reached = [cells_through(plan, record["looks"], next_stage=False)]  # stopped between stages
        if not record["finished"]:
            reached.append(cells_through(plan, record["looks"], next_stage=True))  # stopped inside one
        specs = next((c for c in reached if sorted(s.cell_id for s in c) == sorted(recorded["cells"])), reached[-1])
    assert sorted(s.cell_id for s in specs) == sorted(recorded["cells"])
    assert grid_hash(specs) == recorded["grid_hash"]
    assert [CellSpec.from_dict(s).cell_id for s in recorded["specs"]] == recorded["cells"]


@pytest.mark.parametrize("space", ["particles-lambda", "paper-levers"])
def test_committed_rows_without_a_manifest_are_still_cells_of_their_space(space):
    """The same for the merged example rows of spaces whose defaults were pinned (particles-lambda) or
    did not change (paper-levers)."""
    recorded = set(pd.read_parquet(EXAMPLES / f"{space}.parquet", columns=["cell_id"])["cell_id"])
    assert recorded and recorded == {s.cell_id for s in expand(space)}


@pytest.mark.parametrize("changes, needle", [
    (dict(lambda_unpaired_schedule="cosine"), "lambda_unpaired_schedule must be one of"),
    (dict(lambda_schedule_frac=0.0), "lambda_schedule_frac must be in"),
    (dict(method="osp", lambda_schedule_frac=7.0), "lambda_schedule_frac must be in"),  # refused before set aside
    (dict(disc_steps=0), "disc_steps must be >= 1"),
    (dict(base_steps_growth=0.0), "base_steps_growth must be > 0"),
    (dict(domain="vae", vae_recon_loss="l1"), "vae_recon_loss must be one of"),
    (dict(domain="vae", vae_adversary_input="x"), "vae_adversary_input must be one of"),
])
def test_bad_knob_values_are_refused(changes, needle):
    with pytest.raises(SpecError, match=needle):
        CellSpec(**{"domain": "particles", **changes}).resolved()


def test_lambda_schedules():
    spec = CellSpec(domain="signaling", train_steps=100, lambda_schedule_frac=0.5).resolved()
    assert [lambda_factor(spec, s) for s in (0, 50, 99)] == [1.0, 1.0, 1.0]
    warm = spec.replace(lambda_unpaired_schedule="warmup")
    assert [lambda_factor(warm, s) for s in (0, 25, 50, 80)] == [0.0, 0.5, 1.0, 1.0]
    anneal = spec.replace(lambda_unpaired_schedule="anneal")
    assert [lambda_factor(anneal, s) for s in (0, 25, 50, 80)] == [1.0, 0.5, 0.0, 0.0]


def test_base_retries_escalate_the_budget(monkeypatch, tiny):
    spec = tiny("particles", particles_accept_return=1e9, base_max_attempts=3, base_steps_growth=2.0).resolved()
    domain = get_domain("particles")
    seen = []
    monkeypatch.setattr(domain, "train_base", lambda s, seed, progress=None: (seen.append(s.base_train_steps), (None, 0.0))[1])
    with pytest.raises(bases.BaseRejected):
        bases.train_accepted_base(spec)
    assert seen == [30, 60, 120]


def test_paired_loss_without_the_listener_term_is_the_speaker_mse(tiny):
    spec = tiny("particles", paired=4).resolved()
    domain = get_domain("particles")
    base = domain.new_agents(spec, 1)
    paired = domain.paired(spec, base, 4, torch.Generator().manual_seed(0))
    agents = domain.new_agents(spec, 2)
    speaker_only = domain.paired_loss(spec.replace(particles_paired_listener=False), agents, paired)
    assert speaker_only == torch.nn.functional.mse_loss(agents.speak(paired["state"]), paired["message"])
    assert domain.paired_loss(spec, agents, paired) > speaker_only


def test_vae_paired_mean_is_the_sum_over_its_widths(tiny):
    spec = tiny("vae", paired=4).resolved()
    domain = get_domain("vae")
    base = domain.new_agents(spec, 1)
    paired = domain.paired(spec, base, 4, torch.Generator().manual_seed(0))
    agents = domain.new_agents(spec, 2)
    enc = (agents.encode(paired["image"])[0] - paired["encoding"]).pow(2)
    dec = (agents.decode(paired["encoding"]) - paired["recon"]).pow(2)
    mean = domain.paired_loss(spec.replace(vae_paired_reduction="mean"), agents, paired)
    assert float(mean.detach()) == pytest.approx(float((enc.mean() + dec.mean()).detach()))


@pytest.mark.parametrize("name, changes", [
    ("particles", dict(particles_replay_size=64)),
    ("particles", dict(disc_steps=2, lambda_unpaired_schedule="warmup")),
    ("vae", dict(vae_adversary_input="z", vae_recon_loss="mse")),
])
def test_non_default_knobs_run_deterministically_and_restore(name, changes, tiny):
    spec = tiny(name, method="asp", paired=2, train_steps=40, **changes)
    states = []
    row = run_cell(spec, checkpoint=lambda s: states.append(copy.deepcopy(s)), checkpoint_every_steps=17)
    assert comparable(run_cell(spec)) == comparable(row)
    assert comparable(run_cell(spec, restore=states[0])) == comparable(row)
    assert comparable(row) != comparable(run_cell(tiny(name, method="asp", paired=2, train_steps=40)))


def test_the_knobs_page_is_what_the_declarations_say():
    """docs/knobs.md is generated from the knob declarations; a knob added, renamed or given another default or
    range without regenerating it fails here."""
    from asp_dist.commands.fields import KNOBS_PAGE, knobs_page

    page = Path(__file__).resolve().parents[1] / KNOBS_PAGE
    assert page.read_text() == knobs_page(), f"{KNOBS_PAGE} is stale: asp-dist fields --markdown > {KNOBS_PAGE}"
    assert all(f"`{k.name}`" in page.read_text() for d in DOMAINS.values() if d.name in ("particles", "vae", "levers")
               for k in d.knobs)
