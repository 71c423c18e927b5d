"""run_cell end to end on the signaling game: determinism, checkpoint/restore, row contents."""

import json

import pytest
from checkpoints import checkpoint_sink

from asp_dist.spec import FIELD_NAMES
from asp_dist.training import artefacts
from asp_dist.training.bases import base_from_bytes, base_to_bytes, train_accepted_base
from asp_dist.training.cell import run_cell
from asp_dist.training.records import TERMS
from asp_dist.training.row import VOLATILE_COLUMNS, comparable
from asp_dist.training.row import schema as row_schema


@pytest.mark.parametrize("method", ["pc", "osp", "asp"])
def test_smoke_cell_per_method(tiny_signaling, method):
    row = run_cell(tiny_signaling.replace(method=method))
    assert row["method"] == method and row["domain"] == "signaling"
    assert 0.0 <= row["eval_mixed"] <= 1.0
    assert row["eval_mixed"] == pytest.approx((row["eval_mixed_base_speaker"] + row["eval_mixed_new_speaker"]) / 2)
    assert row["eval_self_play_base"] == 1.0
    assert row["eval_mixed_higher_is_better"] is True
    assert {f for f in FIELD_NAMES if f in row_schema(row["domain"]).names} <= set(row)
    assert row["time_train_wall_s"] > 0 and row["time_total_cpu_s"] > 0
    assert (row["loss_unpaired"] is not None) == (method == "asp")
    assert (row["loss_self_play"] is not None) == (method != "pc")


def test_whole_cell_is_deterministic(tiny_signaling):
    a, b = run_cell(tiny_signaling), run_cell(tiny_signaling)
    assert comparable(a) == comparable(b)
    assert set(a) - set(comparable(a)) <= VOLATILE_COLUMNS


def test_shared_base_gives_the_same_row_as_training_it(tiny_signaling):
    base = base_from_bytes(base_to_bytes(train_accepted_base(tiny_signaling)), tiny_signaling)
    assert comparable(run_cell(tiny_signaling, base=base)) == comparable(run_cell(tiny_signaling))


def test_base_for_other_settings_is_refused(tiny_signaling):
    base = train_accepted_base(tiny_signaling.replace(trial=5))
    with pytest.raises(ValueError, match="other settings"):
        run_cell(tiny_signaling, base=base)


@pytest.mark.parametrize("method", ["osp", "asp"])
def test_restore_mid_cell_gives_the_uninterrupted_row(tiny_signaling, method):
    spec = tiny_signaling.replace(method=method)
    saved, keep = checkpoint_sink()

    uninterrupted = run_cell(spec, checkpoint=keep, checkpoint_every_steps=20)
    assert len(saved) == 2  # steps 20 and 40 of 60
    for blob in saved:
        state = artefacts.from_bytes(blob, "checkpoint")
        resumed = run_cell(spec, restore=state)
        assert resumed["resumed_from_step"] == state["trainer"]["step"]
        assert comparable(resumed) == comparable(uninterrupted)


def test_a_checkpoint_from_before_engines_were_named_still_restores(tiny_signaling):
    """Version 1 checkpoints did not name their engine; the reference Trainer's still load."""
    saved, keep = checkpoint_sink()

    uninterrupted = run_cell(tiny_signaling, checkpoint=keep, checkpoint_every_steps=30)
    state = artefacts.from_bytes(saved[0], "checkpoint")
    assert state["engine"] == "autograd" and state["cell_ids"] == [tiny_signaling.resolved().cell_id]
    old = {"version": 1, "cell_id": state["cell_ids"][0], "trainer": state["trainer"], "timings": state["timings"][0]}
    resumed = run_cell(tiny_signaling, restore=old)
    assert resumed["resumed_from_step"] == 30 and comparable(resumed) == comparable(uninterrupted)


def test_a_reference_checkpoint_with_its_sums_by_name_still_restores(tiny_signaling):
    """Before the one records class (asp_dist.training.records) the reference Trainer kept its loss and curve
    sums as dicts by term name: such a state continues to the uninterrupted row and curve."""
    spec = tiny_signaling.replace(train_steps=1000)  # curve points every 20 updates, each the mean of the last 2
    saved, keep = checkpoint_sink()
    curve: list = []
    uninterrupted = run_cell(spec, checkpoint=keep, checkpoint_every_steps=959, curve=curve)
    state = artefacts.from_bytes(saved[0], "checkpoint")
    trainer = dict(state["trainer"])
    records = trainer.pop("records")
    assert records["loss_count"] == 59 and records["curve_count"] == 1  # inside both windows
    trainer["loss_sums"] = {k: float(records["loss_sums"][0, c]) for c, k in enumerate(TERMS[:5])} | {
        "_count": records["loss_count"]}
    trainer["curve_sums"] = {k: float(records["curve_sums"][0, c]) for c, k in enumerate(TERMS)} | {
        "_count": records["curve_count"]}
    resumed_curve: list = []
    resumed = run_cell(spec, restore=dict(state, trainer=trainer), curve=resumed_curve)
    assert resumed["resumed_from_step"] == 959 and comparable(resumed) == comparable(uninterrupted)
    assert resumed_curve == curve


def test_checkpoint_of_another_cell_is_refused(tiny_signaling):
    states = []
    run_cell(tiny_signaling, checkpoint=states.append, checkpoint_every_steps=30)
    with pytest.raises(ValueError, match="checkpoint belongs to a pack of"):
        run_cell(tiny_signaling.replace(trial=1), restore=states[0])


def test_progress_is_reported(tiny_signaling):
    seen = []
    run_cell(tiny_signaling, progress=lambda phase, done, total, info: seen.append((phase, done, total)))
    train = [s for s in seen if s[0] == "train"]
    assert train[-1][1:] == (60, 60) and len(train) >= 10
    assert seen[-1][0] == "eval"


def test_metric_directions_are_recorded(tiny_signaling):
    row = run_cell(tiny_signaling)
    directions = json.loads(row["metric_directions"])
    assert directions["mixed"] == "higher"
    assert {f"eval_{k}" for k in directions} <= set(row)
