"""The particle world's hand-derived update (particles_fused.py) against the autograd reference."""

from __future__ import annotations

import pytest
import torch

from asp_dist.domains import get_domain
from asp_dist.spec import CellSpec
from asp_dist.training.fast.flat_adam import FlatAdam
from asp_dist.training.fast.particles import FusedParticleTrainer
from asp_dist.training.methods import method_weights
from asp_dist.training.trainer import Trainer

SMALL = dict(domain="particles", particles_hidden=16, particles_message_dim=12, unpaired_size=64)


def trainer_pair(**changes) -> tuple[Trainer, FusedParticleTrainer]:
    """The reference and the fused trainer from the same spec, data, initial weights and RNG."""
    spec = CellSpec(**{**SMALL, **changes}).resolved()
    domain = get_domain("particles")
    base = domain.new_agents(spec, 99)
    gen = torch.Generator().manual_seed(0)
    paired = domain.paired(spec, base, spec.paired, gen) if spec.paired else {}
    weights = method_weights(spec)
    unpaired = domain.unpaired(spec, base, spec.unpaired_size, gen) if weights.needs_adversary else {}
    make = lambda cls: cls(spec, domain, domain.new_agents(spec, 1), paired, unpaired, weights)  # noqa: E731
    return make(Trainer), make(FusedParticleTrainer)


def flat_grad(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in module.parameters()])


@pytest.mark.parametrize("changes", [
    dict(method="pc", paired=4),
    dict(method="osp", paired=0),
    dict(method="osp", paired=5),
    dict(method="asp", paired=0),
    dict(method="asp", paired=4),
    dict(method="asp", paired=3, adversary_loss="non_saturating"),
    dict(method="asp", paired=2, particles_rollout_len=3),
    dict(method="asp", paired=2, disc_layers=2, unpaired_batch=5),
    dict(method="asp", paired=2, disc_steps=3, unpaired_batch=6),
    dict(method="asp", paired=3, lambda_unpaired_schedule="warmup", lambda_schedule_frac=0.5, train_steps=8),
    dict(method="asp", paired=3, lambda_unpaired_schedule="anneal", lambda_schedule_frac=0.5, train_steps=8),
], ids=lambda c: "-".join(f"{k}={v}" for k, v in c.items()))
def test_fused_update_equals_autograd(changes):
    ref, fused = trainer_pair(**changes)
    for step in range(4):
        ref.train_step()
        fused.train_step()
        # Same model gradient (autograd leaves it in .grad; the fused trainer in its flat buffer) ...
        expected = flat_grad(ref.agents)
        assert torch.allclose(fused.opt.grad, expected, rtol=1e-4, atol=1e-6 * expected.abs().max()), f"step {step}"
        # ... so the same parameters after each Adam step, for the agents and the discriminator.
        for a, b in zip(ref.agents.parameters(), fused.agents.parameters()):
            assert torch.allclose(a, b, atol=1e-5)
        if ref.adversaries is not None:
            for a, b in zip(ref.adversaries.parameters(), fused.adversaries.parameters()):
                assert torch.allclose(a, b, atol=1e-5)
    if "pos" in ref.sp_state:
        assert torch.equal(ref.sp_state["pos"], fused.sp_state["pos"]), "the same actions were sampled"
    assert torch.equal(ref.gen.get_state(), fused.gen.get_state()), "the same random draws were made"


def test_fused_loss_diagnostics_equal_the_reference():
    ref, fused = trainer_pair(method="asp", paired=4, train_steps=10)
    for _ in range(10):
        ref.train_step()
        fused.train_step()
    expected, got = ref.loss_columns(), fused.loss_columns()
    assert expected.keys() == got.keys()
    for name in expected:
        assert got[name] == pytest.approx(expected[name], rel=1e-4, abs=1e-6), name


def test_flat_adam_matches_torch_adam():
    torch.manual_seed(0)
    a, b = torch.nn.Linear(5, 3), torch.nn.Linear(5, 3)
    b.load_state_dict(a.state_dict())
    ref, flat = torch.optim.Adam(a.parameters(), lr=0.01), FlatAdam(b.parameters(), lr=0.01)
    x = torch.randn(7, 5)
    for _ in range(20):
        ref.zero_grad()
        a(x).pow(2).sum().backward()
        ref.step()
        b.zero_grad()
        b(x).pow(2).sum().backward()
        torch.cat([p.grad.reshape(-1) for p in b.parameters()], out=flat.grad)
        flat.step()
    for p, q in zip(a.parameters(), b.parameters()):
        assert torch.allclose(p, q, atol=1e-6)
    # The module's parameters are views of the flat buffer: loading a state writes the buffer.
    b.load_state_dict({k: torch.zeros_like(v) for k, v in b.state_dict().items()})
    assert flat.param.abs().sum() == 0
