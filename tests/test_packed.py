"""Packed training (asp_dist.training.engines, stacked, pipeline), every check for every domain with a packed trainer:
each pack member against the reference Trainer (autograd), update by update; whole tiny cells
against run_cell (whatever trains a single cell of the domain); pack-mates; a diverging member;
checkpoints of the trainer and of a whole pack. A newly registered domain is tested here without
a new line (tests/packed_cases.py: its case, or the generic one); domain-specific checks are in
tests/test_packed_<domain>.py."""

from __future__ import annotations

import dataclasses
import io
import json
import logging

import pytest
import torch
from budgets import TINY, tiny_spec
from checkpoints import checkpoint_sink
from packed_cases import (
    DOMAINS,
    AdamDrift,
    adam_sqrt_v,
    case_for,
    disc_grad_tol,
    disc_params,
    flat_grads,
    flat_params,
    float32_tol,
    lone,
    other_value,
    packed_module,
    stacked_sqrt_v,
    trainer_class,
)

from asp_dist.core.registry import get_domain
from asp_dist.knobs import ANY, Knob
from asp_dist.training import artefacts, engines
from asp_dist.training.bases import train_accepted_base
from asp_dist.training.cell import run_cell
from asp_dist.training.engines import lone_trainer, pack_key, run_pack, supports
from asp_dist.training.methods import method_weights
from asp_dist.training.row import comparable
from asp_dist.training.stacked import StackedParams
from asp_dist.training.trainer import Trainer


def assert_states_equal(got: list[torch.Tensor], expected: list[torch.Tensor], what: str) -> None:
    assert len(got) == len(expected), what
    for a, b in zip(got, expected):
        assert torch.equal(a, b), what


# ---- a pack's update against the reference, member by member ----------------------------------------
@pytest.mark.parametrize("domain,name", [(d, n) for d in DOMAINS for n in case_for(d).all_packs])
def test_packed_update_equals_the_reference_member_by_member(domain, name):
    case = case_for(domain)
    specs = [case.spec(**c) for c in case.all_packs[name]]
    data = [case.member_data(s) for s in specs]
    pack, singles = case.make_pack(specs, data), [case.make_reference(s, d) for s, d in zip(specs, data)]
    terms = [case.grad_terms(s, single.agents) for s, single in zip(specs, singles)]
    drift = [(AdamDrift(s.lr), AdamDrift(s.disc_lr)) for s in specs]
    for step in range(case.small["train_steps"]):
        pack.train_step()
        for i, (s, single) in enumerate(zip(specs, singles)):
            single.train_step()
            # Same gradient up to float32 rounding (packed_cases.float32_tol) ...
            expected, got = flat_grads(single.agents), pack.net.member_flat(i, pack.net.grad)
            assert torch.allclose(got, expected, rtol=0, atol=float32_tol(expected, terms[i])), \
                f"member {i} ({s.cell_id}), update {step}: gradient"
            # ... so the same parameters after each Adam step, for the agents and the discriminators
            # (disc_steps Adam steps an update), up to where those differences can take them (AdamDrift).
            theta = flat_params(single.agents)
            assert drift[i][0].add(*adam_sqrt_v(single.agents, single.opt), theta, err=(got - expected).abs()).close(
                flat_params(pack.members[i].agents), theta), f"member {i}, update {step}: parameters"
            if single.adversaries is not None:
                phi = flat_params(single.adversaries)
                sqrt_v, t = adam_sqrt_v(single.adversaries, *single.adversaries.optims.values())
                err = disc_grad_tol(s, single.adversaries.discs.values(), sqrt_v, t)
                assert drift[i][1].add(sqrt_v, t, phi, err=err, steps=s.disc_steps).close(
                    disc_params(pack.members[i]), phi), f"member {i}, update {step}: discriminators"
    for i, single in enumerate(singles):
        # The same random draws in the same order (the generator ends where the single cell's does) ...
        assert torch.equal(pack.members[i].gen.get_state(), single.gen.get_state()), f"member {i}: generator"
        # ... so the same self-play: the same actions, positions, games, exactly.
        if single.sp_state:
            assert_states_equal(case.pack_state(pack, i), case.trainer_state(single), f"member {i}: self-play state")
        expected, got = single.loss_columns(), pack.loss_columns(i)
        assert expected.keys() == got.keys()
        for key in expected:
            assert (got[key] is None) == (expected[key] is None), (i, key)
            if expected[key] is not None:
                assert got[key] == pytest.approx(expected[key], rel=1e-4, abs=1e-6), (i, key)


@pytest.mark.parametrize("domain", DOMAINS)
def test_curve_points_equal_the_single_cell_paths(domain):
    """60 updates: a curve point after every update (every diagnostic), the final window over the last
    6; against the trainer run_cell picks (the reference, or a pack of one: tests/test_packed_<domain>.py)."""
    case = case_for(domain)
    specs = [case.spec(**c, train_steps=60) for c in case.packs["mixed"][:6]]
    data = [case.member_data(s) for s in specs]
    d = get_domain(domain)
    pack = case.make_pack(specs, data)
    singles = [lone(s, d.new_agents(s, s.seed_for("init")), p, u) for s, (p, u) in zip(specs, data)]
    for _ in range(60):
        pack.train_step()
        for single in singles:
            single.train_step()
    for i, single in enumerate(singles):
        assert len(pack.members[i].curve) == len(single.members[0].curve) == 60
        for p, q in zip(pack.members[i].curve, single.members[0].curve):
            assert p.keys() == q.keys()
            assert p == pytest.approx(q, rel=1e-4, abs=1e-6)


# ---- whole tiny cells: run_pack against run_cell, and run_pack's checkpoints -------------------------
TINY_CHUNK = 4  # draws made ahead in chunks of 4 updates: the checkpoint after update 9 is inside one
EVERY = 3  # checkpoint_every_steps


@pytest.fixture(scope="module", params=DOMAINS)
def tiny_run(request):
    """One domain's tiny cells (its case's tiny_cells): their bases (trials 0 and 1, trained once), and
    one run_pack of them with curves and a checkpoint every EVERY updates (kept through torch.save)."""
    domain = request.param
    specs = [tiny_spec(domain, **c) for c in case_for(domain).tiny_cells]
    bases = {}
    for trial in (0, 1):
        s = tiny_spec(domain, trial=trial).resolved()
        bases[s.base_key] = train_accepted_base(s)
    states, keep = checkpoint_sink()

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(packed_module(domain), "CHUNK", TINY_CHUNK)
        results = run_pack(specs, bases=bases, curves=True, checkpoint=keep, checkpoint_every_steps=EVERY)
    return dict(domain=domain, specs=specs, bases=bases, results=results, states=states)


def assert_figures_match(got: str, expected: str) -> None:
    """Figure data as JSON: the same structure; numbers (vectors rounded to 4 decimals) a rounding step apart at most."""
    def walk(a, b, where):
        if isinstance(b, dict):
            assert isinstance(a, dict) and a.keys() == b.keys(), where
            for k in b:
                walk(a[k], b[k], f"{where}.{k}")
        elif isinstance(b, list):
            assert isinstance(a, list) and len(a) == len(b), where
            for k, (x, y) in enumerate(zip(a, b)):
                walk(x, y, f"{where}[{k}]")
        elif isinstance(b, float):
            assert a == pytest.approx(b, rel=0, abs=1.01e-4), where
        else:
            assert a == b, where

    walk(json.loads(got), json.loads(expected), "figure_data")


def assert_rows_match(got: dict, expected: dict) -> None:
    got, expected = comparable(got), comparable(expected)
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        if key == "figure_data" and value is not None:
            assert_figures_match(got[key], value)
        elif isinstance(value, float) and not isinstance(value, bool):
            assert got[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
        else:
            assert got[key] == value, key


def test_whole_tiny_cells_give_run_cells_rows_and_curves(tiny_run):
    specs, bases, results = tiny_run["specs"], tiny_run["bases"], tiny_run["results"]
    assert [r.spec.cell_id for r in results] == [s.resolved().cell_id for s in specs]  # in the specs' order
    for s, result in zip(specs, results):
        assert result.error is None
        curve: list = []
        row = run_cell(s, base=bases[s.resolved().base_key], curve=curve)
        assert_rows_match(result.row, row)
        assert result.row["cell_id"] == row["cell_id"]
        assert len(result.curve) == len(curve)
        for p, q in zip(result.curve, curve):
            assert p.keys() == q.keys()
            assert p == pytest.approx(q, rel=1e-4, abs=1e-6)  # probes included


def test_run_pack_restored_mid_run_gives_the_rows_of_an_uninterrupted_run(tiny_run, monkeypatch):
    """The whole-cell path: a pack's checkpoint (the last one, inside a chunk of draws) taken
    through torch.save, restored into a new run_pack of the same cells: every member's row and curve
    are the uninterrupted run's, bit for bit. A trainer may place its members in another order than
    the specs' (levers: ASP first), which the checkpoint must not mind."""
    domain, specs, states = tiny_run["domain"], tiny_run["specs"], tiny_run["states"]
    monkeypatch.setattr(packed_module(domain), "CHUNK", TINY_CHUNK)
    assert method_weights(specs[0]).needs_adversary is False  # a PC member first: a trainer may reorder
    steps = tiny_spec(domain).resolved().train_steps
    assert len(states) == (steps - 1) // EVERY
    # the last checkpoint that falls inside a chunk of draws (what a sweep restores from, mostly)
    at = max(k for k in range(EVERY, steps, EVERY) if k % TINY_CHUNK)
    state = artefacts.from_bytes(states[at // EVERY - 1], "checkpoint")
    assert state["cell_ids"] == [s.resolved().cell_id for s in specs] and state["trainer"]["step"] == at
    resumed = run_pack(specs, bases=tiny_run["bases"], curves=True, restore=state)
    for a, b in zip(tiny_run["results"], resumed):
        assert a.error is None and b.error is None
        assert comparable(b.row) == comparable(a.row) and b.curve == a.curve
        assert a.row["resumed_from_step"] is None and b.row["resumed_from_step"] == at


def test_run_pack_refuses_a_checkpoint_of_another_pack(tiny_run):
    specs, bases = tiny_run["specs"], tiny_run["bases"]
    state = artefacts.from_bytes(tiny_run["states"][0], "checkpoint")
    with pytest.raises(ValueError, match="checkpoint belongs to a pack of"):
        run_pack(specs[:2], bases=bases, restore=state)
    with pytest.raises(ValueError, match="checkpoint belongs to a pack of"):
        run_pack(list(reversed(specs)), bases=bases, restore=state)


def test_run_pack_reports_a_diverging_member_failed(tiny_run, monkeypatch):
    """An ASP member whose U is NaN (what `poisoned` does to a trainer's data; a huge learning rate diverges on
    some domains and CPUs only) fails alone with a non-finite loss or gradient; its OSP mate gets its row."""
    domain, bases = tiny_run["domain"], tiny_run["bases"]
    card = get_domain(domain)
    sample = type(card).unpaired
    monkeypatch.setattr(type(card), "unpaired", lambda self, *args: {
        k: v.float().fill_(float("nan")) for k, v in sample(self, *args).items()})
    specs = [tiny_spec(domain, method="osp", paired=2, trial=0), tiny_spec(domain, method="asp", paired=2, trial=0)]
    ok, failed = run_pack(specs, bases=bases)
    assert failed.row is None and "non-finite" in failed.error
    assert ok.error is None and ok.row["eval_mixed"] == ok.row["eval_mixed"]  # a row, with finite metrics


# ---- pack-mates ----------------------------------------------------------------------------------
@pytest.mark.parametrize("domain", DOMAINS)
def test_member_does_not_depend_on_its_pack_mates(domain):
    case = case_for(domain)
    u = case.small["unpaired_size"]
    me = case.spec(method="asp", paired=3, trial=0, train_steps=40)
    mates = [case.spec(method=m, paired=k, trial=t, unpaired_size=size, train_steps=40)
             for m, k, t, size in [("pc", 6, 1, u), ("osp", 0, 0, u), ("asp", 9, 2, 100), ("pc", 0, 3, u)]]
    alone, crowd = case.make_pack([me]), case.make_pack(mates[:2] + [me] + mates[2:])
    a, b = alone.members[0], crowd.members[2]
    # (how far float rounding can take the weights apart: packed_cases.AdamDrift, from alone's Adam state)
    discs, drift, disc_drift = list(range(len(a.discs))), AdamDrift(me.lr), AdamDrift(me.disc_lr)
    for _ in range(40):
        alone.train_step()
        crowd.train_step()
        err = (crowd.net.member_flat(2, crowd.net.grad) - alone.net.member_flat(0, alone.net.grad)).abs()
        drift.add(*stacked_sqrt_v(alone.net, [0]), flat_params(a.agents), err=err)
        sqrt_v, t = stacked_sqrt_v(alone.dnet, discs)
        disc_drift.add(sqrt_v, t, disc_params(a), err=disc_grad_tol(me, a.discs, sqrt_v, t), steps=me.disc_steps)
    # Its own random stream, consumed alike, so the same self-play (actions, positions, games) ...
    assert torch.equal(a.gen.get_state(), b.gen.get_state())
    assert_states_equal(case.pack_state(alone, 0), case.pack_state(crowd, 2), "self-play state")
    # ... and the same weights up to float rounding (other shapes round differently) ...
    assert drift.close(flat_params(b.agents), flat_params(a.agents))
    assert disc_drift.close(disc_params(b), disc_params(a))
    assert alone.loss_columns(0) == pytest.approx(crowd.loss_columns(2), rel=1e-4)


@pytest.mark.parametrize("domain", DOMAINS)
def test_member_is_bit_for_bit_the_same_beside_any_mate_of_the_same_shape(domain):
    """Where the pack's shapes agree (members, padded paired rows), what the mate is - its method,
    data, trial, adversary - changes nothing at all in the other member."""
    case = case_for(domain)
    me = case.spec(method="osp", paired=3, trial=0, train_steps=30)
    runs = []
    for mate in (case.spec(**m, train_steps=30) for m in case.same_shape_mates):
        pack = case.make_pack([me, mate])
        for _ in range(30):
            pack.train_step()
        runs.append((flat_params(pack.members[0].agents), pack.loss_columns(0), case.pack_state(pack, 0),
                     pack.members[0].gen.get_state()))
    (p1, l1, x1, g1), (p2, l2, x2, g2) = runs
    assert torch.equal(p1, p2) and l1 == l2 and torch.equal(g1, g2)
    assert_states_equal(x1, x2, "self-play state")


# ---- a diverging member ---------------------------------------------------------------------------
def poisoned(data: tuple[dict, dict], which: int) -> tuple[dict, dict]:
    """A member's data (P, U) with NaN for every float of P (which=0) or of U (which=1): the loss that
    reads it, so its gradient, is non-finite in the first update on any CPU (NaN survives every float
    op, whichever rows are drawn), where a huge learning rate overflows on some CPUs only (lr=1e30
    left a lever PC member finite on an Intel Xeon)."""
    data = tuple({k: v.clone() for k, v in d.items()} for d in data)
    floats = [v for v in data[which].values() if v.is_floating_point()]
    assert floats, f"no float tensor in {'PU'[which]} to poison"
    for v in floats:
        v.fill_(float("nan"))
    return data


@pytest.mark.parametrize("domain", DOMAINS)
def test_diverging_members_are_frozen_and_reported_and_others_go_on(domain):
    """One diverging member of each method beside three healthy ones, by construction (`poisoned`): an
    ASP member's discriminator gradient goes non-finite (NaN in its U; the particle pack checks only
    the network gradient, which the NaN discriminator then makes non-finite, so there the frozen
    discriminator is NaN), an OSP or PC member's network gradient (NaN in its P). The same pack with
    the same last members on clean data is the control."""
    case = case_for(domain)
    specs = [case.spec(method="asp", paired=3, trial=0), case.spec(method="osp", paired=2, trial=1),
             case.spec(method="pc", paired=4, trial=2)]
    specs += [case.spec(method=m, paired=1, trial=3 + k) for k, m in enumerate(("asp", "osp", "pc"))]
    clean = [case.member_data(s) for s in specs]
    runs, held = {}, {}
    bad = clean[:3] + [poisoned(clean[3], 1), poisoned(clean[4], 0), poisoned(clean[5], 0)]
    for name, data in (("bad", bad), ("good", clean)):
        pack = case.make_pack(specs, data)
        for step in range(case.small["train_steps"]):
            pack.train_step()
            if step == 4:  # (the bad members fail in their first update)
                held[name] = [(flat_params(m.agents), disc_params(m)) for m in pack.members[3:]]
        runs[name] = pack
    for k, frozen in enumerate(runs["bad"].members[3:]):
        what = f"{frozen.spec.method} member"
        assert frozen.failed and "non-finite" in frozen.error and frozen.failed_step is not None, what
        assert frozen.failed_step == 0, what
        assert torch.isfinite(flat_params(frozen.agents)).all(), f"{what}: frozen before the non-finite step"
        # frozen means frozen: its network and its discriminators have not moved since (bit for bit,
        # NaN included)
        assert torch.equal(held["bad"][k][0], flat_params(frozen.agents)), what
        assert torch.equal(held["bad"][k][1].view(torch.int32), disc_params(frozen).view(torch.int32)), what
    assert not any(m.failed for m in runs["good"].members)
    for i in range(3):  # the others are exactly what they are beside healthy members
        assert not runs["bad"].members[i].failed
        assert torch.equal(flat_params(runs["bad"].members[i].agents), flat_params(runs["good"].members[i].agents))
        assert torch.equal(disc_params(runs["bad"].members[i]), disc_params(runs["good"].members[i]))
        assert runs["bad"].loss_columns(i) == runs["good"].loss_columns(i)


# ---- a trainer's checkpoint ------------------------------------------------------------------------
@pytest.mark.parametrize("domain", DOMAINS)
def test_restore_mid_pack_continues_bit_for_bit(domain, monkeypatch):
    monkeypatch.setattr(packed_module(domain), "CHUNK", 8)  # several chunks of random draws, restored mid-chunk
    case = case_for(domain)
    specs = [case.spec(**c, train_steps=30) for c in case.packs["mixed"][:6]]
    data = [case.member_data(s) for s in specs]
    whole = case.make_pack(specs, data)
    for _ in range(30):
        whole.train_step()
    first = case.make_pack(specs, data)
    for _ in range(13):
        first.train_step()
    buf = io.BytesIO()
    torch.save(first.state_dict(), buf)
    resumed = case.make_pack(specs, data)
    resumed.load_state_dict(artefacts.from_bytes(buf.getvalue(), "checkpoint"))
    for _ in range(17):
        resumed.train_step()
    for net in ("net", "dnet"):
        for buffer in ("param", "exp_avg", "exp_avg_sq"):
            assert torch.equal(getattr(getattr(resumed, net), buffer), getattr(getattr(whole, net), buffer)), \
                (net, buffer)
    for i in range(len(specs)):
        assert torch.equal(resumed.members[i].gen.get_state(), whole.members[i].gen.get_state())
        assert_states_equal(case.pack_state(resumed, i), case.pack_state(whole, i), f"member {i}: self-play state")
        assert resumed.loss_columns(i) == whole.loss_columns(i)
        assert resumed.members[i].curve == whole.members[i].curve


# ---- the registry ---------------------------------------------------------------------------------
@pytest.mark.parametrize("domain", DOMAINS)
def test_a_domain_packs_its_own_cells_only(domain):
    module, trainer = packed_module(domain), trainer_class(domain)
    s = tiny_spec(domain)
    assert supports(s) and trainer.supports(s)
    assert pack_key(s) == (domain, *module.pack_key(s)) == (domain, *trainer.pack_key(s))
    assert pack_key(s) == pack_key(tiny_spec(domain, method="asp", paired=3, trial=4, lr=0.1))
    for other in DOMAINS + ["signaling"]:
        if other != domain:
            assert not trainer.supports(tiny_spec(other))
    assert not supports(tiny_spec("signaling"))


@pytest.mark.parametrize("domain", DOMAINS)
def test_a_knob_the_packed_trainer_does_not_declare_makes_it_refuse_every_cell(domain, monkeypatch, caplog):
    """A knob added to the domain (its game reads it) but not to its packed trainer's `implements`: the
    trainer registry refuses the trainer with one warning naming the knob, and every cell of the domain
    trains on the next trainer (the reference for packs; the domain's next lone trainer or the reference
    for lone cells), so the kernel cannot silently ignore the knob."""
    trainer, card = trainer_class(domain), get_domain(domain)
    s = tiny_spec(domain, method="asp", paired=2).resolved()
    assert engines.trainer_problems(trainer, domain) == [] and trainer in engines.trainers_of(domain)
    new = Knob(f"{domain}_new_idea", float, 0.5, "a knob only the game knows")
    monkeypatch.setattr(type(card), "knobs", (*card.knobs, new))
    with caplog.at_level(logging.WARNING, logger=engines.__name__):
        assert trainer not in engines.trainers_of(domain)
        assert trainer not in engines.trainers_of(domain)
    refused = [r.getMessage() for r in caplog.records if trainer.__name__ in r.getMessage()]
    assert len(refused) == 1 and f"{domain}_new_idea" in refused[0], refused
    assert engines.pack_trainer(s) is None and not engines.supports(s)
    assert engines.lone_trainer(s) is not trainer


@pytest.mark.parametrize("domain", DOMAINS)
def test_a_cell_a_lone_trainer_cannot_honour_falls_back_with_one_log_line(domain, monkeypatch, caplog):
    """A knob value outside what the lone trainer implements: the cell trains on the next trainer that
    supports it, and one log line names the trainer passed over and the knob value."""
    trainer = engines.lone_trainer(tiny_spec(domain, method="asp", paired=2))
    if getattr(trainer, "implements", None) is None:
        pytest.skip(f"{domain}'s lone trainer runs the domain's own game functions")
    name = next(n for n, allowed in trainer.implements.items() if allowed is ANY and n not in getattr(trainer, "shared", ()))
    s = tiny_spec(domain, method="asp", paired=2).resolved()
    monkeypatch.setitem(trainer.implements, name, (getattr(s, name),))
    odd = dataclasses.replace(s, **{name: other_value(getattr(s, name))}).resolved()
    assert trainer.supports(s) and not trainer.supports(odd)
    with caplog.at_level(logging.INFO, logger=engines.__name__):
        chosen = engines.lone_trainer(odd)
    assert chosen is not trainer and chosen.supports(odd)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and trainer.__name__ in lines[0] and f"{name}=" in lines[0] and odd.cell_id in lines[0]


# What run_cell trains a lone cell on, per built-in domain (a plugin's packed trainer: the rule only).
LONE = {"particles": "PackedParticleTrainer", "levers": "PackedLeverTrainer", "vae": "HandDerivedVAETrainer"}


@pytest.mark.parametrize("domain", DOMAINS)
def test_a_lone_cell_trains_on_the_first_lone_trainer_that_supports_it(domain):
    """run_cell's trainer (engines.lone_trainer): a one-member pack where the packed trainer says `lone`,
    else the domain's next lone trainer (the VAE's hand-derived one), else the reference Trainer (the
    other checks here compare packs with whichever it is); built as the pipeline builds it, one member."""
    s = tiny_spec(domain, method="asp", paired=2).resolved()
    d, data = get_domain(domain), case_for(domain).member_data(s)
    chosen = lone_trainer(s)
    assert chosen.lone and chosen.supports(s)
    assert chosen.__name__ == LONE.get(domain, chosen.__name__)
    assert chosen is next(t for t in (*d.trainers, Trainer) if t.lone and t.supports(s))
    trainer = lone(s, d.new_agents(s, 0), *data)
    assert type(trainer) is chosen and len(trainer.members) == 1 and trainer.engine == chosen.engine
    if not trainer_class(domain).lone:
        assert chosen is not trainer_class(domain)


def test_stacked_adam_matches_torch_adam():
    """StackedParams' one fused Adam step over the stacked buffer (two learning rates) is torch's Adam
    per module, and the modules' parameters are views of the buffer (loading a state writes it)."""
    torch.manual_seed(0)
    modules = [torch.nn.Linear(5, 3) for _ in range(3)]
    refs = [torch.nn.Linear(5, 3) for _ in range(3)]
    lrs = [0.01, 0.03, 0.01]
    for a, b in zip(refs, modules):
        a.load_state_dict(b.state_dict())
    stacked = StackedParams(modules, lrs)
    opts = [torch.optim.Adam(a.parameters(), lr=lr) for a, lr in zip(refs, lrs)]
    x = torch.randn(7, 5)
    drift = [AdamDrift(lr) for lr in lrs]  # how far float rounding takes them apart (packed_cases)
    for _ in range(20):
        for a, opt in zip(refs, opts):
            opt.zero_grad()
            a(x).pow(2).sum().backward()
            opt.step()
        for i, b in enumerate(modules):
            b.zero_grad()
            b(x).pow(2).sum().backward()
            for p, (start, n) in zip(b.parameters(), stacked.member_ranges[i]):
                stacked.grad[start:start + n] = p.grad.reshape(-1)
        stacked.step()
        for a, b, opt, d in zip(refs, modules, opts, drift):
            d.add(*adam_sqrt_v(a, opt), flat_params(a), err=(flat_grads(b) - flat_grads(a)).abs())
    for a, b, d in zip(refs, modules, drift):
        assert d.close(flat_params(b), flat_params(a))
    modules[1].load_state_dict({k: torch.zeros_like(v) for k, v in modules[1].state_dict().items()})
    assert stacked.member_flat(1).abs().sum() == 0 and stacked.member_flat(0).abs().sum() > 0
