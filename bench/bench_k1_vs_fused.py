"""A 1-member PackedParticleTrainer against the single-cell FusedParticleTrainer, per update.

    OMP_NUM_THREADS=1 python bench/bench_k1_vs_fused.py [--updates 384] [--blocks 5]

The question (issue 13): can the single-cell particle path train a cell as a one-member pack and
the hand-derived single-cell kernel go? Cells: paper settings, trial 0, paired 1 / 3 / 6 per method.
One process; per method, fused and 1-member-pack blocks alternate (each block: --updates updates of
each of the method's cells, from the start of training; a multiple of the pack's CHUNK of 128 draws);
CPU time per update, median over blocks, and the pack/fused ratio. On a shared machine only the
ratio means something: the load average is printed.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

from asp_dist.domains import get_domain  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.fast.particles import FusedParticleTrainer  # noqa: E402
from asp_dist.training.methods import method_weights  # noqa: E402
from asp_dist.training.packed.particles import PackedParticleTrainer  # noqa: E402

METHODS, PAIRED = ("pc", "osp", "asp"), (1, 3, 6)


def data_for(spec: CellSpec, base) -> tuple[dict, dict]:
    domain = get_domain("particles")
    gen = torch.Generator().manual_seed(spec.seed_for("data"))
    paired = domain.paired(spec, base, spec.paired, gen) if spec.paired else {}
    unpaired = domain.unpaired(spec, base, spec.unpaired_size, gen) if method_weights(spec).needs_adversary else {}
    return paired, unpaired


def cpu_of(steps, updates: int) -> float:
    c0 = time.process_time()
    for _ in range(updates):
        for step in steps:
            step()
    return time.process_time() - c0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--updates", type=int, default=384)
    ap.add_argument("--blocks", type=int, default=5)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    domain = get_domain("particles")
    print(f"# torch {torch.__version__} ({torch.backends.cpu.get_cpu_capability()}), 1 thread, "
          f"load average {os.getloadavg()} at start", flush=True)
    print("| method | fused CPU ms/update | 1-member pack CPU ms/update | pack / fused | blocks (fused, pack) |")
    print("|---|---:|---:|---:|---|")
    ratios = []
    for method in METHODS:
        specs = [CellSpec(domain="particles", method=method, paired=p, trial=0).resolved() for p in PAIRED]
        base = domain.new_agents(specs[0], 10_000)
        data = [data_for(s, base) for s in specs]
        fused = [FusedParticleTrainer(s, domain, domain.new_agents(s, s.seed_for("init")), d[0], d[1],
                                      method_weights(s)) for s, d in zip(specs, data)]
        packs = [PackedParticleTrainer([s], [d[0]], [d[1]], [domain.new_agents(s, s.seed_for("init"))])
                 for s, d in zip(specs, data)]
        fsteps, psteps = [t.train_step for t in fused], [p.train_step for p in packs]
        cpu_of(fsteps, 128), cpu_of(psteps, 128)  # warm-up (one chunk of draws)
        fb, pb = [], []
        n = args.updates * len(specs)
        for _ in range(args.blocks):
            fb.append(cpu_of(fsteps, args.updates) / n * 1e3)
            pb.append(cpu_of(psteps, args.updates) / n * 1e3)
        f, p = statistics.median(fb), statistics.median(pb)
        ratios.append(p / f)
        print(f"| {method} | {f:.3f} | {p:.3f} | {p / f:.3f} | {' '.join(f'{x:.3f}' for x in fb)}; "
              f"{' '.join(f'{x:.3f}' for x in pb)} |", flush=True)
    print(f"# load average {os.getloadavg()} at end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
