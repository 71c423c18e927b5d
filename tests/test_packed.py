"""Packed particle training (asp_dist/training/packed/particles.py) against the single-cell path
the sweep runs for these specs (the fused trainer, itself tested against autograd in
test_particles_fused.py): member by member, update by update, whole cells, and pack-mates."""

from __future__ import annotations

import io

import pytest
import torch
from budgets import tiny_spec

import asp_dist.training.packed.particles as packed_mod
from asp_dist.domains import get_domain
from asp_dist.spec import CellSpec
from asp_dist.training.bases import train_accepted_base
from asp_dist.training.cell import run_cell
from asp_dist.training.fast import choose_trainer
from asp_dist.training.fast.particles import FusedParticleTrainer
from asp_dist.training.methods import method_weights
from asp_dist.training.packed import pack_key, run_pack, supports
from asp_dist.training.packed.particles import PackedParticleTrainer
from asp_dist.training.row import comparable

SMALL = dict(domain="particles", particles_hidden=16, particles_message_dim=12, unpaired_size=64, train_steps=8)
DOMAIN = get_domain("particles")


def spec(**changes) -> CellSpec:
    return CellSpec(**{**SMALL, **changes}).resolved()


def member_data(s: CellSpec) -> tuple[dict, dict]:
    """P and U of a member from a fixed (untrained) base, as test_particles_fused draws them."""
    base = DOMAIN.new_agents(s, 99)
    gen = torch.Generator().manual_seed(s.paired * 7919 + s.trial)
    paired = DOMAIN.paired(s, base, s.paired, gen) if s.paired else {}
    unpaired = DOMAIN.unpaired(s, base, s.unpaired_size, gen) if method_weights(s).needs_adversary else {}
    return paired, unpaired


def make_pack(specs: list[CellSpec], data: list[tuple[dict, dict]] | None = None) -> PackedParticleTrainer:
    data = data or [member_data(s) for s in specs]
    return PackedParticleTrainer(specs, [d[0] for d in data], [d[1] for d in data],
                                 [DOMAIN.new_agents(s, s.seed_for("init")) for s in specs])


def make_single(s: CellSpec, data: tuple[dict, dict]):
    """The trainer run_cell uses for `s` (the fused one, for every spec a pack accepts)."""
    trainer = choose_trainer(s, DOMAIN, DOMAIN.new_agents(s, s.seed_for("init")), data[0], data[1], method_weights(s))
    assert isinstance(trainer, FusedParticleTrainer)
    return trainer


def flat_params(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


# Each pack holds members that differ in everything a member may differ in; members of one pack
# share the fields in packed.SHARED (so the rollout length, discriminator shape and disc_steps
# get packs of their own).
PACKS = {
    "mixed": [
        dict(method="asp", paired=4, trial=0),
        dict(method="pc", paired=4, trial=0),
        dict(method="osp", paired=0, trial=1),
        dict(method="osp", paired=5, trial=2, particles_gamma=0.9, particles_entropy=0.05, lr=2e-3),
        dict(method="asp", paired=0, trial=1, unpaired_size=40, disc_lr=3e-3),
        dict(method="asp", paired=3, trial=2, adversary_loss="non_saturating", lambda_unpaired=0.3),
        dict(method="asp", paired=3, trial=0, lambda_unpaired_schedule="warmup", lambda_schedule_frac=0.5),
        dict(method="asp", paired=2, trial=3, lambda_unpaired_schedule="anneal", lambda_schedule_frac=0.5,
             particles_value_coef=0.3),
        dict(method="pc", paired=0, trial=1),  # nothing to learn: no optimiser step, as the fused trainer
    ],
    "pc-only": [dict(method="pc", paired=4), dict(method="pc", paired=2, trial=1, lambda_paired=0.5),
                dict(method="pc", paired=0)],
    "rollout-3": [dict(method="asp", paired=2, particles_rollout_len=3),
                  dict(method="osp", paired=1, trial=1, particles_rollout_len=3),
                  dict(method="pc", paired=3, particles_rollout_len=3)],
    "disc-2-layers": [dict(method="asp", paired=2, disc_layers=2, unpaired_batch=5),
                      dict(method="asp", paired=0, trial=1, disc_layers=2, unpaired_batch=5)],
    "disc-steps-3": [dict(method="asp", paired=2, disc_steps=3, unpaired_batch=6),
                     dict(method="osp", paired=2, trial=1, disc_steps=3, unpaired_batch=6)],
}


@pytest.mark.parametrize("name", PACKS)
def test_packed_update_equals_single_cell_member_by_member(name):
    specs = [spec(**c) for c in PACKS[name]]
    data = [member_data(s) for s in specs]
    pack, singles = make_pack(specs, data), [make_single(s, d) for s, d in zip(specs, data)]
    for step in range(SMALL["train_steps"]):
        pack.train_step()
        for i, single in enumerate(singles):
            single.train_step()
            # Same gradient (the fused trainer keeps it in its flat buffer) ...
            expected, got = single.opt.grad, pack.net.member_flat(i, pack.net.grad)
            assert torch.allclose(got, expected, rtol=1e-4, atol=1e-6 * max(expected.abs().max(), 1e-3)), \
                f"member {i} ({specs[i].cell_id}), update {step}: gradient"
            # ... so the same parameters after each Adam step, for the agents and the discriminator.
            assert torch.allclose(flat_params(pack.members[i].agents), flat_params(single.agents), atol=1e-5), \
                f"member {i}, update {step}: parameters"
            if single.adversaries is not None:
                assert torch.allclose(flat_params(pack.members[i].disc), flat_params(single.adversaries), atol=1e-5)
    for i, single in enumerate(singles):
        # The same random draws in the same order (the generator ends where the single cell's does) ...
        assert torch.equal(pack.members[i].gen.get_state(), single.gen.get_state()), f"member {i}: generator"
        # ... and so the same actions: the same positions, exactly.
        if "pos" in single.sp_state:
            assert torch.equal(pack.pos[i], single.sp_state["pos"]), f"member {i}: rollout state"
        expected, got = single.loss_columns(), pack.loss_columns(i)
        assert expected.keys() == got.keys()
        for key in expected:
            assert (got[key] is None) == (expected[key] is None), key
            if expected[key] is not None:
                assert got[key] == pytest.approx(expected[key], rel=1e-4, abs=1e-6), (i, key)


def test_curve_points_equal_single_cell():
    """60 updates: a curve point after every update, the final window over the last 6."""
    specs = [spec(**c, train_steps=60) for c in PACKS["mixed"][:6]]
    data = [member_data(s) for s in specs]
    pack, singles = make_pack(specs, data), [make_single(s, d) for s, d in zip(specs, data)]
    for _ in range(60):
        pack.train_step()
        for single in singles:
            single.train_step()
    for i, single in enumerate(singles):
        assert len(pack.members[i].curve) == len(single.curve) == 60
        for p, q in zip(pack.members[i].curve, single.curve):
            assert p.keys() == q.keys()
            assert p == pytest.approx(q, rel=1e-4, abs=1e-6)


@pytest.fixture(scope="module")
def tiny_bases():
    """Bases of the tiny particle cells of trials 0 and 1, trained once."""
    bases = {}
    for trial in (0, 1):
        s = tiny_spec("particles", trial=trial).resolved()
        bases[s.base_key] = train_accepted_base(s)
    return bases


TINY_CELLS = [dict(method="asp", paired=3, trial=0), dict(method="pc", paired=2, trial=0),
              dict(method="osp", paired=0, trial=1), dict(method="asp", paired=0, trial=1),
              dict(method="osp", paired=4, trial=1), dict(method="pc", paired=0, trial=0)]


def assert_rows_match(got: dict, expected: dict) -> None:
    got, expected = comparable(got), comparable(expected)
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        if isinstance(value, float) and not isinstance(value, bool):
            assert got[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
        else:
            assert got[key] == value, key


def test_whole_tiny_cells_give_run_cells_rows_and_curves(tiny_bases):
    specs = [tiny_spec("particles", **c) for c in TINY_CELLS]
    results = run_pack(specs, bases=tiny_bases, curves=True)
    for s, result in zip(specs, results):
        assert result.error is None
        curve: list = []
        row = run_cell(s, base=tiny_bases[s.resolved().base_key], curve=curve)
        assert_rows_match(result.row, row)
        assert result.row["cell_id"] == row["cell_id"]
        assert len(result.curve) == len(curve)
        for p, q in zip(result.curve, curve):
            assert p.keys() == q.keys()
            assert p == pytest.approx(q, rel=1e-4, abs=1e-6)  # probes included


def test_member_does_not_depend_on_its_pack_mates():
    me = spec(method="asp", paired=3, trial=0, train_steps=40)
    mates = [spec(method=m, paired=k, trial=t, unpaired_size=u, train_steps=40)
             for m, k, t, u in [("pc", 6, 1, 64), ("osp", 0, 0, 64), ("asp", 9, 2, 100), ("pc", 0, 3, 64)]]
    alone, crowd = make_pack([me]), make_pack(mates[:2] + [me] + mates[2:])
    for _ in range(40):
        alone.train_step()
        crowd.train_step()
    a, b = alone.members[0], crowd.members[2]
    # Its own random stream, consumed alike, so the same actions and positions ...
    assert torch.equal(a.gen.get_state(), b.gen.get_state())
    assert torch.equal(alone.pos[0], crowd.pos[2])
    # ... and the same weights up to float rounding (other shapes round differently) ...
    assert torch.allclose(flat_params(a.agents), flat_params(b.agents), atol=1e-5)
    assert torch.allclose(flat_params(a.disc), flat_params(b.disc), atol=1e-5)
    assert alone.loss_columns(0) == pytest.approx(crowd.loss_columns(2), rel=1e-4)


def test_member_is_bit_for_bit_the_same_beside_any_mate_of_the_same_shape():
    """Where the pack's shapes agree (members, padded paired rows), what the mate is - its
    method, data, trial, adversary - changes nothing at all in the other member."""
    me = spec(method="osp", paired=3, trial=0, train_steps=30)
    runs = []
    for mate in (spec(method="pc", paired=3, trial=1, train_steps=30),
                 spec(method="asp", paired=2, trial=2, adversary_loss="non_saturating", unpaired_size=50,
                      train_steps=30)):
        pack = make_pack([me, mate])
        for _ in range(30):
            pack.train_step()
        runs.append((flat_params(pack.members[0].agents), pack.loss_columns(0), pack.pos[0].clone()))
    (p1, l1, x1), (p2, l2, x2) = runs
    assert torch.equal(p1, p2) and l1 == l2 and torch.equal(x1, x2)


def test_diverging_member_is_frozen_and_reported_and_others_go_on():
    healthy = [spec(method="asp", paired=3, trial=0), spec(method="osp", paired=2, trial=1),
               spec(method="pc", paired=4, trial=2)]
    bad, good = spec(method="asp", paired=1, trial=3, lr=1e30), spec(method="asp", paired=1, trial=3, lr=2e-3)
    runs = {}
    for name, last in (("bad", bad), ("good", good)):
        pack = make_pack(healthy + [last])
        for _ in range(SMALL["train_steps"]):
            pack.train_step()
        runs[name] = pack
    frozen = runs["bad"].members[3]
    assert frozen.failed and "non-finite" in frozen.error and frozen.failed_step is not None
    assert torch.isfinite(flat_params(frozen.agents)).all(), "frozen before the non-finite step"
    assert not runs["good"].members[3].failed
    for i in range(3):  # the others are exactly what they are beside a healthy fourth member
        assert not runs["bad"].members[i].failed
        assert torch.equal(flat_params(runs["bad"].members[i].agents), flat_params(runs["good"].members[i].agents))
        assert runs["bad"].loss_columns(i) == runs["good"].loss_columns(i)


def test_run_pack_reports_a_diverging_member_failed(tiny_bases):
    specs = [tiny_spec("particles", method="osp", paired=2, trial=0),
             tiny_spec("particles", method="asp", paired=2, trial=0, lr=1e30)]
    ok, failed = run_pack(specs, bases=tiny_bases)
    assert failed.row is None and "non-finite" in failed.error
    assert ok.error is None and ok.row["eval_mixed"] == ok.row["eval_mixed"]  # a row, with finite metrics


def test_restore_mid_pack_continues_bit_for_bit(monkeypatch):
    monkeypatch.setattr(packed_mod, "CHUNK", 8)  # several chunks of random draws, restored mid-chunk
    specs = [spec(**c, train_steps=30) for c in PACKS["mixed"][:6]]
    data = [member_data(s) for s in specs]
    whole = make_pack(specs, data)
    for _ in range(30):
        whole.train_step()
    first = make_pack(specs, data)
    for _ in range(13):
        first.train_step()
    buf = io.BytesIO()
    torch.save(first.state_dict(), buf)
    resumed = make_pack(specs, data)
    resumed.load_state_dict(torch.load(io.BytesIO(buf.getvalue()), weights_only=False))
    for _ in range(17):
        resumed.train_step()
    assert torch.equal(resumed.net.param, whole.net.param) and torch.equal(resumed.dnet.param, whole.dnet.param)
    for i in range(len(specs)):
        assert torch.equal(resumed.members[i].gen.get_state(), whole.members[i].gen.get_state())
        assert resumed.loss_columns(i) == whole.loss_columns(i)
        assert resumed.members[i].curve == whole.members[i].curve


def test_what_can_share_a_pack():
    assert supports(spec(method="asp", paired=2))
    assert not supports(spec(method="asp", paired=2, particles_replay_size=100))  # the reference trainer's
    assert not supports(spec(method="osp", paired=2, particles_paired_listener=False))
    assert not supports(tiny_spec("signaling"))
    assert pack_key(spec(method="pc", paired=1, trial=4, lr=0.1)) == pack_key(spec(method="asp", paired=6))
    with pytest.raises(ValueError, match="particles_hidden"):
        make_pack([spec(method="pc", paired=1), spec(method="pc", paired=1, particles_hidden=8)])
