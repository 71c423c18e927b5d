"""What the packed trainers share: stacked parameters with one batched Adam step, per-member
columns of scalars, and the allocator setting that packed updates want.

    StackedParams         the parameters of M modules of one architecture in one flat buffer
                          (member-stacked blocks), their gradient buffer and Adam moments, one
                          fused Adam step for all of them; freezing of diverged members
    column                per-member Python scalars as a (M, 1[, 1]) tensor
    retain_freed_memory   glibc: keep freed memory in the heap instead of returning it at each free

The whole-cell side (bases, data, checkpoints, evaluation, rows) is asp_dist.training.packed.driver.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from typing import Sequence

import torch

BETAS, EPS = (0.9, 0.999), 1e-8  # torch.optim.Adam's and FlatAdam's defaults


def column(values: Sequence[float], *, dims: int = 2, dtype=torch.float32) -> torch.Tensor:
    """Per-member scalars as a (M, 1[, 1]) tensor; float32 rounding of each Python float, as
    a Python scalar gets in an op with a float32 tensor."""
    return torch.tensor(list(values), dtype=dtype).view(-1, *([1] * (dims - 1)))


class StackedParams:
    """The parameters of M modules of one architecture, stacked: each parameter tensor becomes a
    contiguous (M, *shape) block of one flat buffer (tensor-major, so that batched matmuls write
    their gradients into contiguous blocks), with a matching gradient buffer and Adam moments.
    Each module's parameters are re-pointed to views of its slice of the blocks (as FlatAdam does
    for one module), so the modules see every update."""

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
        kernel: one pass over the buffer; FlatAdam's arithmetic up to rounding)."""
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
    (bench/bench_packed_levers.py found the single-cell path's timings the same either way)."""
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
