"""One rule (asp_dist.results.grouping) names conditions and treatments on both paths: the tracker, from the
plan's specs (tracking.cells.describe_cells), and the analysis, from rows (analysis.layout.domain_layout and
label_rows). For the same grid, a cell's tracker run gets the labels its row gets in the report. The one
difference there was (the tracker sorted a label's knobs alphabetically) is gone: both take CellSpec field
order."""

from __future__ import annotations

import subprocess
import sys

import pandas as pd
import pytest

from asp_dist.analysis.layout import domain_layout, label_rows
from asp_dist.results import grouping
from asp_dist.spec import CellSpec
from asp_dist.tracking.cells import describe_cells


def grid(domain, methods, shared=(None, (None,)), method_only=(None, (), (None,)), **fixed):
    """Resolved specs: every method x paired (0, 2) x each value of the shared knob (`shared`: knob, values).
    The methods of `method_only` (knob, methods, values) take each value of that knob, the others its first."""
    (s_knob, s_values), (m_knob, m_methods, m_values) = shared, method_only
    specs = []
    for m in methods:
        for p in (0, 2):
            for s in s_values:
                for v in (m_values if m in m_methods else m_values[:1]):
                    knobs = {k: x for k, x in ((s_knob, s), (m_knob, v)) if k is not None}
                    specs.append(CellSpec(domain=domain, method=m, paired=p, trial=0, **fixed, **knobs).resolved())
    return specs


def analysis_labels(specs) -> dict[str, tuple[str, str]]:
    """cell_id -> (condition, treatment) of the specs' rows, with a fake metric, through the analysis."""
    rows = pd.DataFrame([{**s.to_dict(), "cell_id": s.cell_id, "eval_fake": float(i), "eval_fake_higher_is_better": True}
                         for i, s in enumerate(specs)])
    out = {}
    for _, g in rows.groupby("domain"):
        labelled = label_rows(g, domain_layout(g, "eval_fake"), "eval_fake")
        out.update(zip(labelled["cell_id"], zip(labelled["condition"], labelled["treatment"])))
    return out


def tracker_labels(specs) -> dict[str, tuple[str, str]]:
    return {cid: (c.condition, c.treatment) for cid, c in describe_cells(specs, "g", "rev").items()}


GRIDS = {
    "signaling-skew-and-lambda": lambda: grid("signaling", ("pc", "osp", "asp"), ("signaling_skew", (0.5, 1.0, 2.0)),
                                              ("lambda_unpaired", ("asp",), (0.5, 1.0))),
    "vae-latent-and-lambda": lambda: grid("vae", ("osp", "asp"), ("vae_latent_dim", (8, 16)),
                                          ("lambda_unpaired", ("asp",), (0.1, 0.3)), vae_train_images=300),
    "no-shared-knob": lambda: grid("signaling", ("osp", "asp"), method_only=("lambda_unpaired", ("asp",), (0.03, 1.0))),
    "shared-only": lambda: grid("levers", ("pc", "asp"), ("lambda_paired", (0.5, 1.0))),
    "two-domains": lambda: (grid("signaling", ("osp", "asp"), ("signaling_skew", (0.0, 1.5)))
                            + grid("vae", ("osp", "asp"), method_only=("lambda_unpaired", ("asp",), (0.5, 2.0)),
                                   vae_train_images=300)),
}


@pytest.mark.parametrize("name", GRIDS)
def test_tracker_and_analysis_give_a_cell_the_same_condition_and_treatment(name):
    specs = GRIDS[name]()
    tracker, analysis = tracker_labels(specs), analysis_labels(specs)
    assert tracker == analysis
    assert len(set(tracker.values())) > 1  # the grid does split into conditions or treatments


def test_labels_read_as_the_rule_says():
    labels = tracker_labels(GRIDS["signaling-skew-and-lambda"]())
    assert {c for c, _ in labels.values()} == {"signaling_skew=0.5", "signaling_skew=1", "signaling_skew=2"}
    assert {t for _, t in labels.values()} == {"pc", "osp", "asp[lambda_unpaired=0.5]", "asp[lambda_unpaired=1]"}
    assert {c for c, _ in tracker_labels(GRIDS["no-shared-knob"]()).values()} == {"all"}


def test_two_knobs_in_one_label_are_in_the_same_order_on_both_paths():
    """A condition and a treatment of two knobs each: both paths list them in CellSpec field order (a tracker
    run path names exactly the report's label; before the rule was shared, the tracker sorted them)."""
    specs = [CellSpec(domain="signaling", method=m, paired=2, trial=0, signaling_skew=s, train_steps=t,
                      lambda_unpaired=lam if m == "asp" else 1.0, lr=lr if m == "asp" else 1e-3).resolved()
             for m in ("osp", "asp") for s in (0.5, 1.0) for t in (100, 200) for lam in (0.5, 1.0) for lr in (1e-3, 3e-4)]
    tracker, analysis = tracker_labels(specs), analysis_labels(specs)
    one = next(s for s in specs if s.method == "asp" and s.signaling_skew == 0.5 and s.train_steps == 100
               and s.lambda_unpaired == 0.5 and s.lr == 3e-4).cell_id
    assert analysis[one] == ("train_steps=100, signaling_skew=0.5", "asp[lambda_unpaired=0.5, lr=0.0003]")
    assert tracker == analysis


def test_the_rule_on_plain_dicts():
    """group_records on dicts: a knob no method varies is neither shared nor method-only, and a missing key
    reads as None. Formatting: integral floats lose ".0", others go through :g, None and NaN as text."""
    records = [{"method": "osp", "a": 1, "b": 0.5, "c": 7}, {"method": "osp", "a": 2, "b": 0.5, "c": 7},
               {"method": "asp", "a": 1, "b": 0.5, "c": 7}, {"method": "asp", "a": 2, "c": 7}]
    g = grouping.group_records(records, ["a", "b", "c"])
    assert g.shared == ["a"] and g.method_only == {"osp": [], "asp": ["b"]}
    assert g.condition_of(records[3]) == "a=2" and g.treatment_of(records[3]) == "asp[b=None]"
    assert g.treatment_of(records[0]) == "osp"
    assert grouping.condition_label([], {}) == "all"
    assert [grouping.fmt_value(v) for v in (2.0, 0.1, 3e-4, 8, None, float("nan"), True, "neg_bce")] == \
           ["2", "0.1", "0.0003", "8", "None", "nan", "True", "neg_bce"]


def test_tracking_cells_import_no_pandas():
    probe = ("import sys, asp_dist.tracking.cells; "
             "print(sorted(m for m in sys.modules if m.split('.')[0] in ('pandas', 'torch', 'ray')))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"
