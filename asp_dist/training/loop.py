"""What the cell pipeline (asp_dist.training.pipeline.run_unit: a cell, a pack) uses besides its trainer:
phase timers, the learning curve's probe and the loop that trains to the end.

    PhaseTimer    wall and CPU seconds per phase (base, data, train, eval): the row's time_* columns
    make_probe    a cheap evaluation against the base for the learning curve
    train_to_end  train_step() until the last update, with progress and checkpoints
"""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Callable, Iterator

import torch

from asp_dist.core.contract import ProgressFn
from asp_dist.spec import CellSpec
from asp_dist.training.bases import BaseModel
from asp_dist.training.row import PHASES


class PhaseTimer:
    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)

    def carry(self, seconds: dict[str, float]) -> None:
        """Add the phase seconds of a checkpoint's earlier run (its "timings")."""
        for name, value in seconds.items():
            self.seconds[name] += value

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


def make_probe(spec: CellSpec, domain, base: BaseModel, agents: torch.nn.Module):
    """A cheap evaluation for the learning curve: the domain's own, on a tenth of eval_episodes,
    with a generator of its own so that probing never changes what is trained."""
    small = spec.replace(eval_episodes=max(1, spec.eval_episodes // 10))

    def probe(step: int) -> dict[str, float]:
        with torch.no_grad():
            return domain.evaluate(small, base.agents, agents, torch.Generator().manual_seed(spec.seed_for("eval") + step))

    return probe


def train_to_end(trainer, steps: int, progress: ProgressFn | None, save_state: Callable[[], None] | None,
                 checkpoint_every_s: float, checkpoint_every_steps: int | None,
                 live: Callable[[], None] | None = None) -> None:
    """Run trainer.train_step() until `steps` updates: progress (and `live`, which passes on the curve
    points closed since its last call) every 1 % of them and once at the end, and save_state (when
    given) every `checkpoint_every_steps` updates, or every `checkpoint_every_s` seconds without a
    step interval -- never after the last update. Stops early once every member has failed (frozen: a
    diverged lone cell has nothing left to train), looked at every 1 %. One loop for a cell and for a pack."""
    report_every = max(1, steps // 100)
    last_save = time.monotonic()
    while trainer.step < steps:
        trainer.train_step()
        if trainer.step % report_every == 0 or trainer.step == steps:
            if progress is not None:
                progress("train", trainer.step, steps, {})
            if live is not None:
                live()
            if all(m.failed for m in trainer.members):
                break
        if save_state is not None and trainer.step < steps:
            due = (trainer.step % checkpoint_every_steps == 0) if checkpoint_every_steps else \
                (time.monotonic() - last_save >= checkpoint_every_s)
            if due:
                save_state()
                last_save = time.monotonic()
    if live is not None:
        live()
