"""The VAE's updates against the matmul rate of their own shapes: where an update's time goes, and what
stands between it and its matmuls.

    OMP_NUM_THREADS=1 python bench/vae_roofline.py --json vae-roofline.json    # about 2 min idle
    OMP_NUM_THREADS=1 python bench/vae_roofline.py --updates 50 --blocks 1     # a quick try

For each update of the paper's VAE grid (latent 32, hidden 512; the base at batch 128 on the hand-derived
update train_base runs, and on the autograd reference; a PC, an OSP and an ASP cell with 32 paired on the
trainer a sweep picks, engines.lone_trainer, the hand-derived one, and on the one-pass autograd trainer):

- its matrix products are captured while one update runs (a TorchDispatchMode sees every aten mm, addmm,
  bmm and baddbmm with its operands' shapes and strides: the transposed operands nn.Linear hands MKL
  included), then each is timed alone with operands of the same layout; their flop over their summed time
  is the matmul rate *of the update's shapes* ("shape rate");
- the update is timed (CPU, median of --blocks blocks of --updates, after warm-up);
- "of shape rate" is the matmuls' time alone over the update's: 100 % would be an update that only
  multiplies matrices;
- the Adam floor: one fused Adam step (torch's kernel) over the update's parameters, timed alone. It is a
  memory-bound pass over weights, gradients and both moments that no fusion of the forward or backward
  removes, so matmuls / (matmuls + Adam) is the ceiling of "of shape rate" for an update that keeps
  float32 Adam; "other" is what is left (elementwise kernels, the loss, autograd, Python).

Then the settings the question names, each measured on the same shapes in the same run:
- the allocator: asp_dist.training.stacked.retain_freed_memory (glibc keeps freed blocks), page faults
  per update and the time, on the base and the ASP cell (process-wide, so last);
- the memory layout: the first layer's forward as nn.Linear runs it (x @ Wᵀ, the weight stored out x in)
  against the weight stored in x out (x @ W);
- oneDNN's implicit bfloat16 for float32 matmuls (torch.backends.mkldnn.matmul.fp32_precision = "bf16",
  AMX or AVX-512 BF16 where the CPU has them): its speed on the largest matmul and its relative error
  against float64. Measured, not used: it changes the arithmetic the paper's results rest on.
One thread throughout (a sweep runs one worker per core; thread settings are the sweep's), and denormals flushed
as training flushes them (asp_dist.training.float_mode; --keep-denormals: not): Adam's decaying averages reach
them after ~700 updates and then slow a base update by 40 %, which would make every figure depend on how
many updates ran before it.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from _common import machine_info  # noqa: E402
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402

from asp_dist.domains import get_domain  # noqa: E402
from asp_dist.domains.vae import VAEDomain  # noqa: E402
from asp_dist.domains.vae.base_update import HandDerivedBaseUpdate  # noqa: E402
from asp_dist.domains.vae.fast import OnePassVAETrainer  # noqa: E402
from asp_dist.domains.vae.game import VAE, as_float, image_rows, train_images  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.engines import lone_trainer  # noqa: E402
from asp_dist.training.float_mode import denormals_flushed  # noqa: E402

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


def minor_faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


# ---- the updates -----------------------------------------------------------------------------
def base_updates(spec: CellSpec) -> dict[str, tuple[Callable[[], None], list[torch.Tensor]]]:
    """The base's update as train_base runs it (hand-derived) and as its reference does (autograd)."""
    images = train_images(spec)
    out = {}
    for name in ("base", "base (autograd)"):
        vae = VAE(spec.vae_latent_dim, spec.vae_hidden)
        gen = torch.Generator().manual_seed(0)
        batch = lambda gen=gen: as_float(image_rows(images, torch.randint(len(images), (spec.vae_base_batch,),  # noqa: E731
                                                                          generator=gen)))
        if name == "base":
            update = HandDerivedBaseUpdate(vae, spec.vae_base_lr, spec.vae_kl_weight, spec.vae_recon_loss)
            step = lambda update=update, batch=batch, gen=gen: update.step(batch(), gen)  # noqa: E731
        else:
            opt = torch.optim.Adam(vae.parameters(), lr=spec.vae_base_lr, **VAEDomain.optimizer_options)

            def step(vae=vae, opt=opt, batch=batch, gen=gen):
                loss, *_ = vae.vae_loss(batch(), gen, spec.vae_kl_weight, spec.vae_recon_loss)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
        out[name] = (step, list(vae.parameters()))
    return out


def cell_updates(spec: CellSpec) -> dict[str, tuple[Callable[[], None], list[torch.Tensor]]]:
    domain = get_domain("vae")
    base, _ = domain.train_base(spec.replace(base_train_steps=20).resolved(), 0)
    out = {}
    for method in ("pc", "osp", "asp"):
        cell = spec.replace(method=method).resolved()
        gen = torch.Generator().manual_seed(1)
        paired = domain.paired(cell, base, cell.paired, gen)
        unpaired = domain.unpaired(cell, base, cell.unpaired_size, gen)
        for name, cls in ((method, lone_trainer(cell)), (f"{method} (one-pass)", OnePassVAETrainer)):
            trainer = cls.build([cell], [paired], [unpaired], [domain.new_agents(cell, 1)])
            params = list(trainer.agents.parameters())
            if trainer.adversaries is not None:
                params += list(trainer.adversaries.parameters())
            out[name] = (trainer.train_step, params)
    return out


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


def layout(spec: CellSpec, rows: int) -> dict:
    """The first layer's forward with the weight as nn.Linear stores it (out x in, used transposed) and
    stored in x out."""
    x, w, b = torch.randn(rows, 784), torch.randn(spec.vae_hidden, 784), torch.randn(spec.vae_hidden)
    w_in_out = w.t().contiguous()
    as_stored = cpu_per_call(lambda: torch.addmm(b, x, w.t()), 300)
    transposed = cpu_per_call(lambda: torch.addmm(b, x, w_in_out), 300)
    print(f"layout, {rows} x 784 @ 784 x {spec.vae_hidden}: x @ Wᵀ (nn.Linear) {as_stored * 1e6:.0f} µs, "
          f"x @ W (stored in x out) {transposed * 1e6:.0f} µs ({as_stored / transposed:.2f}x)")
    return {"rows": rows, "linear_us": as_stored * 1e6, "in_out_us": transposed * 1e6}


def implicit_bf16(rows: int, hidden: int) -> dict | None:
    """oneDNN's bfloat16 for a float32 matmul: speed and error (the setting is restored after)."""
    matmul = getattr(getattr(torch.backends, "mkldnn", None), "matmul", None)
    if matmul is None or not hasattr(matmul, "fp32_precision"):
        print("implicit bf16: this torch has no torch.backends.mkldnn.matmul.fp32_precision")
        return None
    a, b = torch.randn(rows, 784), torch.randn(784, hidden)
    exact = a.double() @ b.double()
    before = matmul.fp32_precision
    try:
        fp32 = cpu_per_call(lambda: a @ b, 300)
        err32 = float((a @ b - exact).abs().max() / exact.abs().max())
        matmul.fp32_precision = "bf16"
        bf16 = cpu_per_call(lambda: a @ b, 300)
        err16 = float((a @ b - exact).abs().max() / exact.abs().max())
    finally:
        matmul.fp32_precision = before
    print(f"implicit bf16, {rows} x 784 @ 784 x {hidden}: float32 {fp32 * 1e6:.0f} µs (error {err32:.1e}), "
          f"bf16 {bf16 * 1e6:.0f} µs (error {err16:.1e}): {fp32 / bf16:.2f}x")
    return {"fp32_us": fp32 * 1e6, "bf16_us": bf16 * 1e6, "fp32_rel_error": err32, "bf16_rel_error": err16}


def allocator(updates: dict, names: list[str], n: int) -> list[dict]:
    """Page faults and CPU per update before and after retain_freed_memory (process-wide: run last)."""
    from asp_dist.training.stacked import retain_freed_memory

    out = []
    for setting in ("glibc default", "retain_freed_memory"):
        if setting == "retain_freed_memory":
            retain_freed_memory()
        for name in names:
            step = updates[name][0]
            cpu_per_call(step, 10, 1)
            faults, c = minor_faults(), time.process_time()
            for _ in range(n):
                step()
            ms, per = (time.process_time() - c) / n * 1e3, (minor_faults() - faults) / n
            print(f"allocator {setting:20s} {name:16s} {ms:6.2f} ms  {per:6.1f} page faults per update")
            out.append({"setting": setting, "update": name, "update_ms": ms, "faults_per_update": per})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--updates", type=int, default=200, help="updates per timed block")
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--keep-denormals", action="store_true",
                    help="time without flushing denormals (training flushes them: asp_dist.training.float_mode)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    spec = CellSpec(domain="vae", paired=32, vae_latent_dim=32).resolved()
    flushing = denormals_flushed()  # as training runs (asp_dist.training.float_mode); --keep-denormals: not
    if not args.keep_denormals:
        flushing.__enter__()
    updates = {**base_updates(spec), **cell_updates(spec)}
    rows = [roofline(name, step, params, args.updates, args.blocks) for name, (step, params) in updates.items()]
    result = {"machine": machine_info(), "load_before": load_before, "rows": rows,
              "layout": [layout(spec, r) for r in (spec.vae_base_batch, spec.batch_size + spec.paired,
                                                   spec.paired)],
              "implicit_bf16": implicit_bf16(spec.vae_base_batch, spec.vae_hidden),
              "allocator": allocator(updates, ["base", "asp"], args.updates),
              "load_after": os.getloadavg(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    print(f"load average before {load_before[0]:.2f}, after {result['load_after'][0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
