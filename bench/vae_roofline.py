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
import os
import resource
import sys
import time
from pathlib import Path
from typing import Callable

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from _common import machine_info  # noqa: E402
from _roofline import cpu_per_call, finish, roofline  # noqa: E402

from asp_dist.core.registry import get_domain  # noqa: E402
from asp_dist.domains.vae import VAEDomain  # noqa: E402
from asp_dist.domains.vae.base_update import HandDerivedBaseUpdate  # noqa: E402
from asp_dist.domains.vae.fast import OnePassVAETrainer  # noqa: E402
from asp_dist.domains.vae.game import VAE, as_float, image_rows, train_images  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.engines import lone_trainer  # noqa: E402
from asp_dist.training.float_mode import denormals_flushed  # noqa: E402


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
              "allocator": allocator(updates, ["base", "asp"], args.updates)}
    finish(result, load_before, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
