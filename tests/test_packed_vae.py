"""The VAE's packed trainer (asp_dist/domains/vae/packed.py), what is particular to it: each member
against the single-cell path run_cell takes for a VAE cell (the one-pass trainer,
asp_dist.domains.vae.fast.OnePassVAETrainer) after one update and over a whole tiny training, for
packs mixing methods and every per-member knob; a member beside other pack-mates (other shapes);
what can share a pack. Checks of every packed trainer (packs against the reference Trainer member by
member, whole cells against run_cell, pack-mates of one shape bit for bit, divergence, checkpoints)
are in tests/test_packed.py; single VAE cells train on the one-pass trainer, not as packs of one."""

from __future__ import annotations

import pytest
import torch
from budgets import tiny_spec
from packed_cases import (
    VAE,
    AdamDrift,
    adam_sqrt_v,
    disc_grad_tol,
    disc_params,
    flat_grads,
    flat_params,
    float32_tol,
    stacked_sqrt_v,
)

from asp_dist.core.registry import get_domain
from asp_dist.domains.vae.fast import OnePassVAETrainer
from asp_dist.domains.vae.hand_derived import HandDerivedVAETrainer
from asp_dist.domains.vae.packed import IMPLEMENTS, PackedVAETrainer, pack_key
from asp_dist.training.engines import lone_trainer, pack_trainer, sweep_packs
from asp_dist.training.methods import method_weights

DOMAIN = get_domain("vae")
# Gradients and weights agree up to float32 rounding: packed_cases.float32_tol and AdamDrift.
LOSS_REL = 1e-5

# Packs of different methods and knob values (members share the fields in SHARED, so the
# discriminator's depth and steps get a pack of their own).
PACKS = {
    "methods-and-knobs": [
        dict(method="asp", paired=4, trial=0),
        dict(method="pc", paired=5, trial=1, vae_paired_reduction="mean"),
        dict(method="osp", paired=3, trial=2, vae_recon_loss="mse", vae_kl_weight=0.5, lr=2e-3),
        dict(method="asp", paired=0, trial=1, vae_adversary_input="z", adversary_loss="non_saturating",
             unpaired_size=40, disc_lr=3e-3),
        dict(method="asp", paired=2, trial=3, lambda_unpaired_schedule="warmup", lambda_schedule_frac=0.5,
             vae_train_images=200, vae_recon_loss="mse", vae_paired_reduction="mean", lambda_paired=0.3),
        dict(method="asp", paired=3, trial=4, lambda_unpaired_schedule="anneal", lambda_schedule_frac=0.5,
             lambda_unpaired=0.3, vae_adversary_input="z"),
        dict(method="pc", paired=0, trial=0),  # nothing to learn
    ],
    "disc-1-layer-2-steps": [
        dict(method="asp", paired=2, trial=0, disc_layers=1, disc_steps=2, unpaired_batch=5),
        dict(method="osp", paired=4, trial=1, disc_layers=1, disc_steps=2, unpaired_batch=5, vae_recon_loss="mse"),
        dict(method="pc", paired=3, trial=2, disc_layers=1, disc_steps=2, unpaired_batch=5),
        dict(method="asp", paired=1, trial=3, disc_layers=1, disc_steps=2, unpaired_batch=5,
             vae_adversary_input="z", adversary_loss="non_saturating", vae_paired_reduction="mean"),
    ],
}


def pack_and_singles(changes: list[dict], **common):
    """A pack of `changes`, each member's single-cell trainer (run_cell's: the one-pass trainer), from
    the same data and initial weights, and each single's Drift."""
    specs = [VAE.spec(**c, **common) for c in changes]
    data = [VAE.member_data(s) for s in specs]
    pack = VAE.make_pack(specs, data)
    singles = [OnePassVAETrainer(s, DOMAIN, DOMAIN.new_agents(s, s.seed_for("init")), p, u, method_weights(s))
               for s, (p, u) in zip(specs, data)]
    return specs, pack, singles, [Drift(single) for single in singles]


class Drift:
    """How far float rounding can take a pack member's weights from its single trainer's
    (packed_cases.AdamDrift, from the single's Adam state): `step` after each of the single's updates,
    with the member's gradient in the pack."""

    def __init__(self, single):
        s, self.single = single.spec, single
        self.terms = VAE.grad_terms(s, single.agents)
        self.agents, self.disc = AdamDrift(s.lr), AdamDrift(s.disc_lr)

    def step(self, pack_grad: torch.Tensor) -> None:
        single, s = self.single, self.single.spec
        self.agents.add(*adam_sqrt_v(single.agents, single.opt), flat_params(single.agents),
                        err=(pack_grad - flat_grads(single.agents)).abs())
        if single.adversaries is not None:
            sqrt_v, t = adam_sqrt_v(single.adversaries, *single.adversaries.optims.values())
            err = disc_grad_tol(s, single.adversaries.discs.values(), sqrt_v, t)
            self.disc.add(sqrt_v, t, flat_params(single.adversaries), err=err, steps=s.disc_steps)


def assert_member_matches(pack, i: int, drift: Drift, what: str, *, at_end: bool) -> None:
    single = drift.single
    assert drift.agents.close(flat_params(pack.members[i].agents), flat_params(single.agents)), f"{what}: weights"
    if single.adversaries is not None:
        assert drift.disc.close(disc_params(pack.members[i]), flat_params(single.adversaries)), \
            f"{what}: discriminator"
    if at_end:  # (the pack draws a chunk of updates ahead: its generators meet the single cell's at the end)
        assert torch.equal(pack.members[i].gen.get_state(), single.gen.get_state()), f"{what}: the draws differ"


@pytest.mark.parametrize("name", PACKS)
def test_first_update_equals_the_one_pass_trainer_member_by_member(name):
    specs, pack, singles, drifts = pack_and_singles(PACKS[name], train_steps=20)
    pack.train_step()
    for i, (single, drift) in enumerate(zip(singles, drifts)):
        single.train_step()
        expected, got = flat_grads(single.agents), pack.net.member_flat(i, pack.net.grad)
        drift.step(got)
        what = f"member {i} ({specs[i].method}, {PACKS[name][i]})"
        torch.testing.assert_close(got, expected, rtol=0, atol=float32_tol(expected, drift.terms),
                                   msg=f"{what}: gradient")
        assert_member_matches(pack, i, drift, what, at_end=False)


@pytest.mark.parametrize("name", PACKS)
def test_whole_tiny_training_equals_the_one_pass_trainer(name):
    """20 updates: every update a curve point, the final window the last 2; loss columns, curves,
    final weights (the VAE's and the discriminator's) and the generators."""
    specs, pack, singles, drifts = pack_and_singles(PACKS[name], train_steps=20)
    for _ in range(20):
        pack.train_step()
        for i, (single, drift) in enumerate(zip(singles, drifts)):
            single.train_step()
            drift.step(pack.net.member_flat(i, pack.net.grad))
    for i, single in enumerate(singles):
        what = f"member {i} ({specs[i].method}, {PACKS[name][i]})"
        assert_member_matches(pack, i, drifts[i], what, at_end=True)
        expected, got = single.loss_columns(), pack.loss_columns(i)
        assert expected.keys() == got.keys()
        for key, value in expected.items():
            assert (got[key] is None) == (value is None), (what, key)
            if value is not None:
                assert got[key] == pytest.approx(value, rel=LOSS_REL, abs=1e-6), (what, key)
        assert len(pack.members[i].curve) == len(single.curve) == 20
        for p, q in zip(pack.members[i].curve, single.curve):
            assert p.keys() == q.keys() and p == pytest.approx(q, rel=LOSS_REL, abs=1e-6), what


def test_a_member_does_not_depend_on_its_pack_mates():
    """The same member in packs of other sizes, paired rows and discriminator counts: its own draws,
    and the same weights and losses up to float rounding (other shapes round differently)."""
    me = dict(method="asp", paired=3, trial=0, vae_adversary_input="z", vae_recon_loss="mse")
    packs = [[me],
             [dict(method="pc", paired=9, trial=1), me],
             [dict(method="asp", paired=1, trial=2, adversary_loss="non_saturating", unpaired_size=30),
              dict(method="osp", paired=0, trial=3, vae_kl_weight=0.2), me,
              dict(method="asp", paired=6, trial=4, lambda_unpaired_schedule="warmup")]]
    runs = [VAE.make_pack([VAE.spec(**c, train_steps=20) for c in changes]) for changes in packs]
    rows = [changes.index(me) for changes in packs]
    (alone, *_), s = runs[0].members, runs[0].members[0].spec
    # how far rounding can take the others from alone (packed_cases.AdamDrift, from alone's Adam state)
    drifts = [(AdamDrift(s.lr), AdamDrift(s.disc_lr)) for _ in packs[1:]]
    for _ in range(20):
        for pack in runs:
            pack.train_step()
        grad, (sqrt_v, t) = runs[0].net.member_flat(0, runs[0].net.grad), stacked_sqrt_v(runs[0].dnet, [0])
        for (drift, disc_drift), pack, i in zip(drifts, runs[1:], rows[1:]):
            drift.add(*stacked_sqrt_v(runs[0].net, [0]), flat_params(alone.agents),
                      err=(pack.net.member_flat(i, pack.net.grad) - grad).abs())
            disc_drift.add(sqrt_v, t, disc_params(alone), err=disc_grad_tol(s, alone.discs, sqrt_v, t),
                           steps=s.disc_steps)
    alone_losses = runs[0].loss_columns(0)
    for (drift, disc_drift), pack, i in zip(drifts, runs[1:], rows[1:]):
        member = pack.members[i]
        assert torch.equal(member.gen.get_state(), alone.gen.get_state())
        assert drift.close(flat_params(member.agents), flat_params(alone.agents)), "weights"
        assert disc_drift.close(disc_params(member), disc_params(alone)), "discriminator"
        assert pack.loss_columns(i) == pytest.approx(alone_losses, rel=LOSS_REL)


def test_mates_with_other_knob_values_change_nothing_at_one_shape():
    """A mate whose reconstruction loss, adversary input and adversarial loss differ from the member's
    makes the pack compute both ways and pick per member (torch.where): the member's arithmetic is
    still bit for bit what it is beside a mate of its own knob values."""
    me = VAE.spec(method="asp", paired=3, trial=0, train_steps=30)
    runs = []
    for mate in (VAE.spec(method="asp", paired=3, trial=1, train_steps=30),
                 VAE.spec(method="asp", paired=2, trial=2, vae_recon_loss="mse", vae_adversary_input="z",
                          adversary_loss="non_saturating", unpaired_size=50, train_steps=30)):
        pack = VAE.make_pack([me, mate])
        for _ in range(30):
            pack.train_step()
        runs.append((flat_params(pack.members[0].agents), disc_params(pack.members[0]), pack.loss_columns(0)))
    (p1, d1, l1), (p2, d2, l2) = runs
    assert torch.equal(p1, p2) and torch.equal(d1, d2) and l1 == l2


def test_a_pc_member_is_not_harmed_by_the_self_play_rows_it_rides_along_in():
    """A PC member's self-play rows are computed (weight 0) beside members with self-play; a log σ²
    whose exp overflows there (exp(200) is inf in float32) must not reach its gradient as inf·0."""
    specs = [VAE.spec(method="osp", paired=2, trial=0), VAE.spec(method="pc", paired=3, trial=1)]
    data = [VAE.member_data(s) for s in specs]
    agents = [DOMAIN.new_agents(s, s.seed_for("init")) for s in specs]
    single_agents = DOMAIN.new_agents(specs[1], specs[1].seed_for("init"))
    for vae in (agents[1], single_agents):
        with torch.no_grad():
            vae.encoder[2].bias[vae.latent_dim:] = 400.0  # log σ² = 400 on every input
    pack = PackedVAETrainer(specs, [d[0] for d in data], [d[1] for d in data], agents)
    single = OnePassVAETrainer(specs[1], DOMAIN, single_agents, *data[1], method_weights(specs[1]))
    drift = Drift(single)
    for _ in range(3):
        pack.train_step()
        single.train_step()
        drift.step(pack.net.member_flat(1, pack.net.grad))
    assert not any(m.failed for m in pack.members)
    assert drift.agents.close(flat_params(pack.members[1].agents), flat_params(single.agents))


def test_what_can_share_a_pack():
    spec, supports = VAE.spec, PackedVAETrainer.supports
    assert supports(tiny_spec("vae")) and supports(spec(method="asp", paired=2))
    for knob, values in IMPLEMENTS.items():  # every value the spec accepts is implemented
        for value in values if isinstance(values, tuple) else ():
            assert supports(spec(method="asp", paired=2, **{knob: value})), (knob, value)
    assert not supports(tiny_spec("particles")) and not supports(tiny_spec("levers"))
    # per-member knobs do not split packs; shapes and the length of training do
    assert pack_key(spec(method="pc", paired=1, trial=4, lr=0.1, vae_recon_loss="mse", vae_kl_weight=0.3,
                         vae_train_images=100)) == pack_key(
        spec(method="asp", paired=6, unpaired_size=33, adversary_loss="non_saturating", vae_adversary_input="z",
             vae_paired_reduction="mean", lambda_unpaired_schedule="warmup", disc_lr=0.01))
    for changes in (dict(vae_latent_dim=8), dict(vae_hidden=32), dict(batch_size=8), dict(train_steps=9),
                    dict(disc_steps=2), dict(disc_layers=1), dict(disc_hidden=8), dict(unpaired_batch=4)):
        assert pack_key(spec(method="pc")) != pack_key(spec(method="pc", **changes)), changes
    with pytest.raises(ValueError, match="vae_hidden"):
        VAE.make_pack([spec(method="pc", paired=1), spec(method="pc", paired=1, vae_hidden=32)])


def test_a_single_vae_cell_trains_on_the_hand_derived_trainer():
    """The packed trainer is for packs only, and kept out of sweeps (measured slower: docs/performance.md):
    a lone VAE cell keeps run_cell's hand-derived trainer."""
    s = tiny_spec("vae", method="asp", paired=2).resolved()
    assert not PackedVAETrainer.lone and not PackedVAETrainer.in_sweeps
    assert pack_trainer(s) is PackedVAETrainer and not sweep_packs(s)
    assert lone_trainer(s) is HandDerivedVAETrainer
