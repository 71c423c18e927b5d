"""Do two runs of the same grid agree? Medians per (domain, method, paired[, knob]) with percentile-
bootstrap 95 % intervals over trials, side by side: issue 13's check that packed and single-cell
training give the same results up to noise.

    python bench/compare_grids.py results/paper-packed results/examples/paper-particles.parquet --domain particles

A and B are sweep directories or merged .parquet files. Only trials present in both are compared.
For each group: the median of A and of B with their intervals, whether each median lies inside the
other's interval, and the interval of the median of per-trial differences A − B (cells paired by
trial). A verdict line counts the groups whose intervals overlap.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from asp_dist.analysis.markdown import to_markdown
from asp_dist.analysis.rank_tests import bootstrap_median_ci
from asp_dist.results.store import read_rows


def load(path: str) -> pd.DataFrame:
    return pd.read_parquet(path) if path.endswith(".parquet") else read_rows(Path(path))


def compare(a: pd.DataFrame, b: pd.DataFrame, metric: str, keys: list[str], n_boot: int, seed: int) -> pd.DataFrame:
    ci = lambda x: bootstrap_median_ci(x, n_boot=n_boot, seed=seed)  # noqa: E731
    trials = sorted(set(a["trial"]) & set(b["trial"]))
    a, b = a[a["trial"].isin(trials)], b[b["trial"].isin(trials)]
    b_by_key = b.set_index(keys)
    out = []
    for key, ga in a.groupby(keys, sort=True):
        if key not in b_by_key.index:
            continue
        gb = b_by_key.loc[[key]]
        xa, xb = ga[metric].to_numpy(float), gb[metric].to_numpy(float)
        lo_a, hi_a = ci(xa)
        lo_b, hi_b = ci(xb)
        paired = ga.set_index("trial")[metric].sub(gb.reset_index().set_index("trial")[metric]).dropna().to_numpy()
        lo_d, hi_d = ci(paired)
        med_a, med_b = float(np.median(xa)), float(np.median(xb))
        out.append({**dict(zip(keys, key if isinstance(key, tuple) else (key,))), "n_a": len(xa), "n_b": len(xb),
                    "median_a": med_a, "ci_a": f"{lo_a:.4g}–{hi_a:.4g}", "median_b": med_b, "ci_b": f"{lo_b:.4g}–{hi_b:.4g}",
                    "a_in_b": lo_b <= med_a <= hi_b, "b_in_a": lo_a <= med_b <= hi_a,
                    "overlap": max(lo_a, lo_b) <= min(hi_a, hi_b),
                    "median_diff": float(np.median(paired)) if len(paired) else np.nan,
                    "diff_ci": f"{lo_d:.4g}–{hi_d:.4g}", "diff_ci_has_0": bool(lo_d <= 0 <= hi_d)})
    return pd.DataFrame(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--domain", required=True)
    ap.add_argument("--metric", default="eval_mixed")
    ap.add_argument("--by", nargs="*", default=[], help="extra grouping columns (e.g. vae_latent_dim)")
    ap.add_argument("--bootstrap", type=int, default=5000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    a, b = (d[d["domain"] == args.domain] for d in (load(args.a), load(args.b)))
    if a.empty or b.empty:
        raise SystemExit(f"no {args.domain} rows in {'A' if a.empty else 'B'}")
    table = compare(a, b, args.metric, ["method", "paired", *args.by], args.bootstrap, args.seed)
    trials = sorted(set(a["trial"]) & set(b["trial"]))
    print(f"{args.domain}, {args.metric}: A = {args.a} ({len(a)} rows), B = {args.b} ({len(b)} rows); "
          f"{len(trials)} trials in both; bootstrap {args.bootstrap}, seed {args.seed}")
    print(to_markdown(table).rstrip() if args.markdown else table.to_string(index=False))
    print(f"groups: {len(table)}; intervals overlap in {int(table['overlap'].sum())}; A's median inside B's interval "
          f"in {int(table['a_in_b'].sum())}, B's inside A's in {int(table['b_in_a'].sum())}; interval of the median "
          f"per-trial difference contains 0 in {int(table['diff_ci_has_0'].sum())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
