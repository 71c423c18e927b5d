"""No code runs from a results directory: every place asp-dist reads a stored base or checkpoint reads it with
torch.load(weights_only=True) (asp_dist/training/artefacts.py). A pickle planted there (its __reduce__ creates a
marker file) is refused in one line, never unpickled: the base cache sets it aside and trains the base again,
replay trains it again without touching the sweep, a trial's checkpoint starts its cell over. Truncated, empty
and old-format files are refused the same way, never with a traceback."""

from __future__ import annotations

import pickle

import pytest
import torch
from budgets import tiny_spec
from planted import PLANTS

from asp_dist.core.contract import assert_same_params
from asp_dist.results import store
from asp_dist.sweep.base_cache import base_path, get_base
from asp_dist.sweep.ledger import new_manifest
from asp_dist.sweep.replay import replay_cell
from asp_dist.training import artefacts
from asp_dist.training.bases import BaseModel, base_from_bytes, base_to_bytes, train_accepted_base
from asp_dist.training.cell import run_cell


def test_the_planted_files_do_run_code_when_unpickled(tmp_path):
    """What the tests below plant is a real attack: an ordinary unpickling runs it."""
    for name, plant in PLANTS.items():
        marker = tmp_path / f"{name}.ran"
        data = plant(marker)
        if name == "torch-pickle":
            import io

            torch.load(io.BytesIO(data), weights_only=False)
        else:
            pickle.loads(data)
        assert marker.exists(), name


@pytest.mark.parametrize("plant", PLANTS)
def test_a_planted_pickle_is_refused_unread(tmp_path, plant):
    marker = tmp_path / "ran"
    with pytest.raises(artefacts.DamagedArtefact, match="refused unread") as err:
        artefacts.from_bytes(PLANTS[plant](marker), "planted.pt")
    assert not marker.exists(), "unpickling the planted file ran its code"
    assert "\n" not in str(err.value) and str(err.value).startswith("planted.pt ")


def bad_base_files(spec, tmp_path) -> dict[str, bytes]:
    """Every kind of base file the cache must refuse, with the bytes of each."""
    good = base_to_bytes(train_accepted_base(spec))
    other = base_to_bytes(train_accepted_base(spec.replace(trial=spec.trial + 1)))
    old = _old_format_base(spec)
    files = {name: plant(tmp_path / "ran") for name, plant in PLANTS.items()}
    files.update({"truncated": good[: len(good) // 2], "empty": b"", "text": b"not a torch file at all\n",
                  "other-key": other, "old-format": old,
                  "not-a-base": artefacts.to_bytes({"weights": [1, 2, 3]}),
                  "wrong-shapes": _with_weights(good, spec, lambda w: {k: v[..., :1] for k, v in w.items()})})
    return files


def _old_format_base(spec) -> bytes:
    """A base as asp-dist stored them before 2026-12-06: the pickled BaseModel."""
    import io

    base = train_accepted_base(spec)
    buf = io.BytesIO()
    torch.save(BaseModel(agents=base.agents, key=base.key, score=base.score, attempts=1, seed=base.seed), buf)
    return buf.getvalue()


def _with_weights(data: bytes, spec, change) -> bytes:
    state = artefacts.from_bytes(data, "base")
    return artefacts.to_bytes(dict(state, weights=change(state["weights"])))


def test_the_cache_sets_aside_every_unreadable_base_and_trains_it_again(tmp_path, capsys):
    spec = tiny_spec("signaling", method="asp", paired=2, trial=0).resolved()
    expected = train_accepted_base(spec)
    for name, data in bad_base_files(spec, tmp_path).items():
        sweep = tmp_path / name
        path = base_path(store.bases_dir(sweep), spec.base_key)
        path.parent.mkdir(parents=True)
        path.write_bytes(data)
        base, cached = get_base(spec, store.bases_dir(sweep))
        assert not (tmp_path / "ran").exists(), f"{name}: the planted file ran"
        assert not cached and base.key == spec.base_key, name
        assert base.meta() == expected.meta(), f"{name}: not the base the spec trains"
        assert_same_params(base.agents, expected.agents, name)
        assert base_from_bytes(path.read_bytes(), spec).key == spec.base_key, f"{name}: the new base was not stored"
        (aside,) = (sweep / store.DAMAGED_DIR).glob("*/bases/*.pt")
        assert aside.read_bytes() == data, f"{name}: the damaged file was not kept as it was"
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"asp-dist: warning: base file {path}"), (name, lines)
        assert "trained again" in lines[0], lines


def test_a_stored_base_loads_as_it_was_stored(tmp_path):
    """The new format keeps a base's facts and its modules' train/eval modes, and is read with weights_only."""
    spec = tiny_spec("particles", method="asp", paired=2, trial=0).resolved()
    base = train_accepted_base(spec)
    loaded = base_from_bytes(base_to_bytes(base), spec)
    assert loaded.meta() == base.meta() and (loaded.train_wall_s, loaded.train_cpu_s) == (base.train_wall_s,
                                                                                         base.train_cpu_s)
    assert [m.training for m in loaded.agents.modules()] == [m.training for m in base.agents.modules()]
    assert not any(m.training for m in loaded.agents.modules())  # the particle base is stored in eval mode


@pytest.mark.parametrize("plant", PLANTS)
def test_replay_with_a_planted_base_runs_nothing_and_writes_nothing(tmp_path, plant, capsys):
    specs = [tiny_spec("signaling", method="asp", paired=2, trial=0).resolved()]
    sweep = tmp_path / "lone"
    store.write_manifest(sweep, new_manifest("lone", "test", specs))
    store.write_row(sweep, run_cell(specs[0], base=get_base(specs[0], store.bases_dir(sweep))[0]), "lone")
    path = base_path(store.bases_dir(sweep), specs[0].base_key)
    path.write_bytes(PLANTS[plant](tmp_path / "ran"))
    before = {p: p.read_bytes() for p in sweep.rglob("*") if p.is_file()}
    result = replay_cell(sweep, specs[0].cell_id)
    assert not (tmp_path / "ran").exists(), "replay ran the planted base"
    assert result.identical, result.text()
    assert {p: p.read_bytes() for p in sweep.rglob("*") if p.is_file()} == before, "replay wrote into the sweep"
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "refused unread" in lines[0] and "trained again" in lines[0], lines
