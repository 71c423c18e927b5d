"""How one domain's rows are organised, read from the rows alone: conditions, treatments, score.

- *knob*: a CellSpec field other than the identity (domain, method, paired, trial, root_seed)
  that takes more than one value among a domain's rows of one method. A knob varied within
  every method (latent size, skew) defines a *condition*: methods are compared within it.
  A knob varied only within some methods (say λ1 of ASP) splits that method into *treatments*
  (``asp[lambda_unpaired=0.5]``) that are compared like methods.
- *block*: one (root_seed, trial, paired) of a condition. Within a block PC/OSP/ASP share the
  base model, the paired and unpaired sets and the initial weights, so comparisons are paired
  over blocks.
- *score*: the metric oriented so that larger is better (negated when the rows say lower is better).
- *arm*: a method named ``<method>@<label>`` (asp_dist.method_registry) is a treatment of its own; the
  ``@default`` arm is its method's *companion*, compared with it alone (tables.default_vs_tuned_table).

The knob rule and the label format live in asp_dist.results.grouping, which the trackers share (their run
paths name the same conditions and treatments). This module reads rows: which columns are knobs
(CellSpec fields, in field order) and when a column varies (pandas' nunique, NaN counted as a value).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Iterator, Sequence

import pandas as pd

from asp_dist.errors import SpecError
from asp_dist.method_registry import is_companion as _is_companion_method
from asp_dist.method_registry import split_arm
from asp_dist.results.grouping import NOT_KNOBS, condition_label, split_knobs, treatment_label
from asp_dist.results.grouping import fmt_value as fmt_value  # re-exported: the analysis's tables format with it
from asp_dist.spec import FIELD_NAMES

METHOD_ORDER = ("pc", "osp", "asp")


@dataclass
class DomainLayout:
    """How one domain's rows are organised: direction, conditions and treatments."""

    domain: str
    higher_is_better: bool
    shared_knobs: list[str]
    method_knobs: dict[str, list[str]]  # method -> knobs varied only within (some) methods

    def condition_of(self, values: dict[str, Any]) -> str:
        """The condition label of a row or spec dict (its shared knobs' values)."""
        return condition_label(self.shared_knobs, values)


def metric_direction(rows: pd.DataFrame, metric: str) -> bool:
    """True if higher is better for `metric` in these rows (one domain), read from the rows themselves."""
    domain = rows["domain"].iloc[0]
    flag_col = f"{metric}_higher_is_better"
    if flag_col in rows and rows[flag_col].notna().any():
        values = set(rows[flag_col].dropna().astype(bool))
        if len(values) > 1:
            raise SpecError(f"rows of domain {domain} disagree on whether higher {metric} is better")
        return values.pop()
    if "metric_directions" in rows:
        name = metric.removeprefix("eval_")
        found = set()
        for text in rows["metric_directions"].dropna().unique():
            try:
                found.add(json.loads(text).get(name))
            except (TypeError, ValueError, AttributeError):
                continue
        found.discard(None)
        if len(found) == 1:
            return found.pop() == "higher"
        if len(found) > 1:
            raise SpecError(f"rows of domain {domain} disagree on the direction of {metric}")
    raise SpecError(f"rows of domain {domain} do not say whether higher or lower {metric} is better "
                    f"(no {flag_col} column, no entry {metric.removeprefix('eval_')!r} in metric_directions)")


def domain_layout(rows: pd.DataFrame, metric: str) -> DomainLayout:
    """One domain's layout, with results.grouping's rule. Knobs are taken in CellSpec field order, and a
    column varies when pandas' nunique(dropna=False) counts more than one value among a method's rows.
    Methods are taken in order of appearance."""
    domain = rows["domain"].iloc[0]
    candidates = [c for c in FIELD_NAMES if c in rows.columns and c not in NOT_KNOBS]
    methods = list(rows["method"].unique())
    grouping = split_knobs(methods, candidates,
                           lambda col, m: rows.loc[rows["method"] == m, col].nunique(dropna=False) > 1)
    return DomainLayout(domain, metric_direction(rows, metric), grouping.shared, grouping.method_only)


def label_rows(rows: pd.DataFrame, layout: DomainLayout, metric: str) -> pd.DataFrame:
    """Add `condition` (shared knob values), `treatment` (method + method-only knobs) and `score`."""
    rows = rows.copy()
    # (No shared knobs: one condition. Spelled out because pandas 2 iterates no tuples over zero columns.)
    rows["condition"] = "all" if not layout.shared_knobs else [
        layout.condition_of(dict(zip(layout.shared_knobs, vals)))
        for vals in rows[layout.shared_knobs].itertuples(index=False, name=None)]
    rows["treatment"] = [treatment_label(rec["method"], layout.method_knobs.get(rec["method"], []), rec)
                         for rec in rows.to_dict("records")]
    values = pd.to_numeric(rows[metric], errors="coerce").astype(float)
    rows["score"] = values if layout.higher_is_better else -values
    if "root_seed" not in rows:
        rows["root_seed"] = 0
    return rows


def method_of(treatment: str) -> str:
    """The method (an arm's full name) of a treatment label: ``osp@default[lr=0.01]`` -> ``osp@default``."""
    return treatment.split("[")[0]


def base_method(treatment: str) -> str:
    """The registered method of a treatment, arm label dropped: ``osp@default[lr=0.01]`` -> ``osp``."""
    return split_arm(method_of(treatment))[0]


def is_companion(treatment: str) -> bool:
    """Whether a treatment is of a method's ``@default`` arm (left out of the main tests)."""
    return _is_companion_method(method_of(treatment))


def treatment_order(names: Sequence[str]) -> list[str]:
    """The paper's methods first, each followed by its arms (``osp``, ``osp[...]``, ``osp@default``), then
    the others by name."""
    def key(t: str) -> tuple:
        m, label = split_arm(method_of(t))
        return (METHOD_ORDER.index(m) if m in METHOD_ORDER else len(METHOD_ORDER), m, label is not None,
                label or "", t)

    return sorted(set(names), key=key)


def condition_key(condition: str) -> tuple:
    """Natural order of condition labels: "vae_latent_dim=8" before "vae_latent_dim=16"."""
    key = []
    for part in condition.split(", "):
        name, _, value = part.partition("=")
        try:
            key.append((name, 0, float(value), ""))
        except ValueError:
            key.append((name, 1, 0.0, value))
    return tuple(key)


def by_condition(rows: pd.DataFrame) -> Iterator[tuple[str, pd.DataFrame]]:
    """(condition, rows) in natural condition order."""
    for cond in sorted(rows["condition"].unique(), key=condition_key):
        yield cond, rows[rows["condition"] == cond]


def is_asp(treatment: str) -> bool:
    """ASP or an arm of it (an arm trains as its method)."""
    return base_method(treatment) == "asp"
