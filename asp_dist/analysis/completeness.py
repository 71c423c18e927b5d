"""What is missing from a sweep: planned cells without a row, failed cells, and blocks lacking a treatment.

The planned grid and the failure records are read through the result store
(`asp_dist.results.store`); a missing cell is described from its spec in the manifest, never
from its id. Manifests written before the specs were stored give ids only: such a cell is
listed by id, with the domain and method its failure record names, if any.
"""

from __future__ import annotations

from typing import Any

import pandas as pd

from asp_dist.analysis.layout import DomainLayout, by_condition, treatment_order
from asp_dist.results import store
from asp_dist.results.location import AnyPath, as_path
from asp_dist.results.query import Inputs
from asp_dist.sweep import ledger

MISSING_COLUMNS = ["sweep", "kind", "domain", "condition", "method", "paired", "trial", "cell_id", "error"]
DESCRIBED = ("domain", "method", "paired", "trial")


def planned_cells(sweep_dir: AnyPath) -> tuple[dict[str, dict[str, Any] | None] | None, list[str]]:
    """(cell_id -> resolved spec dict, in grid order, or None for the whole when the sweep has no
    usable manifest; notes). A manifest from before the specs were stored maps every id to None."""
    name = as_path(sweep_dir).name
    try:
        manifest = store.read_manifest(sweep_dir)
    except (OSError, ValueError) as err:  # the store's SchemaError is a ValueError too
        return None, [f"{name}: manifest.json cannot be read ({err}); the planned grid is unknown"]
    if manifest is None:
        if (as_path(sweep_dir) / ledger.TUNE_PLAN_FILE).exists():  # a tune run plans configurations, not a grid
            return None, [f"{name}: a tune run (asp-dist tune): its cells are its configurations' "
                          f"({ledger.TUNE_CONFIGURATIONS}); only failed cells and incomplete blocks are reported"]
        return None, [f"{name}: no manifest.json, the planned grid is unknown; "
                      "only failed cells and incomplete blocks are reported"]
    cells, specs = manifest["cells"], manifest.get("specs")
    if not (isinstance(specs, list) and len(specs) == len(cells)):
        specs = [None] * len(cells)
    planned: dict[str, dict[str, Any] | None] = {}
    for cell_id, spec in zip(cells, specs):
        planned.setdefault(cell_id, spec if isinstance(spec, dict) else None)
    return planned, []


def failure_records(sweep_dir: AnyPath) -> tuple[dict[str, dict[str, Any]], list[str]]:
    """cell_id -> the store's failure record, and notes (unreadable records are a note, not a crash)."""
    try:
        return store.failed_cells(sweep_dir), []
    except (OSError, ValueError) as err:
        return {}, [f"{as_path(sweep_dir).name}: the failure records under failed/ cannot be read ({err}); "
                    "failed cells are listed as not finished"]


def describe_cell(spec: dict[str, Any] | None, failure: dict[str, Any] | None,
                  layouts: dict[str, DomainLayout]) -> dict[str, Any]:
    """domain, method, paired, trial (and the condition, when the domain's knobs are known) of a missing cell."""
    if spec is None:
        return {k: failure[k] for k in ("domain", "method") if failure and failure.get(k) is not None}
    out = {k: spec.get(k) for k in DESCRIBED}
    layout = layouts.get(spec.get("domain"))
    if layout is not None:
        out["condition"] = layout.condition_of(spec)
    return out


def missing_cells(sweep_dir: AnyPath, layouts: dict[str, DomainLayout]) -> tuple[list[dict], list[str], bool]:
    """(missing cells of one sweep, notes, whether its planned grid is known)."""
    name = as_path(sweep_dir).name
    planned, notes = planned_cells(sweep_dir)
    failed, more = failure_records(sweep_dir)
    notes += more
    done = store.done_cell_ids(sweep_dir)
    if planned is None:
        gone = [c for c in failed if c not in done]
    else:
        gone = [c for c in planned if c not in done]
        notes.append(f"{name}: {len(planned) - len(gone)} of {len(planned)} planned cells finished"
                     + (f", {len(gone)} missing" if gone else ""))
    if failed:
        notes.append(f"{name}: {len(failed)} cell(s) recorded as failed under failed/")
    out = []
    for cid in gone:
        failure = failed.get(cid)
        out.append({"sweep": name, "kind": "failed" if failure is not None else "not finished (manifest)",
                    "cell_id": cid, "error": store.last_error_line(failure) if failure is not None else None,
                    **describe_cell((planned or {}).get(cid), failure, layouts)})
    return out, notes, planned is not None


def incomplete_blocks(rows: pd.DataFrame) -> list[dict]:
    """One entry per (block, treatment) absent from a block where other treatments of its condition ran."""
    out = []
    for domain, in_domain in rows.groupby("domain", sort=True):
        for cond, g in by_condition(in_domain):
            treatments = treatment_order(g["treatment"])
            for (_seed, trial, paired), b in g.groupby(["root_seed", "trial", "paired"], sort=True):
                present = set(b["treatment"])
                for t in treatments:
                    if t not in present:
                        out.append({"sweep": "", "kind": "incomplete block", "cell_id": None, "domain": domain,
                                    "method": t, "paired": int(paired), "trial": int(trial), "condition": cond})
    return out


def completeness(rows: pd.DataFrame, inputs: Inputs | None,
                 layouts: dict[str, DomainLayout] | None = None) -> tuple[pd.DataFrame, list[str], bool]:
    """(the `missing` table, notes, whether every input's planned grid is known).

    A cell missing from the manifest also leaves its block incomplete; both views are kept, they
    answer different questions (what never ran / what the rank tests had to leave out)."""
    missing, notes = [], []
    layouts = layouts or {}
    sweeps = inputs.sweep_dirs if inputs is not None else []
    grids_known = bool(sweeps)
    for sweep in sweeps:
        found, more, known = missing_cells(sweep, layouts)
        missing.extend(found)
        notes.extend(more)
        grids_known = grids_known and known
    missing.extend(incomplete_blocks(rows))
    # Every file read must lie in one of the sweeps, or rows came from outside any known grid.
    cells = [store.cells_dir(d).resolve() for d in sweeps]
    grid_known = grids_known and all(any(c in f.parents for c in cells) for f in inputs.files)
    return pd.DataFrame(missing, columns=MISSING_COLUMNS), notes, grid_known
