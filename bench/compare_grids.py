"""Do two runs of the same grid agree? Medians per (domain, method, paired[, knob]) with percentile-
bootstrap 95 % intervals over trials, side by side: the check that packed and single-cell
training give the same results up to noise.

    python bench/compare_grids.py results/paper-packed results/examples/paper-particles.parquet --domain particles

A and B are sweep directories or merged .parquet files. Only trials present in both are compared.
For each group: the median of A and of B with their intervals, whether each median lies inside the
other's interval, and the interval of the median of per-trial differences A − B (cells paired by
trial). A verdict line counts the groups whose intervals overlap.

A thin wrapper over asp_dist.analysis.compare, kept for the commands recorded in docs/performance.md;
`asp-dist compare A B [--by COL …] [--margin M]` adds the equivalence verdict and its exit status.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from asp_dist.analysis.compare import compare, counts_line
from asp_dist.analysis.markdown import to_markdown
from asp_dist.results.store import read_rows


def load(path: str) -> pd.DataFrame:
    """Rows in file order (as this script always read them, so that its recorded outputs reproduce;
    `asp-dist compare` reads through the schema-checked reader, sorted by trial)."""
    return pd.read_parquet(path) if path.endswith(".parquet") else read_rows(Path(path))


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
    print(counts_line(table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
