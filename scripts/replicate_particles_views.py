"""The views of the particles replication registered in docs/reproduction.md (addendum of 2026-12-02 19:55 UTC),
each as its own set of rows for `asp-dist stats`:

    all            every trial whose 9 cells are done (rule 1: this one decides)
    without-2051   the same without trial 2051 (its base was rejected on one machine and accepted on the other)
    amd, intel     split by the machine that trained the trial: a row's `cpu_model` where it has one, else its
                   `finished_at` (before 17:00 UTC on 2026-12-02 the AMD EPYC, from 18:00 UTC the Intel Xeon)

    python scripts/replicate_particles_views.py results/examples/replicate-particles /tmp/rpart-views
    asp-dist stats /tmp/rpart-views/all.parquet --out /tmp/rpart-views/all --no-figures   # and so on

Only complete trials are kept (all 9 cells: PC, OSP, ASP at 2, 3 and 4 paired); a trial split across machines
would be refused (a pack trains on one machine, so none is)."""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

from asp_dist.results import store

AMD_BEFORE = pd.Timestamp("2026-12-02 17:00", tz="UTC")
INTEL_FROM = pd.Timestamp("2026-12-02 18:00", tz="UTC")


def machine(row) -> str:
    model = row.get("cpu_model")
    if isinstance(model, str) and model:
        return "amd" if "AMD" in model else "intel" if "Intel" in model else "other"
    finished = pd.Timestamp(row["finished_at"])
    finished = finished.tz_localize("UTC") if finished.tzinfo is None else finished.tz_convert("UTC")
    if finished < AMD_BEFORE:
        return "amd"
    if finished >= INTEL_FROM:
        return "intel"
    raise SystemExit(f"row {row['cell_id']} finished at {finished}, between the machines: no rule names it")


def main(sweep: str, out: str) -> None:
    rows = store.read_rows(Path(sweep), strict=True)
    per_trial = rows.groupby("trial")["cell_id"].nunique()
    complete = rows[rows["trial"].isin(per_trial[per_trial == 9].index)].copy()
    complete["machine"] = complete.apply(machine, axis=1)
    split = complete.groupby("trial")["machine"].nunique()
    if (split > 1).any():
        raise SystemExit(f"trials trained on two machines: {sorted(split[split > 1].index)}")
    views = {"all": complete, "without-2051": complete[complete["trial"] != 2051],
             "amd": complete[complete["machine"] == "amd"], "intel": complete[complete["machine"] == "intel"]}
    Path(out).mkdir(parents=True, exist_ok=True)
    for name, view in views.items():
        view.drop(columns="machine").to_parquet(Path(out, f"{name}.parquet"), index=False)
        print(f"{name}: {view['trial'].nunique()} trials, {len(view)} rows -> {out}/{name}.parquet")
    incomplete = sorted(set(rows["trial"]) - set(complete["trial"]))
    print(f"left out (fewer than 9 cells done): {incomplete or 'none'}")


if __name__ == "__main__":
    main(*sys.argv[1:3])
