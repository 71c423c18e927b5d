"""The one cell pipeline: a cell is a unit of one, a pack a unit of K cells, whatever trains them.

    bases    each member's base from `bases` (the sweep's cache) or trained here, once per key
    data     P and U per (base, data seed, paired count, the domain's paired_fields and unpaired_fields), sampled
             once in that order and shared by the methods; fresh agents per member
    train    one trainer (asp_dist.training.engines: a domain's packed trainer for a pack, the cell's
             lone trainer for a cell) of the members whose base was accepted, checkpointed and restored
             as a whole in one format (CHECKPOINT_VERSION)
    eval     per member, with its own generator; one row per member (build_row)

run_cell (asp_dist.training.cell) is run_unit with one cell and its lone trainer, engines.run_pack
run_unit with a domain's packed trainer; the sweep's one Tune trial function (asp_dist.sweep.trial) calls
one of the two per unit. A trainer follows `UnitTrainer` below; the reference Trainer and every packed
trainer do.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from asp_dist.core.contract import ProgressFn
from asp_dist.core.registry import get_domain
from asp_dist.spec import CellSpec
from asp_dist.training.bases import BaseModel, BaseRejected, train_accepted_base
from asp_dist.training.float_mode import denormals_flushed
from asp_dist.training.loop import PhaseTimer, make_probe, train_to_end
from asp_dist.training.methods import method_weights
from asp_dist.training.row import InvalidRow, build_row
from asp_dist.training.torch_runtime import keep_dynamo_unloaded

# The one checkpoint format of cells and packs: {"version", "engine", "cell_ids", "trainer", "timings"}.
# 3: one format for both (before: a cell's v1/v2 with "cell_id", a pack's v1 without "engine"): upgrade_checkpoint.
CHECKPOINT_VERSION = 3


# run_unit's `on_points`: [(a member's spec, its curve points closed since the last call)]
PointsFn = Callable[[list[tuple[CellSpec, list[dict[str, float]]]]], None]


class CellDiverged(RuntimeError):
    """A cell whose gradient or recorded loss became non-finite (its trainer froze it). Deterministic: the
    sweep records it as the cell's failure once instead of retrying it; run_cell raises it."""


class MemberView(Protocol):
    """What the pipeline reads and sets on a member of a trainer (stacked.PackMember plus the networks a
    domain's member adds; the reference Trainer is its own one member)."""

    agents: torch.nn.Module
    probe: Callable[[int], dict[str, float]] | None
    curve: list[dict[str, float]]
    error: str | None

    @property
    def failed(self) -> bool: ...


class UnitTrainer(Protocol):
    """A trainer as the pipeline drives it (built by its class's ``build``, asp_dist.training.engines).

    Built from one spec, paired set, unpaired set and fresh agents per member, in the order member_order()
    gives; after train_step() has run train_steps times, member i's agents hold its trained weights and
    loss_columns(i) its row's loss_* columns. state_dict() is everything to continue bit for bit after
    load_state_dict() on a trainer built from the same inputs; `engine` names its format."""

    engine: str
    members: Sequence[MemberView]
    step: int
    train_steps: int

    @staticmethod
    def member_order(specs: Sequence[CellSpec]) -> list[int]:
        """The members' places in the trainer: indices into `specs` (a trainer may want, say, the
        members with a discriminator first)."""

    def train_step(self) -> None: ...

    def loss_columns(self, i: int) -> dict[str, float | None]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


@dataclass
class CellResult:
    """One member's outcome: its result row (as run_cell's) and curve, or why it failed (`exception`:
    BaseRejected, CellDiverged, InvalidRow; `error`: its message)."""

    spec: CellSpec
    row: dict[str, Any] | None = None
    curve: list[dict[str, float]] | None = None
    exception: Exception | None = None

    @property
    def error(self) -> str | None:
        return None if self.exception is None else str(self.exception)


def upgrade_checkpoint(state: dict) -> dict:
    """A checkpoint of any earlier format in today's (CHECKPOINT_VERSION). A cell's v1/v2 named its cell
    ("cell_id") and, from v2, its engine (v1: "autograd" for the reference's torch.optim state, else the
    retired particle kernel "fused-particles"); a pack's v1 named its cells but no engine (None: the
    domain's packed trainer, the only one packs had); a one-member pack's engine was "pack-of-one/<class>"."""
    if state.get("version", 1) >= CHECKPOINT_VERSION:
        return state
    if "cell_ids" in state:  # a pack's v1
        return dict(state, version=CHECKPOINT_VERSION, engine=None)
    engine = state.get("engine")
    if engine is None:
        opt = state["trainer"].get("opt")
        engine = "autograd" if isinstance(opt, dict) and "param_groups" in opt else "fused-particles"
    return {"version": CHECKPOINT_VERSION, "engine": engine.removeprefix("pack-of-one/"),
            "cell_ids": [state.get("cell_id")], "trainer": state["trainer"], "timings": [state.get("timings", {})]}


def one_domain(specs: Sequence[CellSpec]) -> str:
    """The one domain of a unit's cells (ValueError when they mix domains: a pack never does)."""
    domains = sorted({s.domain for s in specs})
    if len(domains) > 1:
        raise ValueError(f"a pack holds cells of one domain, got {', '.join(domains)}")
    return domains[0]


def generator_from_state(state: torch.Tensor) -> torch.Generator:
    """A new CPU generator in the given state (the state itself is not shared)."""
    gen = torch.Generator()
    gen.set_state(state)
    return gen


def run_unit(trainer_class: type, specs: Sequence[CellSpec], *, bases: dict[str, BaseModel | None] | None = None,
             curves: bool = False, progress: ProgressFn | None = None, checkpoint: Callable[[dict], None] | None = None,
             restore: dict | None = None, checkpoint_every_s: float = 30.0,
             checkpoint_every_steps: int | None = None, on_points: PointsFn | None = None) -> list[CellResult]:
    """Train `specs` (cells of one domain) on one trainer of `trainer_class`: bases, data, training, evaluation.

    trainer_class  what trains them (asp_dist.training.engines): a lone trainer takes one cell, a packed
                trainer any number that it supports and that share its pack_key
    bases       trained bases by base_key (as the sweep's base cache hands them out); a missing one is
                trained here, once per key (its time goes to the first member of that base)
    curves      record each member's learning curve with probes (~50 points, ~10 with probe_* metrics)
    on_points   with curves: called while the unit trains (every 1 % of its updates, and at the end) with
                [(spec, points)]: each member's curve points closed since the last call (after a restore:
                from its first point, the restored ones included). It only reads the curve: rows are the
                same with or without it
    checkpoint  called with the unit's full training state every `checkpoint_every_steps` updates, or
                every `checkpoint_every_s` seconds when no step interval is given
    restore     a state previously passed to `checkpoint` by a unit of the same cells (and the same
                rejected bases), in any earlier format (upgrade_checkpoint): training continues from it,
                and every member's row equals the one an uninterrupted run gives (resumed_from_step says
                where it continued). A state of other cells is refused (ValueError); a state of another
                engine (made by older code, or for another trainer) is not restored, and the unit starts over

    Returns one CellResult per spec, in order. Phase timings in a member's row: base, data and
    eval are its own; train is the unit's training time divided by the number of members."""
    keep_dynamo_unloaded()
    specs = [s.resolved() for s in specs]
    if not specs:
        return []
    domain = get_domain(one_domain(specs))
    bases = dict(bases or {})
    results = [CellResult(spec) for spec in specs]
    timers = [PhaseTimer() for _ in specs]
    reused = [True] * len(specs)
    for i, spec in enumerate(specs):
        if spec.base_key in bases:
            continue
        try:
            with timers[i].phase("base"):
                bases[spec.base_key] = train_accepted_base(spec, progress)
            reused[i] = False
        except BaseRejected as exc:
            bases[spec.base_key] = None
            results[i].exception = exc
    live = [i for i, spec in enumerate(specs) if bases.get(spec.base_key) is not None]
    for i in range(len(specs)):
        if i not in live and results[i].exception is None:
            results[i].exception = BaseRejected(f"base {specs[i].base_key} rejected (see the first cell of that base)")
    if not live:
        return results

    # A checkpoint names its unit by the live members' cell ids in the order of `specs` (the sweep
    # compares them with its own); the trainer's state is in the trainer's order, which follows.
    # Refused before any data is sampled.
    live_ids = [specs[i].cell_id for i in live]
    if restore is not None:
        restore = upgrade_checkpoint(restore)
        if restore.get("cell_ids") != live_ids:
            raise ValueError(f"checkpoint belongs to a pack of {restore.get('cell_ids')}, not of {live_ids}")
        if restore["engine"] not in (None, trainer_class.engine):
            restore = None  # its state would not load into this trainer: start over

    # P and U depend on (base, paired), not the method: sample each once, P first, U from the same stream.
    paired, unpaired, agents, data_cache = {}, {}, {}, {}
    for i in live:
        spec, base = specs[i], bases[specs[i].base_key]
        weights = method_weights(spec)
        with timers[i].phase("data"):
            key = (spec.base_key, spec.seed_for("data"), spec.paired, *(getattr(spec, f) for f in domain.paired_fields))
            if key not in data_cache:
                gen = torch.Generator().manual_seed(spec.seed_for("data"))
                p = domain.paired(spec, base.agents, spec.paired, gen) if spec.paired > 0 else {}
                data_cache[key] = (p, gen.get_state(), {})
            p, after_p, u_cache = data_cache[key]
            paired[i], unpaired[i] = p, {}
            if weights.needs_adversary:
                u_key = (spec.unpaired_size, *(getattr(spec, f) for f in domain.unpaired_fields))
                if u_key not in u_cache:
                    u_cache[u_key] = domain.unpaired(spec, base.agents, spec.unpaired_size,
                                                     generator_from_state(after_p))
                unpaired[i] = u_cache[u_key]
            agents[i] = domain.new_agents(spec, spec.seed_for("init"))

    order = [live[k] for k in trainer_class.member_order([specs[i] for i in live])]
    wall, cpu = time.perf_counter(), time.process_time()
    trainer = trainer_class.build([specs[i] for i in order], [paired[i] for i in order],
                                  [unpaired[i] for i in order], [agents[i] for i in order])
    paired.clear(), unpaired.clear(), data_cache.clear()  # the trainer holds its own (padded) copies
    if curves:
        for i, member in zip(order, trainer.members):
            member.probe = make_probe(specs[i], domain, bases[specs[i].base_key], member.agents)
    resumed_from = None
    if restore is not None:
        trainer.load_state_dict(restore["trainer"])
        resumed_from = trainer.step
        for i, carried in zip(live, restore["timings"]):
            timers[i].carry(carried)

    def save_state() -> None:
        share = {"time_train_wall_s": (time.perf_counter() - wall) / len(live),
                 "time_train_cpu_s": (time.process_time() - cpu) / len(live)}
        timings = []
        for i in live:  # each member's phases so far, with its share of the unit's training up to now
            seconds = dict(timers[i].seconds)
            for name, value in share.items():
                seconds[name] = seconds.get(name, 0.0) + value
            timings.append(seconds)
        checkpoint({"version": CHECKPOINT_VERSION, "engine": trainer.engine, "cell_ids": live_ids,
                    "trainer": trainer.state_dict(), "timings": timings})

    sent = [0] * len(order)

    def pass_on_points() -> None:
        batch = []
        for k, (i, member) in enumerate(zip(order, trainer.members)):
            if len(member.curve) > sent[k]:
                batch.append((specs[i], [dict(p) for p in member.curve[sent[k]:]]))
                sent[k] = len(member.curve)
        if batch:
            on_points(batch)

    with denormals_flushed():
        train_to_end(trainer, trainer.train_steps, progress, save_state if checkpoint is not None else None,
                     checkpoint_every_s, checkpoint_every_steps,
                     pass_on_points if on_points is not None and curves else None)
    share_wall = (time.perf_counter() - wall) / len(live)
    share_cpu = (time.process_time() - cpu) / len(live)

    for k, (i, member) in enumerate(zip(order, trainer.members)):
        if member.failed:  # frozen; a pack went on without it
            results[i].exception = CellDiverged(f"cell {specs[i].cell_id}: {member.error}; member frozen")
            continue
        spec, base, timer = specs[i], bases[specs[i].base_key], timers[i]
        timer.seconds["time_train_wall_s"] += share_wall
        timer.seconds["time_train_cpu_s"] += share_cpu
        with timer.phase("eval"):
            member.agents.eval()
            with torch.no_grad():
                metrics = domain.evaluate(spec, base.agents, member.agents,
                                          torch.Generator().manual_seed(spec.seed_for("eval")))
            figure = domain.figure_data(spec, base.agents, member.agents) if spec.record_figure_data else None
        try:
            results[i].row = build_row(spec, domain, base, base_reused=reused[i], metrics=metrics,
                                       losses=trainer.loss_columns(k), figure=figure, timings=timer.columns(),
                                       resumed_from=resumed_from)
        except InvalidRow as exc:  # this member only: the unit's others keep their rows
            results[i].exception = exc
            continue
        results[i].curve = member.curve if curves else None
        if progress is not None:
            progress("eval", k + 1, len(live), {"mixed": metrics["mixed"]})
    return results
