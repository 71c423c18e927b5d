"""Particle world speed and memory on one thread: base training, per-update time per method,
and (optionally) whole cells at paper settings.

    python bench/bench_particles.py                      # base + per-update times (about a minute)
    python bench/bench_particles.py --cells pc,osp,asp   # also one full cell per method (minutes)

Per-update time is given for the trainer that cells run (a one-member pack of asp_dist/domains/particles/packed.py,
run_cell's lone trainer) and for the autograd reference it is tested against; it is the median over blocks of --updates updates after a warm-up, with the
paper's batch (8 envs), the full paired set (6) and the ASP discriminator where it applies.
Peak memory is the process's maximum resident set size (ru_maxrss) after each phase.
Load on a shared machine inflates every figure: the load average is printed with them.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from _common import cell_timing, peak_rss_mib  # noqa: E402

from asp_dist.core.registry import get_domain  # noqa: E402
from asp_dist.domains.particles.packed import PackedParticleTrainer  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.bases import train_accepted_base  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402
from asp_dist.training.engines import lone_trainer  # noqa: E402
from asp_dist.training.methods import method_weights  # noqa: E402
from asp_dist.training.trainer import Trainer  # noqa: E402


def per_update_ms(spec: CellSpec, base, updates: int, blocks: int, engine: str) -> list[float]:
    """engine: 'pack' (the one-member pack run_cell trains on: engines.lone_trainer) or 'autograd' (the reference)."""
    domain = get_domain(spec.domain)
    data_gen = torch.Generator().manual_seed(0)
    paired = domain.paired(spec, base.agents, spec.paired, data_gen)
    weights = method_weights(spec)
    unpaired = domain.unpaired(spec, base.agents, spec.unpaired_size, data_gen) if weights.needs_adversary else {}
    agents = domain.new_agents(spec, 1)
    if engine == "pack":  # what run_cell runs: a pack of one wherever the packed trainer implements the knobs
        assert lone_trainer(spec) is PackedParticleTrainer, f"{spec.cell_id}: the packed trainer does not implement these knobs"
        trainer = PackedParticleTrainer.build([spec], [paired], [unpaired], [agents])
    else:
        trainer = Trainer(spec, domain, agents, paired, unpaired, weights)
    for _ in range(100):  # warm-up
        trainer.train_step()
    times = []
    for _ in range(blocks):
        t0 = time.perf_counter()
        for _ in range(updates):
            trainer.train_step()
        times.append((time.perf_counter() - t0) / updates * 1e3)
    return times


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--paired", type=int, default=6)
    ap.add_argument("--trial", type=int, default=0)
    ap.add_argument("--updates", type=int, default=500, help="updates per timing block")
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--cells", default="", help="comma-separated methods to run as full cells (paper settings)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    print(f"# {platform.node()} {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"1 thread, load average {os.getloadavg()[0]:.2f} at start")
    spec0 = CellSpec(domain="particles", paired=args.paired, trial=args.trial).resolved()
    t0, c0 = time.perf_counter(), time.process_time()
    base = train_accepted_base(spec0)
    print(f"base: score {base.score:.1f} after {base.attempts} attempt(s); "
          f"{time.perf_counter() - t0:.1f} s wall, {time.process_time() - c0:.1f} s CPU; "
          f"peak RSS {peak_rss_mib():.0f} MiB")

    for method, engine in [(m, e) for m in ("pc", "osp", "asp") for e in ("pack", "autograd")]:
        spec = spec0.replace(method=method).resolved()
        ms = per_update_ms(spec, base, args.updates, args.blocks, engine)
        print(f"per-update {method} ({engine}): median {statistics.median(ms):.3f} ms (blocks {', '.join(f'{m:.3f}' for m in ms)}); "
              f"x {spec.train_steps} updates = {statistics.median(ms) * spec.train_steps / 1e3:.1f} s; "
              f"peak RSS {peak_rss_mib():.0f} MiB")

    for method in filter(None, args.cells.split(",")):
        spec = spec0.replace(method=method)
        row = run_cell(spec, base=base)
        print(f"cell {method} (base shared): {cell_timing(row)}; mixed {row['eval_mixed']:.1f}; "
              f"peak RSS {peak_rss_mib():.0f} MiB")
    print(f"# load average {os.getloadavg()[0]:.2f} at end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
