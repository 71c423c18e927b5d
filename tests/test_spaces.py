"""Named grids: sizes of the paper's spaces, overrides, stable hashes, clear errors."""

from __future__ import annotations

import pytest

from asp_dist.errors import SweepError
from asp_dist.spec import SpecError
from asp_dist.sweep import spaces
from asp_dist.sweep.spaces import expand, grid_hash, load_space


def test_named_spaces_exist():
    assert {"smoke", "signaling-skew", "paper-particles", "paper-vae", "paper-levers", "paper"} <= set(
        spaces.known_spaces())


@pytest.mark.parametrize("name, cells", [
    ("paper-particles", 30 * 7 * 3),
    # the d=32, 32-paired cells appear in both VAE grids and count once
    ("paper-vae", 10 * 8 * 3 + 10 * 7 * 3 - 10 * 3),
    ("paper-levers", 20 * 7 * 3),
    ("smoke", 3 * 3 * 2),
])
def test_grid_sizes(name, cells):
    raw = load_space(name)
    assert len({tuple(sorted(c.items())) for c in raw}) == cells


def test_paper_vae_grids():
    raw = load_space("paper-vae")
    paired_grid = [c for c in raw if c["vae_latent_dim"] == 32]
    assert {c["paired"] for c in paired_grid} == {0, 1, 2, 4, 8, 16, 32, 64}
    latent_grid = [c for c in raw if c["paired"] == 32]
    assert {c["vae_latent_dim"] for c in latent_grid} == {2, 4, 8, 16, 32, 64, 128}
    assert {c["trial"] for c in raw} == set(range(10))


def test_paper_includes_every_paper_space():
    assert len(load_space("paper")) == sum(len(load_space(n)) for n in ("paper-particles", "paper-vae", "paper-levers"))
    assert len(expand("paper")) == 630 + 420 + 420


def test_smoke_expands_to_resolved_unique_cells_in_base_order():
    specs = expand("smoke")
    assert len(specs) == 18 and len({s.cell_id for s in specs}) == 18
    assert all(s.train_steps == 150 and s.unpaired_size == 256 and s.domain == "signaling" for s in specs)
    assert all(s.lr is not None for s in specs), "specs must be resolved (domain defaults filled)"
    trials = [s.trial for s in specs]
    assert trials == sorted(trials), "cells of one trial (one base) run together"


def test_skew_space_covers_a_skew_axis():
    raw = load_space("signaling-skew")
    assert len({c["signaling_skew"] for c in raw}) >= 4
    assert {c["method"] for c in raw} == {"pc", "osp", "asp"}


def test_grid_hash_is_stable_and_order_free():
    specs = expand("smoke")
    assert grid_hash(specs) == grid_hash(list(reversed(specs)))
    assert grid_hash(specs) != grid_hash(specs[:-1])
    assert len(grid_hash(specs)) == 16


def write(tmp_path, text, name="custom.toml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_space_file_by_path_with_overrides_and_range(tmp_path):
    path = write(tmp_path, """
[fixed]
train_steps = 10
[[grid]]
fixed = { signaling_skew = 2.5, lr = "0.1" }
[grid.axes]
domain = ["signaling"]
method = ["asp"]
paired = { first = 1, last = 3 }
""")
    specs = expand(path)
    assert [s.paired for s in specs] == [1, 2, 3]
    assert all(s.train_steps == 10 and s.signaling_skew == 2.5 and s.lr == 0.1 for s in specs)


def test_duplicate_cells_across_grids_are_dropped(tmp_path):
    path = write(tmp_path, """
[[grid]]
axes = { method = ["pc", "asp"], paired = [1] }
[[grid]]
axes = { method = ["asp"], paired = [1, 2] }
""")
    assert len(load_space(path)) == 4
    assert len(expand(path)) == 3


@pytest.mark.parametrize("text, message", [
    ("[[grid]]\naxes = { method = ['xsp'] }", "unknown method 'xsp'"),
    ("[[grid]]\naxes = { domain = ['chess'] }", "unknown domain 'chess'"),
    ("[[grid]]\naxes = { paired = [-1] }", "paired must be an integer >= 0"),
    ("[[grid]]\naxes = { paired = ['two'] }", "paired must be of type int"),
    ("[[grid]]\naxes = { not_a_knob = [1] }", "unknown cell field 'not_a_knob'"),
    ("[[grid]]\naxes = { lr = [-0.5] }", "lr must be >= 0"),
    ("[[grid]]\naxes = { paired = [] }", "non-empty list"),
    ("[[grid]]\naxes = { paired = { first = 3, last = 1 } }", "last < first"),
    ("[[grid]]\naxes = { paired = [1] }\nfixed = { paired = 2 }", "both an axis and fixed"),
    ("colour = 'red'", "unknown key(s) colour"),
    ("[[grid]]\naxis = { paired = [1] }", "unknown key(s) axis"),
    ("description = 'nothing'", "needs at least one [[grid]]"),
    ("[[grid]\n", "invalid TOML"),
    ("include = ['no-such-space']", "unknown space 'no-such-space'"),
])
def test_bad_spaces_give_one_clear_line(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(SpecError) as err:
        expand(path)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_self_include_is_refused(tmp_path):
    path = write(tmp_path, "include = ['loop']", name="loop.toml")
    (tmp_path / "loop.toml").write_text(f"include = ['{path}']")
    with pytest.raises(SweepError, match="includes itself"):
        expand(path)


def test_unknown_space_names_the_known_ones():
    with pytest.raises(SweepError, match="unknown space 'nope'.*smoke"):
        expand("nope")
    with pytest.raises(SweepError, match="does not exist"):
        expand("/no/such/space.toml")
