"""The lever world's packed trainer (asp_dist/domains/levers/packed.py), what is particular to it:
what can share a pack, and ε-greedy exploration compared in float32 as dqn_step compares it. Checks
of every packed trainer (packs against the reference Trainer member by member, whole cells against
run_cell, pack-mates, divergence, checkpoints of the trainer and of a whole pack) are in
tests/test_packed.py; here also: a single lever cell trains as a one-member pack, whose updates
equal the reference Trainer's."""

from __future__ import annotations

import pytest
import torch
from budgets import tiny_spec
from packed_cases import LEVERS, AdamDrift, adam_sqrt_v, flat_grads, flat_params, float32_tol, lone

import asp_dist.domains.levers.packed as packed_mod
from asp_dist.core.registry import get_domain
from asp_dist.domains.levers.packed import PackedLeverTrainer, pack_key

supports = PackedLeverTrainer.supports


def test_what_can_share_a_pack():
    spec = LEVERS.spec
    assert supports(spec(method="asp", paired=2)) and supports(tiny_spec("levers"))
    assert not supports(tiny_spec("signaling")) and not supports(tiny_spec("particles"))
    assert pack_key(spec(method="pc", paired=1, trial=4, lr=0.1, levers_eps_end=0.2)) == pack_key(
        spec(method="asp", paired=6, unpaired_size=33, adversary_loss="non_saturating"))
    assert pack_key(spec(method="pc")) != pack_key(spec(method="pc", levers_replay_size=48))
    with pytest.raises(ValueError, match="levers_hidden"):
        LEVERS.make_pack([spec(method="pc", paired=1), spec(method="pc", paired=1, levers_hidden=4)])


def test_exploration_coins_compare_in_float32_as_dqn_step_does():
    """ε is a Python float in dqn_step (`rand < eps`, compared in float32); the pack pre-draws the
    coins and compares them with its own ε column. A coin equal to float32(ε) tells the two apart."""
    eps = 0.525
    coin = torch.tensor(eps, dtype=torch.float32)
    assert float(coin) != eps  # the case that matters: float32(ε) differs from ε
    pack = LEVERS.make_pack([LEVERS.spec(method="osp", paired=1, levers_eps_start=eps, levers_eps_end=eps)])
    pack._draw_chunk()
    coins = torch.stack([coin, coin.nextafter(torch.tensor(0.0)), coin.nextafter(torch.tensor(1.0))])
    expected = coins < eps  # what dqn_step computes for these coins
    assert torch.equal(packed_mod.explore(coins, pack.eps[0, 0].view(1)), expected)


@pytest.mark.parametrize("changes", [
    dict(method="pc", paired=4),
    dict(method="osp", paired=0),
    dict(method="osp", paired=3, levers_eps_start=0.5, levers_eps_end=0.2, levers_eps_decay_frac=0.3),
    dict(method="asp", paired=2),
    dict(method="asp", paired=3, adversary_loss="non_saturating", lambda_unpaired=0.5),
    dict(method="asp", paired=2, disc_layers=2, disc_steps=2, unpaired_batch=5),
    dict(method="asp", paired=3, lambda_unpaired_schedule="warmup", lambda_schedule_frac=0.5),
], ids=lambda c: "-".join(f"{k}={v}" for k, v in c.items()))
def test_single_lever_cell_is_a_pack_of_one_equal_to_the_reference(changes):
    spec = LEVERS.spec(**changes)
    data, domain = LEVERS.member_data(spec), get_domain("levers")
    ref = LEVERS.make_reference(spec, data)
    single = lone(spec, domain.new_agents(spec, spec.seed_for("init")), data[0], data[1])
    assert type(single) is PackedLeverTrainer and single.engine == "PackedLeverTrainer"
    pack, terms = single, LEVERS.grad_terms(spec, ref.agents)
    drift = AdamDrift(spec.lr)
    for step in range(spec.train_steps):
        ref.train_step()
        single.train_step()
        # the same gradient and parameters up to float32 rounding (packed_cases.float32_tol, AdamDrift)
        expected, got = flat_grads(ref.agents), pack.net.member_flat(0, pack.net.grad)
        assert torch.allclose(got, expected, rtol=0, atol=float32_tol(expected, terms)), f"update {step}: gradient"
        theta = flat_params(ref.agents)
        assert drift.add(*adam_sqrt_v(ref.agents, ref.opt), theta, err=(got - expected).abs()).close(
            flat_params(single.members[0].agents), theta), f"update {step}"
    assert single.step == ref.step == spec.train_steps
    assert torch.equal(ref.gen.get_state(), single.members[0].gen.get_state()), "the same random draws were made"
    expected, got = ref.loss_columns(), single.loss_columns(0)
    assert expected.keys() == got.keys()
    for key, value in expected.items():
        assert (got[key] is None) == (value is None), key
        if value is not None:
            assert got[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
