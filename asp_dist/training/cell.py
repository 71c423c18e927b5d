"""run_cell: one (domain, method, paired, trial) cell end to end, returning one result row.

Pure PyTorch, no Ray: the sweep service wraps this, tests call it directly. Phases:

    base   train (or receive) the base convention, retrying until it meets the domain's bar
    data   sample the paired set P and the unpaired set U from the base
    train  train new agents with the method's loss, L = w_sp·L_sp + λ0·L_p + λ1·L_u
    eval   mixed teams (Eq. 1), both directions, self-play of the new agents and of the base

The trainer is chosen per cell (choose_trainer): a particle or lever cell whose knobs its domain's
packed trainer implements trains as a one-member pack of it (asp_dist.training.packed.single), a VAE
cell on its one-pass trainer (asp_dist.training.fast), every other cell on the reference Trainer
(asp_dist.training.trainer: autograd). The full training
state can be checkpointed at any step and restored; a restored run gives the same row as an
uninterrupted one (all randomness flows through saved generators).
"""

from __future__ import annotations

from typing import Any, Callable

import torch

from asp_dist.domains import get_domain
from asp_dist.domains.contract import Domain, ProgressFn, Tensors
from asp_dist.spec import CellSpec
from asp_dist.training import packed
from asp_dist.training.bases import BaseModel, train_accepted_base
from asp_dist.training.fast import fast_trainer
from asp_dist.training.loop import PhaseTimer, make_probe, train_to_end
from asp_dist.training.methods import LossWeights, method_weights
from asp_dist.training.packed.single import PackOfOne
from asp_dist.training.row import build_row
from asp_dist.training.trainer import Trainer

# 2: the checkpoint names its trainer's engine (version 1 did not).
CHECKPOINT_VERSION = 2

Checkpoint = Callable[[dict], None]


def run_cell(spec: CellSpec, *, base: BaseModel | None = None, progress: ProgressFn | None = None,
             checkpoint: Checkpoint | None = None, restore: dict | None = None,
             checkpoint_every_steps: int | None = None, checkpoint_every_s: float = 30.0,
             curve: list[dict[str, float]] | None = None) -> dict[str, Any]:
    """Run one cell and return its result row (a flat dict of scalars and strings).

    base        a trained base to reuse (else trained here, deterministically from the spec)
    progress    progress(phase, done, total, info), called about 100 times during training
    checkpoint  called with the full training state every `checkpoint_every_steps` updates, or
                every `checkpoint_every_s` seconds when no step interval is given
    restore     a state previously passed to `checkpoint`: training continues from it. A state of
                another cell is refused (ValueError); a state of another engine than the one that
                trains this cell now (made by older code: checkpoint_engine) is not restored, and
                the cell starts over
    curve       a list to fill with the cell's learning curve: ~50 points (dicts with "step",
                loss terms, discriminator accuracy and D(fake), and at ~10 of them "probe_*"
                metrics: the domain's evaluation against the base on a tenth of eval_episodes)
    """
    spec = spec.resolved()
    domain = get_domain(spec.domain)
    if restore is not None and restore.get("cell_id") != spec.cell_id:
        raise ValueError(f"checkpoint belongs to cell {restore.get('cell_id')}, not {spec.cell_id}")
    timer = PhaseTimer()
    base_reused = base is not None
    if base is None:
        with timer.phase("base"):
            base = train_accepted_base(spec, progress)
    elif base.key != spec.base_key:
        raise ValueError(f"base {base.key} was trained for other settings than this cell's ({spec.base_key})")

    weights = method_weights(spec)
    with timer.phase("data"):
        data_gen = torch.Generator().manual_seed(spec.seed_for("data"))
        paired = domain.paired(spec, base.agents, spec.paired, data_gen) if spec.paired > 0 else {}
        unpaired = domain.unpaired(spec, base.agents, spec.unpaired_size, data_gen) if weights.needs_adversary else {}
        agents = domain.new_agents(spec, spec.seed_for("init"))
        trainer = choose_trainer(spec, domain, agents, paired, unpaired, weights)
    if curve is not None:
        trainer.probe = make_probe(spec, domain, base, agents)
    if restore is not None and checkpoint_engine(restore) != trainer.engine:
        restore = None  # its state would not load into this trainer: start over
    if restore is not None:
        trainer.load_state_dict(restore["trainer"])
        timer.carry(restore["timings"])
    resumed_from = trainer.step if restore is not None else None

    def save_state() -> None:
        checkpoint({"version": CHECKPOINT_VERSION, "cell_id": spec.cell_id, "engine": trainer.engine,
                    "trainer": trainer.state_dict(), "timings": dict(timer.seconds)})

    with timer.phase("train"):
        train_to_end(trainer, spec.train_steps, progress, save_state if checkpoint is not None else None,
                     checkpoint_every_s, checkpoint_every_steps)

    with timer.phase("eval"):
        agents.eval()
        with torch.no_grad():
            metrics = domain.evaluate(spec, base.agents, agents, torch.Generator().manual_seed(spec.seed_for("eval")))
        figure = domain.figure_data(spec, base.agents, agents) if spec.record_figure_data else None
    if progress is not None:
        progress("eval", 1, 1, {"mixed": metrics["mixed"]})

    if curve is not None:
        curve.extend(trainer.curve)
    return build_row(spec, domain, base, base_reused=base_reused, metrics=metrics, losses=trainer.loss_columns(),
                     figure=figure, timings=timer.columns(), resumed_from=resumed_from)


def choose_trainer(spec: CellSpec, domain: Domain, agents: torch.nn.Module, paired: Tensors, unpaired: Tensors,
                   weights: LossWeights) -> Trainer | PackOfOne:
    """The trainer of one cell, chosen per cell (not by the domain): a one-member pack of the domain's
    packed trainer where the domain trains its single cells so and the trainer implements every
    knob value of the spec (asp_dist.training.packed.single_cell_trainer; today lever cells and
    particle cells without the replay buffer or the speaker-only paired loss), else the domain's fast trainer
    (asp_dist.training.fast; today the VAE's), else the reference Trainer."""
    single = packed.single_cell_trainer(spec, agents, paired, unpaired)
    if single is not None:
        return single
    cls = fast_trainer(spec) or Trainer
    return cls(spec, domain, agents, paired, unpaired, weights)


def checkpoint_engine(state: dict) -> str:
    """The engine (the trainer's `engine`) whose training state a run_cell checkpoint holds. Version 1
    checkpoints did not say: they came from the reference Trainer ("autograd", a torch.optim state
    with its param_groups) or from the retired single-cell particle kernel ("fused-particles")."""
    if "engine" in state:
        return state["engine"]
    opt = state["trainer"].get("opt")
    return "autograd" if isinstance(opt, dict) and "param_groups" in opt else "fused-particles"
