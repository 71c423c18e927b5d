"""What the packed-training tests need to know of a domain: a small spec, packs to check member by
member, and where a member's self-play state lives (in a pack and in the reference Trainer).

tests/test_packed.py runs every check for every registered domain with a packed trainer (one whose
class says `packs`, asp_dist.training.engines): such a domain is tested without a line here (with GENERIC_PACKS and its tiny budget),
and a case below adds the packs and state that make its checks sharper. Domain-specific checks are
in tests/test_packed_<domain>.py.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Callable

import torch
from budgets import TINY

from asp_dist.core.registry import DOMAINS as REGISTRY
from asp_dist.core.registry import get_domain
from asp_dist.domains.levers import AGENTS
from asp_dist.knobs import BASE_ONLY
from asp_dist.spec import CellSpec
from asp_dist.training.engines import lone_trainer
from asp_dist.training.methods import method_weights
from asp_dist.training.trainer import Trainer

# Every registered domain with a packed trainer (the plugin's included, should it bring one).
DOMAINS = sorted(name for name in REGISTRY if any(t.packs for t in get_domain(name).trainers))

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
    """The domain's packed trainer: the first of its trainers that packs."""
    return next(t for t in get_domain(domain).trainers if t.packs)


def packed_module(domain: str) -> ModuleType:
    """The module of the domain's packed trainer (its CHUNK, SHARED, ... constants)."""
    return sys.modules[trainer_class(domain).__module__]


def lone(spec: CellSpec, agents: torch.nn.Module, paired, unpaired):
    """The trainer run_cell trains `spec` on (asp_dist.training.engines.lone_trainer), built as the cell
    pipeline builds it: a one-member pack, the VAE's one-pass trainer or the reference Trainer."""
    return lone_trainer(spec).build([spec.resolved()], [paired], [unpaired], [agents])


# ---- tolerances: float32 rounding ----------------------------------------------------------------
# A packed trainer computes the reference's update in another order (batched matmuls, hand-derived
# backward passes, fused Adam), and each CPU's kernels (AVX-512, AVX2, scalar: ATEN_CPU_CAPABILITY)
# order sums their own way, so the two agree up to float32 rounding only. A gradient element is a sum
# over the batch rows of products that each pass back through a layer's width: rows × width terms
# at most, and a float32 sum of n terms is within n·u·Σ|terms| of exact (u = 2**-24, the unit
# roundoff). float32_tol takes max|g| for Σ|terms|; ROUNDING_C covers that ratio and the drift of
# the point each gradient is taken at after earlier steps. Parameters: AdamDrift (Adam's step is
# lr·m̂/(√v̂+ε), so a gradient difference moves it in proportion to lr).
# Measured 2026-12-01 on an Intel Xeon (AVX-512; ATEN_CPU_CAPABILITY unset, avx2 and default, the
# four test_packed*.py files): gradients at most 0.40·n·u·max|g| (a particle OSP cell under
# "default"), hence ROUNDING_C = 4, a safety factor of 10; agents' parameters at most 0.92 of
# AdamDrift's bound (a parameter one ulp apart after the first step), hence DRIFT_SAFETY = 2;
# discriminators at most 0.03 of theirs. They still fail on a real mismatch: the particle trainer's
# speaker gradient scaled by 1.01 (or 1.001) fails 11 (10) of 11 single-cell cases, an Adam learning
# rate off by 1% fails every single-cell case at its first update.
U32 = 2.0 ** -24
ROUNDING_C = 4.0
BETAS, EPS = (0.9, 0.999), 1e-8  # torch.optim.Adam's defaults: every optimiser here
DRIFT_SAFETY = 2.0  # on AdamDrift's first-order bound


def float32_tol(expected: torch.Tensor, terms: int, c: float = ROUNDING_C) -> float:
    """Absolute tolerance for `expected` recomputed in float32 in another order: c·n·u·max|expected|
    (n = `terms`, the longest chain of accumulated terms behind an element). 0 for an all-zero
    `expected` (no update): then the other computation must give exact zeros too."""
    return c * terms * U32 * float(expected.abs().max()) if expected.numel() else 0.0


def adam_ratio_bound(t: int) -> float:
    """R_t ≥ |m̂|/√v̂ after t Adam steps (Cauchy-Schwarz over the two moving averages' weights): 1
    at the first step, 1.03 at 8, 1.76 at 60."""
    b1, b2 = BETAS
    return sum(((1 - b1) * b1 ** k / (1 - b1 ** t)) ** 2 / ((1 - b2) * b2 ** k / (1 - b2 ** t))
               for k in range(t)) ** 0.5


class AdamDrift:
    """Element-wise bound on how far two copies of parameters get apart when Adam steps them from one
    start with gradients that differ by `err` (element-wise, as measured, or a float32_tol bound).
    Adam's step is lr·m̂/(√v̂+ε); m̂ and √v̂ are weighted means over the steps (of g, and an L2 norm of
    g), so each moves by at most the largest gradient difference so far, e, and the step by at most
    lr·(1+R)·e/(√v̂+ε) (first order; R = adam_ratio_bound), never more than 2·lr·R. Each copy also
    rounds its new parameter (≤ u·|θ|) and its step (a few u of it). So the bound scales with lr: a
    small part of a step where the gradient is well above its difference, up to a whole step where
    it is not. √v̂ is read from an optimiser's state after the step (`adam_sqrt_v`, `stacked_sqrt_v`)."""

    def __init__(self, lr: float):
        self.lr, self.err, self.tol = lr, torch.zeros(()), torch.zeros(())

    def add(self, sqrt_v: torch.Tensor, t: int, theta: torch.Tensor, *, err: torch.Tensor | float,
            steps: int = 1) -> AdamDrift:
        """Account for `steps` Adam steps (the t-th and those just before it)."""
        self.err = torch.maximum(self.err, torch.as_tensor(err, dtype=torch.float32))
        r = adam_ratio_bound(t)
        step = self.lr * (torch.clamp((1 + r) * self.err / (sqrt_v + EPS), max=2 * r) + 8 * U32 * r)
        self.tol = self.tol + steps * (step + 2 * U32 * theta.abs())
        return self

    def close(self, got: torch.Tensor, expected: torch.Tensor) -> bool:
        return bool(((got - expected).abs() <= DRIFT_SAFETY * self.tol).all())


def disc_grad_tol(s: CellSpec, discs, sqrt_v: torch.Tensor, t: int) -> float:
    """float32_tol of a member's discriminators' gradient, which the tests do not see (the reference
    adds the model loss's to it): n = the real and fake rows (2·unpaired_batch) × the discriminators'
    widest layer, the scale bounded from Adam's √v̂, |g_t| ≤ √v̂·√((1-β2^t)/(1-β2))."""
    terms = 2 * s.unpaired_batch * max(max(p.shape) for d in discs for p in d.parameters())
    return float32_tol(sqrt_v * ((1 - BETAS[1] ** t) / (1 - BETAS[1])) ** 0.5, terms) if t else 0.0


def adam_sqrt_v(module: torch.nn.Module, *optimizers: torch.optim.Optimizer) -> tuple[torch.Tensor, int]:
    """Adam's bias-corrected √v̂ of `module`'s parameters (flat, in parameters() order; 0 before their
    first step) from the torch optimisers holding them, and their step count."""
    states = {p: st for opt in optimizers for p, st in opt.state.items()}
    out, t = [torch.zeros(0)], 0
    for p in module.parameters():
        st = states.get(p, {})
        if "exp_avg_sq" in st:
            t = int(st["step"])
            out.append((st["exp_avg_sq"] / (1 - BETAS[1] ** t)).sqrt().reshape(-1))
        else:
            out.append(torch.zeros(p.numel()))
    return torch.cat(out), t


def stacked_sqrt_v(net, rows: list[int]) -> tuple[torch.Tensor, int]:
    """The same from a pack's StackedParams, for its member rows `rows` (flat, concatenated)."""
    t = int(net.steps)
    v = torch.cat([torch.zeros(0)] + [net.member_flat(k, net.exp_avg_sq) for k in rows])
    return (v / (1 - BETAS[1] ** t)).sqrt() if t else v, t


def _rows(s: CellSpec) -> int:
    """Rows of the largest batch an update reduces over (self-play, paired or unpaired)."""
    return max(s.batch_size, s.unpaired_batch or 0, s.paired)


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
    rows: Callable[[CellSpec], int] = _rows  # rows of the largest batch of an update (grad_terms)
    # two mates that give a pack of the same shapes beside an OSP member (paired 3): its update must not see
    # which one it has (a PC mate rides along in the self-play rows of the particle and lever packs)
    same_shape_mates: tuple[dict, dict] = (
        dict(method="pc", paired=3, trial=1),
        dict(method="asp", paired=2, trial=2, adversary_loss="non_saturating", unpaired_size=50))

    def grad_terms(self, s: CellSpec, agents: torch.nn.Module) -> int:
        """n of float32_tol for a member's gradients: batch rows × the widest layer its gradient
        passes (the agents' widest weight dimension, the discriminator's width when it has one)."""
        width = max(max(p.shape) for p in agents.parameters())
        if method_weights(s).needs_adversary:
            width = max(width, s.disc_hidden)
        return self.rows(s) * width

    def spec(self, **changes) -> CellSpec:
        return CellSpec(**{"domain": self.domain, **self.small, **changes}).resolved()

    @property
    def all_packs(self) -> dict[str, list[dict]]:
        """The packs checked member by member: the case's own, then those generated from its trainer's
        `implements` (knob_packs)."""
        return {**self.packs, **knob_packs(self)}

    def member_data(self, s: CellSpec) -> tuple[dict, dict]:
        """P and U of a member from a fixed (untrained) base; copies of one draw per (base fields,
        paired count, U's size, the domain's paired_fields and unpaired_fields) -- what they depend on, as run_pack's data cache has it (sampling a
        particle P rolls out 4,096 episodes: the tests' costliest setup)."""
        adversary = method_weights(s).needs_adversary
        domain = get_domain(self.domain)
        key = (s.base_key, s.paired, s.unpaired_size if adversary else None,
               *(getattr(s, f) for f in (*domain.paired_fields, *domain.unpaired_fields)))
        if key not in _DATA:
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
    rows=lambda s: max(s.batch_size * s.particles_rollout_len, s.unpaired_batch, s.paired),  # envs × steps
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
    # a DQN update: batch_size fresh and batch_size replayed games, AGENTS seats each
    rows=lambda s: max(2 * s.batch_size * AGENTS, s.unpaired_batch, s.paired * AGENTS),
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

# A VMAS pack plays the self-play members' worlds only (a PC member has none), so the mates of one shape are
# two that play; smoke-sized otherwise, as a plugin's generic case.
VMAS = [PackCase(name, small={**get_domain(name).smoke, "train_steps": 8},
                 same_shape_mates=(dict(method="osp", paired=3, trial=1),
                                   dict(method="asp", paired=2, trial=2, adversary_loss="non_saturating",
                                        unpaired_size=50)))
        for name in ("vmas_speaker_listener", "vmas_reference") if name in REGISTRY]

CASES = {case.domain: case for case in (PARTICLES, LEVERS, VAE, *VMAS)}


def other_value(value: Any) -> Any:
    """A value of a knob's type other than `value`, near it: half a float, the other bool, half an int
    (or one more, for 0 to 2)."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1 if value <= 2 else value // 2
    return value / 2


def knob_packs(case: PackCase) -> dict[str, list[dict]]:
    """Packs generated from what the domain's packed trainer says it implements (its `implements`) and the
    knobs' metadata, so that a knob the trainer declares is checked against the reference without a line
    here: "knobs", one ASP member per per-member knob and value (each value a tuple lists, each choice
    of a text knob, another value of any other; defaults included once, as the first member), and
    "<knob>" for each knob the pack shares (a pack key field), two members at another value. BASE_ONLY
    knobs shape the base alone: nothing of the trainer's to check."""
    trainer, small = trainer_class(case.domain), case.spec()
    knobs = {k.name: k for k in get_domain(case.domain).knobs}
    members, shared = [dict(method="asp", paired=2, trial=0)], {}
    for name, allowed in trainer.implements.items():
        if allowed is BASE_ONLY:
            continue
        current = getattr(small, name)
        if isinstance(allowed, tuple):
            values = allowed
        elif name in knobs and knobs[name].choices:
            values = knobs[name].choices
        else:
            values = (other_value(current),)
        values = [v for v in values if v != current]
        if name in trainer.shared:
            for v in values[:1]:
                shared[f"knob-{name}"] = [dict(method="asp", paired=2, **{name: v}),
                                          dict(method="osp", paired=1, trial=1, **{name: v})]
        else:
            members += [dict(method="asp", paired=2, trial=len(members) % 3, **{name: v}) for v in values]
    return {"knobs": members, **shared}


def case_for(domain: str) -> PackCase:
    """The domain's case; a registered domain without one gets the generic packs at its tiny budget."""
    small = TINY[domain] if domain in TINY else get_domain(domain).smoke  # a plugin's: its own smoke values
    return CASES.get(domain) or PackCase(domain, small={**small, "train_steps": 8})
