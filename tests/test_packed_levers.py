"""The lever world's packed trainer (asp_dist/training/packed/levers.py), what is particular to it:
what can share a pack, and ε-greedy exploration compared in float32 as dqn_step compares it. Checks
of every packed trainer (packs against the reference Trainer member by member, whole cells against
run_cell, pack-mates, divergence, checkpoints of the trainer and of a whole pack) are in
tests/test_packed.py; single lever cells train on the reference Trainer."""

from __future__ import annotations

import pytest
import torch
from budgets import tiny_spec
from packed_cases import LEVERS

import asp_dist.training.packed.levers as packed_mod
from asp_dist.training.packed.levers import pack_key, supports


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
