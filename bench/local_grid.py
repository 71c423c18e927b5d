"""Run a small grid of cells one after another in this process (no Ray), sharing bases.

Used by the domain result runs and as the sequential baseline of the sweep benchmark.

    python bench/local_grid.py --domain particles --methods pc,osp,asp --paired 0,2,4,6 \
        --trials 0-4 --out results/local/particles.parquet [--set key=value ...] [--resume]

Rows are appended to --out after every cell (so an interrupted run keeps what finished, and
--resume skips cells already there); a median/quartile table of eval_mixed is printed at the end.
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


def parse_range(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        if "-" in part:
            lo, hi = part.split("-")
            out.extend(range(int(lo), int(hi) + 1))
        else:
            out.append(int(part))
    return out


def summary(df: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    g = df.groupby(by)["eval_mixed"]
    return pd.DataFrame({"n": g.size(), "q1": g.quantile(0.25), "median": g.median(), "q3": g.quantile(0.75),
                         "mean": g.mean()}).round(4)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--domain", required=True)
    ap.add_argument("--methods", default="pc,osp,asp")
    ap.add_argument("--paired", default="0,2,4,6")
    ap.add_argument("--trials", default="0-4")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a CellSpec field")
    ap.add_argument("--out", required=True)
    ap.add_argument("--resume", action="store_true", help="skip cells whose cell_id is already in --out")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    overrides = parse_overrides(args.set)
    specs = [CellSpec(domain=args.domain, method=m, paired=p, trial=t, **overrides).resolved()
             for t in parse_range(args.trials) for p in parse_range(args.paired) for m in args.methods.split(",")]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = pd.read_parquet(out) if out.exists() and args.resume else None
    if out.exists() and not args.resume:
        print(f"{out} exists; pass --resume to continue it or choose another --out", file=sys.stderr)
        return 2
    rows = [] if done is None else done.to_dict("records")
    seen = {r["cell_id"] for r in rows}
    bases: dict[str, object] = {}
    t0 = time.time()
    todo = [s for s in specs if s.cell_id not in seen]
    for i, spec in enumerate(todo, 1):
        if spec.base_key not in bases:
            tb = time.time()
            bases[spec.base_key] = train_accepted_base(spec)
            b = bases[spec.base_key]
            print(f"  base trial {spec.trial}: score {b.score:.3f} after {b.attempts} attempt(s), "
                  f"{time.time() - tb:.1f}s", flush=True)
        row = run_cell(spec, base=bases[spec.base_key])
        rows.append(row)
        pd.DataFrame(rows).to_parquet(out.with_suffix(".tmp.parquet"))
        os.replace(out.with_suffix(".tmp.parquet"), out)
        elapsed = time.time() - t0
        print(f"[{i}/{len(todo)}] {spec.cell_id}: mixed={row['eval_mixed']:.4f} "
              f"sp_new={row['eval_self_play_new']:.4f} train={row['time_train_wall_s']:.1f}s "
              f"elapsed={elapsed:.0f}s eta={elapsed / i * (len(todo) - i):.0f}s", flush=True)
    df = pd.DataFrame(rows)
    print(summary(df, ["paired", "method"]).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
