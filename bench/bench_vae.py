"""Benchmark of the MNIST VAE domain on one thread: time per update per method, per cell, peak
memory, and the floating-point work of an update against the machine's measured matmul rate.

    python bench/bench_vae.py [--updates 200] [--cells] [--latent 32] [--paired 32]

--cells also runs one whole cell per method at the domain's defaults (train_steps updates plus
evaluation on the 10k test images) on a base trained with --base-steps updates (the base's
cost is reported separately: per update and extrapolated to the paper's 5,000).
bench/bench_packing.py (the packing figures in one run) imports its operation counts and timers.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from _common import cell_timing, peak_rss_mib  # noqa: E402

from asp_dist.core.registry import get_domain  # noqa: E402
from asp_dist.data.mnist import PIXELS, load_mnist  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.bases import BaseModel  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402
from asp_dist.training.engines import lone_trainer  # noqa: E402
from asp_dist.training.methods import method_weights  # noqa: E402


def matmul_rate(m: int = 128, k: int = 784, n: int = 512, reps: int = 300) -> tuple[float, float]:
    """GFLOP per wall second and per CPU second of an (m x k) @ (k x n) float32 matmul (default: the
    shape of a base update's first layer), after 20 warm-up products."""
    a, b = torch.randn(m, k), torch.randn(k, n)
    for _ in range(20):
        a @ b
    t, c = time.perf_counter(), time.process_time()
    for _ in range(reps):
        a @ b
    flop = 2 * m * k * n * reps
    return flop / (time.perf_counter() - t) / 1e9, flop / max(time.process_time() - c, 1e-9) / 1e9


def matmul_gflops(m: int = 128, k: int = 784, n: int = 512, reps: int = 300) -> float:
    return matmul_rate(m, k, n, reps)[0]


def vae_macs(d: int, hidden: int) -> int:
    """Multiply-accumulates of one image through encoder and decoder (forward)."""
    return PIXELS * hidden + hidden * 2 * d + d * hidden + hidden * PIXELS


def base_update_flops(spec: CellSpec) -> float:
    """Floating-point work of one base update (vae_base_batch images, forward + backward)."""
    return spec.vae_base_batch * 2 * 3 * vae_macs(spec.vae_latent_dim, spec.vae_hidden)


def base_update_time(spec: CellSpec, steps: int, seed: int = 0) -> tuple[float, float]:
    """(wall, CPU) seconds per base update of the domain's own train_base, run for `steps` (>= 2)
    updates and timed between its first and last progress report: without the set-up, the first
    update(s) and the final evaluation on the test images."""
    if steps < 2:
        raise ValueError(f"base_update_time needs at least 2 steps, got {steps}")
    marks: list[tuple[int, float, float]] = []

    def progress(phase: str, done: int, total: int, info: dict) -> None:
        marks.append((done, time.perf_counter(), time.process_time()))

    get_domain("vae").train_base(spec.replace(base_train_steps=steps).resolved(), seed, progress)
    (d0, w0, c0), (d1, w1, c1) = marks[0], marks[-1]
    return (w1 - w0) / (d1 - d0), (c1 - c0) / (d1 - d0)


def update_flops(spec: CellSpec) -> float:
    """Floating-point work of one training update (forward + backward ≈ 3 × forward)."""
    w = method_weights(spec)
    per_image = 2 * 3 * vae_macs(spec.vae_latent_dim, spec.vae_hidden)
    flops = 0.0
    if w.needs_self_play:
        flops += spec.batch_size * per_image
    if w.paired:
        flops += spec.paired * per_image
    if w.needs_adversary:
        disc = spec.vae_latent_dim * spec.disc_hidden + (spec.disc_layers - 1) * spec.disc_hidden ** 2 + spec.disc_hidden
        flops += 2 * 3 * disc * (spec.batch_size + spec.unpaired_batch) * 2  # disc step + model term
    return flops


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--updates", type=int, default=200)
    ap.add_argument("--latent", type=int, default=32)
    ap.add_argument("--paired", type=int, default=32)
    ap.add_argument("--base-steps", type=int, default=300)
    ap.add_argument("--cells", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    t = time.perf_counter()
    load_mnist()
    print(f"MNIST load + verify: {time.perf_counter() - t:.2f}s  (peak RSS {peak_rss_mib():.0f} MiB)")
    rate = matmul_gflops()
    print(f"matmul 128x784 @ 784x512, 1 thread: {rate:.1f} GFLOP/s (the reference rate below)")
    print(f"matmul 64x784 @ 784x512: {matmul_gflops(64):.1f} GFLOP/s; 32x784: {matmul_gflops(32):.1f}; "
          f"10000x784: {matmul_gflops(10_000, reps=5):.1f}")

    domain = get_domain("vae")
    spec0 = CellSpec(domain="vae", paired=args.paired, vae_latent_dim=args.latent, base_train_steps=args.base_steps)
    spec0 = spec0.resolved()
    t, c = time.perf_counter(), time.process_time()
    agents, score = domain.train_base(spec0, seed=0)
    per_base_update = (time.perf_counter() - t) / args.base_steps
    per_base_cpu = (time.process_time() - c) / args.base_steps
    base = BaseModel(agents=agents, key=spec0.base_key, score=score, attempts=1, seed=0)
    base_flops = base_update_flops(spec0)
    # GFLOP/s are per CPU second: on a shared machine wall time measures the neighbours too.
    print(f"base update (batch {spec0.vae_base_batch}): {per_base_update * 1e3:.1f} ms wall, {per_base_cpu * 1e3:.1f} ms CPU "
          f"({base_flops / per_base_cpu / 1e9:.1f} GFLOP/s per CPU s, {base_flops / per_base_cpu / 1e9 / rate:.0%} of matmul) "
          f"-> 5,000 updates ≈ {per_base_cpu * 5000:.0f} CPU s")

    for method in ("pc", "osp", "asp"):
        spec = spec0.replace(method=method).resolved()
        data_gen = torch.Generator().manual_seed(1)
        paired = domain.paired(spec, base.agents, spec.paired, data_gen)
        unpaired = domain.unpaired(spec, base.agents, spec.unpaired_size, data_gen)
        # the trainer run_cell picks (the VAE's one-pass update; bench/bench_packing.py times the reference beside it)
        trainer = lone_trainer(spec).build([spec], [paired], [unpaired], [domain.new_agents(spec, 1)])
        for _ in range(10):
            trainer.train_step()
        t, c = time.perf_counter(), time.process_time()
        for _ in range(args.updates):
            trainer.train_step()
        wall, cpu = (time.perf_counter() - t) / args.updates, (time.process_time() - c) / args.updates
        flops = update_flops(spec)
        print(f"{method:4s} update (paired {spec.paired}, d {spec.vae_latent_dim}): {wall * 1e3:.2f} ms wall, "
              f"{cpu * 1e3:.2f} ms CPU; {flops / 1e9:.3f} GFLOP -> {flops / cpu / 1e9:.1f} GFLOP/s per CPU s "
              f"({flops / cpu / 1e9 / rate:.0%} of matmul); x {spec.train_steps} steps ≈ {cpu * spec.train_steps:.1f} CPU s")

    if args.cells:
        for method in ("pc", "osp", "asp"):
            spec = spec0.replace(method=method)
            row = run_cell(spec, base=base)
            print(f"{method:4s} cell: {cell_timing(row)}")
    print(f"peak RSS: {peak_rss_mib():.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
