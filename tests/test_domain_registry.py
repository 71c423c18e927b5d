"""Every registered domain, one contract (BenchMARL-style: parametrised over the registry).

check_domain (asp_dist/domains/contract.py) checks determinism, shapes and gradients; here we
add what the sweep relies on: bases and agents survive a save/load round trip (the base
cache stores bases as bytes), a whole tiny cell runs for every method, and the paper's
facts about the domain are declared."""

from __future__ import annotations

import pytest
import torch

from asp_dist.domains import DOMAINS
from asp_dist.domains.contract import assert_same_params, check_domain
from asp_dist.training.bases import base_from_bytes, base_to_bytes, train_accepted_base
from asp_dist.training.cell import run_cell
from asp_dist.training.row import comparable

domains = pytest.mark.parametrize("domain", list(DOMAINS.values()), ids=list(DOMAINS))


@domains
def test_contract(domain, tiny):
    check_domain(domain, tiny(domain.name, method="asp", paired=4))


@domains
def test_base_and_agents_round_trip(domain, tiny):
    spec = tiny(domain.name, paired=2).resolved()
    base = train_accepted_base(spec)
    loaded = base_from_bytes(base_to_bytes(base))
    assert (loaded.key, loaded.score, loaded.seed) == (base.key, base.score, base.seed)
    assert_same_params(base.agents, loaded.agents, "base round trip")
    agents = domain.new_agents(spec, 11)
    copy = domain.new_agents(spec, 12)
    copy.load_state_dict(agents.state_dict())
    assert_same_params(agents, copy, "agents round trip")
    # A cell on the loaded base gives the row of a cell on the original one.
    assert comparable(run_cell(spec, base=loaded)) == comparable(run_cell(spec, base=base))


@domains
@pytest.mark.parametrize("method", ["pc", "osp", "asp"])
def test_every_method_runs(domain, method, tiny):
    row = run_cell(tiny(domain.name, method=method, paired=2))
    assert row["domain"] == domain.name and row["method"] == method
    assert all(torch.isfinite(torch.tensor(row[f"eval_{m}"])) for m in domain.metrics), "every declared metric, finite"
    assert (row["loss_unpaired"] is not None) == (method == "asp")


@domains
def test_paper_facts(domain):
    facts = domain.paper
    assert facts.metric_label and facts.claim
    if facts.test_paired is not None:
        lo, hi = facts.test_paired
        assert 0 <= lo < hi
    for knob in facts.knob_labels:
        assert knob.startswith(domain.name + "_"), f"{knob} is not a {domain.name} knob"
