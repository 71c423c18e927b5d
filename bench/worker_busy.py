"""How busy a finished run kept its workers, from its rows alone: the share of workers × wall spent inside units.

    python bench/worker_busy.py results/examples/tune-particles [results/examples/confirm-tuned-levers ...]
                                [--workers 2] [--since ISO] [--until ISO] [--json out.json]

Every row records the wall seconds its cell spent in its unit (`time_total_wall_s`; a pack's members split the
pack's time between them, so a pack's rows add up to its wall) and when it finished (`finished_at`). The run's
wall is taken from the start of its first unit (the first finished row's time minus its unit's wall) to the last
row. busy = (Σ unit wall + Σ base training) / (workers × run wall), each base the rows use counted once at
its recorded training time (a pack's rows leave the base it trained out of their unit time). What is not busy is the driver's share: Tune's scheduling and
trial start-up, a worker idle while the other trains a base both need, and for `asp-dist tune` its batches
(TPE waits for the slower configuration of each batch) and its methods run one after another. A run that was
stopped and resumed spans its pause too, so measure runs that ran in one go, or one stretch of a run: --since
and --until keep the rows finished in that window (UTC, e.g. 2026-12-04T07:35). A base that was rejected (its
trial has no rows) and a base's failed attempts before the accepted one are not counted: a run that rejects
bases reads less busy than its workers were.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd


def busy(run_dir: Path, workers: int, since: str | None = None, until: str | None = None) -> dict:
    rows = pd.read_parquet(run_dir / "cells", columns=["cell_id", "pack", "finished_at", "time_total_wall_s", "base_key",
                                                       "base_train_wall_s"])
    rows["finished_at"] = pd.to_datetime(rows["finished_at"])
    if since:
        rows = rows[rows["finished_at"] >= pd.Timestamp(since, tz="UTC")]
    if until:
        rows = rows[rows["finished_at"] <= pd.Timestamp(until, tz="UTC")]
    unit = rows["pack"].fillna(rows["cell_id"])
    unit_wall = rows.groupby(unit)["time_total_wall_s"].sum()
    first = rows.loc[rows["finished_at"].idxmin()]
    start = first["finished_at"] - pd.Timedelta(seconds=float(unit_wall[first["pack"] or first["cell_id"]]))
    wall = (rows["finished_at"].max() - start).total_seconds()
    # A unit's rows leave out the base it trained (a pack's members record no base time): each base the window's
    # rows use is counted once, at its recorded training time (the accepted base's; rejected bases have no rows).
    bases = float(rows.groupby("base_key")["base_train_wall_s"].first().fillna(0.0).sum())
    inside = float(unit_wall.sum()) + bases
    return {"run": str(run_dir), "cells": len(rows), "units": len(unit_wall), "workers": workers,
            "wall_min": wall / 60, "unit_wall_min": inside / 60, "bases_min": bases / 60,
            "busy": inside / (workers * wall)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="a run's directory (holds cells/)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--since", help="only rows finished at or after this UTC time")
    parser.add_argument("--until", help="only rows finished at or before this UTC time")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    out = [busy(run, args.workers, args.since, args.until) for run in args.runs]
    for r in out:
        print(f"{r['run']}: {r['cells']} cells in {r['units']} units, {r['unit_wall_min']:.1f} min inside units "
              f"(bases {r['bases_min']:.1f}) on "
              f"{r['workers']} workers over {r['wall_min']:.1f} min: busy {100 * r['busy']:.0f} %")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
