"""run_cell: one (domain, method, paired, trial) cell end to end, returning one result row.

Pure PyTorch, no Ray: the sweep service wraps this, tests call it directly. Phases:

    base   train (or receive) the base convention, retrying until it meets the domain's bar
    data   sample the paired set P and the unpaired set U from the base
    train  train new agents with the method's loss, L = w_sp·L_sp + λ0·L_p + λ1·L_u
    eval   mixed teams (Eq. 1), both directions, self-play of the new agents and of the base

The full training state can be checkpointed at any step and restored; a restored run gives
the same row as an uninterrupted one (all randomness flows through saved generators).
"""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Any, Callable, Iterator

import torch

from asp_dist.domains import get_domain
from asp_dist.domains.contract import ProgressFn
from asp_dist.spec import CellSpec
from asp_dist.training.bases import BaseModel, train_accepted_base
from asp_dist.training.fast import choose_trainer
from asp_dist.training.methods import method_weights
from asp_dist.training.row import PHASES, build_row

CHECKPOINT_VERSION = 1

Checkpoint = Callable[[dict], None]


class PhaseTimer:
    def __init__(self, carried: dict[str, float] | None = None):
        self.seconds: dict[str, float] = defaultdict(float, carried or {})

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.seconds[f"time_{name}_wall_s"] += time.perf_counter() - wall
            self.seconds[f"time_{name}_cpu_s"] += time.process_time() - cpu

    def columns(self) -> dict[str, float]:
        out = {f"time_{p}_{k}": float(self.seconds.get(f"time_{p}_{k}", 0.0)) for p in PHASES for k in ("wall_s", "cpu_s")}
        out["time_total_wall_s"] = sum(out[f"time_{p}_wall_s"] for p in PHASES)
        out["time_total_cpu_s"] = sum(out[f"time_{p}_cpu_s"] for p in PHASES)
        return out


def run_cell(spec: CellSpec, *, base: BaseModel | None = None, progress: ProgressFn | None = None,
             checkpoint: Checkpoint | None = None, restore: dict | None = None,
             checkpoint_every_steps: int | None = None, checkpoint_every_s: float = 30.0,
             curve: list[dict[str, float]] | None = None) -> dict[str, Any]:
    """Run one cell and return its result row (a flat dict of scalars and strings).

    base        a trained base to reuse (else trained here, deterministically from the spec)
    progress    progress(phase, done, total, info), called about 100 times during training
    checkpoint  called with the full training state every `checkpoint_every_steps` updates, or
                every `checkpoint_every_s` seconds when no step interval is given
    restore     a state previously passed to `checkpoint`: training continues from it
    curve       a list to fill with the cell's learning curve: ~50 points (dicts with "step",
                loss terms, discriminator accuracy and D(fake), and at ~10 of them "probe_*"
                metrics: the domain's evaluation against the base on a tenth of eval_episodes)
    """
    spec = spec.resolved()
    domain = get_domain(spec.domain)
    if restore is not None and restore.get("cell_id") != spec.cell_id:
        raise ValueError(f"checkpoint belongs to cell {restore.get('cell_id')}, not {spec.cell_id}")
    timer = PhaseTimer(restore["timings"] if restore else None)
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
    if restore is not None:
        trainer.load_state_dict(restore["trainer"])
    resumed_from = trainer.step if restore is not None else None

    def save_state() -> None:
        checkpoint({"version": CHECKPOINT_VERSION, "cell_id": spec.cell_id, "trainer": trainer.state_dict(),
                    "timings": dict(timer.seconds)})

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


def make_probe(spec: CellSpec, domain, base: BaseModel, agents: torch.nn.Module):
    """A cheap evaluation for the learning curve: the domain's own, on a tenth of eval_episodes,
    with a generator of its own so that probing never changes what is trained."""
    small = spec.replace(eval_episodes=max(1, spec.eval_episodes // 10))

    def probe(step: int) -> dict[str, float]:
        with torch.no_grad():
            return domain.evaluate(small, base.agents, agents, torch.Generator().manual_seed(spec.seed_for("eval") + step))

    return probe


def train_to_end(trainer, steps: int, progress: ProgressFn | None, save_state: Callable[[], None] | None,
                 checkpoint_every_s: float, checkpoint_every_steps: int | None) -> None:
    """Run trainer.train_step() until `steps` updates: progress every 1 % of them, and save_state (when
    given) every `checkpoint_every_steps` updates, or every `checkpoint_every_s` seconds without a
    step interval -- never after the last update. One loop for a cell and for a pack."""
    report_every = max(1, steps // 100)
    last_save = time.monotonic()
    while trainer.step < steps:
        trainer.train_step()
        if progress is not None and (trainer.step % report_every == 0 or trainer.step == steps):
            progress("train", trainer.step, steps, {})
        if save_state is not None and trainer.step < steps:
            due = (trainer.step % checkpoint_every_steps == 0) if checkpoint_every_steps else \
                (time.monotonic() - last_save >= checkpoint_every_s)
            if due:
                save_state()
                last_save = time.monotonic()
