"""What `asp-dist tune` costs over a plain sweep of the same cells, in one run on one machine.

    python bench/bench_tune.py [--space tune-smoke] [--budget 3] [--workers 2] [--json out.json]

1. `asp-dist tune SPACE --budget B` into a scratch results root (wall time, from the command's start to its end);
2. the cells that run trained (every configuration's, read back from its configurations.parquet) written as
   one space file, one sub-grid per configuration with its knob values fixed, then `asp-dist sweep` of it
   into another scratch root (same workers; packed per trial where the tune run packed a configuration:
   `--pack trial`, so a configuration's cells of one trial share a pack as they did).
Both runs start their own embedded Ray and train their own bases. The overhead is tune / sweep − 1 (the goal:
within 10 %); with cells of a second or two (the signaling smoke space) the fixed costs of one Tune experiment
per method dominate, so the figure that matters is the one on a real space's cells.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run(args: list[str]) -> float:
    env = dict(os.environ, OMP_NUM_THREADS="1", RAY_USAGE_STATS_ENABLED="0")
    start = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "asp_dist", *args], env=env, capture_output=True, text=True, cwd=REPO)
    took = time.perf_counter() - start
    if out.returncode != 0:
        raise SystemExit(f"asp-dist {' '.join(args)} exited {out.returncode}:\n{out.stderr[-3000:]}")
    return took


def sweep_space_of(tune_dir: Path, path: Path) -> int:
    """The tune run's cells as a space file (one sub-grid per configuration); returns the number of cells."""
    import pandas as pd

    from asp_dist.results.store import read_rows

    rows = read_rows(tune_dir)
    configs = pd.read_parquet(tune_dir / "configurations.parquet")
    lines, cells = [], 0
    for _, config in configs.iterrows():
        ids = config["cell_ids"].split(",")
        mine = rows[rows["cell_id"].isin(ids)]
        fixed = {k[5:]: config[k] for k in configs.columns if k.startswith("knob_") and pd.notna(config[k])}
        keep = ("train_steps", "unpaired_size")
        fixed.update({k: mine[k].iloc[0].item() for k in keep if k in mine and mine[k].nunique() == 1})
        fixed_text = ", ".join(f"{k} = {json.dumps(v.item() if hasattr(v, 'item') else v)}" for k, v in fixed.items())
        lines += ["[[grid]]", f"fixed = {{ {fixed_text} }}", "[grid.axes]",
                  f"domain = {json.dumps(sorted(set(mine['domain'])))}",
                  f"method = {json.dumps(sorted(set(mine['method'])))}",
                  f"paired = {json.dumps(sorted(int(x) for x in set(mine['paired'])))}",
                  f"trial = {json.dumps(sorted(int(x) for x in set(mine['trial'])))}", ""]
        cells += len(ids)
    path.write_text("\n".join(lines))
    return cells


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--space", default="tune-smoke")
    ap.add_argument("--budget", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="asp-bench-tune-") as scratch:
        root = Path(scratch)
        tune_s = run(["tune", args.space, "--budget", str(args.budget), "--workers", str(args.workers),
                      "--results", str(root / "tune"), "--ray-temp-dir", str(root / "r1")])
        tune_dir = next((root / "tune").iterdir())
        cells = sweep_space_of(tune_dir, root / "same-cells.toml")
        sweep_s = run(["sweep", str(root / "same-cells.toml"), "--workers", str(args.workers), "--pack", "trial",
                       "--results", str(root / "sweep"), "--ray-temp-dir", str(root / "r2")])
    load_after = os.getloadavg()
    result = {"space": args.space, "budget": args.budget, "workers": args.workers, "cells": cells,
              "tune_s": tune_s, "sweep_s": sweep_s, "overhead": tune_s / sweep_s - 1,
              "load_average_before": load_before, "load_average_after": load_after, "cores": os.cpu_count()}
    print(f"{args.space}, budget {args.budget}, {cells} cells, {args.workers} workers: tune {tune_s:.1f} s, "
          f"sweep of the same cells {sweep_s:.1f} s, overhead {100 * result['overhead']:+.0f} %")
    print(f"load average before {load_before[0]:.2f}, after {load_after[0]:.2f}; {os.cpu_count()} cores")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
