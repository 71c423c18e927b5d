"""Packed lever training vs today's single-cell path: time per member-update and peak memory.

    OMP_NUM_THREADS=1 python bench/bench_packed_levers.py               # K = 1, 8, 21, 64 (about 4 minutes idle)
    OMP_NUM_THREADS=1 python bench/bench_packed_levers.py --by-method   # also packs of one method

Cells are the paper-levers grid's (PC / OSP / ASP x paired {0, 1, 2, 4, 6, 8, 10} x trials, paper
settings: hidden 32, batch 128, replay 4,096, |U| 4,096) in the order trial, paired, method: a pack
of K holds the first K, so K = 21 is one trial's cells and every K has the grid's mix of methods.
For each K, in a fresh process (its peak RSS is its own, ru_maxrss):

- packed: one PackedLeverTrainer of the K cells (asp_dist/training/packed/levers.py);
- single: the same K cells one at a time on the trainer run_cell picks (choose_trainer: the
  reference autograd Trainer for lever cells), i.e. today's sweep path. K = 1 is one trial's 21
  cells, each alone: on the single path and as 1-member packs (the packed trainer's own overhead).

Time per member-update = wall (and CPU) time of --updates updates / (updates x K), median over
--blocks blocks; packed and single blocks alternate, so a load that changes during the run hits
both. On a shared machine the CPU-time ratio is the steadier one.
Peak RSS is read after the packed phase (before any single trainer exists); the K = 1 process
first measures a worker of today's sweep: one ASP cell (the largest: U and two discriminators)
and nothing else. Creating a pack also raises glibc's mmap/trim thresholds for the process
(stacked.retain_freed_memory); the single path's timings are the same with or without that.
The base of each trial is an untrained CommNet (an update costs the same whatever the base
taught); P and U are sampled from it as run_cell samples them. Updates are timed after 20 warm-up
updates (the replay buffer holds games from then on, as in 99.9 % of a cell's updates); about 1 in
10 records its losses (a curve window), against about 1 in 5 over a whole cell. Load on a shared
machine inflates every figure: the load average is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from _common import peak_rss_mib  # noqa: E402

from asp_dist.domains import get_domain  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.cell import choose_trainer  # noqa: E402
from asp_dist.training.methods import method_weights  # noqa: E402
from asp_dist.training.packed.levers import PackedLeverTrainer  # noqa: E402

METHODS, PAIRED = ("pc", "osp", "asp"), (0, 1, 2, 4, 6, 8, 10)


def grid_cells(k: int, method: str | None) -> list[CellSpec]:
    cells, trial = [], 0
    while len(cells) < k:
        cells += [CellSpec(domain="levers", method=m, paired=p, trial=trial).resolved()
                  for p in PAIRED for m in METHODS if method in (None, m)]
        trial += 1
    return cells[:k]


def cell_data(specs: list[CellSpec]) -> list[tuple[dict, dict]]:
    """P and U per cell, as run_cell samples them (shared by the methods of one trial and paired count)."""
    domain, bases, cache, out = get_domain("levers"), {}, {}, []
    for s in specs:
        base = bases.setdefault(s.trial, domain.new_agents(s, 10_000 + s.trial))
        key = (s.trial, s.paired)
        if key not in cache:
            gen = torch.Generator().manual_seed(s.seed_for("data"))
            cache[key] = [domain.paired(s, base, s.paired, gen) if s.paired else {}, gen, None]
        entry = cache[key]
        if method_weights(s).needs_adversary and entry[2] is None:
            entry[2] = domain.unpaired(s, base, s.unpaired_size, entry[1])
        out.append((entry[0], entry[2] if method_weights(s).needs_adversary else {}))
    return out


def timed(step, updates: int) -> tuple[float, float]:
    """(wall, CPU) seconds of `updates` calls."""
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(updates):
        step()
    return time.perf_counter() - t0, time.process_time() - c0


def ms_per(times: list[tuple[float, float]], n: int) -> tuple[float, float]:
    return sum(t[0] for t in times) / n * 1e3, sum(t[1] for t in times) / n * 1e3


def one(k: int, method: str | None, updates: int, blocks: int) -> dict:
    """One process: K = 1 is the 21 cells of trial 0 each alone (single path and 1-member packs);
    K > 1 the first K cells as one pack (ASP members first, as run_pack orders them) and,
    interleaved, the same cells alone."""
    torch.set_num_threads(1)
    domain = get_domain("levers")

    def agents(s):
        return domain.new_agents(s, s.seed_for("init"))

    def single(s, d):
        return choose_trainer(s, domain, agents(s), d[0], d[1], method_weights(s))

    out: dict = {"k": k}
    if k == 1:  # a worker of today's sweep: one ASP cell (the largest: U), nothing else in the process
        asp = grid_cells(21, "asp")[-1]
        trainer = single(asp, cell_data([asp])[0])
        timed(trainer.train_step, 20)
        out["rss_single_mib"] = peak_rss_mib()
        del trainer
    specs = grid_cells(21 if k == 1 else k, method)
    specs.sort(key=lambda s: not method_weights(s).needs_adversary)
    data = cell_data(specs)
    out["rss_data_mib"] = peak_rss_mib()
    groups = [[i] for i in range(len(specs))] if k == 1 else [list(range(len(specs)))]
    packs = [PackedLeverTrainer([specs[i] for i in g], [data[i][0] for i in g], [data[i][1] for i in g],
                                [agents(specs[i]) for i in g]) for g in groups]
    for p in packs:
        timed(p.train_step, 20)
    out.update(rss_packed_mib=peak_rss_mib(), mix={m: sum(s.method == m for s in specs) for m in METHODS},
               load_start=os.getloadavg()[0])
    singles = [single(s, d) for s, d in zip(specs, data)]
    for t in singles:
        timed(t.train_step, 20)
    out["single_trainer"] = sorted({type(t).__name__ for t in singles})
    per = updates * len(specs)
    packed, alone = [], []  # (wall, CPU) ms per member-update, per block
    for _ in range(blocks):
        packed.append(ms_per([timed(p.train_step, updates) for p in packs], per))
        alone.append(ms_per([timed(t.train_step, updates) for t in singles], per))
    for name, blocks_ in (("packed", packed), ("single", alone)):
        out[f"{name}_ms"] = statistics.median(b[0] for b in blocks_)
        out[f"{name}_cpu_ms"] = statistics.median(b[1] for b in blocks_)
        out[f"{name}_blocks"] = blocks_
    out["speedup"] = out["single_ms"] / out["packed_ms"]
    out["speedup_cpu"] = out["single_cpu_ms"] / out["packed_cpu_ms"]
    out["load_end"] = os.getloadavg()[0]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ks", default="1,8,21,64", help="pack sizes")
    ap.add_argument("--updates", type=int, default=100, help="updates per timing block")
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--by-method", action="store_true", help="also time packs of one method (K = 21 and the largest)")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--method", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", help="write every figure as JSON lines here")
    args = ap.parse_args(argv)
    if args.one is not None:
        print(json.dumps(one(args.one, args.method, args.updates, args.blocks)))
        return 0

    ks = [int(k) for k in args.ks.split(",")]
    runs = [(k, None) for k in ks]
    if args.by_method:
        runs += [(k, m) for m in METHODS for k in sorted({21, max(ks)})]
    print(f"# {platform.node()} {platform.processor() or platform.machine()}, torch {torch.__version__} "
          f"({torch.backends.cpu.get_cpu_capability()}), 1 thread, load average {os.getloadavg()[0]:.2f} at start")
    print("| K | cells (pc/osp/asp) | single path, ms per member-update (wall / CPU) | packed (wall / CPU) "
          "| speed-up (wall / CPU) | peak RSS | load |")
    print("|---|---|---|---|---|---|---|")
    lines = []
    for k, method in runs:
        cmd = [sys.executable, __file__, "--one", str(k), "--updates", str(args.updates), "--blocks", str(args.blocks)]
        if method:
            cmd += ["--method", method]
        proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
        if proc.returncode:
            sys.stderr.write(proc.stderr)
            return proc.returncode
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        r["method"] = method
        lines.append(r)
        mix = "/".join(str(r["mix"][m]) for m in METHODS) + (" (each alone)" if k == 1 else "")
        rss = f"{r['rss_packed_mib']:.0f} MiB (data {r['rss_data_mib']:.0f})"
        if "rss_single_mib" in r:
            rss = f"single-cell worker {r['rss_single_mib']:.0f} MiB; " + rss
        print(f"| {k} | {mix} | {r['single_ms']:.3f} / {r['single_cpu_ms']:.3f} | {r['packed_ms']:.3f} / "
              f"{r['packed_cpu_ms']:.3f} | {r['speedup']:.1f}x / {r['speedup_cpu']:.1f}x | {rss} "
              f"| {r['load_start']:.1f}-{r['load_end']:.1f} |", flush=True)
    print(f"# load average {os.getloadavg()[0]:.2f} at end")
    if args.out:
        with open(args.out, "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
