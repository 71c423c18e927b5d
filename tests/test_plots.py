"""Figures and report: files produced, non-empty, for every kind of figure the rows support."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from test_stats import make_rows, write_sweep

from asp_dist.analysis.job import compute
from asp_dist.analysis.plots import plot_all
from asp_dist.analysis.tables import StatsConfig
from asp_dist.cli import main
from asp_dist.commands.stats import run_stats_job


@pytest.fixture
def figures_not_rendered(monkeypatch):
    """For a test of which figures are drawn and in what order: each is built, then closed unrendered (a
    curve figure of eight panels takes a second to render; other tests here check the files)."""
    from asp_dist.analysis import plots

    def close(fig, out_dir, stem):
        plots.plt.close(fig)
        return []

    monkeypatch.setattr(plots, "save_figure", close)


def _nonempty(paths):
    for p in paths:
        assert p.exists() and p.stat().st_size > 2000, p


def test_paired_knob_and_effect_figures(tmp_path):
    rows = pd.DataFrame(make_rows(trials=range(4), knobs={"signaling_skew": [0.0, 1.0, 2.0]}))
    res = compute(rows, StatsConfig(n_boot=200))
    figures, notes = plot_all(res, tmp_path / "figures")
    names = {f.name for f in figures}
    assert names == {"signaling_metric_vs_paired", "signaling_metric_vs_signaling_skew",
                     "signaling_asp_effect_vs_signaling_skew"}, names
    for f in figures:
        assert {p.suffix for p in f.paths} == {".png", ".svg"}
        _nonempty(f.paths)
    svg = (tmp_path / "figures" / "signaling_metric_vs_paired.svg").read_text()
    assert "higher is better" in svg and "paired examples" in svg
    assert notes == []


def test_vae_latent_size_figure_says_lower_is_better(tmp_path):
    rows = pd.DataFrame(make_rows(domain="vae", paired=(32,), trials=range(3), higher=False,
                                  knobs={"vae_latent_dim": [2, 8, 32, 128]}))
    figures, _ = plot_all(compute(rows, StatsConfig(n_boot=200)), tmp_path)
    by_name = {f.name: f for f in figures}
    assert "vae_metric_vs_vae_latent_dim" in by_name
    svg = by_name["vae_metric_vs_vae_latent_dim"].paths[1].read_text()
    assert "lower is better" in svg and "latent size" in svg


def test_latent_and_communication_scatters_from_figure_data(tmp_path):
    rng = np.random.default_rng(0)
    rows = make_rows(domain="vae", paired=(0, 8), trials=range(2), higher=False)
    images = lambda: rng.integers(0, 256, (10, 784)).tolist()  # noqa: E731
    for r in rows:
        labels = rng.integers(0, 10, 200).tolist()
        recon = {"labels": list(range(10)), "side": 28, "original": images(), "base": images(), "new": images(),
                 "base_encoder_new_decoder": images(), "new_encoder_base_decoder": images()}
        r["figure_data"] = json.dumps({"kind": "latent2d", "base": rng.normal(size=(200, 2)).tolist(),
                                       "new": rng.normal(size=(200, 2)).tolist(), "labels": labels, "recon": recon})
    lev = make_rows(domain="levers", paired=(0, 4), trials=range(2), higher=False)
    for r in lev:
        r["figure_data"] = json.dumps({"kind": "comm", "base": rng.normal(size=(90, 16)).tolist(),
                                       "new": rng.normal(size=(90, 16)).tolist(), "ids": (list(range(10)) * 9)})
    res = compute(pd.DataFrame(rows + lev), StatsConfig(n_boot=200))
    figures, notes = plot_all(res, tmp_path)
    names = {f.name for f in figures}
    assert {"vae_latent2d_all", "vae_reconstructions_all", "levers_comm_all"} <= names
    assert notes == []
    _nonempty([p for f in figures for p in f.paths])
    scatter = next(f for f in figures if f.name == "vae_latent2d_all")
    assert "digit" in scatter.paths[1].read_text()


def test_malformed_figure_data_is_a_note_not_a_crash(tmp_path):
    rows = make_rows(domain="levers", paired=(0,), trials=range(1), higher=False)
    for r in rows:
        r["figure_data"] = json.dumps({"kind": "comm", "base": [[1.0, 2.0]], "new": [[1.0]], "ids": [1, 2]})
    figures, notes = plot_all(compute(pd.DataFrame(rows), StatsConfig(n_boot=200)), tmp_path)
    assert not any(f.name.startswith("levers_comm") for f in figures)
    assert len(notes) == 1 and "not drawn" in notes[0]


def test_whole_job_writes_tables_figures_and_report(tmp_path):
    rows = make_rows(trials=range(4))
    gone = make_rows(methods=("pc",), paired=(8,), trials=range(1))[0] | {"cell_id": "signaling-pc-p8-t0-x"}
    sweep = write_sweep(tmp_path / "job", rows, planned=rows + [gone])
    report = run_stats_job([str(sweep)], cfg=StatsConfig(n_boot=200), log=lambda m: None)
    text = report.read_text()
    assert "## At a glance: did ASP beat OSP and PC?" in text
    assert "ASP beat PC and OSP" in text
    assert "signaling-pc-p8-t0-x" in text  # the missing cell is named
    assert "![signaling: eval_mixed against paired count](figures/signaling_metric_vs_paired.png)" in text
    for name in ("summary", "tests", "pairwise", "by_paired", "efficiency", "claim_2n", "missing"):
        assert (sweep / "stats" / f"{name}.parquet").exists() and (sweep / "stats" / f"{name}.md").exists()
    # Rerunning over the same sweep ignores the stats/ folder it wrote and gives the same tables.
    before = pd.read_parquet(sweep / "stats" / "summary.parquet")
    assert main(["stats", str(sweep), "--no-figures", "--quiet", "--bootstrap", "200"]) == 0
    pd.testing.assert_frame_equal(before, pd.read_parquet(sweep / "stats" / "summary.parquet"))


def test_several_inputs_need_an_output_directory(tmp_path):
    a = write_sweep(tmp_path / "a", make_rows(trials=range(2)))
    b = write_sweep(tmp_path / "b", make_rows(domain="vae", paired=(8, 16), trials=range(2), higher=False))
    assert main(["stats", str(a), str(b), "--quiet", "--no-figures"]) == 2
    assert main(["stats", str(a), str(b), "--quiet", "--no-figures", "--out", str(tmp_path / "m"),
                 "--bootstrap", "200", "--paired-range", "vae=8-16"]) == 0
    text = (tmp_path / "m" / "report.md").read_text()
    assert "**vae**" in text and "**signaling**" in text
    assert main(["stats", str(a), "--paired-range", "vae=x"]) == 2


CURVE_FIGURES = {f"signaling_curve_{s}" for s in ("d_fake", "loss_disc", "disc_acc_fake", "probe_mixed",
                                                 "probe_self_play_new")}


def _synthetic_curve(row: dict, rng) -> list[dict]:
    """50 points like the trainer's: diagnostics at every point, probes at every fifth."""
    out = []
    for k in range(50):
        step = 2 * (k + 1)
        point = {"step": step, "lambda_unpaired_now": row["lambda_unpaired"], "loss_disc": 1.4 - step / 200,
                 "d_fake": 0.5 - step / 400 + 0.02 * rng.normal(), "disc_acc_fake": 0.5 + step / 300,
                 "loss_total": 1.0 / step}
        if k % 5 == 4:
            point.update(probe_mixed=0.5 + step / 250 + 0.05 * rng.normal(), probe_self_play_new=0.9)
        out.append(point)
    return out


def test_learning_curve_figures_from_a_sweep_but_not_from_merged_parquet(tmp_path):
    from asp_dist.results import store

    rng = np.random.default_rng(1)
    rows = make_rows(paired=(0, 2, 4), trials=range(3))
    sweep = write_sweep(tmp_path / "sw", rows)
    for r in rows:
        assert store.write_curve(sweep, r, _synthetic_curve(r, rng))
    report = run_stats_job([str(sweep)], cfg=StatsConfig(n_boot=200), log=lambda m: None)
    for name in CURVE_FIGURES:
        _nonempty([sweep / "figures" / f"{name}.png", sweep / "figures" / f"{name}.svg"])
    text = report.read_text()
    assert "![signaling: learning curve of d_fake](figures/signaling_curve_d_fake.png)" in text
    svg = (sweep / "figures" / "signaling_curve_probe_mixed.svg").read_text()
    assert "higher is better" in svg and "training step" in svg

    # The same rows merged into one .parquet file: no curves to read, so no curve figure and no error.
    merged = tmp_path / "merged.parquet"
    pd.DataFrame(rows).to_parquet(merged)
    report = run_stats_job([str(merged)], out=str(tmp_path / "m"), cfg=StatsConfig(n_boot=200), log=lambda m: None)
    drawn = {p.stem for p in (tmp_path / "m" / "figures").glob("*.png")}
    assert "signaling_metric_vs_paired" in drawn and not any("_curve_" in n for n in drawn)
    assert "learning curve" not in report.read_text()


def test_curve_figures_are_capped_per_domain(tmp_path, figures_not_rendered):
    from asp_dist.analysis.plots import MAX_CURVE_FIGURES_PER_DOMAIN, plot_curves

    rng = np.random.default_rng(2)
    rows = make_rows(paired=(0, 4), trials=range(2), knobs={"signaling_skew": [0.0, 1.0, 2.0]})
    curves = pd.DataFrame([{**{k: r[k] for k in ("cell_id", "domain", "method", "paired", "trial")}, **p}
                           for r in rows for p in _synthetic_curve(r, rng)])
    res = compute(pd.DataFrame(rows), StatsConfig(n_boot=200))
    figures, notes = plot_curves(res, curves, "signaling", tmp_path)
    assert len(figures) == MAX_CURVE_FIGURES_PER_DOMAIN < 3 * len(CURVE_FIGURES)
    assert figures[0].name == "signaling_curve_d_fake_signaling_skew_0"
    assert len(notes) == 1 and "not drawn" in notes[0]


def test_curve_figures_from_real_cells(tmp_path, tiny):
    from asp_dist.results import store
    from asp_dist.training.cell import run_cell

    sweep = tmp_path / "real"
    for method in ("pc", "asp"):
        for trial in (0, 1):
            curve: list[dict] = []
            row = run_cell(tiny("signaling", method=method, paired=2, trial=trial, train_steps=100), curve=curve)
            assert store.write_curve(sweep, row, curve)
            assert store.write_row(sweep, row, "real")
    run_stats_job([str(sweep)], cfg=StatsConfig(n_boot=200), log=lambda m: None)
    drawn = {p.stem for p in (sweep / "figures").glob("*.png")}
    assert {"signaling_curve_d_fake", "signaling_curve_probe_mixed"} <= drawn, drawn


def test_curve_figures_under_the_cap_start_with_the_condition_of_most_paired_counts(tmp_path, figures_not_rendered):
    """A paired-count grid beside a knob grid at one count (the VAE's two grids): the figures kept
    under the cap are first those of the condition with panels to compare."""
    from asp_dist.analysis.plots import plot_curves

    rng = np.random.default_rng(3)
    rows = (make_rows(paired=(4,), trials=range(2), knobs={"signaling_skew": [0.0, 1.0, 3.0]})
            + make_rows(paired=(0, 2, 4), trials=range(2), knobs={"signaling_skew": [2.0]}))
    curves = pd.DataFrame([{**{k: r[k] for k in ("cell_id", "domain", "method", "paired", "trial")}, **p}
                           for r in rows for p in _synthetic_curve(r, rng)])
    figures, _ = plot_curves(compute(pd.DataFrame(rows), StatsConfig(n_boot=200)), curves, "signaling", tmp_path)
    assert figures[0].name == "signaling_curve_d_fake_signaling_skew_2"
