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

import json
import platform
import socket
import subprocess
import time
from collections import defaultdict
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch

from asp_dist import __version__
from asp_dist.adversary import Adversaries
from asp_dist.bases import BaseModel, train_accepted_base
from asp_dist.domains import get_domain
from asp_dist.domains.base import Domain, Progress, Tensors
from asp_dist.methods import LossWeights, compose_loss, method_weights
from asp_dist.spec import CellSpec

PHASES = ("base", "data", "train", "eval")
CHECKPOINT_VERSION = 1
# Columns that legitimately differ between two runs of the same spec (time, place, resumption).
VOLATILE_COLUMNS = frozenset(
    [f"time_{p}_{k}" for p in PHASES + ("total",) for k in ("wall_s", "cpu_s")]
    + ["base_train_wall_s", "base_train_cpu_s", "node", "finished_at", "resumed_from_step", "base_reused"]
)

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


class Trainer:
    """The training loop shared by every domain and method."""

    def __init__(self, spec: CellSpec, domain: Domain, agents: torch.nn.Module, paired: Tensors,
                 unpaired: Tensors, weights: LossWeights):
        self.spec, self.domain, self.agents = spec, domain, agents
        self.paired, self.unpaired, self.weights = paired, unpaired, weights
        self.opt = torch.optim.Adam(agents.parameters(), lr=spec.lr, **domain.optimizer_options)
        self.gen = torch.Generator().manual_seed(spec.seed_for("train"))
        self.adversaries = None
        if weights.needs_adversary:
            self.adversaries = Adversaries(domain.channel_dims(spec), spec.disc_hidden, spec.disc_layers,
                                           spec.disc_lr, seed=spec.seed_for("init") + 1000,
                                           optimizer_options=domain.optimizer_options)
        self.sp_state = domain.init_self_play(spec, agents, self.gen) if weights.needs_self_play else {}
        self.step = 0
        # Diagnostics: mean of each loss term over the last 10 % of training.
        self.window_start = int(0.9 * spec.train_steps)
        self.loss_sums: dict[str, float] = defaultdict(float)

    def train_step(self) -> None:
        spec, w = self.spec, self.weights
        sp_loss = paired_loss = unpaired_loss = None
        sp_out = None
        if w.needs_self_play:
            sp_out = self.domain.self_play_step(spec, self.agents, self.sp_state, self.gen)
            sp_loss = sp_out.loss
        if w.paired != 0.0:
            paired_loss = self.domain.paired_loss(spec, self.agents, self.paired)
        disc_loss = None
        if self.adversaries is not None:
            fake = sp_out.outputs if sp_out is not None and sp_out.outputs else \
                self.domain.convention_outputs(spec, self.agents, spec.unpaired_batch, self.gen)
            real = {ch: u[torch.randint(len(u), (spec.unpaired_batch,), generator=self.gen)]
                    for ch, u in self.unpaired.items()}
            disc_loss = self.adversaries.step(real, fake)
            unpaired_loss = self.adversaries.model_loss(fake, spec.adversary_loss)
        total = compose_loss(w, sp_loss, paired_loss, unpaired_loss)
        self.opt.zero_grad(set_to_none=True)
        if total.requires_grad:
            total.backward()
            self.opt.step()
        if self.step >= self.window_start:
            for name, value in (("self_play", sp_loss), ("paired", paired_loss), ("unpaired", unpaired_loss),
                                ("disc", disc_loss), ("total", total)):
                if value is not None:
                    self.loss_sums[name] += float(value.detach() if torch.is_tensor(value) else value)
            self.loss_sums["_count"] += 1
        self.step += 1

    def loss_columns(self) -> dict[str, float | None]:
        n = self.loss_sums.get("_count", 0)
        return {f"loss_{k}": (self.loss_sums[k] / n if n and k in self.loss_sums else None)
                for k in ("self_play", "paired", "unpaired", "disc", "total")}

    def state_dict(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "agents": self.agents.state_dict(),
            "opt": self.opt.state_dict(),
            "adversaries": self.adversaries.full_state() if self.adversaries is not None else None,
            "gen": self.gen.get_state(),
            "sp_state": {k: v.clone() for k, v in self.sp_state.items()},
            "loss_sums": dict(self.loss_sums),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.step = state["step"]
        self.agents.load_state_dict(state["agents"])
        self.opt.load_state_dict(state["opt"])
        if self.adversaries is not None:
            self.adversaries.load_full_state(state["adversaries"])
        self.gen.set_state(state["gen"])
        self.sp_state = {k: v.clone() for k, v in state["sp_state"].items()}
        self.loss_sums = defaultdict(float, state["loss_sums"])


def run_cell(spec: CellSpec, *, base: BaseModel | None = None, progress: Progress | None = None,
             checkpoint: Checkpoint | None = None, restore: dict | None = None,
             checkpoint_every_steps: int | None = None, checkpoint_every_s: float = 30.0) -> dict[str, Any]:
    """Run one cell and return its result row (a flat dict of scalars and strings).

    base        a trained base to reuse (else trained here, deterministically from the spec)
    progress    progress(phase, done, total, info), called about 100 times during training
    checkpoint  called with the full training state every `checkpoint_every_steps` updates, or
                every `checkpoint_every_s` seconds when no step interval is given
    restore     a state previously passed to `checkpoint`: training continues from it
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
        trainer = domain.make_trainer(spec, agents, paired, unpaired, weights) \
            or Trainer(spec, domain, agents, paired, unpaired, weights)
    if restore is not None:
        trainer.load_state_dict(restore["trainer"])
    resumed_from = trainer.step if restore is not None else None

    def save_state() -> None:
        checkpoint({"version": CHECKPOINT_VERSION, "cell_id": spec.cell_id, "trainer": trainer.state_dict(),
                    "timings": dict(timer.seconds)})

    report_every = max(1, spec.train_steps // 100)
    last_save = time.monotonic()
    with timer.phase("train"):
        while trainer.step < spec.train_steps:
            trainer.train_step()
            if progress is not None and (trainer.step % report_every == 0 or trainer.step == spec.train_steps):
                progress("train", trainer.step, spec.train_steps, {})
            if checkpoint is not None and trainer.step < spec.train_steps:
                due = (trainer.step % checkpoint_every_steps == 0) if checkpoint_every_steps else \
                    (time.monotonic() - last_save >= checkpoint_every_s)
                if due:
                    save_state()
                    last_save = time.monotonic()

    with timer.phase("eval"):
        agents.eval()
        with torch.no_grad():
            metrics = domain.evaluate(spec, base.agents, agents, torch.Generator().manual_seed(spec.seed_for("eval")))
        figure = domain.figure_data(spec, base.agents, agents) if spec.record_figure_data else None
    if progress is not None:
        progress("eval", 1, 1, {"mixed": metrics["mixed"]})

    row: dict[str, Any] = spec.to_dict()
    row.update({"cell_id": spec.cell_id, "seed_init": spec.seed_for("init"), "seed_train": spec.seed_for("train")})
    row.update({k: v for k, v in base.meta().items() if k != "base_attempt_scores"})
    row["base_attempt_scores"] = json.dumps(base.meta()["base_attempt_scores"])
    row.update({"base_reused": base_reused, "base_train_wall_s": base.train_wall_s, "base_train_cpu_s": base.train_cpu_s})
    row.update({f"eval_{k}": float(v) for k, v in metrics.items()})
    row["eval_mixed_higher_is_better"] = domain.metrics["mixed"].higher_is_better
    row["metric_directions"] = json.dumps({k: ("higher" if m.higher_is_better else "lower")
                                           for k, m in domain.metrics.items()}, sort_keys=True)
    row.update(trainer.loss_columns())
    row["figure_data"] = json.dumps(figure) if figure is not None else None
    row.update(timer.columns())
    row.update(environment_columns())
    row["resumed_from_step"] = resumed_from
    return row


def environment_columns() -> dict[str, Any]:
    return {
        "node": socket.gethostname(),
        "finished_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "asp_dist_version": __version__,
        "torch_version": torch.__version__,
        "numpy_version": np.__version__,
        "python_version": platform.python_version(),
        "code_revision": code_revision(),
    }


_REVISION: str | None = None


def code_revision() -> str:
    """Git commit of the asp_dist source (with '+dirty' for local changes), or 'unknown'."""
    global _REVISION
    if _REVISION is None:
        root = Path(__file__).resolve().parent.parent
        try:
            sha = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=root, capture_output=True,
                                 text=True, timeout=5).stdout.strip()
            dirty = subprocess.run(["git", "status", "--porcelain", "--", "asp_dist"], cwd=root,
                                   capture_output=True, text=True, timeout=5).stdout.strip()
            _REVISION = (sha + ("+dirty" if dirty else "")) if sha else "unknown"
        except (OSError, subprocess.SubprocessError):
            _REVISION = "unknown"
    return _REVISION


def comparable(row: dict[str, Any]) -> dict[str, Any]:
    """A row without the columns that differ between runs of one spec (for equality checks)."""
    return {k: v for k, v in row.items() if k not in VOLATILE_COLUMNS}
