"""Learning curves: ~50 points per cell, recorded without changing what is trained."""

from __future__ import annotations

import copy

import pytest

from asp_dist.core.registry import DOMAINS
from asp_dist.training.cell import run_cell
from asp_dist.training.row import comparable
from asp_dist.training.trainer import CURVE_POINTS, PROBE_EVERY


@pytest.mark.parametrize("name", list(DOMAINS))
def test_recording_a_curve_changes_nothing_trained(name, tiny):
    spec = tiny(name, method="asp", paired=2)
    curve: list[dict] = []
    assert comparable(run_cell(spec, curve=curve)) == comparable(run_cell(spec))
    steps = spec.resolved().train_steps
    assert [p["step"] for p in curve] == list(range(1, steps + 1))[: len(curve)] or len(curve) == CURVE_POINTS
    assert curve[-1]["step"] == steps
    assert {"loss_self_play", "loss_unpaired", "loss_disc", "disc_acc_real", "disc_acc_fake", "d_fake"} <= set(curve[-1])
    assert any(k.startswith("probe_mixed") for k in curve[-1]), "the last point always probes"


def test_fifty_points_ten_probes_and_restore(tiny):
    spec = tiny("signaling", method="asp", paired=2, train_steps=500)
    curve: list[dict] = []
    run_cell(spec, curve=curve)
    assert len(curve) == CURVE_POINTS and [p["step"] for p in curve] == [10 * (i + 1) for i in range(CURVE_POINTS)]
    assert sum("probe_mixed" in p for p in curve) == CURVE_POINTS // PROBE_EVERY
    assert 0.0 <= min(p["disc_acc_fake"] for p in curve) <= max(p["disc_acc_fake"] for p in curve) <= 1.0
    # A cell restored mid-way records the same curve as an uninterrupted one.
    states: list[dict] = []
    run_cell(spec, checkpoint=lambda state: states.append(copy.deepcopy(state)), checkpoint_every_steps=237, curve=[])
    resumed: list[dict] = []
    run_cell(spec, restore=states[0], curve=resumed)
    assert resumed == curve


def test_lambda_schedule_shows_in_the_curve(tiny):
    curve: list[dict] = []
    run_cell(tiny("signaling", method="asp", paired=2, train_steps=500, lambda_unpaired_schedule="warmup",
                  lambda_schedule_frac=0.5), curve=curve)
    lam = [p["lambda_unpaired_now"] for p in curve]
    full = lam[-1]
    assert lam[0] < 0.05 * full and lam[24] == pytest.approx(full * 249 / 250) and lam[30] == full


def test_curves_are_stored_once_and_read_back_and_queried(tiny, tmp_path):
    from asp_dist.results import store
    from asp_dist.results.query import run_query

    spec = tiny("signaling", method="asp", paired=2, train_steps=100)
    curve: list[dict] = []
    row = run_cell(spec, curve=curve)
    assert store.write_curve(tmp_path, row, curve) is True
    assert store.write_curve(tmp_path, row, curve[:3]) is False, "a finished curve is never overwritten"
    back = store.read_curves(tmp_path)
    assert len(back) == len(curve) and set(back["cell_id"]) == {row["cell_id"]}
    assert list(back["step"]) == [int(p["step"]) for p in curve]
    assert back["loss_disc"].tolist() == pytest.approx([p["loss_disc"] for p in curve])
    store.write_row(tmp_path, row, "test")
    df = run_query([str(tmp_path)], sql="SELECT count(*) AS n, max(step) AS last FROM curves", curves=True)
    assert (int(df["n"][0]), int(df["last"][0])) == (len(curve), 100)
