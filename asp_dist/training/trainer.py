"""The training loop of one cell: L = w_sp·L_sp + λ0·L_p + λ1·L_u, one update at a time.

The domain supplies the pieces (self-play step, paired loss, convention outputs); the method
supplies the weights (asp_dist.training.methods); the adversaries (asp_dist.training.adversary)
are stepped once per update before the model's gradient. The whole state, generator included,
is a state_dict, so a restored trainer continues bit for bit.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import torch

from asp_dist.core.contract import Domain, SelfPlayOut, Tensors
from asp_dist.core.registry import get_domain
from asp_dist.spec import CellSpec
from asp_dist.training.adversary import Adversaries
from asp_dist.training.methods import LossWeights, compose_loss, lambda_factor, method_weights
from asp_dist.training.records import CURVE_POINTS, PROBE_EVERY, TERMS, Records, member_terms  # noqa: F401


class Trainer:
    """The training loop shared by every domain and method (the reference path: autograd and
    torch.optim.Adam). It trains every cell alone that no faster trainer of its domain implements
    (asp_dist.training.engines: a particle or lever cell trains as a one-member pack of its domain's
    hand-derived packed trainer, a VAE cell on a subclass that computes the same update in one pass);
    those trainers are tested against this one. It is its own one member for the cell pipeline
    (asp_dist.training.pipeline.UnitTrainer): `members`, `build`, `loss_columns(0)`."""

    # Capabilities (asp_dist.training.engines): trains one cell at a time, any cell.
    engine = "autograd"  # names the format of state_dict() in checkpoints
    packs = False
    lone = True
    in_sweeps = True
    error: str | None = None  # the reference does not freeze a cell: a non-finite loss fails where it arises
    failed = False

    def __init__(self, spec: CellSpec, domain: Domain, agents: torch.nn.Module, paired: Tensors,
                 unpaired: Tensors, weights: LossWeights):
        self.spec, self.domain, self.agents = spec, domain, agents
        self.paired, self.unpaired, self.weights = paired, unpaired, weights
        self.opt = self.make_optimizer(agents.parameters(), lr=spec.lr)
        self.gen = torch.Generator().manual_seed(spec.seed_for("train"))
        self.adversaries = None
        if weights.needs_adversary:
            self.adversaries = Adversaries(domain.channel_dims(spec), spec.disc_hidden, spec.disc_layers,
                                           spec.disc_lr, seed=spec.seed_for("init") + 1000,
                                           make_optimizer=self.make_optimizer)
        self.sp_state = domain.init_self_play(spec, agents, self.gen) if weights.needs_self_play else {}
        self.step = 0
        # Diagnostics (asp_dist.training.records, as a packed trainer keeps them for each member): the mean
        # of each loss term over the last 10 % of training (the row's loss_* columns) and the learning
        # curve. The paired loss is computed, so recorded, whenever it has a weight.
        self.records = Records([member_terms(weights, int(weights.paired != 0.0))], spec.train_steps)
        self.curve: list[dict[str, float]] = []
        # probe(step) -> metrics: a cheap evaluation against the base, set by run_cell; it draws
        # from its own generator, so probing never changes what is trained.
        self.probe: Callable[[int], dict[str, float]] | None = None

    @classmethod
    def supports(cls, spec: CellSpec) -> bool:
        """Whether this trainer implements every knob value of `spec` (the reference does)."""
        return True

    @classmethod
    def build(cls, specs: Sequence[CellSpec], paired: Sequence[Tensors], unpaired: Sequence[Tensors],
              agents: Sequence[torch.nn.Module]) -> Trainer:
        """The trainer of one cell, from the pipeline's per-member lists (of one entry)."""
        if len(specs) != 1:
            raise ValueError(f"{cls.__name__} trains one cell at a time, got {len(specs)}")
        spec = specs[0]
        return cls(spec, get_domain(spec.domain), agents[0], paired[0], unpaired[0], method_weights(spec))

    @staticmethod
    def member_order(specs: Sequence[CellSpec]) -> list[int]:
        return list(range(len(specs)))

    @property
    def members(self) -> tuple[Trainer]:
        return (self,)

    @property
    def train_steps(self) -> int:
        return self.spec.train_steps

    def make_optimizer(self, params, lr: float):
        """The optimiser of the new agents and of each discriminator."""
        return torch.optim.Adam(params, lr=lr, **self.domain.optimizer_options)

    def weights_now(self) -> LossWeights:
        """The loss weights of the current update: λ1 follows lambda_unpaired_schedule."""
        w = self.weights
        factor = lambda_factor(self.spec, self.step)
        return w if factor == 1.0 else LossWeights(w.self_play, w.paired, w.unpaired * factor)

    def recording(self) -> bool:
        """Whether this update's loss values are recorded (final window or a curve window)."""
        return self.records.recording(self.step)

    def train_step(self) -> None:
        spec, w = self.spec, self.weights_now()
        record = self.recording()
        diagnostics: dict[str, float] | None = {} if record else None
        sp_out, paired_loss = self.model_terms(w)
        sp_loss = sp_out.loss if sp_out is not None else None
        unpaired_loss = disc_loss = None
        if self.adversaries is not None:
            fake = sp_out.outputs if sp_out is not None and sp_out.outputs else \
                self.domain.convention_outputs(spec, self.agents, spec.unpaired_batch, self.gen)
            for k in range(spec.disc_steps):
                real = {ch: u[torch.randint(len(u), (spec.unpaired_batch,), generator=self.gen)]
                        for ch, u in self.unpaired.items()}
                disc_loss = self.adversaries.step(real, fake, diagnostics if k == 0 else None)
            unpaired_loss = self.adversaries.model_loss(fake, spec.adversary_loss)
        total = compose_loss(w, sp_loss, paired_loss, unpaired_loss)
        self.opt.zero_grad(set_to_none=True)
        if total.requires_grad:
            total.backward()
            self.opt.step()
        if record:
            for name, value in (("self_play", sp_loss), ("paired", paired_loss), ("unpaired", unpaired_loss),
                                ("disc", disc_loss), ("total", total)):
                if value is not None:
                    diagnostics[name] = float(value.detach() if torch.is_tensor(value) else value)
            self.record(diagnostics)
        self.step += 1
        self.finish_curve_point()

    def model_terms(self, w: LossWeights) -> tuple[SelfPlayOut | None, torch.Tensor | None]:
        """This update's self-play step (None without self-play) and paired loss (None when λ0 = 0),
        the self-play step first: it draws from the trainer's generator."""
        sp_out = self.domain.self_play_step(self.spec, self.agents, self.sp_state, self.gen) if w.needs_self_play else None
        paired_loss = self.domain.paired_loss(self.spec, self.agents, self.paired) if w.paired != 0.0 else None
        return sp_out, paired_loss

    def record(self, values: dict[str, float]) -> None:
        """Add one recorded update's values (by TERMS name) to the records."""
        self.records.add(self.step, torch.tensor([[values.get(name, 0.0) for name in TERMS]], dtype=torch.float64))

    def finish_curve_point(self) -> None:
        """After update `step`, close the curve point that ends there (if one does)."""
        self.records.finish_point(self.step, self.members)

    def loss_columns(self, i: int = 0) -> dict[str, float | None]:
        """The row's loss_* columns (of member `i`, the only one: 0)."""
        return self.records.loss_columns(i)

    def state_dict(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "agents": self.agents.state_dict(),
            "opt": self.opt.state_dict(),
            "adversaries": self.adversaries.full_state() if self.adversaries is not None else None,
            "gen": self.gen.get_state(),
            "sp_state": {k: v.clone() for k, v in self.sp_state.items()},
            "records": self.records.state(),
            "curve": [dict(p) for p in self.curve],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.step = state["step"]
        self.agents.load_state_dict(state["agents"])
        self.opt.load_state_dict(state["opt"])
        if self.adversaries is not None:
            self.adversaries.load_full_state(state["adversaries"])
        # A saved optimiser state carries its param_groups' options; a state saved by older code
        # (the VAE before fused Adam) would switch today's options off for the rest of the cell.
        for opt in [self.opt, *(self.adversaries.optims.values() if self.adversaries is not None else ())]:
            for group in opt.param_groups:
                group.update(self.domain.optimizer_options)
        self.gen.set_state(state["gen"])
        self.sp_state = {k: v.clone() for k, v in state["sp_state"].items()}
        if "records" in state:
            self.records.load(state["records"])
        else:  # a state of older code: the sums by name
            self.records.load_single(state["loss_sums"], state.get("curve_sums", {}))
        self.curve = [dict(p) for p in state.get("curve", [])]
