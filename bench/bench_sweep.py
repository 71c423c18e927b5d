"""Sweep overhead benchmark: the same 20 signaling cells run

    (a) one after another in this process,
    (b) with multiprocessing.Pool(2),
    (c) through `asp-dist sweep --workers 2` (embedded Ray),
    (d) through `asp-dist sweep --workers 1`,

and the ratios (c)/(b) (target <= 1.05) and (d)/(c) (target >= 1.85) reported. For the sweeps
two times are given: the whole command as a user sees it (Ray start-up included) and the span
from the first cell's start to the last cell's file (the steady-state cost per cell).

    python bench/bench_sweep.py [--steps 600] [--out bench/results/sweep.json]

Every process runs with one torch thread. The machine's load average is printed: timings
taken while other jobs run are noisy.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.sweep.base_cache import get_base  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402

METHODS = ("osp", "asp")
PAIRED = (0, 2, 4, 8, 16)
TRIALS = (0, 1)


def bench_space(steps: int) -> str:
    return (f"description = \"bench: 20 signaling cells\"\n[[grid]]\nfixed = {{ train_steps = {steps} }}\n"
            f"[grid.axes]\ndomain = [\"signaling\"]\nmethod = {list(METHODS)}\npaired = {list(PAIRED)}\n"
            f"trial = {list(TRIALS)}\n").replace("'", '"')


def specs(steps: int) -> list[CellSpec]:
    return [CellSpec(domain="signaling", method=m, paired=p, trial=t, train_steps=steps).resolved()
            for t in TRIALS for p in PAIRED for m in METHODS]


def _one_cell(args) -> float:
    """CPU seconds of one cell (its row's time_total_cpu_s)."""
    spec, cache = args
    torch.set_num_threads(1)
    base, _ = get_base(spec, Path(cache))
    return run_cell(spec, base=base)["time_total_cpu_s"]


def run_sequential(cells, cache) -> tuple[float, float]:
    t = time.perf_counter()
    cpu = sum(_one_cell((spec, cache)) for spec in cells)
    return time.perf_counter() - t, cpu


def run_pool(cells, cache) -> tuple[float, float]:
    t = time.perf_counter()
    with mp.get_context("spawn").Pool(2) as pool:
        cpu = sum(pool.map(_one_cell, [(s, cache) for s in cells], chunksize=1))
    return time.perf_counter() - t, cpu


def run_sweep_cli(space: Path, results: Path, workers: int) -> tuple[float, float, float]:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "asp_dist.cli", "sweep", str(space), "--name", f"w{workers}",
                    "--results", str(results), "--workers", str(workers)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    total = time.perf_counter() - t
    from asp_dist.results.store import read_rows

    df = read_rows(results / f"w{workers}")
    files = sorted((results / f"w{workers}" / "cells").glob("domain=*/method=*/*.parquet"))
    ends = {f.stem: f.stat().st_mtime for f in files}
    starts = [ends[r.cell_id] - r.time_total_wall_s for r in df.itertuples()]
    return total, max(ends.values()) - min(starts), float(df["time_total_cpu_s"].sum())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=600, help="train_steps per cell (about 1-2 s each)")
    ap.add_argument("--out", default="bench/results/sweep.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cells = specs(args.steps)
    load_before = os.getloadavg()
    out: dict = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "cells": len(cells),
                 "train_steps": args.steps, "cpus": os.cpu_count(), "machine": platform.platform(),
                 "processor": platform.processor() or platform.machine(), "loadavg_before": load_before}
    with tempfile.TemporaryDirectory(prefix="asp-bench-") as tmp:
        tmp = Path(tmp)
        space = tmp / "bench.toml"
        space.write_text(bench_space(args.steps))
        out["sequential_s"], out["sequential_cell_cpu_s"] = run_sequential(cells, tmp / "bases-seq")
        print(f"(a) sequential        {out['sequential_s']:6.1f} s", flush=True)
        out["pool2_s"], out["pool2_cell_cpu_s"] = run_pool(cells, tmp / "bases-pool")
        print(f"(b) Pool(2)           {out['pool2_s']:6.1f} s", flush=True)
        out["sweep2_total_s"], out["sweep2_span_s"], out["sweep2_cell_cpu_s"] = run_sweep_cli(space, tmp / "results", 2)
        print(f"(c) sweep --workers 2 {out['sweep2_total_s']:6.1f} s total, {out['sweep2_span_s']:.1f} s cells", flush=True)
        out["sweep1_total_s"], out["sweep1_span_s"], out["sweep1_cell_cpu_s"] = run_sweep_cli(space, tmp / "results", 1)
        print(f"(d) sweep --workers 1 {out['sweep1_total_s']:6.1f} s total, {out['sweep1_span_s']:.1f} s cells", flush=True)
    out["loadavg_after"] = os.getloadavg()
    out["ratio_sweep2_over_pool_total"] = out["sweep2_total_s"] / out["pool2_s"]
    out["ratio_sweep2_over_pool_span"] = out["sweep2_span_s"] / out["pool2_s"]
    out["speedup_workers2_total"] = out["sweep1_total_s"] / out["sweep2_total_s"]
    out["speedup_workers2_span"] = out["sweep1_span_s"] / out["sweep2_span_s"]
    out["speedup_pool_over_sequential"] = out["sequential_s"] / out["pool2_s"]
    # Cores the cells actually got (CPU seconds of the cells / wall seconds): 2.0 is an idle
    # 2-core machine with two workers; far less means other jobs were taking the CPU.
    out["cores_used_pool2"] = out["pool2_cell_cpu_s"] / out["pool2_s"]
    out["cores_used_sweep2_span"] = out["sweep2_cell_cpu_s"] / out["sweep2_span_s"]
    out["cores_used_sequential"] = out["sequential_cell_cpu_s"] / out["sequential_s"]
    print(json.dumps(out, indent=1))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
