"""Particle speaker–listener world: contract, environment rules, A2C plumbing, whole cells."""

from __future__ import annotations

import io

import pytest
import torch
from budgets import tiny_spec

from asp_dist.core.registry import get_domain
from asp_dist.domains.particles import BOX, MOVES, NEAR_REWARD, POOL, ParticleAgents, a2c_update, env_step, target_for
from asp_dist.spec import CellSpec, SpecError
from asp_dist.training import artefacts
from asp_dist.training.bases import train_accepted_base
from asp_dist.training.cell import run_cell
from asp_dist.training.row import comparable


def tiny(**changes) -> CellSpec:
    return tiny_spec("particles", **changes)



def test_target_depends_on_trial_not_on_base_seed():
    a, b = tiny(trial=0).resolved(), tiny(trial=1).resolved()
    assert not torch.equal(target_for(a), target_for(b))
    assert torch.equal(target_for(a), target_for(tiny(trial=0, base_train_steps=99).resolved()))
    assert target_for(a).abs().max() <= BOX


def test_env_rules():
    target = torch.tensor([0.0, 0.0])
    pos = torch.tensor([[4.5, 0.0], [0.5, 0.5], [-5.0, -5.0], [3.0, 0.0]])
    actions = torch.tensor([1, 0, 2, 2])  # +x (clipped), stay, -x (clipped), -x
    new, reward = env_step(pos, actions, target)
    assert torch.equal(new, torch.tensor([[5.0, 0.0], [0.5, 0.5], [-5.0, -5.0], [2.0, 0.0]]))
    assert reward[1] == NEAR_REWARD  # within 1.4 of the target
    assert torch.allclose(reward[[0, 2, 3]], 1 / torch.tensor([5.0, 50 ** 0.5, 2.0]))
    assert MOVES.abs().sum(1).tolist() == [0, 1, 1, 1, 1]


def test_message_gradient_reaches_the_speaker():
    spec = tiny().resolved()
    agents = ParticleAgents(spec.particles_message_dim, spec.particles_hidden)
    gen = torch.Generator().manual_seed(0)
    state = get_domain("particles").init_self_play(spec, agents, gen)
    out = a2c_update(spec, agents, state, state["target"], gen)
    out.loss.backward()
    assert agents.speaker[0].weight.grad.abs().sum() > 0, "the listener's policy gradient must flow into the speaker"
    assert out.outputs["message"].shape == (spec.batch_size * spec.particles_rollout_len, spec.particles_message_dim)
    assert out.outputs["message"].abs().max() <= 1.0


def test_envs_advance_and_respawn():
    spec = tiny(particles_rollout_len=3).resolved()
    agents = ParticleAgents(spec.particles_message_dim, spec.particles_hidden)
    gen = torch.Generator().manual_seed(0)
    state = get_domain("particles").init_self_play(spec, agents, gen)
    t0 = state["t"].clone()
    for _ in range(spec.particles_episode_len):
        a2c_update(spec, agents, state, state["target"], gen)
    # 40 updates x 3 steps = 120 steps = 3 whole episodes: every env is back at its phase.
    assert torch.equal(state["t"], t0)
    assert len(set(t0.tolist())) > 1, "envs start staggered over the episode"


def test_paired_tuples_come_from_the_base():
    spec = tiny(paired=5).resolved()
    d = get_domain("particles")
    base, _ = d.train_base(spec, seed=1)
    p = d.paired(spec, base, 5, torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert torch.allclose(base.speak(p["state"]), p["message"], atol=1e-6)
    assert p["action"].dtype == torch.long and p["action"].max() < 5
    u = d.unpaired(spec, base, 32, torch.Generator().manual_seed(0))["message"]
    assert u.shape == (32, spec.particles_message_dim)


def test_invalid_knobs_rejected():
    with pytest.raises(SpecError, match="particles_gamma"):
        tiny(particles_gamma=1.5).resolved()
    with pytest.raises(SpecError, match="paired must be <="):
        tiny(paired=POOL + 1).resolved()
    with pytest.raises(SpecError, match="particles_rollout_len"):
        tiny(particles_rollout_len=0).resolved()


def test_cell_is_deterministic_and_restorable():
    spec = tiny(method="asp", paired=2)
    base = train_accepted_base(spec)
    row_a = run_cell(spec, base=base)
    row_b = run_cell(spec, base=base)
    assert comparable(row_a) == comparable(row_b)

    saved = {}

    def keep_first(state):  # serialise as a sweep would: the live state keeps changing afterwards
        if "mid" not in saved:
            buf = io.BytesIO()
            torch.save(state, buf)
            saved["mid"] = buf.getvalue()

    run_cell(spec, base=base, checkpoint=keep_first, checkpoint_every_steps=15)
    row_c = run_cell(spec, base=base, restore=artefacts.from_bytes(saved["mid"], "checkpoint"))
    assert row_c["resumed_from_step"] == 15
    assert {k: v for k, v in comparable(row_c).items() if k != "resumed_from_step"} == \
           {k: v for k, v in comparable(row_a).items() if k != "resumed_from_step"}


@pytest.mark.parametrize("method", ["pc", "osp", "asp"])
def test_smoke_cell_per_method(method):
    row = run_cell(tiny(method=method, paired=3))
    for k in ("mixed", "mixed_base_speaker", "mixed_new_speaker", "self_play_new", "self_play_base"):
        assert 0.0 <= row[f"eval_{k}"] <= NEAR_REWARD * 40
    assert row["eval_mixed"] == pytest.approx((row["eval_mixed_base_speaker"] + row["eval_mixed_new_speaker"]) / 2)
    assert (row["loss_unpaired"] is not None) == (method == "asp")
    assert (row["loss_self_play"] is not None) == (method != "pc")
