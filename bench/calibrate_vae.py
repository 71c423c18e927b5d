"""λ0/λ1 calibration grid for the VAE domain: one base per trial, shared by every cell.

    python bench/calibrate_vae.py --trials 0 --paired 4,16 --lambda-paired 1,10 \
        --lambda-unpaired 1,10 --out results/local/vae_calib.parquet

OSP cells run for every λ0, ASP cells for every (λ0, λ1); PC has no λ to tune beyond its
scale (with one loss term, λ0 only rescales Adam's step, which Adam normalises away).
Prints the median mixed MSE per configuration (lower is better).
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
    return [float(x) for x in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", default="0")
    ap.add_argument("--paired", default="4,16")
    ap.add_argument("--lambda-paired", default="1,10")
    ap.add_argument("--lambda-unpaired", default="1,10")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    overrides = parse_overrides(args.set)

    configs = [("osp", l0, 0.0) for l0 in floats(args.lambda_paired)]
    configs += [("asp", l0, l1) for l0 in floats(args.lambda_paired) for l1 in floats(args.lambda_unpaired)]
    rows, t0 = [], time.time()
    for trial in (int(t) for t in args.trials.split(",")):
        base = None
        for paired in (int(p) for p in args.paired.split(",")):
            for method, l0, l1 in configs:
                spec = CellSpec(domain="vae", method=method, paired=paired, trial=trial, lambda_paired=l0,
                                lambda_unpaired=l1 if method == "asp" else None, **overrides)
                if base is None:
                    base = train_accepted_base(spec)
                    print(f"base trial {trial}: test MSE {base.score:.4f} ({time.time() - t0:.0f}s)", flush=True)
                row = run_cell(spec, base=base)
                rows.append(row)
                print(f"{method} p={paired} l0={l0} l1={l1}: mixed={row['eval_mixed']:.4f} "
                      f"(b->n {row['eval_mixed_base_encoder']:.4f}, n->b {row['eval_mixed_new_encoder']:.4f}) "
                      f"sp_new={row['eval_self_play_new']:.4f} ({time.time() - t0:.0f}s)", flush=True)
                out = Path(args.out)
                out.parent.mkdir(parents=True, exist_ok=True)
                pd.DataFrame(rows).to_parquet(out)
    df = pd.DataFrame(rows)
    table = df.groupby(["method", "lambda_paired", "lambda_unpaired", "paired"])["eval_mixed"].median().unstack()
    print(table.round(4).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
