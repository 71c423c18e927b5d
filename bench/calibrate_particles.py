"""λ0 / λ1 calibration grid for the particle world, on trials kept apart from the result runs.

    python bench/calibrate_particles.py --trials 100,101 --paired 4 --set train_steps=5000 \
        --out results/local/particles_calib.parquet

One base per trial (trained once, shared); for each (trial, paired): OSP at every λ0 of
--lambda-paired and ASP at every λ1 of --lambda-unpaired (with the default λ0). Rows are
appended after every cell; a table of the median mixed reward per setting is printed at the end.
The domain defaults apply: since 2026-11-25 a particle ASP cell warms λ1 up over the first half
(`--set lambda_unpaired_schedule=constant` gives the constant λ1 this grid was first run with).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import pandas as pd  # noqa: E402
import torch  # noqa: E402

from asp_dist.commands.common import parse_overrides  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.training.bases import train_accepted_base  # noqa: E402
from asp_dist.training.cell import run_cell  # noqa: E402


def floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", default="100,101")
    ap.add_argument("--paired", default="4")
    ap.add_argument("--lambda-paired", default="0.3,1,3", help="λ0 values tried with OSP")
    ap.add_argument("--lambda-unpaired", default="0.1,0.3,1", help="λ1 values tried with ASP")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a CellSpec field")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    overrides = parse_overrides(args.set)

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    t0 = time.time()
    for trial in (int(t) for t in args.trials.split(",")):
        base = None
        for paired in (int(p) for p in args.paired.split(",")):
            specs = [CellSpec(domain="particles", method="osp", paired=paired, trial=trial, lambda_paired=l0, **overrides)
                     for l0 in floats(args.lambda_paired)]
            specs += [CellSpec(domain="particles", method="asp", paired=paired, trial=trial, lambda_unpaired=l1,
                               **overrides) for l1 in floats(args.lambda_unpaired)]
            for spec in specs:
                if base is None:
                    base = train_accepted_base(spec)
                    print(f"base trial {trial}: score {base.score:.1f}, attempts {base.attempts}", flush=True)
                row = run_cell(spec, base=base)
                rows.append(row)
                pd.DataFrame(rows).to_parquet(out)
                print(f"{spec.method} p{paired} t{trial} λ0={row['lambda_paired']} λ1={row['lambda_unpaired']}: "
                      f"mixed={row['eval_mixed']:.1f} sp_new={row['eval_self_play_new']:.1f} "
                      f"train={row['time_train_wall_s']:.0f}s elapsed={time.time() - t0:.0f}s", flush=True)
    df = pd.DataFrame(rows)
    g = df.groupby(["method", "lambda_paired", "lambda_unpaired"])
    print(g[["eval_mixed", "eval_mixed_base_speaker", "eval_mixed_new_speaker", "eval_self_play_new"]]
          .median().round(1).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
