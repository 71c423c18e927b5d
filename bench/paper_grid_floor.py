"""The arithmetic floor of a grid: its floating-point work at the machine's matmul rate, and how
far a finished sweep of it was from that floor.

    OMP_NUM_THREADS=1 python bench/paper_grid_floor.py                          # the paper grid, 2 workers
    OMP_NUM_THREADS=1 python bench/paper_grid_floor.py --sweep results/paper-packed   # + the sweep's span

Work counted (forward + backward = 3 x forward, 2 flop per multiply-accumulate):
- VAE cells: train_steps x the update's work (bench_vae.update_flops: self-play batch, paired rows,
  discriminator), the paired pool and U encoded by the base, and the evaluation on eval_episodes
  test images (both encoders, four decodes). The ten cheap probes per cell are left out.
- VAE bases: one per distinct base key: base_train_steps x base_update_flops + its test evaluation.
- Particles and levers: a rough estimate, 6 x (parameters of the new agents, plus the
  discriminator's for ASP) x (rows per update: batch + paired rows + for ASP the real batch) x
  train_steps. Their networks have a few thousand weights: their work is small, and no matmul of
  theirs could run at the rate below, so the floor is the VAE's in practice.
The floor is the work / (the one-thread matmul rate, 128x784 @ 784x512 per CPU second, measured
here unless --rate is given) / workers. With --sweep, the sweep's span (manifest.json written → last
cell file written, as docs/performance.md's earlier grid figures) and span / floor, and per domain its CPU
time from the rows (data, training, evaluation, each base once) over the workers against its floor, and
when its last cell was written.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import pandas as pd  # noqa: E402
import torch  # noqa: E402
from bench_vae import base_update_flops, matmul_rate, update_flops  # noqa: E402

from asp_dist.core.registry import get_domain  # noqa: E402
from asp_dist.data.mnist import PIXELS  # noqa: E402
from asp_dist.domains.vae import PAIRED_BLOCK  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.sweep.spaces import expand  # noqa: E402
from asp_dist.training.adversary import Discriminator  # noqa: E402
from asp_dist.training.methods import method_weights  # noqa: E402


def vae_cell_flops(spec: CellSpec) -> float:
    d, h = spec.vae_latent_dim, spec.vae_hidden
    enc, dec = PIXELS * h + h * 2 * d, d * h + h * PIXELS
    w = method_weights(spec)
    data = 2 * PAIRED_BLOCK * max(1, math.ceil(spec.paired / PAIRED_BLOCK)) * (enc + dec) if spec.paired else 0
    data += 2 * spec.unpaired_size * enc if w.needs_adversary else 0
    evaluation = 2 * spec.eval_episodes * (2 * enc + 4 * dec)
    return spec.train_steps * update_flops(spec) + data + evaluation


def vae_base_flops(spec: CellSpec) -> float:
    d, h = spec.vae_latent_dim, spec.vae_hidden
    return spec.base_train_steps * base_update_flops(spec) + 2 * spec.eval_episodes * (PIXELS * h + h * 2 * d + d * h + h * PIXELS)


def small_cell_flops(spec: CellSpec, params: dict) -> float:
    """A rough estimate for the particle and lever cells (see the module docstring): it leaves out
    levers' several agents per game, replayed batches, rollout length and disc_steps."""
    w = method_weights(spec)
    key = (spec.domain, spec.base_key, spec.disc_hidden, spec.disc_layers)
    if key not in params:
        agents = get_domain(spec.domain).new_agents(spec, 0)
        dims = get_domain(spec.domain).channel_dims(spec)
        disc = sum(sum(p.numel() for p in Discriminator(dim, spec.disc_hidden, spec.disc_layers).parameters())
                   for dim in dims.values())
        params[key] = (sum(p.numel() for p in agents.parameters()), disc)
    agents, disc = params[key]
    rows = spec.batch_size + spec.paired
    work = agents * rows + (disc * (spec.batch_size + spec.unpaired_batch) if w.needs_adversary else 0)
    return 6 * work * spec.train_steps


def sweep_span_s(sweep: Path) -> tuple[float, int]:
    """Seconds from the sweep's manifest to its last cell file, and the number of cell files."""
    cells = list((sweep / "cells").rglob("*.parquet"))
    if not cells:
        raise SystemExit(f"{sweep}: no finished cells under cells/")
    start = (sweep / "manifest.json").stat().st_mtime
    return max(c.stat().st_mtime for c in cells) - start, len(cells)


def domain_split(sweep: Path, floor_min: dict[str, float], workers: int) -> dict[str, dict[str, float]]:
    """Per domain: its CPU time in the sweep's rows (training, evaluation, data and each base once) over the
    workers, against its floor; and when its last cell was written (minutes after the manifest)."""
    from asp_dist.results.store import read_rows

    rows = read_rows(sweep)
    start = (sweep / "manifest.json").stat().st_mtime
    finished = pd.to_datetime(rows["finished_at"], utc=True).map(lambda t: t.timestamp()) - start
    split = {}
    print(f"  {'domain':10s} {'cells':>6s} {'CPU min / workers':>18s} {'floor min':>10s} {'ratio':>6s} {'last cell at':>13s}")
    for domain, group in rows.groupby("domain"):
        cpu = group[["time_data_cpu_s", "time_train_cpu_s", "time_eval_cpu_s"]].sum().sum()
        cpu += group.drop_duplicates("base_key")["base_train_cpu_s"].sum()
        worker_min = cpu / 60 / workers
        split[domain] = {"cells": len(group), "cpu_min_per_worker": worker_min, "floor_min": floor_min.get(domain, 0.0),
                         "last_cell_min": float(finished[group.index].max() / 60)}
        print(f"  {domain:10s} {len(group):6d} {worker_min:18.1f} {split[domain]['floor_min']:10.1f} "
              f"{worker_min / max(split[domain]['floor_min'], 1e-9):6.2f} {split[domain]['last_cell_min']:13.1f}")
    return split


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--space", default="paper")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rate", type=float, help="GFLOP per CPU second of one thread (default: measured now)")
    ap.add_argument("--sweep", type=Path, help="a finished sweep of the space: report its span against the floor")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    specs = expand(args.space)
    work: dict[str, float] = defaultdict(float)
    bases, params = {}, {}
    for spec in specs:
        if spec.domain == "vae":
            work["vae cells"] += vae_cell_flops(spec)
            bases.setdefault(spec.base_key, spec)
        else:
            work[f"{spec.domain} cells (estimate)"] += small_cell_flops(spec, params)
    work["vae bases"] = sum(vae_base_flops(s) for s in bases.values())
    rate = args.rate or max(matmul_rate()[1] for _ in range(3))
    total = sum(work.values())
    floor_s = total / (rate * 1e9 * args.workers)
    print(f"{args.space}: {len(specs)} cells, {len(bases)} VAE bases; one-thread matmul rate {rate:.1f} GFLOP/s, "
          f"{args.workers} workers; load {os.getloadavg()[0]:.2f}")
    for name, flops in sorted(work.items(), key=lambda kv: -kv[1]):
        print(f"  {name:34s} {flops / 1e12:8.1f} TFLOP  {flops / (rate * 1e9 * args.workers) / 60:6.1f} min at the rate")
    print(f"  {'total':34s} {total / 1e12:8.1f} TFLOP  floor {floor_s / 60:.1f} min")
    out = {"space": args.space, "cells": len(specs), "vae_bases": len(bases), "rate_gflops": rate,
           "workers": args.workers, "tflop": {k: v / 1e12 for k, v in work.items()}, "floor_min": floor_s / 60}
    if args.sweep:
        span, n = sweep_span_s(args.sweep)
        out.update(sweep=str(args.sweep), span_min=span / 60, cell_files=n, span_over_floor=span / floor_s)
        print(f"{args.sweep}: {n} cells, span {span / 60:.1f} min = {span / floor_s:.2f} x the floor")
        floor_by_domain = defaultdict(float)
        for name, flops in work.items():
            floor_by_domain[name.split()[0]] += flops / (rate * 1e9 * args.workers) / 60
        out["by_domain"] = domain_split(args.sweep, floor_by_domain, args.workers)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
