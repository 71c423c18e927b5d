"""The particle world's packed trainer (asp_dist/domains/particles/packed.py), what is particular to it:
a single particle cell trains as a one-member pack (run_cell's lone trainer), and that pack's
hand-derived update against the autograd reference, for every method and both adversarial losses,
rollouts longer than one step, deeper discriminators, several discriminator steps and λ1 schedules;
what can share a pack. Checks of every packed trainer (packs of any size against the reference,
whole cells, pack-mates, divergence, checkpoints) are in tests/test_packed.py."""

from __future__ import annotations

import pytest
import torch
from budgets import tiny_spec
from checkpoints import checkpoint_sink
from packed_cases import PARTICLES, AdamDrift, adam_sqrt_v, disc_grad_tol, flat_grads, flat_params, float32_tol, lone

from asp_dist.core.registry import get_domain
from asp_dist.domains.particles.packed import PackedParticleTrainer
from asp_dist.spec import CellSpec
from asp_dist.training import artefacts
from asp_dist.training.bases import train_accepted_base
from asp_dist.training.cell import CellDiverged, run_cell
from asp_dist.training.engines import lone_trainer, pack_key, supports
from asp_dist.training.methods import method_weights
from asp_dist.training.pipeline import upgrade_checkpoint
from asp_dist.training.row import comparable
from asp_dist.training.trainer import Trainer

# Four updates (or eight, for the λ1 schedules): the pack makes the draws of a whole cell ahead, so
# its generator ends where the reference's does.
SMALL = dict(domain="particles", particles_hidden=16, particles_message_dim=12, unpaired_size=64, train_steps=4)
DOMAIN = get_domain("particles")


def trainer_pair(**changes) -> tuple[Trainer, PackedParticleTrainer]:
    """The reference and run_cell's trainer (a pack of one) from the same spec, data, initial weights and RNG."""
    spec = CellSpec(**{**SMALL, **changes}).resolved()
    base = DOMAIN.new_agents(spec, 99)
    gen = torch.Generator().manual_seed(0)
    paired = DOMAIN.paired(spec, base, spec.paired, gen) if spec.paired else {}
    weights = method_weights(spec)
    unpaired = DOMAIN.unpaired(spec, base, spec.unpaired_size, gen) if weights.needs_adversary else {}
    ref = Trainer(spec, DOMAIN, DOMAIN.new_agents(spec, 1), paired, unpaired, weights)
    single = lone(spec, DOMAIN.new_agents(spec, 1), paired, unpaired)
    assert type(single) is PackedParticleTrainer and len(single.members) == 1
    return ref, single


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
def test_single_cell_update_equals_autograd(changes):
    ref, single = trainer_pair(**changes)
    pack, member, s = single, single.members[0], ref.spec
    terms = PARTICLES.grad_terms(s, ref.agents)
    drift, disc_drift = AdamDrift(s.lr), AdamDrift(s.disc_lr)
    for step in range(s.train_steps):
        ref.train_step()
        single.train_step()
        # Same model gradient (autograd leaves it in .grad; the pack in its flat buffer) up to float32
        # rounding (packed_cases.float32_tol) ...
        expected, got = flat_grads(ref.agents), pack.net.member_flat(0, pack.net.grad)
        assert torch.allclose(got, expected, rtol=0, atol=float32_tol(expected, terms)), f"step {step}"
        # ... so the same parameters after each Adam step up to where those differences can take them
        # (AdamDrift), for the agents (the caller's module: its parameters are views of the pack's
        # buffer) and the discriminator.
        theta = flat_params(ref.agents)
        assert drift.add(*adam_sqrt_v(ref.agents, ref.opt), theta, err=(got - expected).abs()).close(
            flat_params(member.agents), theta), f"step {step}: parameters"
        if ref.adversaries is not None:
            phi = flat_params(ref.adversaries)
            sqrt_v, t = adam_sqrt_v(ref.adversaries, *ref.adversaries.optims.values())
            disc_drift.add(sqrt_v, t, phi, err=disc_grad_tol(s, member.discs, sqrt_v, t), steps=s.disc_steps)
            assert disc_drift.close(flat_params(member.discs[0]), phi), f"step {step}: discriminator"
    assert single.step == ref.step == ref.spec.train_steps
    if "pos" in ref.sp_state:
        assert torch.equal(ref.sp_state["pos"], pack.pos[0]), "the same actions were sampled"
    assert torch.equal(ref.gen.get_state(), member.gen.get_state()), "the same random draws were made"


def test_single_cell_loss_diagnostics_and_curve_equal_the_reference():
    ref, single = trainer_pair(method="asp", paired=4, train_steps=10)
    for _ in range(10):
        ref.train_step()
        single.train_step()
    expected, got = ref.loss_columns(), single.loss_columns(0)
    assert expected.keys() == got.keys()
    for name in expected:
        assert got[name] == pytest.approx(expected[name], rel=1e-4, abs=1e-6), name
    curve = single.members[0].curve
    assert len(curve) == len(ref.curve) == 10
    for p, q in zip(curve, ref.curve):
        assert p.keys() == q.keys() and p == pytest.approx(q, rel=1e-4, abs=1e-6)


def test_what_trains_as_a_pack_and_what_on_the_reference():
    spec = PARTICLES.spec
    assert supports(spec(method="asp", paired=2))
    for knobs in (dict(particles_replay_size=100), dict(particles_paired_listener=False)):
        s = spec(method="osp", paired=2, **knobs)
        assert not supports(s)  # not in a pack, and not as a pack of one: the reference Trainer's
        assert lone_trainer(s) is Trainer and type(lone(s, DOMAIN.new_agents(s, 0), {}, {})) is Trainer
    assert pack_key(spec(method="pc", paired=1, trial=4, lr=0.1)) == pack_key(spec(method="asp", paired=6))
    no_data = [({}, {})] * 2  # (refused before the data is read)
    with pytest.raises(ValueError, match="particles_hidden"):
        PARTICLES.make_pack([spec(method="pc", paired=1), spec(method="pc", paired=1, particles_hidden=8)], no_data)
    with pytest.raises(ValueError, match="cannot be packed"):
        PARTICLES.make_pack([spec(method="pc", paired=1, particles_replay_size=100)], no_data[:1])


def test_a_diverging_single_cell_fails():
    """A pack freezes a diverging member and goes on; a cell alone has nothing to go on with: run_cell
    raises CellDiverged (the sweep records it as the cell's failure, no retries), as the reference
    raises sampling from a non-finite policy."""
    ref, single = trainer_pair(method="asp", paired=2, lr=1e30)
    with pytest.raises(RuntimeError, match="probability tensor contains"):
        for _ in range(4):
            ref.train_step()
    for _ in range(4):
        single.train_step()
    member = single.members[0]
    assert member.failed and "non-finite" in member.error and torch.isfinite(flat_params(member.agents)).all()
    spec = tiny_spec("particles", method="asp", paired=2, lr=1e30)
    with pytest.raises(CellDiverged, match="non-finite"):
        run_cell(spec, base=train_accepted_base(spec))


def test_a_checkpoint_of_another_engine_starts_the_cell_over():
    """Checkpoints name their engine; one this cell's trainer cannot load (the retired fused kernel's,
    from before the engine was named) is not restored: the cell starts over and gives the row of an
    uninterrupted run."""
    spec = tiny_spec("particles", method="osp", paired=2)
    base = train_accepted_base(spec)
    saved, keep = checkpoint_sink()

    row = run_cell(spec, base=base, checkpoint=keep, checkpoint_every_steps=15)
    states = [artefacts.from_bytes(b, "checkpoint") for b in saved]
    # (that the cell's own checkpoints restore bit for bit: tests/test_particles.py)
    assert [s["engine"] for s in states] == ["PackedParticleTrainer"] * 2
    # A version-1 checkpoint of the fused kernel: a Trainer-shaped state with FlatAdam's optimiser state.
    fused = {"version": 1, "cell_id": states[0]["cell_ids"][0], "timings": {"time_train_cpu_s": 99.0},
             "trainer": {"step": 15, "opt": {"steps": 15, "exp_avg": torch.zeros(3), "exp_avg_sq": torch.zeros(3)}}}
    assert upgrade_checkpoint(fused)["engine"] == "fused-particles"
    old = {"version": 1, "trainer": {"opt": {"state": {}, "param_groups": []}}}
    assert upgrade_checkpoint(old)["engine"] == "autograd"
    # A version-2 checkpoint of a one-member pack (before cells and packs shared one format) still restores.
    v2 = {"version": 2, "cell_id": states[0]["cell_ids"][0], "engine": "pack-of-one/PackedParticleTrainer",
          "trainer": states[0]["trainer"], "timings": states[0]["timings"][0]}
    up = upgrade_checkpoint(v2)
    assert (up["version"], up["engine"], up["cell_ids"], up["timings"]) == (
        states[0]["version"], "PackedParticleTrainer", states[0]["cell_ids"], states[0]["timings"])
    resumed = run_cell(spec, base=base, restore=v2)
    assert resumed["resumed_from_step"] == 15 and comparable(resumed) == comparable(row)
    over = run_cell(spec, base=base, restore=fused)
    assert over["resumed_from_step"] is None and over["time_train_cpu_s"] < 99.0
    assert comparable(over) == comparable(row)
