"""Benchmark of the CommNet lever domain on one thread: base training, time per update per
method, one whole cell per method, and peak memory.

    python bench/bench_levers.py [--updates 300] [--paired 4] [--set key=value ...]

Wall and CPU seconds are both printed: on a shared machine wall time includes waiting for a
core, CPU time does not (CPU time still grows somewhat under contention: caches, SMT).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from _common import peak_rss_mib  # noqa: E402

from asp_dist.commands.common import parse_overrides  # noqa: E402
from asp_dist.core.registry import get_domain  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.bases import train_accepted_base  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402
from asp_dist.training.methods import method_weights  # noqa: E402
from asp_dist.training.trainer import Trainer  # noqa: E402


class Clock:
    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.wall, time.process_time() - self.cpu


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--updates", type=int, default=300)
    ap.add_argument("--paired", type=int, default=4)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a CellSpec field")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    overrides = parse_overrides(args.set)
    spec = CellSpec(domain="levers", paired=args.paired, trial=0, **overrides).resolved()
    domain = get_domain("levers")
    print(f"levers: hidden {spec.levers_hidden}, batch {spec.batch_size}, train_steps {spec.train_steps}, "
          f"base_train_steps {spec.base_train_steps}, paired {spec.paired}")

    with Clock() as c:
        base = train_accepted_base(spec)
    print(f"base: reward {base.score:.4f} after {base.attempts} attempt(s); {c.wall:.2f}s wall, {c.cpu:.2f}s CPU "
          f"({1e3 * c.cpu / (base.attempts * spec.base_train_steps):.2f} ms CPU per update)")

    for method in ("pc", "osp", "asp"):
        s = spec.replace(method=method).resolved()
        data_gen = torch.Generator().manual_seed(s.seed_for("data"))
        w = method_weights(s)
        paired = domain.paired(s, base.agents, s.paired, data_gen) if s.paired else {}
        unpaired = domain.unpaired(s, base.agents, s.unpaired_size, data_gen) if w.needs_adversary else {}
        trainer = Trainer(s, domain, domain.new_agents(s, s.seed_for("init")), paired, unpaired, w)
        for _ in range(20):
            trainer.train_step()
        with Clock() as c:
            for _ in range(args.updates):
                trainer.train_step()
        print(f"{method:>3} update: {1e3 * c.wall / args.updates:.2f} ms wall, {1e3 * c.cpu / args.updates:.2f} ms CPU")

    for method in ("pc", "osp", "asp"):
        with Clock() as c:
            row = run_cell(spec.replace(method=method), base=base)
        print(f"{method:>3} cell: {c.wall:.2f}s wall, {c.cpu:.2f}s CPU (train {row['time_train_wall_s']:.2f}s, "
              f"eval {row['time_eval_wall_s']:.3f}s wall); mixed error {row['eval_mixed']:.4f}")
    print(f"peak RSS {peak_rss_mib():.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
