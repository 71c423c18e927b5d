"""The paper's facts reach the tables, figures and report from each domain's PaperFacts, and
rows of a domain the registry does not know get the generic behaviour."""

from __future__ import annotations

import dataclasses

import pandas as pd
import pytest
from test_stats import make_rows

import asp_dist.analysis as analysis
from asp_dist.analysis.job import compute
from asp_dist.analysis.paper import knob_label, metric_label, paper_claim, paper_threshold
from asp_dist.analysis.plots import plot_all
from asp_dist.analysis.report import write_report
from asp_dist.analysis.tables import StatsConfig
from asp_dist.core.registry import DOMAINS


def patch_facts(monkeypatch, domain: str, **changes) -> None:
    cls = type(DOMAINS[domain])
    monkeypatch.setattr(cls, "paper", dataclasses.replace(cls.paper, **changes))


def test_the_facade_exports_what_the_cli_uses():
    assert sorted(analysis.__all__) == ["StatsConfig", "paper_paired_ranges", "paper_thresholds", "plot_all",
                                        "run_stats", "write_report", "write_tables"]
    for name in analysis.__all__:
        assert callable(getattr(analysis, name)), name
    with pytest.raises(AttributeError):
        analysis.compute_everything  # noqa: B018


def test_friedman_range_for_vae_comes_from_its_paper_facts(monkeypatch):
    assert analysis.paper_paired_ranges()["vae"] == DOMAINS["vae"].paper.test_paired
    rows = pd.DataFrame(make_rows(domain="vae", paired=(4, 8, 16, 32), trials=range(4), higher=False))
    assert compute(rows, StatsConfig(n_boot=200)).tables["tests"].iloc[0]["paired_range"] == "8-32"
    patch_facts(monkeypatch, "vae", test_paired=(16, 32))
    assert analysis.paper_paired_ranges()["vae"] == (16, 32) and StatsConfig().paired_ranges["vae"] == (16, 32)
    t = compute(rows, StatsConfig(n_boot=200)).tables["tests"].iloc[0]
    assert t["paired_range"] == "16-32" and t["n_blocks"] == 2 * 4
    patch_facts(monkeypatch, "vae", test_paired=None)  # the paper tests every count
    assert "vae" not in analysis.paper_paired_ranges()
    assert compute(rows, StatsConfig(n_boot=200)).tables["tests"].iloc[0]["paired_range"] == "4-32"


def test_efficiency_threshold_comes_from_paper_facts(monkeypatch):
    patch_facts(monkeypatch, "levers", threshold=(0.25, "a threshold from the paper"))
    assert analysis.paper_thresholds()["levers"] == 0.25
    eff = compute(pd.DataFrame(make_rows(domain="levers", trials=range(3), higher=False)),
                  StatsConfig(n_boot=200)).tables["efficiency"]
    assert set(eff["threshold"]) == {0.25} and set(eff["threshold_rule"]) == {"a threshold from the paper"}
    assert paper_threshold("levers", "eval_other") is None  # the facts are about eval_mixed only


def test_unknown_domain_gets_the_generic_behaviour():
    rows = pd.DataFrame(make_rows(domain="oldgame", paired=(0, 1, 2, 4, 8), trials=range(3)))
    res = compute(rows, StatsConfig(n_boot=200))
    assert res.tables["tests"].iloc[0]["paired_range"] == "0-8"  # every paired count
    eff = res.tables["efficiency"]
    assert eff["threshold"].iloc[0] == pytest.approx(0.9 * 3.0) and "90%" in eff["threshold_rule"].iloc[0]
    assert metric_label("oldgame", "eval_mixed") == "eval_mixed" and paper_claim("oldgame") is None
    assert knob_label("oldgame", "oldgame_size") == "oldgame_size"
    assert knob_label("oldgame", "paired") == knob_label("vae", "paired") == "paired examples |P| (count)"


def test_figures_and_report_say_what_the_paper_facts_say(monkeypatch, tmp_path):
    patch_facts(monkeypatch, "signaling", metric_label="zorgs per flurb", claim="ASP beats everyone at zorgs",
                knob_labels={"signaling_skew": "skewness of the flurbs"})
    rows = pd.DataFrame(make_rows(trials=range(3), knobs={"signaling_skew": [0.0, 1.0]}))
    res = compute(rows, StatsConfig(n_boot=200))
    figures, _ = plot_all(res, tmp_path / "figures")
    svg = {f.name: f.paths[1].read_text() for f in figures}
    assert "zorgs per flurb" in svg["signaling_metric_vs_paired"]
    assert "skewness of the flurbs" in svg["signaling_metric_vs_signaling_skew"]
    text = write_report(res, tmp_path, figures).read_text()
    assert "signaling: the paper reports: ASP beats everyone at zorgs." in text
