"""What recording a learning curve costs: the same cells run with and without `curve=`,
interleaved (plain, curve, plain, curve, …) so that drift in machine speed hits both alike.

    OMP_NUM_THREADS=1 python bench/bench_curves.py --domains particles,vae --repeats 3

Default budgets are the paper's (25,000 particle updates, 1,000 VAE updates); the base is
trained once per domain and shared, so only training and evaluation are timed (CPU seconds).
Prints the median CPU time per cell of each variant and the overhead in percent.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.bases import train_accepted_base  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--domains", default="particles,vae")
    ap.add_argument("--method", default="asp")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--train-steps", type=int, default=None, help="override the domain's training budget")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    print(f"load average at start: {os.getloadavg()}")
    for domain in args.domains.split(","):
        knobs = {"train_steps": args.train_steps} if args.train_steps else {}
        spec = CellSpec(domain=domain, method=args.method, paired=4, trial=100, **knobs).resolved()
        base = train_accepted_base(spec)
        times: dict[str, list[float]] = {"plain": [], "curve": []}
        for _ in range(args.repeats):
            for variant in ("plain", "curve"):
                cpu = time.process_time()
                run_cell(spec, base=base, curve=[] if variant == "curve" else None)
                times[variant].append(time.process_time() - cpu)
        plain, curve = statistics.median(times["plain"]), statistics.median(times["curve"])
        print(f"{domain} {args.method} ({spec.train_steps} updates): plain {plain:.2f} s CPU, with curve "
              f"{curve:.2f} s CPU, overhead {100 * (curve / plain - 1):+.1f} %  (runs: {times})")
    print(f"load average at end: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
