"""What a two-stage tune run (search, then validation: docs/decisions/0058) costs against a one-stage one.

    python bench/two_stage_cost.py results/examples/tune-particles results/examples/tune-validated-particles \
        [--json docs/bench-results/two-stage-particles-<date>.json]

Work is counted in cell-updates, as bench/asha_saving.py counts it (a cell trained to curve point k of n does k/n
of its updates; a finished one all of them): a measure of CPU that load on a shared machine does not change. Both
runs' cells must train the same number of updates. Beside it, the CPU seconds the rows record (each row's
time_total_cpu_s, and each distinct base's base_train_cpu_s once): a lower bound for a run with ASHA, whose
stopped configurations write no rows. The target (the tuning study's): the two-stage run within 1.5 × the one-stage
run's work.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

from asp_dist.results.store import read_rows
from asp_dist.sweep.tune_plan import curve_points


def stage_work(table: pd.DataFrame, points: int) -> float:
    """Cell-updates of a configurations table's rows, in whole cells: a configuration ASHA stopped at curve point
    k counts k / points of each of its cells."""
    if "stopped_early" not in table:  # a run without ASHA: every configuration trained to its end
        return float(table["cells"].sum())
    stopped = table["stopped_early"].eq(True)
    done = table.loc[~stopped, "cells"].sum()
    partial = (table.loc[stopped, "cells"] * table.loc[stopped, "stopped_at_point"].astype(float) / points).sum()
    return float(done + partial)


def run_cost(run: Path) -> dict:
    table = pd.read_parquet(run / "configurations.parquet")
    rows = read_rows(run)
    steps = rows["train_steps"].unique()
    if len(steps) != 1:
        raise SystemExit(f"{run}: its cells train {sorted(steps)} updates; one count expected")
    points = curve_points(int(steps[0]))
    stage = table["stage"] if "stage" in table else pd.Series("search", index=table.index)
    bases = rows.drop_duplicates("base_key")
    return {"run": str(run), "train_steps": int(steps[0]),
            "work_cells": {s: stage_work(table[stage == s], points) for s in dict.fromkeys(stage)},
            "rows": len(rows), "bases": len(bases),
            "cpu_s_cells": float(rows["time_total_cpu_s"].sum()),
            "cpu_s_bases": float(bases["base_train_cpu_s"].fillna(0).sum())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("one_stage", type=Path)
    parser.add_argument("two_stage", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    one, two = run_cost(args.one_stage), run_cost(args.two_stage)
    if one["train_steps"] != two["train_steps"]:
        raise SystemExit("the two runs' cells train different numbers of updates: their work does not compare")
    ratio = sum(two["work_cells"].values()) / sum(one["work_cells"].values())
    cpu = (two["cpu_s_cells"] + two["cpu_s_bases"]) / (one["cpu_s_cells"] + one["cpu_s_bases"])
    for r in (one, two):
        print(f"{r['run']}: work {', '.join(f'{s} {w:.0f}' for s, w in r['work_cells'].items())} cells; "
              f"{r['rows']} rows, {r['cpu_s_cells'] / 60:.1f} CPU-min in cells + {r['cpu_s_bases'] / 60:.1f} in "
              f"{r['bases']} bases")
    print(f"two-stage / one-stage: work {ratio:.2f} × (target ≤ 1.5 ×), rows' CPU with bases {cpu:.2f} ×")
    if args.json:
        args.json.write_text(json.dumps({"one_stage": one, "two_stage": two, "work_ratio": ratio,
                                         "cpu_ratio_rows_and_bases": cpu}, indent=1))


if __name__ == "__main__":
    main()
