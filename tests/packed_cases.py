"""What the packed-training tests need to know of a domain: a small spec, packs to check member by
member, and where a member's self-play state lives (in a pack and in the reference Trainer).

tests/test_packed.py runs every check for every domain registered in asp_dist.training.packed.PACKED:
a domain registered there is tested without a line here (with GENERIC_PACKS and its tiny budget),
and a case below adds the packs and state that make its checks sharper. Domain-specific checks are
in tests/test_packed_<domain>.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable

import torch
from budgets import TINY

from asp_dist.domains import get_domain
from asp_dist.spec import CellSpec
from asp_dist.training.methods import method_weights
from asp_dist.training.packed import PACKED, driver, packed_module
from asp_dist.training.trainer import Trainer

DOMAINS = sorted(PACKED)

# A pack of members that differ in everything any member may differ in (methods, paired counts,
# trials, data sizes, learning rates, λ schedules, adversarial losses).
GENERIC_MIXED = [
    dict(method="asp", paired=4, trial=0),
    dict(method="pc", paired=4, trial=0),
    dict(method="osp", paired=0, trial=1),
    dict(method="osp", paired=5, trial=2, lr=2e-3),
    dict(method="asp", paired=0, trial=1, unpaired_size=40, disc_lr=3e-3),
    dict(method="asp", paired=3, trial=2, adversary_loss="non_saturating", lambda_unpaired=0.3),
    dict(method="asp", paired=3, trial=0, lambda_unpaired_schedule="warmup", lambda_schedule_frac=0.5),
    dict(method="asp", paired=2, trial=3, lambda_unpaired_schedule="anneal", lambda_schedule_frac=0.5),
    dict(method="pc", paired=0, trial=1),  # nothing to learn: no optimiser step, as Trainer
]
GENERIC_PACKS = {"mixed": GENERIC_MIXED,
                 "pc-only": [dict(method="pc", paired=4), dict(method="pc", paired=2, trial=1, lambda_paired=0.5),
                             dict(method="pc", paired=0)]}

# Whole tiny cells (tests/budgets.py), run through run_pack and run_cell; a PC member first (a trainer
# may place its members in another order than the specs').
TINY_CELLS = [dict(method="pc", paired=2, trial=0), dict(method="asp", paired=3, trial=0),
              dict(method="osp", paired=0, trial=1), dict(method="asp", paired=0, trial=1),
              dict(method="osp", paired=4, trial=1), dict(method="pc", paired=0, trial=0),
              dict(method="asp", paired=2, trial=1, adversary_loss="non_saturating", record_figure_data=True)]


def flat_params(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


def flat_grads(module: torch.nn.Module) -> torch.Tensor:
    """The last update's gradient (None, i.e. no update, reads as zeros)."""
    return torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in module.parameters()])


def disc_params(member) -> torch.Tensor:
    """A pack member's discriminators' parameters, in Adversaries' order (empty without)."""
    return torch.cat([flat_params(d) for d in member.discs]) if member.discs else torch.zeros(0)


def trainer_class(domain: str) -> type:
    """The domain's packed trainer: what its module's run_pack binds driver.run_pack to."""
    run_pack = packed_module(domain).run_pack
    assert isinstance(run_pack, partial) and run_pack.func is driver.run_pack, \
        f"{domain}: run_pack must be partial(driver.run_pack, Trainer) (asp_dist.training.packed)"
    return run_pack.args[0]


_DATA: dict[tuple, tuple[dict, dict]] = {}  # PackCase.member_data's draws


def _no_state(*_) -> list[torch.Tensor]:
    return []


@dataclass(frozen=True)
class PackCase:
    domain: str
    small: dict[str, Any]  # a small spec's fields: fast updates that still reach every code path
    packs: dict[str, list[dict]] = field(default_factory=lambda: GENERIC_PACKS)  # checked member by member
    tiny_cells: list[dict] = field(default_factory=lambda: TINY_CELLS)  # whole cells at the tiny budget
    # member i's self-play state in a pack, and the reference Trainer's (the same tensors; [] for none)
    pack_state: Callable[[Any, int], list[torch.Tensor]] = _no_state
    trainer_state: Callable[[Trainer], list[torch.Tensor]] = _no_state

    def spec(self, **changes) -> CellSpec:
        return CellSpec(**{"domain": self.domain, **self.small, **changes}).resolved()

    def member_data(self, s: CellSpec) -> tuple[dict, dict]:
        """P and U of a member from a fixed (untrained) base; copies of one draw per (base fields,
        paired count, U's size) -- what they depend on, as run_pack's data cache has it (sampling a
        particle P rolls out 4,096 episodes: the tests' costliest setup)."""
        adversary = method_weights(s).needs_adversary
        key = (s.base_key, s.paired, s.unpaired_size if adversary else None)
        if key not in _DATA:
            domain = get_domain(self.domain)
            base = domain.new_agents(s, 99)
            gen = torch.Generator().manual_seed(s.paired * 7919 + s.trial)
            paired = domain.paired(s, base, s.paired, gen) if s.paired else {}
            unpaired = domain.unpaired(s, base, s.unpaired_size, gen) if adversary else {}
            _DATA[key] = paired, unpaired
        return tuple({k: v.clone() for k, v in d.items()} for d in _DATA[key])

    def make_pack(self, specs: list[CellSpec], data: list[tuple[dict, dict]] | None = None):
        data = data or [self.member_data(s) for s in specs]
        domain = get_domain(self.domain)
        return trainer_class(self.domain)(specs, [d[0] for d in data], [d[1] for d in data],
                                          [domain.new_agents(s, s.seed_for("init")) for s in specs])

    def make_reference(self, s: CellSpec, data: tuple[dict, dict]) -> Trainer:
        """The reference (autograd) trainer of `s`, from the data and initial weights a pack gets."""
        domain = get_domain(self.domain)
        return Trainer(s, domain, domain.new_agents(s, s.seed_for("init")), data[0], data[1], method_weights(s))


# ---- the registered domains' cases ---------------------------------------------------------------
PARTICLES = PackCase(
    "particles",
    small=dict(particles_hidden=16, particles_message_dim=12, unpaired_size=64, train_steps=8),
    # members of one pack share the fields in SHARED, so the rollout length, discriminator shape and
    # disc_steps get packs of their own
    packs={
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
            dict(method="pc", paired=0, trial=1),  # nothing to learn: no optimiser step, as Trainer
        ],
        "pc-only": GENERIC_PACKS["pc-only"],
        "rollout-3": [dict(method="asp", paired=2, particles_rollout_len=3),
                      dict(method="osp", paired=1, trial=1, particles_rollout_len=3),
                      dict(method="pc", paired=3, particles_rollout_len=3)],
        "disc-2-layers": [dict(method="asp", paired=2, disc_layers=2, unpaired_batch=5),
                          dict(method="asp", paired=0, trial=1, disc_layers=2, unpaired_batch=5)],
        "disc-steps-3": [dict(method="asp", paired=2, disc_steps=3, unpaired_batch=6),
                         dict(method="osp", paired=2, trial=1, disc_steps=3, unpaired_batch=6)],
    },
    # a particle cell has no figure data, and its tiny cells are the costliest: the first six
    tiny_cells=TINY_CELLS[:6],
    # the envs' positions: the same actions were sampled
    pack_state=lambda pack, i: [pack.pos[i]],
    trainer_state=lambda t: [t.sp_state["pos"]] if t.sp_state else [],
)

LEVERS = PackCase(
    "levers",
    # replay of 40 games at batch 16: the buffer fills after 3 updates and its write position wraps
    small=dict(levers_hidden=8, batch_size=16, levers_replay_size=40, unpaired_size=60, disc_hidden=8,
               train_steps=8),
    packs={
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
        # ASP members first (as the trainer orders them): their rows are views, not gathers
        "asp-first": [dict(method="asp", paired=2, trial=1), dict(method="asp", paired=0, trial=2),
                      dict(method="osp", paired=5, trial=0), dict(method="pc", paired=1, trial=3)],
        "asp-only": [dict(method="asp", paired=3), dict(method="asp", paired=1, trial=1, unpaired_size=30)],
        "pc-only": GENERIC_PACKS["pc-only"],
        "disc-2-layers-2-steps": [dict(method="asp", paired=2, disc_layers=2, disc_steps=2, unpaired_batch=5),
                                  dict(method="osp", paired=1, trial=1, disc_layers=2, disc_steps=2,
                                       unpaired_batch=5),
                                  dict(method="asp", paired=0, trial=2, disc_layers=2, disc_steps=2,
                                       unpaired_batch=5)],
        "other-shapes": [dict(method="asp", paired=2, levers_num_ids=5, levers_hidden=6, batch_size=7,
                              levers_replay_size=20),
                         dict(method="osp", paired=3, trial=1, levers_num_ids=5, levers_hidden=6, batch_size=7,
                              levers_replay_size=20)],
    },
    # the replay buffer (its write position and fill level, the games, the levers pulled, the rewards)
    pack_state=lambda pack, i: [torch.tensor([pack.pos, pack.filled]), pack.r_ids[i], pack.r_lev[i], pack.r_rew[i]],
    trainer_state=lambda t: [torch.tensor([int(t.sp_state["pos"]), int(t.sp_state["filled"])]), t.sp_state["ids"],
                             t.sp_state["levers"], t.sp_state["reward"]] if t.sp_state else [],
)

VAE = PackCase(
    "vae",
    # a 64-unit VAE on 300 images (the tiny budget's), batch 16: every code path in milliseconds
    small=dict(vae_train_images=300, vae_hidden=64, vae_latent_dim=4, batch_size=16, unpaired_size=64,
               disc_hidden=16, train_steps=8),
    packs={
        # every per-member knob: reconstruction loss, KL weight, adversary input, paired reduction,
        # training images, besides the generic ones
        "mixed": [
            dict(method="asp", paired=4, trial=0),
            dict(method="pc", paired=4, trial=0),
            dict(method="osp", paired=0, trial=1),
            dict(method="osp", paired=5, trial=2, lr=2e-3, vae_recon_loss="mse", vae_kl_weight=0.5),
            dict(method="asp", paired=0, trial=1, unpaired_size=40, disc_lr=3e-3, vae_adversary_input="z"),
            dict(method="asp", paired=3, trial=2, adversary_loss="non_saturating", lambda_unpaired=0.3,
                 vae_paired_reduction="mean", vae_recon_loss="mse"),
            dict(method="asp", paired=3, trial=0, lambda_unpaired_schedule="warmup", lambda_schedule_frac=0.5,
                 vae_train_images=200),
            dict(method="asp", paired=2, trial=3, lambda_unpaired_schedule="anneal", lambda_schedule_frac=0.5,
                 lambda_paired=0.3, vae_adversary_input="z"),
            dict(method="pc", paired=0, trial=1),  # nothing to learn: no optimiser step, as Trainer
            dict(method="osp", paired=2, trial=4, lambda_paired=0.0),  # paired data with weight 0: no paired term
        ],
        # ASP members first (as the trainer orders them): their rows are views, not gathers
        "asp-first": [dict(method="asp", paired=2, trial=1, vae_adversary_input="z"),
                      dict(method="asp", paired=0, trial=2, adversary_loss="non_saturating"),
                      dict(method="osp", paired=5, trial=0), dict(method="pc", paired=1, trial=3)],
        "pc-only": GENERIC_PACKS["pc-only"],
        "disc-1-layer-2-steps": [dict(method="asp", paired=2, disc_layers=1, disc_steps=2, unpaired_batch=5),
                                 dict(method="osp", paired=1, trial=1, disc_layers=1, disc_steps=2,
                                      unpaired_batch=5),
                                 dict(method="asp", paired=0, trial=2, disc_layers=1, disc_steps=2,
                                      unpaired_batch=5, vae_adversary_input="z")],
        "other-shapes": [dict(method="asp", paired=2, vae_latent_dim=2, vae_hidden=16, batch_size=7),
                         dict(method="osp", paired=3, trial=1, vae_latent_dim=2, vae_hidden=16, batch_size=7,
                              vae_recon_loss="mse")],
    },
    # an ASP cell on sampled z beside one on μ of the same trial and paired count: their U differ
    tiny_cells=TINY_CELLS + [dict(method="asp", paired=3, trial=0, vae_adversary_input="z")],
)

CASES = {case.domain: case for case in (PARTICLES, LEVERS, VAE)}


def case_for(domain: str) -> PackCase:
    """The domain's case; a registered domain without one gets the generic packs at its tiny budget."""
    return CASES.get(domain) or PackCase(domain, small={**TINY[domain], "train_steps": 8})
