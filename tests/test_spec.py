import pytest

from asp_dist.spec import FIELD_DOCS, FIELD_NAMES, CellSpec, SpecError, coerce_field


def test_every_field_is_documented():
    missing = [name for name in FIELD_NAMES if not FIELD_DOCS[name]]
    assert not missing


def test_resolved_fills_domain_defaults_and_keeps_overrides():
    spec = CellSpec(domain="signaling", method="osp", paired=3, lr=0.5).resolved()
    assert spec.lr == 0.5
    assert spec.train_steps is not None and spec.signaling_states is not None
    assert spec.vae_latent_dim is None  # other domains' knobs stay empty
    assert spec.lambda_unpaired == 0.0  # no adversary outside ASP
    assert spec.unpaired_batch == spec.batch_size


def test_cell_id_is_stable_and_sensitive():
    a = CellSpec(domain="signaling", method="asp", paired=2, trial=1)
    assert a.cell_id == CellSpec(domain="signaling", method="asp", paired=2, trial=1).cell_id
    # None and the explicit default describe the same cell
    assert a.cell_id == a.replace(lr=a.resolved().lr).cell_id
    assert a.cell_id != a.replace(trial=2).cell_id
    assert a.cell_id != a.replace(lambda_unpaired=0.3).cell_id
    assert a.cell_id.startswith("signaling-asp-p2-t1-")


def test_seeds_share_data_and_init_across_methods_but_not_trials():
    specs = [CellSpec(domain="signaling", method=m, paired=2, trial=0) for m in ("pc", "osp", "asp")]
    assert len({s.seed_for("data") for s in specs}) == 1
    assert len({s.seed_for("init") for s in specs}) == 1
    assert len({s.seed_for("train") for s in specs}) == 3
    assert len({s.base_key for s in specs}) == 1
    other_trial = specs[0].replace(trial=1)
    assert other_trial.seed_for("data") != specs[0].seed_for("data")
    assert other_trial.base_key != specs[0].base_key


def test_base_key_ignores_method_knobs_but_not_domain_knobs():
    s = CellSpec(domain="signaling", trial=0)
    assert s.base_key == s.replace(lr=0.123, method="pc", paired=5, lambda_unpaired=2.0).base_key
    assert s.base_key != s.replace(signaling_skew=2.0).base_key


@pytest.mark.parametrize("changes, message", [
    (dict(domain="nope"), "unknown domain 'nope'"),
    (dict(method="gail"), "unknown method 'gail'"),
    (dict(paired=-1), "paired must be an integer >= 0"),
    (dict(trial=1.5), "trial must be an integer >= 0"),
    (dict(train_steps=0), "train_steps must be >= 1"),
    (dict(lr=0.0), "lr must be > 0"),
    (dict(lambda_paired=-1.0), "lambda_paired must be >= 0"),
    (dict(adversary_loss="wasserstein"), "adversary_loss must be one of"),
    (dict(signaling_tokens=8, signaling_states=4), "signaling_states (4) must be >= signaling_tokens (8)"),
])
def test_invalid_specs_are_rejected_with_clear_messages(changes, message):
    with pytest.raises(SpecError) as err:
        CellSpec(**{"domain": "signaling", **changes}).resolved()
    assert message in str(err.value)


def test_from_dict_and_coercion():
    spec = CellSpec.from_dict({"domain": "signaling", "paired": "3", "lr": "0.1", "record_figure_data": "yes"})
    assert spec.paired == 3 and spec.lr == 0.1 and spec.record_figure_data is True
    with pytest.raises(SpecError, match="unknown cell field"):
        CellSpec.from_dict({"domain": "signaling", "learning_rate": 0.1})
    with pytest.raises(SpecError, match="paired must be of type int"):
        coerce_field("paired", "2.5")


def test_recording_figure_data_does_not_change_training():
    a = CellSpec(domain="signaling", method="asp", paired=2)
    b = a.replace(record_figure_data=True)
    assert a.seed_for("train") == b.seed_for("train") and a.seed_for("eval") == b.seed_for("eval")
