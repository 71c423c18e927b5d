"""Bases only: how good do they get, and does every trial get one? (docs/reproduction.md)

    python bench/base_quality.py --domain vae --trials 100,101 --set base_train_steps=5000,20000 \
        --set vae_kl_weight=1.0,0.5 --out results/calibration/vae_bases.csv
    python bench/base_quality.py --domain particles --trials 100-199 --set base_steps_growth=1.5 \
        --set base_max_attempts=5 --out results/calibration/particle_bases.csv

(the reproduction study's run, 2026-11-24, when 5 attempts and growth 1.0 were the particle defaults;
they are 10 and 1.5 since 2026-11-25, so a run without --set now uses those)

Each base goes through the same acceptance loop as a sweep's (train_accepted_base: retries
with the next seed, budget growing by base_steps_growth); a trial with no accepted base is a
row with accepted = False.

Each --set KEY=V1,V2,… is an axis; every combination runs on every trial. Trials are
calibration ids (100–199): nothing here touches a confirmatory trial. Rows are appended to
--out as they finish, so an interrupted run keeps what it measured.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

from asp_dist.commands.common import parse_overrides  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.bases import BaseRejected, train_accepted_base  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--domain", default="vae")
    ap.add_argument("--trials", default="100", help="comma list or FIRST-LAST")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=V1,V2")
    ap.add_argument("--out", type=Path, default=Path("results/calibration/vae_bases.csv"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    axes = {k: str(v).split(",") for k, v in (item.split("=", 1) for item in args.set)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    new_file = not args.out.exists()
    with args.out.open("a", newline="") as fh:
        writer = None
        first, _, last = args.trials.partition("-")
        trials = range(int(first), int(last) + 1) if last else [int(t) for t in args.trials.split(",")]
        for trial in trials:
            for combo in itertools.product(*axes.values()):
                knobs = parse_overrides([f"{k}={v}" for k, v in zip(axes, combo)])
                spec = CellSpec(domain=args.domain, trial=trial, **knobs).resolved()
                wall, cpu = time.perf_counter(), time.process_time()
                try:
                    base = train_accepted_base(spec)
                    accepted, score, attempts, scores = True, base.score, base.attempts, base.attempt_scores
                except BaseRejected as e:
                    accepted, score, attempts, scores = False, None, spec.base_max_attempts, str(e)
                row = {"domain": args.domain, "trial": trial, **knobs, "accepted": accepted,
                       "score": None if score is None else round(float(score), 6), "attempts": attempts,
                       "attempt_scores": str([round(x, 4) for x in scores]) if accepted else scores,
                       "wall_s": round(time.perf_counter() - wall, 1), "cpu_s": round(time.process_time() - cpu, 1)}
                print(row, flush=True)
                if writer is None:
                    writer = csv.DictWriter(fh, fieldnames=list(row))
                    if new_file:
                        writer.writeheader()
                writer.writerow(row)
                fh.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
