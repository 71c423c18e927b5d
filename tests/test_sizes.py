"""Upper bounds of the size-like knobs, the per-tensor budget and the cap on a space's cells: every size-like
knob has a bound, the bounds sit far above every committed space and golden cell, a space too large is
refused without being built, and a cell that still runs out of memory ends in one line. The refusals
themselves, through the CLI, are cases of tests/test_bad_inputs.py."""

from __future__ import annotations

import tracemalloc

import pytest
from golden.cells import golden_specs

import asp_dist.training.cell as cell_module
from asp_dist.cli import main
from asp_dist.core.registry import DOMAINS, get_domain
from asp_dist.errors import SweepError
from asp_dist.spec import FIELD_NAMES, MAX_TENSOR, UPPER_BOUNDS, CellSpec, field_type
from asp_dist.sweep import spaces

NOT_SIZES = {"trial", "root_seed",  # seeds: any int64 is fine
             "vae_train_images"}  # bounded by VAEDomain.validate: MNIST's 60000 training images
MARGIN = 10  # every committed value is at least this far below its bound


def bounds(domain: str) -> dict[str, int]:
    return {**UPPER_BOUNDS, **get_domain(domain).upper_bounds}


def largest_tensor(spec: CellSpec) -> int:
    domain = get_domain(spec.domain)
    return max({**spec.common_tensor_sizes(domain.channel_dims(spec)), **domain.tensor_sizes(spec)}.values())


def assert_far_within_bounds(spec: CellSpec) -> None:
    for name, bound in bounds(spec.domain).items():
        assert getattr(spec, name) * MARGIN <= bound, f"{spec.cell_id}: {name} = {getattr(spec, name)} near {bound}"
    assert largest_tensor(spec) * MARGIN <= MAX_TENSOR, spec.cell_id


def test_every_size_like_knob_has_an_upper_bound():
    for domain in DOMAINS:
        own = {n for n in FIELD_NAMES if field_type(n) is int and n not in NOT_SIZES
               and (n.startswith(f"{domain}_") or not n.startswith(tuple(f"{d}_" for d in DOMAINS)))}
        assert own <= set(bounds(domain)), f"{domain}: no upper bound for {sorted(own - set(bounds(domain)))}"


@pytest.mark.parametrize("name", spaces.known_spaces())
def test_every_committed_space_expands_far_within_the_bounds(name):
    specs = spaces.expand(name)
    assert 0 < len(specs) * MARGIN <= spaces.MAX_CELLS
    for spec in specs:
        assert_far_within_bounds(spec)


def test_golden_cells_and_domain_defaults_are_far_within_the_bounds():
    # The built-ins' bounds sit far above their defaults (a rule of this package; a plugin sets its own).
    built_in = [d for d in DOMAINS if DOMAINS[d].legacy_identity]
    for spec in [CellSpec.from_dict(d).resolved() for d in golden_specs()] + [CellSpec(domain=d).resolved()
                                                                               for d in built_in]:
        assert_far_within_bounds(spec)


@pytest.mark.parametrize("last", [10**7 - 1, 2**63 - 1])
def test_a_space_too_large_is_refused_without_being_built(tmp_path, last):
    path = tmp_path / "huge.toml"
    path.write_text(f"[[grid]]\naxes = {{ method = ['pc', 'asp'], trial = {{ first = 0, last = {last} }} }}")
    tracemalloc.start()
    try:
        with pytest.raises(SweepError, match=f"more than the {spaces.MAX_CELLS} cells a space may hold"):
            spaces.load_space(str(path))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2**20, f"refusing the space allocated {peak} bytes"


def test_includes_count_towards_the_cap(tmp_path, monkeypatch):
    monkeypatch.setattr(spaces, "MAX_CELLS", 10)
    (tmp_path / "six.toml").write_text("[[grid]]\naxes = { trial = { first = 0, last = 5 } }")
    (tmp_path / "two.toml").write_text(f"include = ['{tmp_path / 'six.toml'}', '{tmp_path / 'six.toml'}']")
    with pytest.raises(SweepError, match="its includes hold 12 cells, more than the 10"):
        spaces.load_space(str(tmp_path / "two.toml"))
    (tmp_path / "more.toml").write_text(f"include = ['{tmp_path / 'six.toml'}']\n"
                                        "[[grid]]\naxes = { paired = [1, 2, 3, 4, 5] }")
    with pytest.raises(SweepError, match=r"give 5 cells after the 6 before it, more than the 10"):
        spaces.load_space(str(tmp_path / "more.toml"))


TORCH_OOM = ("[enforce fail at alloc_cpu.cpp:117] data. DefaultCPUAllocator: can't allocate memory: you tried to "
             "allocate 16000000000000 bytes. Error code 12 (Cannot allocate memory)")


@pytest.mark.parametrize("error, needle", [(RuntimeError(TORCH_OOM), "it asked for 16000000000000 bytes at once"),
                                           (MemoryError(), "out of memory for this cell signaling-asp-p1-t0-")])
def test_a_cell_out_of_memory_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch, error, needle):
    def run_cell(*args, **kwargs):
        raise error

    monkeypatch.setattr(cell_module, "run_cell", run_cell)
    out = tmp_path / "row.parquet"
    assert main(["cell", "--domain", "signaling", "--method", "asp", "--paired", "1", "--quiet",
                 "--out", str(out)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("asp-dist: error: out of memory for this cell"), lines
    assert needle in lines[0]
    assert not out.exists()


def test_any_other_runtime_error_of_a_cell_is_not_called_out_of_memory(monkeypatch):
    def run_cell(*args, **kwargs):
        raise RuntimeError("mat1 and mat2 shapes cannot be multiplied")

    monkeypatch.setattr(cell_module, "run_cell", run_cell)
    with pytest.raises(RuntimeError, match="shapes cannot be multiplied"):
        main(["cell", "--domain", "signaling", "--method", "asp", "--paired", "1", "--quiet"])
