"""What the packed trainers share: stacked parameters with one batched Adam step, the members'
records, per-member columns of scalars, and the allocator setting that packed updates want.

    StackedParams         the parameters of M modules of one architecture in one flat buffer
                          (member-stacked blocks), their gradient buffer and Adam moments, one
                          fused Adam step for all of them; freezing of diverged members
    PackRecords           the update count, the members' records (asp_dist.training.records.Records,
                          the class the reference Trainer records with too), failures, and the
                          checkpoint of all that
    PackedTrainer         a domain's packed trainer's base class: PackRecords with the capabilities
                          of asp_dist.training.engines (packs; `lone` and `in_sweeps` per domain; the
                          knob values it implements), and the pieces every packed update repeats:
                          the constructor's members, λ1 per update of a chunk, the freeze-then-Adam tail
    column                per-member Python scalars as a (M, 1[, 1]) tensor
    retain_freed_memory   glibc: keep freed memory in the heap instead of returning it at each free

The whole-cell side (bases, data, checkpoints, evaluation, rows) is asp_dist.training.pipeline.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from asp_dist.core.registry import get_domain
from asp_dist.knobs import unimplemented
from asp_dist.spec import CellSpec
from asp_dist.training.adversary import Adversaries
from asp_dist.training.methods import LossWeights, lambda_factor, method_weights
from asp_dist.training.records import COL, TERMS, Records, member_terms  # noqa: F401  (TERMS, member_terms: re-exported)

BETAS, EPS = (0.9, 0.999), 1e-8  # torch.optim.Adam's defaults
# What each member records per update (the single-cell trainers' diagnostics), in column order.


def column(values: Sequence[float], *, dims: int = 2, dtype=torch.float32) -> torch.Tensor:
    """Per-member scalars as a (M, 1[, 1]) tensor; float32 rounding of each Python float, as
    a Python scalar gets in an op with a float32 tensor."""
    return torch.tensor(list(values), dtype=dtype).view(-1, *([1] * (dims - 1)))


class StackedParams:
    """The parameters of M modules of one architecture, stacked: each parameter tensor becomes a
    contiguous (M, *shape) block of one flat buffer (tensor-major, so that batched matmuls write
    their gradients into contiguous blocks), with a matching gradient buffer and Adam moments.
    Each module's parameters are re-pointed to views of its slice of the blocks, so the modules see
    every update (and loading a module's state writes the buffer)."""

    def __init__(self, modules: Sequence[torch.nn.Module], lrs: Sequence[float]):
        shapes = [tuple(p.shape) for p in modules[0].parameters()]
        sizes = [int(torch.Size(s).numel()) for s in shapes]
        M, total = len(modules), len(modules) * sum(sizes)
        self.param, self.grad = torch.zeros(total), torch.zeros(total)
        self.exp_avg, self.exp_avg_sq = torch.zeros(total), torch.zeros(total)
        self.steps = torch.zeros(())  # every active member steps together
        self.lrs = list(lrs)
        self.views: list[torch.Tensor] = []       # (M, *shape); biases as (M, 1, out) for baddbmm
        self.grad_views: list[torch.Tensor] = []  # (M, *shape)
        self.member_ranges: list[list[tuple[int, int]]] = [[] for _ in range(M)]
        offset = 0
        for shape, n in zip(shapes, sizes):
            block = self.param[offset:offset + M * n].view(M, *shape)
            self.views.append(block.unsqueeze(1) if len(shape) == 1 else block)
            self.grad_views.append(self.grad[offset:offset + M * n].view(M, *shape))
            for i in range(M):
                self.member_ranges[i].append((offset + i * n, n))
            offset += M * n
        for i, module in enumerate(modules):
            params = list(module.parameters())
            if [tuple(p.shape) for p in params] != shapes:
                raise ValueError("modules of a pack must have the same parameter shapes")
            for p, (start, n) in zip(params, self.member_ranges[i]):
                row = self.param[start:start + n].view_as(p)
                row.copy_(p.detach())
                p.data = row
        self.frozen = torch.zeros(0, dtype=torch.long)
        self._group_by_lr()

    def member_flat(self, i: int, buffer: torch.Tensor | None = None) -> torch.Tensor:
        """Member i's values of `buffer` (default: the parameters) in its module's parameter order."""
        buffer = self.param if buffer is None else buffer
        return torch.cat([buffer[start:start + n] for start, n in self.member_ranges[i]])

    def _group_by_lr(self) -> None:
        """Adam's calls: the whole buffer when every member has one learning rate, else one call
        per learning rate over the slices of its members."""
        if len(set(self.lrs)) == 1:
            self.groups = [(self.lrs[0], [self.param], [self.grad], [self.exp_avg], [self.exp_avg_sq])]
            return
        self.groups = []
        for lr in sorted(set(self.lrs)):
            ranges = [r for i, x in enumerate(self.lrs) if x == lr for r in self.member_ranges[i]]
            self.groups.append((lr, *([buf[start:start + n] for start, n in ranges]
                                      for buf in (self.param, self.grad, self.exp_avg, self.exp_avg_sq))))

    def freeze(self, rows: Sequence[int]) -> None:
        """Members whose parameters Adam must leave as they are: their momentum is cleared here
        and their gradients before every step (zero_frozen_grads), so every update of theirs is
        exactly 0 while the calls, and so every other member's arithmetic, stay the same."""
        for i in rows:
            for start, n in self.member_ranges[i]:
                self.exp_avg[start:start + n] = 0.0
        self.frozen = torch.tensor(sorted(set(self.frozen.tolist()) | set(rows)), dtype=torch.long)

    def zero_frozen_grads(self) -> None:
        if len(self.frozen):
            for g in self.grad_views:
                g.index_fill_(0, self.frozen, 0.0)

    def step(self) -> None:
        """One Adam step of every member from the current contents of `grad` (torch's fused Adam
        kernel: one pass over the buffer; torch.optim.Adam's arithmetic up to rounding)."""
        self.zero_frozen_grads()
        self.steps.add_(1)
        for lr, params, grads, avgs, sqs in self.groups:
            torch._fused_adam_(params, grads, avgs, sqs, [], [self.steps] * len(params), lr=lr, beta1=BETAS[0],
                               beta2=BETAS[1], weight_decay=0.0, eps=EPS, amsgrad=False, maximize=False)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"param": self.param.clone(), "exp_avg": self.exp_avg.clone(), "exp_avg_sq": self.exp_avg_sq.clone(),
                "steps": self.steps.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        for name in ("param", "exp_avg", "exp_avg_sq", "steps"):
            getattr(self, name).copy_(state[name])
        self.frozen = torch.zeros(0, dtype=torch.long)


class PackRecords:
    """What a packed trainer keeps besides its update, the same for every domain: the update count,
    each member's loss sums over the last 10 % of training (its row's loss_* columns) and its
    learning curve, as Trainer.record / finish_curve_point / loss_columns keep them; failures
    (members frozen); and the checkpoint of all that with the stacked parameters.

    A subclass sets, before calling _init_records(): M, members (each with spec, weights, gen,
    terms, probe, curve, failed_step, error, failed), train_steps, net and dnet (StackedParams or
    None), Ma, adv_idx and lam_now (the ASP members, λ1 per update of the
    chunk). It implements _freeze_params(rows) (freeze the members' parameters and
    discriminators) and _draw_chunk() (the random draws of updates [step, step + CHUNK))."""

    def _init_records(self) -> None:
        # per member: the loss terms it has, and its float64 loss weights (as Trainer sums them)
        self.records = Records([m.terms for m in self.members], self.train_steps)
        self.present = self.records.present
        self.w64 = {name: column([getattr(m.weights, name) for m in self.members], dtype=torch.float64).view(-1)
                    for name in ("self_play", "paired")}
        self.step = 0
        self.active = [True] * self.M
        self.chunk_start = self.chunk_end = 0
        self.chunk_gen_states: list[torch.Tensor] = []
        self._lambda_factors: list[torch.Tensor] | None = None  # each ASP member's λ1 factors (_lambda_chunk)

    def in_curve_window(self) -> bool:
        return self.records.in_curve_window(self.step)

    def recording(self) -> bool:
        return self.records.recording(self.step)

    # ---- failures --------------------------------------------------------------------------------
    def _freeze(self, rows: list[int], why: str) -> None:
        """Mark members failed and freeze their parameters (and their discriminators) for good."""
        for i in rows:
            self.active[i] = False
            self.members[i].failed_step = self.step
            self.members[i].error = f"{why} at update {self.step} of {self.train_steps}"
        self._freeze_params(rows)

    def _freeze_params(self, rows: list[int]) -> None:
        raise NotImplementedError

    def _draw_chunk(self) -> None:
        raise NotImplementedError

    def _open_chunk(self, size: int) -> tuple[int, int, dict[int, int]]:
        """The start of every _draw_chunk: the chunk covers the next `size` updates (fewer at the end); each
        member's generator state at its start is kept (a checkpoint inside the chunk re-makes its draws from
        them). Returns (first update, number of updates, member row -> its place among the ASP members)."""
        start, S = self.step, min(size, self.train_steps - self.step)
        self.chunk_gen_states = [m.gen.get_state() for m in self.members]
        self.chunk_start, self.chunk_end = start, start + S
        return start, S, {i: a for a, i in enumerate(self.adv_rows)}

    def _begin_update(self) -> tuple[int, dict[str, torch.Tensor] | None]:
        """The opening of every packed train_step: refuse a finished pack, draw the next chunk's random numbers
        when this update starts one, and say where the update is in its chunk (j) and whether it records its
        diagnostics: `vals` is the dict to fill for _record, or None when this update records nothing."""
        if self.step >= self.train_steps:
            raise RuntimeError(f"the pack has finished its {self.train_steps} updates")
        if self.step >= self.chunk_end:
            self._draw_chunk()
        return self.step - self.chunk_start, ({} if self.recording() else None)

    # ---- diagnostics, as Trainer.record / finish_curve_point / loss_columns ---------------------
    def _record(self, vals: dict[str, torch.Tensor], j: int) -> None:
        """One update's diagnostics (`vals`: per-member "self_play" and "paired", the ASP members'
        others) for update j of the chunk; a member whose loss is not finite is frozen."""
        V = torch.zeros(self.M, len(TERMS), dtype=torch.float64)
        for name, v in vals.items():
            if name in ("self_play", "paired"):
                V[:, COL[name]] = v
            else:  # ASP members only
                V[self.adv_idx, COL[name]] = v.double()
        V.masked_fill_(~self.present, 0.0)  # a term the member does not have counts 0, as in Trainer
        total = self.w64["self_play"] * V[:, 0] + self.w64["paired"] * V[:, 1]
        if self.Ma:
            total[self.adv_idx] += self.lam_now[j] * V[self.adv_idx, 2]
        V[:, COL["total"]] = total
        if not bool(torch.isfinite(V).all()):
            self._freeze([i for i, ok in enumerate(torch.isfinite(V).all(1).tolist()) if not ok and self.active[i]],
                         "non-finite loss")
        self.records.add(self.step, V)

    def _finish_curve_point(self) -> None:
        self.records.finish_point(self.step, self.members)

    def loss_columns(self, i: int) -> dict[str, float | None]:
        return self.records.loss_columns(i)

    # ---- checkpoints -------------------------------------------------------------------------
    def _state(self, **own: Any) -> dict[str, Any]:
        """The trainer's state with the subclass's `own` entries (its self-play state): everything to
        continue bit for bit; the draws of the current chunk are re-made from the generators' states
        at its start."""
        return {
            "step": self.step, "net": self.net.state_dict(),
            "dnet": self.dnet.state_dict() if self.dnet is not None else None,
            **own, "chunk_start": self.chunk_start,
            "gens": [g.clone() for g in self.chunk_gen_states] if self.chunk_end > self.chunk_start
            else [m.gen.get_state() for m in self.members],
            **self.records.state(),
            "members": [{"curve": [dict(p) for p in m.curve], "failed_step": m.failed_step, "error": m.error}
                        for m in self.members],
        }

    def _load_state(self, state: dict[str, Any]) -> None:
        """Load what _state saved (a subclass loads its own entries first)."""
        self.net.load_state_dict(state["net"])
        if self.dnet is not None:
            self.dnet.load_state_dict(state["dnet"])
        self.records.load(state)
        for m, saved in zip(self.members, state["members"]):
            m.curve, m.failed_step, m.error = [dict(p) for p in saved["curve"]], saved["failed_step"], saved["error"]
        for m, g in zip(self.members, state["gens"]):
            m.gen.set_state(g)
        self.active = [not m.failed for m in self.members]
        self._freeze_params([i for i, a in enumerate(self.active) if not a])
        self.step = self.chunk_start = self.chunk_end = state["chunk_start"]
        if state["step"] > self.step:  # re-make the chunk's draws, continue inside it
            self._draw_chunk()
        self.step = state["step"]


class PackedTrainer(PackRecords):
    """Base of a domain's packed trainer: its capabilities as asp_dist.training.engines reads them, and the
    parts of a packed update that do not depend on the domain.

    A subclass sets
        domain      the domain whose cells it trains
        implements  every knob of that domain -> the values its update implements: ANY, a tuple of values,
                    or BASE_ONLY (asp_dist.knobs); the registry refuses a trainer that leaves a knob out
        shared      the spec fields every member shares (tensor shapes, the loop's length): its pack key
        lone        True where a single cell is faster as a one-member pack than on the domain's other trainers
    `engine` is its class name."""

    engine = "packed"  # each subclass: its own name (__init_subclass__)
    packs = True
    lone = False
    in_sweeps = True
    domain = ""
    implements: dict[str, Any] = {}
    shared: tuple[str, ...] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.engine = cls.__name__

    # ---- capabilities -----------------------------------------------------------------------------
    @classmethod
    def unsupported(cls, spec: CellSpec) -> list[str]:
        """What of `spec` this trainer does not implement (`knob=value`, or the domain); empty: it trains it."""
        spec = spec.resolved()
        if spec.domain != cls.domain:
            return [f"domain={spec.domain!r}"]
        return unimplemented(cls.implements, spec)

    @classmethod
    def supports(cls, spec: CellSpec) -> bool:
        return not cls.unsupported(spec)

    @classmethod
    def pack_key(cls, spec: CellSpec) -> tuple:
        """Cells with equal keys can share a pack: their values of `shared`."""
        spec = spec.resolved()
        return tuple(getattr(spec, name) for name in cls.shared)

    @classmethod
    def build(cls, specs: Sequence[CellSpec], paired: Sequence, unpaired: Sequence, agents: Sequence):
        return cls(specs, paired, unpaired, agents)

    @staticmethod
    def member_order(specs: Sequence[CellSpec]) -> list[int]:
        """The members' places in the pack (asp_dist.training.pipeline): the order given."""
        return list(range(len(specs)))

    # ---- what every constructor does first --------------------------------------------------------
    def _init_members(self, specs: Sequence[CellSpec], paired: Sequence, unpaired: Sequence, agents: Sequence,
                      *, paired_rows: str) -> list[tuple[torch.nn.Module, ...]]:
        """Check the members (checked_members), then set what every packed update reads of them, exactly as
        Trainer.__init__ makes it per cell: `members` (spec, loss weights, the generator seeded as the
        reference's, the agents, the discriminators of an ASP member built as Adversaries builds them,
        the paired rows used: len(P[paired_rows]), 0 under a paired weight of 0), M, train_steps,
        disc_steps, ub (unpaired batch), any_self_play, adv_rows / Ma / adv_idx / all_adv / adv_first
        (the ASP members). Returns the ASP members' discriminators, one tuple per member in Adversaries'
        channel order (sorted names)."""
        specs = checked_members(specs, paired, unpaired, agents, trainer=type(self))
        domain = get_domain(self.domain)
        s0 = specs[0]
        self.M, self.train_steps = len(specs), s0.train_steps
        self.disc_steps, self.ub = s0.disc_steps, s0.unpaired_batch
        self.members: list[PackMember] = []
        discs: list[tuple[torch.nn.Module, ...]] = []
        for spec, p, a in zip(specs, paired, agents):
            weights = method_weights(spec)
            gen = torch.Generator().manual_seed(spec.seed_for("train"))
            own: tuple[torch.nn.Module, ...] = ()
            if weights.needs_adversary:
                adv = Adversaries(domain.channel_dims(spec), spec.disc_hidden, spec.disc_layers, spec.disc_lr,
                                  seed=spec.seed_for("init") + 1000, make_optimizer=lambda params, lr: None)
                own = tuple(adv.discs.values())
                discs.append(own)
            n = len(p[paired_rows]) if weights.paired != 0.0 and p else 0
            self.members.append(PackMember(spec=spec, weights=weights, agents=a, discs=own, gen=gen, n_paired=n,
                                           terms=member_terms(weights, n)))
        self.any_self_play = any(m.self_play for m in self.members)
        self.adv_rows = [i for i, m in enumerate(self.members) if m.adversary]
        self.Ma = len(self.adv_rows)
        self.adv_idx = torch.tensor(self.adv_rows, dtype=torch.long)
        self.all_adv = self.Ma == self.M
        self.adv_first = self.adv_rows == list(range(self.Ma))  # member_order may put the ASP members first
        return discs

    # ---- λ1 of the updates of a chunk ---------------------------------------------------------------
    def _lambda_chunk(self, start: int, S: int) -> None:
        """λ1 of updates [start, start + S) of each ASP member into lam_now[:S] (float64; allocated by the
        subclass as (CHUNK, Ma)): w_unpaired · methods.lambda_factor, the reference's own schedule, multiplied in
        float64 as the reference multiplies Python floats. The factors of a member's whole training are taken
        from lambda_factor once (≈ 1 µs an update, once per cell) and sliced per chunk."""
        if self._lambda_factors is None:
            self._lambda_factors = [torch.tensor([lambda_factor(self.members[i].spec, step)
                                                  for step in range(self.train_steps)], dtype=torch.float64)
                                    for i in self.adv_rows]
        for a, i in enumerate(self.adv_rows):
            self.lam_now[:S, a] = self.members[i].weights.unpaired * self._lambda_factors[a][start:start + S]

    # ---- the end of every update ----------------------------------------------------------------------
    def _step_discriminators(self) -> None:
        """The discriminators' Adam step; an ASP member any of whose discriminators' gradient is not finite
        is frozen first (dnet's rows are channel-major: member a's c-th discriminator is row c·Ma + a)."""
        dnet, Ma = self.dnet, self.Ma
        dnet.zero_frozen_grads()
        if not bool(torch.isfinite(dnet.grad.sum())):
            per_member = len(dnet.member_ranges) // Ma
            finite = [all(bool(torch.isfinite(dnet.member_flat(c * Ma + a, dnet.grad)).all()) for c in range(per_member))
                      for a in range(Ma)]
            self._freeze([i for a, i in enumerate(self.adv_rows) if self.active[i] and not finite[a]],
                         "non-finite discriminator gradient")
        dnet.step()

    def _step_model(self, vals: dict | None, j: int, record: bool) -> None:
        """The model's Adam step and the update's bookkeeping: a member whose gradient is not finite is
        frozen first (one reduction over the buffer per update; frozen members' gradients are zeroed
        first, so it sees new failures only), then one Adam step for every member, the update's
        diagnostics recorded, the count advanced and a finished curve point closed."""
        self.net.zero_frozen_grads()
        if not bool(torch.isfinite(self.net.grad.sum())):
            self._freeze([i for i in range(self.M) if self.active[i]
                          and not bool(torch.isfinite(self.net.member_flat(i, self.net.grad)).all())],
                         "non-finite loss gradient")
        self.net.step()
        if record:
            self._record(vals, j)
        self.step += 1
        self._finish_curve_point()


def retain_freed_memory() -> None:
    """Keep freed memory in the process's heap (glibc: mmap threshold 32 MiB, trim threshold
    256 MiB) instead of handing it back to the kernel at every free. Process-wide and idempotent;
    a no-op without glibc's mallopt. A packed trainer whose updates need it calls it once, from
    its constructor (today PackedLeverTrainer).

    Why: a pack's intermediate tensors are K times a single cell's (~0.1-3 MB for lever packs).
    glibc serves blocks over its mmap threshold with a fresh mmap and unmaps them on free, and
    trims the heap top beyond its trim threshold; both thresholds adapt to what was freed before,
    so whether a given process churns depends on its history. A lever pack of 21 cells without
    this page-faults 120 to 1,050 times per update (varying from process to process) and spends
    ~20 % more CPU per update (bench/bench_packed_allocator.py); with it, ~2 faults per update. A
    particle pack (K = 21 or 64) stays under the adapted thresholds by itself (< 1 fault per
    update, the same CPU time either way), so the particle trainer does not call it.

    What it costs: memory the process frees stays mapped until it exits (peak RSS is unchanged;
    the RSS no longer shrinks after a peak), and the setting stays for the rest of the process, so
    a Ray worker that trained a lever pack keeps it for the cells it trains next
    (bench/bench_packed_levers.py, since merged into bench/bench_packing.py, found the single-cell
    path's timings the same either way)."""
    global _MALLOC_DONE
    if _MALLOC_DONE:
        return
    _MALLOC_DONE = True
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    mallopt(-3, 32 << 20)   # M_MMAP_THRESHOLD (its maximum on 64-bit glibc)
    mallopt(-1, 256 << 20)  # M_TRIM_THRESHOLD


_MALLOC_DONE = False


@dataclass(kw_only=True)
class PackMember:
    """One cell of a pack: its spec, its networks and what every packed trainer keeps per member."""

    spec: CellSpec
    weights: LossWeights
    gen: torch.Generator
    agents: torch.nn.Module  # its parameters are views of the pack's buffer: always current
    discs: tuple[torch.nn.Module, ...]  # an ASP member's discriminators (Adversaries' order), likewise; else ()
    n_paired: int
    terms: tuple[str, ...]           # the diagnostics this member records (as its single-cell trainer)
    probe: Callable[[int], dict[str, float]] | None = None
    curve: list[dict[str, float]] = field(default_factory=list)
    failed_step: int | None = None
    error: str | None = None

    @property
    def self_play(self) -> bool:
        return self.weights.needs_self_play

    @property
    def adversary(self) -> bool:
        return self.weights.needs_adversary

    @property
    def failed(self) -> bool:
        return self.error is not None


def checked_members(specs: Sequence[CellSpec], paired: Sequence, unpaired: Sequence, agents: Sequence, *,
                    trainer: type[PackedTrainer]) -> list[CellSpec]:
    """The members' resolved specs, after the checks every packed trainer's constructor makes: one
    spec, P, U and agents per member (at least one), each spec supported by `trainer` (else ValueError
    naming what it does not implement), and all agreeing on its `shared` fields (tensor shapes,
    training length)."""
    specs = [s.resolved() for s in specs]
    if not specs or not len(specs) == len(paired) == len(unpaired) == len(agents):
        raise ValueError("a pack needs one spec, paired set, unpaired set and agents per member (at least one)")
    for s in specs:
        missing = trainer.unsupported(s)
        if missing:
            raise ValueError(f"{s.cell_id} cannot be packed: {trainer.__name__} does not implement {', '.join(missing)}")
        diff = [n for n in trainer.shared if getattr(s, n) != getattr(specs[0], n)]
        if diff:
            raise ValueError(f"{s.cell_id} and {specs[0].cell_id} differ in {', '.join(diff)}: not one pack")
    return specs


def asp_members_first(specs: Sequence[CellSpec]) -> list[int]:
    """A member order (a packed trainer's member_order): members with an adversary first, so that their
    rows of the pack are a prefix (views instead of gathers); otherwise the order given."""
    return sorted(range(len(specs)), key=lambda i: not method_weights(specs[i]).needs_adversary)
