"""How a cell is named, grouped and tagged in a tracker: one CellInfo per cell of the grid, made once by the
driver from the plan (the resolved specs) and handed to every tracker.

    group      domain / condition / treatment / paired count: the path a researcher filters by
               (TensorBoard's run path, W&B's group and job type, MLflow's tags)
    condition  the values of the knobs varied within every method of the domain's cells of this grid (the
               analysis's conditions: latent size, skew, ...); "all" when none is
    treatment  the method, with the knobs varied only within it (``asp[lambda_unpaired=0.5]``)
    tags       trial, sweep name, code revision, cell id
    config     the resolved spec (TensorBoard HParams, MLflow params, W&B config)

Condition and treatment come from asp_dist.results.grouping, the rule the analysis applies to rows, with the
analysis's knob order (CellSpec field order), so a run path names exactly what the report shows
(tests/test_grouping.py). Specs are read here without pandas; two values differ when their reprs do.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from asp_dist.results.grouping import NOT_KNOBS, Grouping, group_records


@dataclass(frozen=True)
class CellInfo:
    cell_id: str
    domain: str
    method: str
    paired: int
    trial: int
    condition: str
    treatment: str
    sweep: str
    revision: str
    config: dict[str, Any] = field(default_factory=dict, compare=False)  # the resolved spec
    metrics: tuple[str, ...] = ()  # the domain's eval metrics (eval_<name> in the row)

    @property
    def group(self) -> str:
        """domain/condition: what W&B groups by and MLflow tags (a condition's methods side by side)."""
        return f"{self.domain}/{self.condition}"

    @property
    def run_path(self) -> str:
        """A path unique per cell: domain/condition/treatment/paired=N/trial=T-<cell id's hash>."""
        return "/".join(safe(p) for p in (self.domain, self.condition, self.treatment, f"paired={self.paired}",
                                          f"trial={self.trial}-{self.cell_id.rsplit('-', 1)[-1][:8]}"))

    @property
    def run_name(self) -> str:
        """A short human name: treatment, paired count, trial."""
        return f"{self.treatment} paired={self.paired} trial={self.trial}"

    @property
    def tags(self) -> dict[str, str]:
        return {"sweep": self.sweep, "cell_id": self.cell_id, "domain": self.domain, "condition": self.condition,
                "method": self.method, "treatment": self.treatment, "paired": str(self.paired),
                "trial": str(self.trial), "code_revision": self.revision}


def safe(part: str) -> str:
    """A path component: no slash, no spaces (", " between knobs becomes ",")."""
    return part.replace("/", "_").replace(", ", ",").replace(" ", "_") or "_"


def describe_cells(specs: Sequence[Any], sweep: str, revision: str,
                   metrics_of: Callable[[str], Sequence[str]] = lambda domain: ()) -> dict[str, CellInfo]:
    """One CellInfo per spec (resolved CellSpecs of one grid), by cell id; `metrics_of(domain)`: its metrics."""
    dicts = [(s.cell_id, s.to_dict()) for s in specs]
    by_domain: dict[str, list[dict[str, Any]]] = {}
    for _, d in dicts:
        by_domain.setdefault(d["domain"], []).append(d)
    # Candidate knobs in CellSpec field order, as the analysis takes them from the row's columns (read off the
    # specs' own class: importing asp_dist.spec would cost the tracker hub's process a fifth of a second).
    fields = [f.name for f in dataclasses.fields(specs[0])] if specs else []
    groupings: dict[str, Grouping] = {domain: group_records(rows, [k for k in fields if k not in NOT_KNOBS
                                                                   and any(k in r for r in rows)])
                                      for domain, rows in by_domain.items()}
    out = {}
    for cell_id, d in dicts:
        domain, method = d["domain"], d["method"]
        g = groupings[domain]
        out[cell_id] = CellInfo(cell_id, domain, method, int(d["paired"]), int(d["trial"]), g.condition_of(d),
                                g.treatment_of(d), sweep, revision, d, tuple(metrics_of(domain)))
    return out
