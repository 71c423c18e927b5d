"""The MNIST VAE domain: contract, determinism, one smoke cell per method, and its own checks.

Every budget is shrunk (a few hundred training images, tens of steps, a 64-unit VAE) so the
file runs in seconds; the paper-size settings are exercised by bench/bench_vae.py instead."""

import copy
import json
import math

import pytest
import torch
from budgets import tiny_spec

from asp_dist.core.registry import get_domain
from asp_dist.domains.vae import VAE
from asp_dist.spec import CellSpec, SpecError
from asp_dist.training.bases import train_accepted_base
from asp_dist.training.cell import run_cell
from asp_dist.training.row import comparable


def tiny(**changes) -> CellSpec:
    return tiny_spec("vae", **changes)


@pytest.fixture(scope="module")
def domain():
    return get_domain("vae")


@pytest.fixture(scope="module")
def base():
    return train_accepted_base(tiny(paired=4))



def test_defaults_follow_the_paper(domain):
    spec = CellSpec(domain="vae").resolved()
    assert (spec.vae_latent_dim, spec.vae_hidden, spec.base_train_steps, spec.vae_base_batch) == (32, 512, 5000, 128)
    assert spec.unpaired_size == 2048 and spec.eval_episodes == 10_000 and spec.vae_train_images == 0
    assert all(not m.higher_is_better for m in domain.metrics.values()), "every VAE metric is an MSE"


def test_whole_cell_is_deterministic():
    spec = tiny(method="asp", paired=4)
    assert comparable(run_cell(spec)) == comparable(run_cell(spec))


@pytest.mark.parametrize("method", ["pc", "osp", "asp"])
def test_smoke_cell_per_method(method, base):
    row = run_cell(tiny(method=method, paired=4), base=base)
    for k in ("eval_mixed", "eval_mixed_base_encoder", "eval_mixed_new_encoder", "eval_self_play_new",
              "eval_self_play_base", "eval_latent_mse"):
        assert math.isfinite(row[k]) and row[k] >= 0, k
    assert row["eval_mixed"] == pytest.approx((row["eval_mixed_base_encoder"] + row["eval_mixed_new_encoder"]) / 2)
    assert row["eval_mixed_higher_is_better"] is False
    assert row["base_score"] == pytest.approx(row["eval_self_play_base"])
    assert (row["loss_unpaired"] is not None) == (method == "asp")
    assert (row["loss_self_play"] is not None) == (method != "pc")


def test_paired_tuples_are_the_base_mapping(domain, base):
    spec = tiny(paired=5).resolved()
    p = domain.paired(spec, base.agents, 5, torch.Generator().manual_seed(0))
    assert p["image"].shape == (5, 784) and p["encoding"].shape == (5, 4) and p["recon"].shape == (5, 784)
    assert 0.0 <= float(p["image"].min()) and float(p["image"].max()) <= 1.0
    with torch.no_grad():
        mu = base.agents.encode(p["image"])[0]
        assert torch.allclose(p["encoding"], mu)
        assert torch.allclose(p["recon"], base.agents.decode(mu))
    u = domain.unpaired(spec, base.agents, 64, torch.Generator().manual_seed(1))
    assert set(u) == {"latent"} and u["latent"].shape == (64, 4) and not u["latent"].requires_grad


def test_a_copy_of_the_base_scores_its_own_self_play(domain, base):
    spec = tiny().resolved()
    m = domain.evaluate(spec, base.agents, copy.deepcopy(base.agents), torch.Generator().manual_seed(0))
    assert m["latent_mse"] == 0.0
    assert m["mixed"] == pytest.approx(m["self_play_base"]) == pytest.approx(m["self_play_new"])
    assert m["self_play_base"] == pytest.approx(base.score)


def test_base_learns_to_reconstruct(domain):
    """40 small batches already bring the base well below an untrained VAE's error."""
    spec = tiny().resolved()
    trained, score = domain.train_base(spec, seed=0)
    untrained = domain.new_agents(spec, seed=0)
    m = domain.evaluate(spec, trained, untrained, torch.Generator().manual_seed(0))
    assert score < 0.7 * m["self_play_new"]


def test_pc_without_paired_data_does_not_train(domain, base):
    spec = tiny(method="pc", paired=0)
    row = run_cell(spec, base=base)
    untrained = domain.new_agents(spec.resolved(), spec.seed_for("init"))
    m = domain.evaluate(spec.resolved(), base.agents, untrained, torch.Generator().manual_seed(0))
    assert row["eval_mixed"] == pytest.approx(m["mixed"])


def test_paired_loss_pulls_the_new_vae_onto_the_base_mapping(domain, base):
    spec = tiny(paired=8).resolved()
    p = domain.paired(spec, base.agents, 8, torch.Generator().manual_seed(0))
    agents = domain.new_agents(spec, seed=3)
    opt = torch.optim.Adam(agents.parameters(), lr=3e-3)
    first = float(domain.paired_loss(spec, agents, p).detach())
    for _ in range(100):
        loss = domain.paired_loss(spec, agents, p)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.1 * first


def test_self_play_outputs_are_the_encoder_means(domain):
    spec = tiny().resolved()
    agents = domain.new_agents(spec, seed=1)
    out = domain.self_play_step(spec, agents, {}, torch.Generator().manual_seed(0))
    assert out.outputs["latent"].shape == (spec.batch_size, 4) and out.outputs["latent"].requires_grad
    assert out.loss.requires_grad and out.info["kl"] >= 0


def test_figure_data_latent2d_and_reconstructions():
    spec = tiny(method="asp", paired=2, vae_latent_dim=2, record_figure_data=True)
    fig = json.loads(run_cell(spec)["figure_data"])
    assert fig["kind"] == "latent2d"
    assert len(fig["base"]) == len(fig["new"]) == len(fig["labels"]) == 1000
    assert all(len(xy) == 2 for xy in fig["base"][:5])
    assert fig["labels"][:4] == [7, 2, 1, 0]
    recon = fig["recon"]
    assert recon["labels"] == list(range(10))
    for key in ("original", "base", "new", "base_encoder_new_decoder", "new_encoder_base_decoder"):
        assert len(recon[key]) == 10 and len(recon[key][0]) == 784
        assert 0 <= min(min(r) for r in recon[key]) and max(max(r) for r in recon[key]) <= 255
    other = json.loads(run_cell(tiny(method="pc", paired=2, record_figure_data=True))["figure_data"])
    assert other["kind"] == "vae_recon" and "base" not in other
    assert run_cell(tiny(method="pc", paired=2))["figure_data"] is None


def test_invalid_knobs_are_spec_errors():
    with pytest.raises(SpecError, match="vae_train_images"):
        tiny(vae_train_images=70_000).resolved()
    with pytest.raises(SpecError, match="eval_episodes"):
        tiny(eval_episodes=20_000).resolved()
    with pytest.raises(SpecError, match="vae_latent_dim"):
        tiny(vae_latent_dim=0).resolved()


def test_vae_module_shapes():
    vae = VAE(latent_dim=3, hidden=8)
    with torch.no_grad():
        mu, logvar = vae.encode(torch.rand(5, 784))
        out = vae.decode(mu)
    assert mu.shape == logvar.shape == (5, 3)
    assert out.shape == (5, 784) and float(out.min()) >= 0 and float(out.max()) <= 1


def vae_trainers(domain, base, classes, **changes):
    """Trainers of `classes` on the same spec, data and initial weights (tiny VAE, 4 paired)."""
    from asp_dist.training.methods import method_weights

    spec = tiny(**{"paired": 4, **changes}).resolved()
    gen = torch.Generator().manual_seed(0)
    paired = domain.paired(spec, base.agents, spec.paired, gen) if spec.paired else {}  # as the pipeline has it
    unpaired = domain.unpaired(spec, base.agents, spec.unpaired_size, gen)
    return [cls(spec, domain, domain.new_agents(spec, 1), paired, unpaired, method_weights(spec)) for cls in classes]


@pytest.mark.parametrize("fast_class", ["OnePassVAETrainer", "HandDerivedVAETrainer"])
@pytest.mark.parametrize("changes", [
    dict(method="osp"), dict(method="asp"), dict(method="pc"), dict(method="osp", paired=0),
    dict(method="asp", paired=0),
    dict(method="asp", vae_recon_loss="mse", vae_adversary_input="z", vae_paired_reduction="mean"),
    dict(method="asp", adversary_loss="non_saturating", disc_steps=2, vae_kl_weight=0.3),
    dict(method="pc", vae_recon_loss="mse", vae_paired_reduction="mean"),
], ids=["osp", "asp", "pc", "osp-0-paired", "asp-0-paired", "asp-mse-z-mean", "asp-nonsat-2disc-kl", "pc-mse-mean"])
def test_the_fast_updates_are_the_reference_update(changes, fast_class, domain, base):
    """Each fast lone trainer computes the reference update: gradients, weights (VAE and discriminator)
    and loss columns equal up to float rounding, the same draws. The one-pass trainer runs self-play and
    paired rows in one batch per network through autograd (PC has nothing to merge: the reference update
    itself); the hand-derived one computes the same gradients in closed form."""
    from asp_dist.domains.vae import fast, hand_derived
    from asp_dist.training.trainer import Trainer

    cls = getattr(fast, fast_class, None) or getattr(hand_derived, fast_class)
    reference, fast = vae_trainers(domain, base, (Trainer, cls), **changes)
    assert cls.supports(fast.spec)
    grads = []
    for trainer in (reference, fast):
        trainer.train_step()  # the first update's gradients, before Adam has amplified any rounding
        grads.append([p.grad.clone() for p in trainer.agents.parameters()])
    for g_ref, g_fast in zip(*grads):
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-4, atol=1e-6)
    while reference.step < reference.spec.train_steps:  # the whole (tiny) training: 3 windows recorded
        reference.train_step()
        fast.train_step()
    modules = [(reference.agents, fast.agents)]
    if reference.adversaries is not None:
        modules.append((reference.adversaries, fast.adversaries))
    for ref_module, fast_module in modules:
        for (name, p_ref), p_fast in zip(ref_module.named_parameters(), fast_module.parameters()):
            torch.testing.assert_close(p_fast, p_ref, rtol=1e-4, atol=1e-5, msg=name)
    ref_losses, fast_losses = reference.loss_columns(), fast.loss_columns()
    assert ref_losses.keys() == fast_losses.keys()
    for k, v in ref_losses.items():
        assert (v is None) == (fast_losses[k] is None) and (v is None or fast_losses[k] == pytest.approx(v, rel=1e-4)), k
    assert torch.equal(reference.gen.get_state(), fast.gen.get_state()), "the draws differ"


def test_a_restored_vae_trainer_keeps_fused_adam(domain, base):
    """A checkpoint from before the VAE used fused Adam (its param_groups say fused=None) must not
    switch today's optimiser options off for the rest of the cell."""
    from asp_dist.domains.vae.fast import OnePassVAETrainer

    (trainer,) = vae_trainers(domain, base, (OnePassVAETrainer,), method="asp")
    trainer.train_step()
    state = copy.deepcopy(trainer.state_dict())
    for opt_state in [state["opt"], *state["adversaries"]["optims"].values()]:
        for group in opt_state["param_groups"]:
            group["fused"] = None  # as torch.optim.Adam() saved it before
    trainer.load_state_dict(state)
    assert all(g["fused"] for opt in [trainer.opt, *trainer.adversaries.optims.values()] for g in opt.param_groups)


@pytest.mark.parametrize("changes", [
    dict(), dict(vae_recon_loss="mse"), dict(vae_base_batch=25, vae_kl_weight=0.3),
], ids=["bce", "mse", "odd-batch-kl"])
def test_the_hand_derived_base_update_is_the_autograd_update(changes):
    """A base trains on hand-derived gradients (domains/vae/base_update.py). From the same weights and
    batch they equal autograd's gradients of the reference loss up to float rounding; a whole (tiny) base
    trained either way ends with the same weights up to rounding amplified by Adam, the same draws, and
    the same score."""
    from asp_dist.domains.vae.base_update import HandDerivedBaseUpdate
    from asp_dist.domains.vae.game import train_base

    spec = tiny(**changes).resolved()
    vae = VAE(spec.vae_latent_dim, spec.vae_hidden)
    x = torch.rand(spec.vae_base_batch, 784).round()  # binary pixels, and grey ones below
    x[::3] = torch.rand(len(x[::3]), 784)
    loss, *_ = vae.vae_loss(x, torch.Generator().manual_seed(5), spec.vae_kl_weight, spec.vae_recon_loss)
    loss.backward()
    update = HandDerivedBaseUpdate(vae, spec.vae_base_lr, spec.vae_kl_weight, spec.vae_recon_loss)
    hand = update.gradients(x, torch.Generator().manual_seed(5))
    for (name, p), g in zip(vae.named_parameters(), hand):
        torch.testing.assert_close(g, p.grad, rtol=1e-5, atol=1e-7, msg=name)

    reference, reference_score = train_base(spec, seed=3, reference=True)
    fast, fast_score = train_base(spec, seed=3)
    for (name, p_ref), p_fast in zip(reference.named_parameters(), fast.parameters()):
        torch.testing.assert_close(p_fast, p_ref, rtol=1e-3, atol=1e-4, msg=name)
    assert fast_score == pytest.approx(reference_score, rel=1e-3)


def test_the_hand_derived_base_update_steps_like_torch_adam():
    """Its Adam step is torch.optim.Adam's (fused, the domain's options) on the same gradients."""
    from asp_dist.domains.vae.base_update import HandDerivedBaseUpdate

    spec = tiny().resolved()
    a, b = VAE(spec.vae_latent_dim, spec.vae_hidden), VAE(spec.vae_latent_dim, spec.vae_hidden)
    b.load_state_dict(a.state_dict())
    opt = torch.optim.Adam(a.parameters(), lr=spec.vae_base_lr, **get_domain("vae").optimizer_options)
    update = HandDerivedBaseUpdate(b, spec.vae_base_lr, spec.vae_kl_weight, spec.vae_recon_loss)
    for step in range(3):
        x = torch.rand(spec.vae_base_batch, 784)
        loss, *_ = a.vae_loss(x, torch.Generator().manual_seed(step), spec.vae_kl_weight, spec.vae_recon_loss)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        update.step(x, torch.Generator().manual_seed(step))
        for (name, p_a), p_b in zip(a.named_parameters(), b.parameters()):
            torch.testing.assert_close(p_b, p_a, rtol=1e-5, atol=1e-6, msg=f"{name}, update {step}")


def test_a_vae_cell_trains_on_the_hand_derived_update(domain):
    """A sweep's lone VAE cell trains on the hand-derived update, whatever the method and paired count."""
    from asp_dist.domains.vae.hand_derived import HandDerivedVAETrainer
    from asp_dist.training.engines import lone_trainer

    for method in ("pc", "osp", "asp"):
        for paired in (0, 4):
            spec = tiny(method=method, paired=paired).resolved()
            expected = HandDerivedVAETrainer if (method, paired) != ("pc", 0) else None
            assert (lone_trainer(spec) is HandDerivedVAETrainer) == (expected is HandDerivedVAETrainer), (method, paired)


def test_the_hand_derived_trainer_resumes_the_reference_checkpoint(domain, base):
    """Its state is the reference Trainer's: a reference checkpoint taken mid-training and resumed on the
    hand-derived trainer ends where the reference ends, to float rounding."""
    from asp_dist.domains.vae.hand_derived import HandDerivedVAETrainer
    from asp_dist.training.trainer import Trainer

    reference, resumed = vae_trainers(domain, base, (Trainer, HandDerivedVAETrainer), method="asp")
    for _ in range(7):
        reference.train_step()
    resumed.load_state_dict(copy.deepcopy(reference.state_dict()))
    while reference.step < reference.spec.train_steps:
        reference.train_step()
        resumed.train_step()
    for (name, p_ref), p in zip(reference.agents.named_parameters(), resumed.agents.parameters()):
        torch.testing.assert_close(p, p_ref, rtol=1e-4, atol=1e-5, msg=name)
    assert torch.equal(reference.gen.get_state(), resumed.gen.get_state())


def test_the_direct_fused_adam_step_is_torch_adams_step():
    """base_update.fused_adam_step is torch.optim.Adam(fused=True).step(), bit for bit, state included; an
    optimizer it does not cover is stepped by its own step()."""
    from asp_dist.domains.vae.base_update import fused_adam_step

    for options in (dict(fused=True), dict(fused=True, weight_decay=0.1), dict()):
        a, b = torch.nn.Linear(5, 3), torch.nn.Linear(5, 3)
        b.load_state_dict(a.state_dict())
        opt_a, opt_b = (torch.optim.Adam(m.parameters(), lr=0.01, **options) for m in (a, b))
        for step in range(3):
            for m in (a, b):
                m.zero_grad()
                m(torch.full((2, 5), float(step + 1))).pow(2).sum().backward()
            opt_a.step()
            fused_adam_step(opt_b)
        for p_a, p_b in zip(a.parameters(), b.parameters()):
            assert torch.equal(p_a, p_b), options
        state_a, state_b = opt_a.state_dict()["state"], opt_b.state_dict()["state"]
        assert all(torch.equal(state_a[k][e], state_b[k][e]) for k in state_a for e in state_a[k]), options


def denormal_survives() -> bool:
    return float(torch.tensor([1e-39]) * 1.0) != 0.0


def test_bases_and_cells_train_with_denormals_flushed_and_the_mode_is_reset_after(monkeypatch):
    """Training flushes denormals (asp_dist.training.float_mode: Adam's decaying averages made a VAE base 40 %
    slower once they reached them), the base's loop and the cell's alike, and leaves the thread as it was."""
    from asp_dist.domains.vae import base_update, hand_derived

    seen = {"base": [], "cell": []}
    base_step, cell_step = base_update.HandDerivedBaseUpdate.step, hand_derived.HandDerivedVAETrainer.train_step

    def watched_base_step(self, *args):
        seen["base"].append(denormal_survives())
        return base_step(self, *args)

    def watched_cell_step(self):
        seen["cell"].append(denormal_survives())
        return cell_step(self)

    monkeypatch.setattr(base_update.HandDerivedBaseUpdate, "step", watched_base_step)
    monkeypatch.setattr(hand_derived.HandDerivedVAETrainer, "train_step", watched_cell_step)
    assert denormal_survives()
    run_cell(tiny(method="osp", paired=4))
    assert seen["base"] and seen["cell"] and not any(seen["base"]) and not any(seen["cell"])
    assert denormal_survives(), "the thread's mode was not reset"
