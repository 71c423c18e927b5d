"""How good can a VAE base get? Trains bases only and prints their test MSE (the paper: 0.006).

    python bench/vae_base_quality.py --trials 100,101 --set base_train_steps=5000,20000 \
        --set vae_kl_weight=1.0,0.5 --out results/calibration/vae_bases.csv

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

from asp_dist.cli import parse_overrides  # noqa: E402
from asp_dist.domains import get_domain  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", default="100")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=V1,V2")
    ap.add_argument("--out", type=Path, default=Path("results/calibration/vae_bases.csv"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    axes = {k: str(v).split(",") for k, v in (item.split("=", 1) for item in args.set)}
    domain = get_domain("vae")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    new_file = not args.out.exists()
    with args.out.open("a", newline="") as fh:
        writer = None
        for trial in (int(t) for t in args.trials.split(",")):
            for combo in itertools.product(*axes.values()):
                knobs = parse_overrides([f"{k}={v}" for k, v in zip(axes, combo)])
                spec = CellSpec(domain="vae", trial=trial, **knobs).resolved()
                wall, cpu = time.perf_counter(), time.process_time()
                _, mse = domain.train_base(spec, spec.seed_for("base"))
                row = {"trial": trial, **knobs, "test_mse": round(float(mse), 6),
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
