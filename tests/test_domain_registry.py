"""Every registered domain, one contract (BenchMARL-style: parametrised over the registry).

check_domain (asp_dist/core/contract.py) checks determinism, shapes and gradients; here we
add what the sweep relies on: bases and agents survive a save/load round trip (the base
cache stores bases as bytes), a whole tiny cell runs for every method, and the paper's
facts about the domain are declared."""

from __future__ import annotations

import pytest
import torch

from asp_dist.core.contract import assert_same_params, check_domain
from asp_dist.core.registry import DOMAINS
from asp_dist.training.bases import base_from_bytes, base_to_bytes, train_accepted_base
from asp_dist.training.cell import run_cell
from asp_dist.training.row import comparable

domains = pytest.mark.parametrize("domain", list(DOMAINS.values()), ids=list(DOMAINS))


@domains
def test_contract(domain, tiny):
    check_domain(domain, tiny(domain.name, method="asp", paired=4))


@pytest.mark.parametrize("bad, says", [(float("nan"), "metric 'mixed' is NaN"), (float("-inf"), "metric 'mixed' is -inf"),
                                       (None, "metric 'mixed' is missing")], ids=["nan", "inf", "missing"])
def test_the_contract_names_a_metric_that_is_not_finite(monkeypatch, capsys, tiny, bad, says):
    """check_domain (and `asp-dist check-domain`) says which metric is NaN, not "same seed gave different
    metrics" (NaN != NaN); a cell of that domain fails with the same words and writes no row."""
    from asp_dist.core.contract import ContractError
    from asp_dist.training.row import InvalidRow

    domain = DOMAINS["signaling"]
    evaluate = domain.evaluate

    def broken(*args):
        metrics = dict(evaluate(*args))
        metrics.pop("mixed") if bad is None else metrics.update(mixed=bad)
        return metrics

    monkeypatch.setattr(domain, "evaluate", broken)
    spec = tiny("signaling", method="asp", paired=2)
    if bad is not None:
        with pytest.raises(ContractError, match=f"evaluate: {says}"):
            check_domain(domain, spec)
    with pytest.raises(InvalidRow, match=f"signaling evaluate gave no valid row: {says}.*; no row written$"):
        run_cell(spec)
    # `asp-dist cell`: one line, exit 1 (the cell ran and failed, as in a sweep), no row printed or written
    from asp_dist.cli import main

    capsys.readouterr()
    assert main(["cell", "--domain", "signaling", "--method", "asp", "--paired", "2", "--quiet"]) == 1
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1 and f"failed: InvalidRow: signaling evaluate gave no valid " \
        f"row: {says}" in err, err


@domains
def test_base_and_agents_round_trip(domain, tiny):
    spec = tiny(domain.name, paired=2).resolved()
    base = train_accepted_base(spec)
    loaded = base_from_bytes(base_to_bytes(base), spec)
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
