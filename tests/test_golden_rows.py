"""Behaviour is pinned: the fixed cells of tests/golden/cells.py give the rows recorded in
tests/golden/rows.parquet (recorded before the package was restructured; re-recorded when the engine
changed on purpose: on 2026-11-24 — the fused particle kernel retired for a pack of one, the VAE on
fused Adam and a one-pass update — which moved 5 of 13 cells' floats by at most 2.1e-7 relative and
no metric beyond 1e-7: docs/decisions/0018-lone-particle-cell-is-a-pack-of-one.md and
docs/decisions/0019-vae-fused-adam-one-pass.md; on 2026-11-25 — single lever cells as packs of one — which
moved the 3 lever cells' loss columns by at most 6.6e-8 relative and no metric). Columns added since
must be spec knobs at their neutral value, so old rows stay what new code would write.

Exact where exactness is guaranteed: integer, bool and string columns, and the spec's own fields
(inputs, no arithmetic), always; computed floats only on a machine whose fingerprint
(golden.record.machine_fingerprint: CPU vendor, model and flags, torch, its SIMD kernels) is the
recording's, in full (tests/golden/machine.json; the AMD EPYC recording of 2026-11-25 is known only
in part, so it matches no machine). Elsewhere computed floats compare within FLOAT_REL: two vendors'
AVX-512 kernels round differently too.

Measured 2026-12-01 on an Intel Xeon (AVX-512, KVM) against the AMD EPYC recording, under
ATEN_CPU_CAPABILITY unset (AVX512) / avx2 / default, largest relative difference (absolute):
  eval_* metrics  1.03e-7 (2.4e-7) / 1.03e-7 (2.4e-7) / 9.5e-8 (2.4e-7)   (4, 4, 2 of 85 values differ)
  loss_* columns  1.12e-7 (1.5e-5) / 7.8e-8 (1.5e-5)  / 1.52e-7 (1.5e-5)  (17, 15, 31 of 45)
  base_score, base_attempt_scores, every discrete column: no difference.
That is at most 2.6 float32 ulps (u = 2**-24 relative is half an ulp): FLOAT_REL = 1.5e-6, ten times
the largest; FLOAT_ABS matters only for values recorded as exactly 0."""

import json
import math
from dataclasses import fields
from pathlib import Path

import pandas as pd
import pytest
from golden.record import machine_fingerprint, run_golden_rows

GOLDEN = Path(__file__).parent / "golden"
RECORDED = pd.read_parquet(GOLDEN / "rows.parquet")
RECORDED_MACHINE = json.loads((GOLDEN / "machine.json").read_text())["fingerprint"]
FLOAT_REL, FLOAT_ABS = 1.5e-6, 1e-12
MACHINE_COLUMNS = {"cpu_capability"}  # which machine, not what it computed: the fingerprint compares it
JSON_FLOAT_COLUMNS = {"base_attempt_scores", "figure_data"}  # strings that carry computed floats


@pytest.fixture(scope="module")
def rerun() -> pd.DataFrame:
    return run_golden_rows()


def exact_here() -> bool:
    """The recording's machine, as far as float rounding goes: a complete fingerprint, equal to this one's."""
    return None not in RECORDED_MACHINE.values() and RECORDED_MACHINE == machine_fingerprint()


def test_columns_added_since_are_neutral_knobs(rerun):
    from asp_dist.spec import HASH_NEUTRAL

    for column in sorted(set(rerun.columns) - set(RECORDED.columns)):
        assert column in HASH_NEUTRAL, f"new row column {column} is not a hash-neutral knob"
        assert (rerun[column] == HASH_NEUTRAL[column]).all(), f"{column} is not at its neutral value"


def close(old, new, where: str) -> None:
    """Floats within FLOAT_REL; JSON strings of floats alike, element by element; anything else equal."""
    if isinstance(old, str) and not isinstance(new, str):
        assert False, f"{where}: {old!r} -> {new!r}"
    if isinstance(old, str):
        old, new = json.loads(old), json.loads(new)
    if isinstance(old, dict):
        assert isinstance(new, dict) and old.keys() == new.keys(), where
        for k in old:
            close(old[k], new[k], f"{where}.{k}")
    elif isinstance(old, list):
        assert isinstance(new, list) and len(old) == len(new), where
        for k, (a, b) in enumerate(zip(old, new)):
            close(a, b, f"{where}[{k}]")
    elif isinstance(old, float):
        assert (math.isnan(old) and math.isnan(new)) or new == pytest.approx(old, rel=FLOAT_REL, abs=FLOAT_ABS), \
            f"{where}: {old!r} -> {new!r}"
    else:
        assert old == new, f"{where}: {old!r} -> {new!r}"


def test_same_cells_same_rows(rerun):
    from asp_dist.spec import CellSpec

    assert list(rerun["cell_id"]) == list(RECORDED["cell_id"]), "cell ids changed: a spec field or hash moved"
    exact, inputs = exact_here(), {f.name for f in fields(CellSpec)}
    for column in RECORDED.columns:
        if column in MACHINE_COLUMNS:
            continue
        computed_float = column not in inputs and (RECORDED[column].dtype.kind == "f" or column in JSON_FLOAT_COLUMNS)
        for i, (old, new) in enumerate(zip(RECORDED[column], rerun[column])):
            where = f"{RECORDED['cell_id'][i]}.{column}"
            if computed_float and not exact and old is not None and old == old:
                close(old, new, where)
            else:
                assert old == new or (old != old and new != new), f"{where}: {old!r} -> {new!r}"


def test_the_recording_machine_is_fingerprinted():
    """machine.json names the recording's machine with every field machine_fingerprint gives (None
    where unknown), and its known fields agree with the rows' own records of it."""
    here = machine_fingerprint()
    assert RECORDED_MACHINE.keys() == here.keys()
    assert RECORDED_MACHINE["cpu_capability"] == RECORDED["cpu_capability"].iloc[0]
    assert RECORDED_MACHINE["torch_version"] == RECORDED["torch_version"].iloc[0]
    assert here["cpu_capability"] and here["torch_version"]
