"""Method arms: `osp@default` trains as OSP under its own name, so one sweep runs a method at two settings;
common_seeds gives every setting of a method the same draws; the stats job compares a companion arm with
its method alone and leaves it out of the main tests."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from budgets import tiny_spec

from asp_dist.analysis.job import compute
from asp_dist.analysis.layout import is_asp, is_companion, treatment_order
from asp_dist.analysis.tables import StatsConfig
from asp_dist.method_registry import OSP, get_method, split_arm
from asp_dist.spec import CellSpec, SpecError
from asp_dist.sweep.spaces import expand


def spec(method: str, **knobs) -> CellSpec:
    return CellSpec(domain="signaling", method=method, paired=2, trial=1, **knobs).resolved()


# ---- the spec and the registry -------------------------------------------------------------------------

def test_an_arm_validates_and_trains_as_its_method():
    assert spec("osp@default").method == "osp@default"
    assert get_method("osp@default") is OSP
    assert split_arm("osp@default") == ("osp", "default") and split_arm("osp") == ("osp", None)
    assert spec("asp@tuned_2-b").lambda_unpaired > 0  # an ASP arm keeps the adversary
    assert spec("osp@x").lambda_unpaired == 0.0


@pytest.mark.parametrize("method, message", [
    ("osp@Default", "the label after '@' must be"),
    ("osp@", "the label after '@' must be"),
    ("osp@a b", "the label after '@' must be"),
    ("osp@a@b", "the label after '@' must be"),
    ("osp@" + "x" * 33, "the label after '@' must be"),
    ("xsp@default", "unknown method 'xsp' (of arm 'xsp@default')"),
])
def test_a_bad_arm_is_one_line(method, message):
    with pytest.raises(SpecError) as err:
        CellSpec(domain="signaling", method=method).resolved()
    assert message in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(SpecError):
        get_method(method)


def test_an_arm_is_a_cell_of_its_own_on_the_shared_base():
    osp, arm = spec("osp"), spec("osp@default")
    assert osp.cell_id != arm.cell_id and arm.cell_id.startswith("signaling-osp@default-p2-t1-")
    assert osp.base_key == arm.base_key
    assert "method" not in arm.base_fields()
    for purpose in ("data", "init"):
        assert osp.seed_for(purpose) == arm.seed_for(purpose)


def test_common_seeds_share_the_draws_of_every_setting_of_a_method():
    other_lr = spec("osp").lr * 3
    common = [spec("osp", common_seeds=True), spec("osp@default", common_seeds=True),
              spec("osp", common_seeds=True, lr=other_lr)]
    asp = spec("asp", common_seeds=True)
    for purpose in ("train", "eval"):
        seeds = {s.seed_for(purpose) for s in common}
        assert len(seeds) == 1 and asp.seed_for(purpose) not in seeds
    # Off (the default), every knob and the arm's name are in the seeds, as before the switch.
    plain = [spec("osp"), spec("osp@default"), spec("osp", lr=other_lr)]
    assert len({s.seed_for("train") for s in plain}) == 3
    assert "common_seeds" not in spec("osp").identity_dict()  # no existing cell id or seed changes
    assert common[0].cell_id != plain[0].cell_id and common[0].base_key == plain[0].base_key


# ---- a space's settings ---------------------------------------------------------------------------------

def test_a_method_table_does_not_reach_its_arm(tmp_path):
    path = tmp_path / "arms.toml"
    path.write_text("""
[fixed]
domain = "signaling"
[[grid]]
axes = { method = ["osp", "osp@default", "osp@low"], paired = [2], trial = [0] }
[methods.osp]
lr = 0.0042
[methods."osp@low"]
lr = 0.0001
""")
    by_method = {s.method: s for s in expand(str(path))}
    default_lr = CellSpec(domain="signaling", method="osp").resolved().lr
    assert by_method["osp"].lr == 0.0042
    assert by_method["osp@default"].lr == default_lr != 0.0042
    assert by_method["osp@low"].lr == 0.0001
    assert len({s.base_key for s in by_method.values()}) == 1


# ---- the stats job -----------------------------------------------------------------------------------

def test_treatment_order_and_companions():
    assert treatment_order(["asp", "osp@default", "pc", "osp", "asp@default", "osp[lr=0.1]"]) == \
        ["pc", "osp", "osp[lr=0.1]", "osp@default", "asp", "asp@default"]
    assert is_asp("asp@default") and is_asp("asp@x[lr=1]") and not is_asp("osp@asp")
    assert is_companion("osp@default") and is_companion("osp@default[lr=1]") and not is_companion("osp@low")


def test_a_companion_at_fewer_settings_keeps_the_conditions():
    """The knob rule counts companions out: osp@default at one skew leaves skew a condition of every method,
    for the analysis and the trackers alike."""
    from test_grouping import analysis_labels, tracker_labels

    specs = [CellSpec(domain="signaling", method=m, paired=p, trial=0, signaling_skew=skew).resolved()
             for m in ("pc", "osp", "asp") for p in (0, 2) for skew in (0.5, 2.0)]
    specs += [CellSpec(domain="signaling", method="osp@default", paired=p, trial=0, signaling_skew=0.5).resolved()
              for p in (0, 2)]
    labels = analysis_labels(specs)
    assert labels == tracker_labels(specs)
    assert {treatment for _, treatment in labels.values()} == {"pc", "osp", "asp", "osp@default"}
    assert {condition for condition, _ in labels.values()} == {"signaling_skew=0.5", "signaling_skew=2"}


def rows(effect: dict[str, float], trials: int = 8, paired=(0, 2, 4)) -> pd.DataFrame:
    """Synthetic signaling rows: block effect + method effect + a little noise (higher is better)."""
    rng = np.random.default_rng(0)
    out = []
    for t in range(trials):
        for p in paired:
            block = rng.normal()
            for m, e in effect.items():
                out.append({"domain": "signaling", "method": m, "paired": p, "trial": t, "root_seed": 0,
                            "lambda_unpaired": 1.0 if m.startswith("asp") else 0.0,
                            "lr": 0.01 if m.endswith("@default") else 0.003, "train_steps": 100,
                            "cell_id": f"signaling-{m}-p{p}-t{t}", "eval_mixed": block + e + 0.01 * rng.normal(),
                            "eval_mixed_higher_is_better": True,
                            "metric_directions": json.dumps({"mixed": "higher"}), "sweep_id": "arms"})
    return pd.DataFrame(out)


def test_stats_leave_companions_out_of_the_main_tests():
    res = compute(rows({"pc": 0.0, "osp": 1.0, "osp@default": 0.5, "asp": 2.0}),
                  StatsConfig(paired_ranges={"signaling": (2, 4)}, n_boot=50))
    t = res.tables
    assert t["tests"].iloc[0]["treatments"] == "pc, osp, asp" and t["tests"].iloc[0]["test"] == "friedman"
    assert t["tests"].iloc[0]["n_blocks"] == 16
    named = set(t["pairwise"]["a"]) | set(t["pairwise"]["b"]) | set(t["by_paired"]["b"]) | set(t["claim_2n"]["other"])
    assert named == {"pc", "osp", "asp"}
    assert "osp@default" in set(t["summary"]["treatment"])  # described, only not tested
    dvt = t["default_vs_tuned"]
    assert len(dvt) == 1
    rec = dvt.iloc[0]
    assert (rec["method"], rec["tuned"], rec["default"]) == ("osp", "osp", "osp@default")
    assert rec["paired_range"] == "2-4" and rec["n_blocks"] == 16
    assert (rec["tuned_better"], rec["tuned_worse"], rec["ties"]) == (16, 0, 0)
    assert rec["median_diff"] == pytest.approx(0.5, abs=0.05) and rec["better"] == "osp"
    assert rec["p_wilcoxon"] < 0.001 and rec["significant"]


def test_default_vs_tuned_in_score_units_when_lower_is_better():
    r = rows({"osp": 0.0, "osp@default": 1.0, "asp": 0.5})
    r["eval_mixed"] = -r["eval_mixed"]  # the default arm now has the larger, worse value
    r["eval_mixed_higher_is_better"] = False
    r["metric_directions"] = json.dumps({"mixed": "lower"})
    res = compute(r, StatsConfig(paired_ranges={"signaling": None}, n_boot=50))
    rec = res.tables["default_vs_tuned"].iloc[0]
    assert rec["n_blocks"] == 24 and rec["tuned_worse"] == 24 and rec["better"] == "osp@default"
    assert rec["median_diff"] == pytest.approx(-1.0, abs=0.05)
    assert res.tables["tests"].iloc[0]["test"] == "wilcoxon"  # osp against asp only


def test_no_companion_no_table():
    res = compute(rows({"pc": 0.0, "osp": 1.0, "asp": 2.0}), StatsConfig(n_boot=50))
    assert res.tables["default_vs_tuned"].empty


# ---- one cell, end to end ------------------------------------------------------------------------------

def test_an_arm_trains_as_its_method_and_is_written_under_its_name(tmp_path):
    from asp_dist.results import store
    from asp_dist.training.cell import run_cell

    osp = tiny_spec("signaling", method="osp", paired=2, trial=0, common_seeds=True)
    row = run_cell(osp.replace(method="osp@default"))
    assert row["method"] == "osp@default" and row["common_seeds"] is True
    same = run_cell(osp)  # same knobs, same draws: the very same training
    assert row["eval_mixed"] == same["eval_mixed"] and row["cell_id"] != same["cell_id"]
    sweep = tmp_path / "sweep"
    assert store.write_row(sweep, row, "arms")
    assert store.is_done(sweep, "signaling", "osp@default", row["cell_id"])
    back = store.read_rows(sweep)
    assert list(back["method"]) == ["osp@default"]
