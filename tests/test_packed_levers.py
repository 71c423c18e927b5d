"""Packed lever training (asp_dist/training/packed/levers.py) against the single-cell path the sweep
runs for lever cells (the reference Trainer: autograd and torch.optim.Adam): member by member,
update by update, whole cells, pack-mates, a diverging member and a restored checkpoint
(of the trainer, and of a whole pack through run_pack)."""

from __future__ import annotations

import io
import json

import pytest
import torch
from budgets import TINY, tiny_spec

import asp_dist.training.packed.levers as packed_mod
from asp_dist.domains import get_domain
from asp_dist.spec import CellSpec
from asp_dist.training.bases import train_accepted_base
from asp_dist.training.cell import run_cell
from asp_dist.training.fast import choose_trainer
from asp_dist.training.methods import method_weights
from asp_dist.training.packed.levers import PackedLeverTrainer, pack_key, run_pack, supports
from asp_dist.training.row import comparable
from asp_dist.training.trainer import Trainer

# Replay of 40 games at batch 16: the buffer fills after 3 updates and its write position wraps.
SMALL = dict(domain="levers", levers_hidden=8, batch_size=16, levers_replay_size=40, unpaired_size=60,
             disc_hidden=8, train_steps=8)
DOMAIN = get_domain("levers")


def spec(**changes) -> CellSpec:
    return CellSpec(**{**SMALL, **changes}).resolved()


def member_data(s: CellSpec) -> tuple[dict, dict]:
    """P and U of a member from a fixed (untrained) base."""
    base = DOMAIN.new_agents(s, 99)
    gen = torch.Generator().manual_seed(s.paired * 7919 + s.trial)
    paired = DOMAIN.paired(s, base, s.paired, gen) if s.paired else {}
    unpaired = DOMAIN.unpaired(s, base, s.unpaired_size, gen) if method_weights(s).needs_adversary else {}
    return paired, unpaired


def make_pack(specs: list[CellSpec], data: list[tuple[dict, dict]] | None = None) -> PackedLeverTrainer:
    data = data or [member_data(s) for s in specs]
    return PackedLeverTrainer(specs, [d[0] for d in data], [d[1] for d in data],
                              [DOMAIN.new_agents(s, s.seed_for("init")) for s in specs])


def make_single(s: CellSpec, data: tuple[dict, dict]) -> Trainer:
    """The trainer run_cell uses for `s`: today the reference Trainer for every lever cell (were a
    fast lever trainer added, the pack would have to be checked against it instead)."""
    trainer = choose_trainer(s, DOMAIN, DOMAIN.new_agents(s, s.seed_for("init")), data[0], data[1], method_weights(s))
    assert type(trainer) is Trainer
    return trainer


def flat_params(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


def flat_grads(module: torch.nn.Module) -> torch.Tensor:
    """The last update's gradient (None, i.e. no update, reads as zeros)."""
    return torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in module.parameters()])


# Each pack holds members that differ in what a member may differ in; members of one pack share the
# fields in packed.SHARED (so discriminator shapes, disc_steps and the network's shapes get packs
# of their own).
PACKS = {
    "mixed": [
        dict(method="asp", paired=4, trial=0),
        dict(method="pc", paired=4, trial=0),
        dict(method="osp", paired=0, trial=1),
        dict(method="osp", paired=6, trial=2, lr=1e-3, levers_eps_start=0.5, levers_eps_end=0.2,
             levers_eps_decay_frac=0.3),
        dict(method="asp", paired=0, trial=1, unpaired_size=45, disc_lr=3e-3),
        dict(method="asp", paired=2, trial=2, adversary_loss="non_saturating", lambda_unpaired=0.5),
        dict(method="asp", paired=3, trial=0, lambda_unpaired_schedule="warmup", lambda_schedule_frac=0.5),
        dict(method="asp", paired=1, trial=3, lambda_unpaired_schedule="anneal", lambda_schedule_frac=0.5,
             lambda_paired=0.3),
        dict(method="pc", paired=0, trial=1),  # nothing to learn: no optimiser step, as Trainer
        dict(method="osp", paired=2, trial=4, lambda_paired=0.0),  # paired data with weight 0: no paired term
    ],
    # ASP members first (as run_pack orders them): their rows are views, not gathers
    "asp-first": [dict(method="asp", paired=2, trial=1), dict(method="asp", paired=0, trial=2),
                  dict(method="osp", paired=5, trial=0), dict(method="pc", paired=1, trial=3)],
    "asp-only": [dict(method="asp", paired=3), dict(method="asp", paired=1, trial=1, unpaired_size=30)],
    "pc-only": [dict(method="pc", paired=4), dict(method="pc", paired=2, trial=1, lambda_paired=0.5),
                dict(method="pc", paired=0)],
    "disc-2-layers-2-steps": [dict(method="asp", paired=2, disc_layers=2, disc_steps=2, unpaired_batch=5),
                              dict(method="osp", paired=1, trial=1, disc_layers=2, disc_steps=2, unpaired_batch=5),
                              dict(method="asp", paired=0, trial=2, disc_layers=2, disc_steps=2, unpaired_batch=5)],
    "other-shapes": [dict(method="asp", paired=2, levers_num_ids=5, levers_hidden=6, batch_size=7,
                          levers_replay_size=20),
                     dict(method="osp", paired=3, trial=1, levers_num_ids=5, levers_hidden=6, batch_size=7,
                          levers_replay_size=20)],
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
            # Same gradient ...
            expected, got = flat_grads(single.agents), pack.net.member_flat(i, pack.net.grad)
            assert torch.allclose(got, expected, rtol=1e-4, atol=1e-6 * max(float(expected.abs().max()), 1e-3)), \
                f"member {i} ({specs[i].cell_id}), update {step}: gradient"
            # ... so the same parameters after each Adam step, for the network and both discriminators.
            assert torch.allclose(flat_params(pack.members[i].agents), flat_params(single.agents), atol=1e-5), \
                f"member {i}, update {step}: parameters"
            if single.adversaries is not None:
                mine = torch.cat([flat_params(d) for d in pack.members[i].discs])
                assert torch.allclose(mine, flat_params(single.adversaries), atol=1e-5), f"member {i}: discriminators"
    for i, single in enumerate(singles):
        # The same random draws in the same order (the generator ends where the single cell's does) ...
        assert torch.equal(pack.members[i].gen.get_state(), single.gen.get_state()), f"member {i}: generator"
        # ... so the same games, ε-greedy levers and rewards in the replay buffer, exactly.
        if single.sp_state:
            st = single.sp_state
            assert (pack.pos, pack.filled) == (int(st["pos"]), int(st["filled"]))
            assert torch.equal(pack.r_ids[i], st["ids"]), f"member {i}: replayed games"
            assert torch.equal(pack.r_lev[i], st["levers"]), f"member {i}: levers pulled"
            assert torch.equal(pack.r_rew[i], st["reward"]), f"member {i}: rewards"
        expected, got = single.loss_columns(), pack.loss_columns(i)
        assert expected.keys() == got.keys()
        for key in expected:
            assert (got[key] is None) == (expected[key] is None), (i, key)
            if expected[key] is not None:
                assert got[key] == pytest.approx(expected[key], rel=1e-4, abs=1e-6), (i, key)


def test_curve_points_equal_single_cell():
    """60 updates: a curve point after every update (every diagnostic), the final window over the last 6."""
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
    """Bases of the tiny lever cells of trials 0 and 1, trained once."""
    bases = {}
    for trial in (0, 1):
        s = tiny_spec("levers", trial=trial).resolved()
        bases[s.base_key] = train_accepted_base(s)
    return bases


TINY_CELLS = [dict(method="pc", paired=2, trial=0), dict(method="asp", paired=3, trial=0),
              dict(method="osp", paired=0, trial=1), dict(method="asp", paired=0, trial=1),
              dict(method="osp", paired=4, trial=1), dict(method="pc", paired=0, trial=0),
              dict(method="asp", paired=2, trial=1, adversary_loss="non_saturating", record_figure_data=True)]


def assert_rows_match(got: dict, expected: dict) -> None:
    got, expected = comparable(got), comparable(expected)
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        if key == "figure_data" and value is not None:  # vectors rounded to 4 decimals: a rounding step apart at most
            mine, theirs = json.loads(got[key]), json.loads(value)
            assert mine["ids"] == theirs["ids"] and mine.keys() == theirs.keys()
            for part in ("base", "new"):
                assert torch.allclose(torch.tensor(mine[part]), torch.tensor(theirs[part]), rtol=0, atol=1.01e-4)
        elif isinstance(value, float) and not isinstance(value, bool):
            assert got[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
        else:
            assert got[key] == value, key


def test_whole_tiny_cells_give_run_cells_rows_and_curves(tiny_bases):
    specs = [tiny_spec("levers", **c) for c in TINY_CELLS]
    results = run_pack(specs, bases=tiny_bases, curves=True)
    assert [r.spec.cell_id for r in results] == [s.resolved().cell_id for s in specs]  # in the specs' order
    for s, result in zip(specs, results):
        assert result.error is None
        curve: list = []
        row = run_cell(s, base=tiny_bases[s.resolved().base_key], curve=curve)
        assert_rows_match(result.row, row)
        assert len(result.curve) == len(curve)
        for p, q in zip(result.curve, curve):
            assert p.keys() == q.keys()
            assert p == pytest.approx(q, rel=1e-4, abs=1e-6)  # probes included


def test_member_does_not_depend_on_its_pack_mates():
    me = spec(method="asp", paired=3, trial=0, train_steps=30)
    mates = [spec(method=m, paired=k, trial=t, unpaired_size=u, train_steps=30)
             for m, k, t, u in [("pc", 6, 1, 60), ("osp", 0, 0, 60), ("asp", 9, 2, 100), ("pc", 0, 3, 60)]]
    alone, crowd = make_pack([me]), make_pack(mates[:2] + [me] + mates[2:])
    for _ in range(30):
        alone.train_step()
        crowd.train_step()
    a, b = alone.members[0], crowd.members[2]
    # Its own random stream, consumed alike, so the same games and levers ...
    assert torch.equal(a.gen.get_state(), b.gen.get_state())
    assert torch.equal(alone.r_ids[0], crowd.r_ids[2]) and torch.equal(alone.r_lev[0], crowd.r_lev[2])
    # ... and the same weights up to float rounding (other shapes may round differently) ...
    assert torch.allclose(flat_params(a.agents), flat_params(b.agents), atol=1e-5)
    for d, e in zip(a.discs, b.discs):
        assert torch.allclose(flat_params(d), flat_params(e), atol=1e-5)
    assert alone.loss_columns(0) == pytest.approx(crowd.loss_columns(2), rel=1e-4)


def test_member_is_bit_for_bit_the_same_beside_any_mate_of_the_same_shape():
    """Where the pack's shapes agree (members, padded paired rows), what the mate is - its method,
    data, trial, adversary - changes nothing at all in the other member."""
    me = spec(method="osp", paired=3, trial=0, train_steps=20)
    runs = []
    for mate in (spec(method="pc", paired=3, trial=1, train_steps=20),
                 spec(method="asp", paired=2, trial=2, adversary_loss="non_saturating", unpaired_size=50,
                      train_steps=20)):
        pack = make_pack([me, mate])
        for _ in range(20):
            pack.train_step()
        runs.append((flat_params(pack.members[0].agents), pack.loss_columns(0), pack.r_lev[0].clone()))
    (p1, l1, x1), (p2, l2, x2) = runs
    assert torch.equal(p1, p2) and l1 == l2 and torch.equal(x1, x2)


@pytest.mark.parametrize("method", ["asp", "osp", "pc"])
def test_diverging_member_is_frozen_and_reported_and_others_go_on(method):
    """An ASP member's discriminator gradient goes non-finite first, an OSP or PC member's network gradient."""
    healthy = [spec(method="asp", paired=3, trial=0), spec(method="osp", paired=2, trial=1),
               spec(method="pc", paired=4, trial=2)]
    bad, good = spec(method=method, paired=1, trial=3, lr=1e30), spec(method=method, paired=1, trial=3, lr=2e-3)
    runs, held = {}, {}
    for name, last in (("bad", bad), ("good", good)):
        pack = make_pack(healthy + [last])
        for step in range(SMALL["train_steps"]):
            pack.train_step()
            if step == 4:  # (the bad member fails in its first updates)
                held[name] = [flat_params(m) for m in (pack.members[3].agents, *pack.members[3].discs)]
        runs[name] = pack
    frozen = runs["bad"].members[3]
    assert frozen.failed and "non-finite" in frozen.error and frozen.failed_step is not None
    assert frozen.failed_step <= 4
    assert torch.isfinite(flat_params(frozen.agents)).all(), "frozen before the non-finite step"
    # frozen means frozen: its network and its discriminators have not moved since
    assert all(torch.equal(x, flat_params(m)) for x, m in zip(held["bad"], (frozen.agents, *frozen.discs)))
    assert not runs["good"].members[3].failed
    for i in range(3):  # the others are exactly what they are beside a healthy fourth member
        assert not runs["bad"].members[i].failed
        assert torch.equal(flat_params(runs["bad"].members[i].agents), flat_params(runs["good"].members[i].agents))
        assert runs["bad"].loss_columns(i) == runs["good"].loss_columns(i)
    disc = [flat_params(d) for d in runs["bad"].members[0].discs]
    assert all(torch.equal(x, flat_params(d)) for x, d in zip(disc, runs["good"].members[0].discs))


def test_run_pack_reports_a_diverging_member_failed(tiny_bases):
    specs = [tiny_spec("levers", method="osp", paired=2, trial=0),
             tiny_spec("levers", method="asp", paired=2, trial=0, lr=1e30)]
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
    assert torch.equal(resumed.net.exp_avg_sq, whole.net.exp_avg_sq)
    assert torch.equal(resumed.r_lev, whole.r_lev) and torch.equal(resumed.r_rew, whole.r_rew)
    for i in range(len(specs)):
        assert torch.equal(resumed.members[i].gen.get_state(), whole.members[i].gen.get_state())
        assert resumed.loss_columns(i) == whole.loss_columns(i)
        assert resumed.members[i].curve == whole.members[i].curve


def test_run_pack_restored_mid_run_gives_the_rows_of_an_uninterrupted_run(tiny_bases, monkeypatch):
    """The whole-cell path: a pack's checkpoint (here after update 9, inside a chunk of draws) taken
    through torch.save, restored into a new run_pack of the same cells: every member's row and curve
    are the uninterrupted run's, bit for bit. The members' places in the trainer differ from the
    specs' order (ASP first), which the checkpoint must not mind."""
    monkeypatch.setattr(packed_mod, "CHUNK", 4)
    specs = [tiny_spec("levers", **c) for c in TINY_CELLS]
    assert method_weights(specs[0]).needs_adversary is False  # a PC member first: the trainer reorders
    states = []

    def keep(state):
        buf = io.BytesIO()
        torch.save(state, buf)
        states.append(buf.getvalue())

    whole = run_pack(specs, bases=tiny_bases, curves=True, checkpoint=keep, checkpoint_every_steps=3)
    assert len(states) == (TINY["levers"]["train_steps"] - 1) // 3
    state = torch.load(io.BytesIO(states[2]), weights_only=False)
    assert state["cell_ids"] == [s.resolved().cell_id for s in specs] and state["trainer"]["step"] == 9
    resumed = run_pack(specs, bases=tiny_bases, curves=True, restore=state)
    for a, b in zip(whole, resumed):
        assert a.error is None and b.error is None
        assert comparable(b.row) == comparable(a.row) and b.curve == a.curve
        assert a.row["resumed_from_step"] is None and b.row["resumed_from_step"] == 9


def test_run_pack_refuses_a_checkpoint_of_another_pack(tiny_bases):
    specs = [tiny_spec("levers", **c) for c in TINY_CELLS[:3]]
    states = []
    run_pack(specs, bases=tiny_bases, checkpoint=states.append, checkpoint_every_steps=5)
    with pytest.raises(ValueError, match="checkpoint belongs to a pack of"):
        run_pack(specs[:2], bases=tiny_bases, restore=states[0])
    with pytest.raises(ValueError, match="checkpoint belongs to a pack of"):
        run_pack(list(reversed(specs)), bases=tiny_bases, restore=states[0])


def test_what_can_share_a_pack():
    assert supports(spec(method="asp", paired=2)) and supports(tiny_spec("levers"))
    assert not supports(tiny_spec("signaling")) and not supports(tiny_spec("particles"))
    assert pack_key(spec(method="pc", paired=1, trial=4, lr=0.1, levers_eps_end=0.2)) == pack_key(
        spec(method="asp", paired=6, unpaired_size=33, adversary_loss="non_saturating"))
    assert pack_key(spec(method="pc")) != pack_key(spec(method="pc", levers_replay_size=48))
    with pytest.raises(ValueError, match="levers_hidden"):
        make_pack([spec(method="pc", paired=1), spec(method="pc", paired=1, levers_hidden=4)])


def test_exploration_coins_compare_in_float32_as_dqn_step_does():
    """ε is a Python float in dqn_step (`rand < eps`, compared in float32); the pack pre-draws the
    coins and compares them with its own ε column. A coin equal to float32(ε) tells the two apart."""
    eps = 0.525
    coin = torch.tensor(eps, dtype=torch.float32)
    assert float(coin) != eps  # the case that matters: float32(ε) differs from ε
    pack = make_pack([spec(method="osp", paired=1, levers_eps_start=eps, levers_eps_end=eps)])
    pack._draw_chunk()
    coins = torch.stack([coin, coin.nextafter(torch.tensor(0.0)), coin.nextafter(torch.tensor(1.0))])
    expected = coins < eps  # what dqn_step computes for these coins
    assert torch.equal(packed_mod.explore(coins, pack.eps[0, 0].view(1)), expected)
