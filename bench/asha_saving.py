"""What ASHA changes in a tune run: the chosen configurations and the training it saves, against the same run
without it (same cells, ranges, budget and seed).

    python bench/asha_saving.py results/examples/tune-levers results/examples/tune-levers-asha [--json out.json]

Both runs' configurations.parquet are read. Per method: the best configuration of each run (its index and its
values: configuration 0 is the method's defaults, the later ones TPE's; the choice is the same when the values
are), its objective, and for the ASHA run how many configurations ASHA stopped and where.
Work is counted in cell-updates (each cell of a configuration trained to its curve point k of n does k/n of its
updates; a finished one all of them): a measure of CPU that load on a shared machine does not change. The
saving is 1 − ASHA's work / the full run's work. Wall times are the runs' own (from their rows' finished_at and
unit times, bench/worker_busy.py), comparable only when both ran alone on one machine.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

from asp_dist.core.registry import get_domain
from asp_dist.sweep.tune_plan import curve_points, winning_configuration


def _points(run: Path) -> int:
    """The cells' number of curve points (one cell's train_steps: a tune run's cells share it)."""
    row = pd.read_parquet(run / "cells", columns=["cell_id", "train_steps"]).iloc[0]
    return curve_points(int(row["train_steps"]))


def _search(table: pd.DataFrame) -> pd.DataFrame:
    return table[table["stage"] == "search"] if "stage" in table else table


def _best(table: pd.DataFrame, method: str, higher: bool) -> pd.Series:
    return winning_configuration(table[table["method"] == method], higher)


def compare(full: Path, asha: Path) -> dict:
    # the searches only: a two-stage run's validation rows are another stage (bench/two_stage_cost.py)
    a, b = (_search(pd.read_parquet(run / "configurations.parquet")) for run in (full, asha))
    plan = json.loads((full / "tune-plan.json").read_text())
    higher = get_domain(plan["domain"]).metrics[plan["settings"]["metric"]].higher_is_better
    n = _points(asha)
    knobs = [c for c in a.columns if c.startswith("knob_")]
    out = {"full": str(full), "asha": str(asha), "curve_points": n, "methods": {}}
    for method in dict.fromkeys(a["method"]):
        fa, fb = _best(a, method, higher), _best(b, method, higher)
        mine = b[b["method"] == method]
        stopped = mine[mine["stopped_early"].astype(bool)] if "stopped_early" in mine else mine.iloc[0:0]
        done = mine["cells"].sum() - stopped["cells"].sum()
        work = done + (stopped["cells"] * stopped["stopped_at_point"].astype(float) / n).sum()
        full_work = a[a["method"] == method]["cells"].sum()
        values = {k[5:]: fa[k] for k in knobs if pd.notna(fa[k])}
        # TPE is told other results once ASHA stops configurations, so an index can hold other values: the
        # choice is the same when the values are
        same = all(pd.isna(fa[k]) and pd.isna(fb[k]) or fa[k] == fb[k] for k in knobs)
        out["methods"][method] = {
            "full_best": int(fa["configuration"]), "full_objective": float(fa["objective"]),
            "asha_best": int(fb["configuration"]), "asha_objective": float(fb["objective"]),
            "same_choice": bool(same), "best_values": values,
            "configurations": len(mine), "stopped": len(stopped), "stopped_at": sorted(int(p) for p in stopped["stopped_at_point"]),
            "work_saved": 1 - float(work) / float(full_work)}
    total_full = a["cells"].sum()
    total_asha = sum((1 - m["work_saved"]) * a[a["method"] == k]["cells"].sum() for k, m in out["methods"].items())
    out["work_saved"] = 1 - total_asha / total_full
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("full", type=Path, help="the tune run without ASHA")
    parser.add_argument("asha", type=Path, help="the same tune run with ASHA")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    out = compare(args.full, args.asha)
    print(f"{out['asha']} against {out['full']} ({out['curve_points']} curve points per cell)")
    for method, m in out["methods"].items():
        print(f"  {method}: best without ASHA {m['full_best']} ({m['full_objective']:.4g}), with ASHA "
              f"{m['asha_best']} ({m['asha_objective']:.4g}): {'the same' if m['same_choice'] else 'another'} "
              f"configuration; ASHA stopped {m['stopped']} of {m['configurations']} (at points {m['stopped_at']}); "
              f"work saved {100 * m['work_saved']:.0f} %")
    print(f"  all methods: work saved {100 * out['work_saved']:.0f} %")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    main()
