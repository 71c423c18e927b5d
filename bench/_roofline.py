"""What the roofline benches share (bench/vae_roofline.py, bench/pack_roofline.py): every matrix product of one
update captured with its operands' layout, each timed alone, and the update against their sum -- the matmul rate
of the update's own shapes, not the machine's peak -- with one fused Adam step over its parameters as the
memory-bound pass any float32-Adam update pays."""

from __future__ import annotations

import json
import os
import statistics
import time
from pathlib import Path
from typing import Any, Callable

import torch
from torch.utils._python_dispatch import TorchDispatchMode

aten = torch.ops.aten
MATMULS = {aten.mm, aten.addmm, aten.bmm, aten.baddbmm}  # every overload: .out too (torch.mm(..., out=))
ADDS_TO_INPUT = {aten.addmm, aten.baddbmm}  # their first operand is the term added, not a factor


class MatmulCapture(TorchDispatchMode):
    """Records each matrix product: (op, [(shape, stride) of each tensor operand], keyword arguments, with
    an out= tensor as its (shape, stride))."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple[Any, list[tuple[tuple, tuple]], dict]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func.overloadpacket in MATMULS:
            operands = [(tuple(a.shape), tuple(a.stride())) for a in args if torch.is_tensor(a)]
            options = {k: (tuple(v.shape), tuple(v.stride())) if torch.is_tensor(v) else v
                       for k, v in (kwargs or {}).items()}
            self.calls.append((func, operands, options))
        return func(*args, **(kwargs or {}))


def matmul_flop(func, operands) -> int:
    """2 x multiply-adds of one product (the bias of addmm/baddbmm is the first operand, not counted)."""
    a, b = (operands[1], operands[2]) if func.overloadpacket in ADDS_TO_INPUT else operands[:2]
    (*batch, m, k), (n,) = a[0], b[0][-1:]
    return 2 * m * k * n * (batch[0] if batch else 1)


def strided(shape: tuple, stride: tuple) -> torch.Tensor:
    """A random tensor of this shape laid out with this stride (a transposed view stays transposed)."""
    storage = sum((s - 1) * st for s, st in zip(shape, stride)) + 1
    return torch.randn(storage).as_strided(shape, stride)


def cpu_per_call(fn: Callable[[], Any], reps: int, blocks: int = 3) -> float:
    """Median CPU seconds per call over `blocks` blocks of `reps` calls, after reps // 5 + 5 warm-up calls."""
    for _ in range(reps // 5 + 5):
        fn()
    times = []
    for _ in range(blocks):
        c = time.process_time()
        for _ in range(reps):
            fn()
        times.append((time.process_time() - c) / reps)
    return statistics.median(times)


def matmul_alone(func, operands, options, reps: int = 200) -> float:
    tensors = [strided(*o) for o in operands]
    kwargs = {k: strided(*v) if k == "out" else v for k, v in options.items()}
    return cpu_per_call(lambda: func(*tensors, **kwargs), reps)


def adam_alone(params: list[torch.Tensor], reps: int = 200) -> float:
    """One fused Adam step (torch.optim.Adam's kernel, the VAE's options) over copies of `params`."""
    p = [torch.randn_like(x) for x in params]
    g, m, v = ([torch.randn_like(x) for x in params] for _ in range(3))
    steps = torch.zeros(())

    def step():
        steps.add_(1)
        torch._fused_adam_(p, g, m, v, [], [steps] * len(p), lr=1e-3, beta1=0.9, beta2=0.999, weight_decay=0.0,
                           eps=1e-8, amsgrad=False, maximize=False)
    return cpu_per_call(step, reps)


def roofline(name: str, step: Callable[[], None], params: list[torch.Tensor], updates: int, blocks: int) -> dict:
    with MatmulCapture() as capture:
        step()
    flop = sum(matmul_flop(f, o) for f, o, _ in capture.calls)
    matmuls = sum(matmul_alone(f, o, s) for f, o, s in capture.calls)
    adam = adam_alone(params)
    update = cpu_per_call(step, updates, blocks)
    row = {"update": name, "matmuls": len(capture.calls), "gflop": flop / 1e9, "update_ms": update * 1e3,
           "matmuls_alone_ms": matmuls * 1e3, "shape_rate_gflops": flop / matmuls / 1e9,
           "update_gflops": flop / update / 1e9, "of_shape_rate": matmuls / update,
           "adam_alone_ms": adam * 1e3, "ceiling_with_adam": matmuls / (matmuls + adam),
           "other_ms": (update - matmuls - adam) * 1e3, "parameters": sum(p.numel() for p in params)}
    print(f"{name:17s} {row['update_ms']:6.2f} ms  {len(capture.calls):2d} matmuls {row['gflop']:.3f} GFLOP alone "
          f"{row['matmuls_alone_ms']:.2f} ms ({row['shape_rate_gflops']:.0f} GFLOP/s)  of shape rate "
          f"{row['of_shape_rate']:.0%}  Adam {row['adam_alone_ms']:.2f} ms -> ceiling {row['ceiling_with_adam']:.0%}  "
          f"other {row['other_ms']:.2f} ms", flush=True)
    return row


def finish(result: dict, load_before: tuple[float, float, float], path: Path | None) -> None:
    """Close a roofline run's result (load after, date), say the load around it, and write it to `path`."""
    result.update(load_after=os.getloadavg(), date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    print(f"load average before {load_before[0]:.2f}, after {result['load_after'][0]:.2f}")
    if path:
        path.write_text(json.dumps(result, indent=1) + "\n")
