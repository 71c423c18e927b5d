"""Named grids ("spaces"): load ``tune_spaces/<name>.toml`` and expand it into resolved cells.

A space file is small and readable (stdlib ``tomllib``)::

    description = "what this grid is for"
    include = ["paper-particles"]      # optional: add the cells of other spaces

    [fixed]                            # optional: CellSpec overrides for every grid below
    root_seed = 0

    [[grid]]                           # one or more sub-grids; cells = union over grids
    name = "paired-count"
    fixed = { vae_latent_dim = 32 }    # optional: overrides for this grid only
    [grid.axes]                        # cartesian product, any CellSpec field
    domain = ["vae"]
    method = ["pc", "osp", "asp"]
    paired = [0, 1, 2, 4, 8, 16, 32, 64]
    trial  = { first = 0, last = 9 }   # inclusive integer range

    [methods.asp]                      # optional: knob values for one method's cells (over [fixed] and a
    lr = 0.001                         #   grid's fixed; never a grid axis)
    settings = ["tuned.toml"]          # optional: files whose [methods.*] tables apply too, e.g. the tuned.toml
                                       #   of `asp-dist tune` (paths relative to this file; its own [methods] win)

    [logging]                          # optional: live trackers of a run of this space (asp_dist.tracking)
    loggers = ["tensorboard"]          # tensorboard | mlflow | wandb | json; --logger on the command line wins
    dir = "runs/trackers"              # optional; also mlflow_uri, wandb_project

A space of more than MAX_CELLS cells is refused from its axis lengths, before any cell is built.
Expansion validates every value through ``CellSpec`` (types, ranges, domain rules), rejects
domains whose module is not in this installation, drops duplicate cells (two sub-grids may
share cells) and orders cells by (domain, trial, paired, method) so that the cells sharing a
base run close together. The grid hash is a stable hash of the sorted cell ids.
"""

from __future__ import annotations

import itertools
import math
import tomllib
from pathlib import Path
from typing import Any

from asp_dist.errors import SpecError, SweepError
from asp_dist.hashing import stable_hash
from asp_dist.spec import CellSpec, coerce_field

# [tune]: asp_dist.sweep.tune_plan; [decide]: asp_dist.study.decide_plan; [methods.<name>] and settings:
# per-method knob values (a tuned.toml)
SPACE_KEYS = {"description", "include", "fixed", "grid", "logging", "tune", "decide", "methods", "settings"}
GRID_KEYS = {"name", "fixed", "axes"}
LOGGING_KEYS = {"loggers", "dir", "mlflow_uri", "wandb_project"}
# Cells one space may hold, counted before a grid is built: the paper's grid has 1470; a million resolved
# cells take ~2 GB and a quarter of an hour to expand, and a sweep of them months of CPU.
MAX_CELLS = 1_000_000


def spaces_dir() -> Path:
    """``tune_spaces/`` next to the package (a source checkout or an editable install)."""
    return Path(__file__).resolve().parents[2] / "tune_spaces"


def known_spaces() -> list[str]:
    d = spaces_dir()
    return sorted(p.stem for p in d.glob("*.toml")) if d.exists() else []


def space_file(name_or_path: str) -> Path:
    """A space by name (``smoke``) or by path to a .toml file."""
    as_path = Path(name_or_path)
    if as_path.suffix == ".toml" or "/" in name_or_path:
        if not as_path.is_file():
            raise SweepError(f"space file {name_or_path} does not exist")
        return as_path
    path = spaces_dir() / f"{name_or_path}.toml"
    if not path.is_file():
        raise SweepError(f"unknown space {name_or_path!r}; choose one of {', '.join(known_spaces())} "
                         f"or pass a path to a .toml file")
    return path


def _axis_values(space: str, field: str, raw: Any) -> range | list[Any]:
    if isinstance(raw, dict):
        if set(raw) != {"first", "last"} or not all(isinstance(v, int) for v in raw.values()):
            raise SweepError(f"space {space}: axis {field} must be a list or {{ first = INT, last = INT }}, "
                             f"got {raw!r}")
        if raw["last"] < raw["first"]:
            raise SweepError(f"space {space}: axis {field} has last < first ({raw!r})")
        if raw["last"] - raw["first"] + 1 > MAX_CELLS:  # before len(): it overflows past 2^63
            raise SweepError(f"space {space}: axis {field} has {raw['last'] - raw['first'] + 1} values, more than "
                             f"the {MAX_CELLS} cells a space may hold; split it into smaller spaces")
        return range(raw["first"], raw["last"] + 1)  # lazy: counted before anything is built
    if not isinstance(raw, list) or not raw:
        raise SweepError(f"space {space}: axis {field} must be a non-empty list, got {raw!r}")
    return raw


def _coerce(space: str, field: str, value: Any) -> Any:
    try:
        return coerce_field(field, value)
    except SpecError as e:
        raise SweepError(f"space {space}: {e}") from None


def load_space(name_or_path: str, _seen: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """The raw (unresolved) cell dicts of a space, includes expanded."""
    path = space_file(name_or_path)
    space = path.stem
    if space in _seen:
        raise SweepError(f"space {space} includes itself (via {' -> '.join(_seen)})")
    data = read_space_toml(path)
    unknown = sorted(set(data) - SPACE_KEYS)
    if unknown:
        raise SweepError(f"space {space}: unknown key(s) {', '.join(unknown)}; "
                         f"allowed: {', '.join(sorted(SPACE_KEYS))}")
    cells: list[dict[str, Any]] = []
    for included in data.get("include", []):
        cells += load_space(included, _seen + (space,))
        if len(cells) > MAX_CELLS:
            raise SweepError(f"space {space}: its includes hold {len(cells)} cells, more than the {MAX_CELLS} "
                             f"a space may hold; split it into smaller spaces")
    fixed = {k: _coerce(space, k, v) for k, v in data.get("fixed", {}).items()}
    per_method = method_settings(path, data)
    grids = data.get("grid", [])
    if not grids and not data.get("include"):
        raise SweepError(f"space {space}: needs at least one [[grid]] or an include list")
    for i, grid in enumerate(grids):
        label = f"{space}[{grid.get('name', i)}]"
        unknown = sorted(set(grid) - GRID_KEYS)
        if unknown:
            raise SweepError(f"space {label}: unknown key(s) {', '.join(unknown)}; "
                             f"allowed: {', '.join(sorted(GRID_KEYS))}")
        grid_fixed = {**fixed, **{k: _coerce(label, k, v) for k, v in grid.get("fixed", {}).items()}}
        axes = {k: _axis_values(label, k, raw) for k, raw in grid.get("axes", {}).items()}
        count = math.prod(len(values) for values in axes.values())
        if len(cells) + count > MAX_CELLS:  # counted first: the product is never built
            sizes = " × ".join(f"{k} ({len(values)})" for k, values in axes.items())
            before = f" after the {len(cells)} before it" if cells else ""
            raise SweepError(f"space {label}: axes {sizes} give {count} cells{before}, more than the {MAX_CELLS} "
                             f"a space may hold; split it into smaller spaces")
        axes = {k: [_coerce(label, k, v) for v in values] for k, values in axes.items()}
        overlap = sorted(set(axes) & set(grid_fixed))
        if overlap:
            raise SweepError(f"space {label}: {', '.join(overlap)} is both an axis and fixed; keep one")
        for method, values in per_method.items():
            clash = sorted(set(values) & set(axes))
            if clash:
                raise SweepError(f"space {label}: {', '.join(clash)} is a grid axis and set for method {method} "
                                 f"([methods] or settings); keep one")
        for combo in itertools.product(*axes.values()):
            cell = {**grid_fixed, **dict(zip(axes, combo))}
            cells.append({**cell, **per_method.get(cell.get("method", "asp"), {})})
    return cells


def method_settings(path: Path, data: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Knob values per method: the [methods.*] tables of the files in `settings` (in order), then the space's
    own [methods.*] (which win), each value checked as a cell field."""
    space = path.stem
    files = data.get("settings", [])
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        raise SweepError(f"space {space}: settings must be a list of file paths, got {files!r}")
    tables = []
    for name in files:
        file = (path.parent / name) if not Path(name).is_absolute() else Path(name)
        if not file.is_file():
            raise SweepError(f"space {space}: its settings file {name} does not exist (looked at {file})")
        try:
            loaded = tomllib.loads(file.read_text())
        except tomllib.TOMLDecodeError as e:
            raise SweepError(f"space {space}: invalid TOML in its settings file {file}: {e}") from None
        tables.append((f"{space} (settings {name})", loaded.get("methods", {})))
    tables.append((space, data.get("methods", {})))
    merged: dict[str, dict[str, Any]] = {}
    for label, table in tables:
        if not isinstance(table, dict) or not all(isinstance(v, dict) for v in table.values()):
            raise SweepError(f"space {label}: [methods] holds one table per method ([methods.asp] ...), got {table!r}")
        for method, values in table.items():
            merged.setdefault(method, {}).update({k: _coerce(label, k, v) for k, v in values.items()})
    return merged


def expand(name_or_path: str) -> list[CellSpec]:
    """Resolved, validated, de-duplicated cells of a space, in a base-friendly order."""
    space = space_file(name_or_path).stem
    raw = load_space(name_or_path)
    specs: dict[str, CellSpec] = {}
    for cell in raw:
        try:
            spec = CellSpec.from_dict(cell).resolved()
        except SpecError as e:
            raise SweepError(f"space {space}: {e}") from None
        specs.setdefault(spec.cell_id, spec)
    if not specs:
        raise SweepError(f"space {space} has no cells")
    return sorted(specs.values(), key=lambda s: (s.domain, s.root_seed, s.trial, s.paired, s.method, s.cell_id))


def read_space_toml(path: Path) -> dict[str, Any]:
    """A space file's TOML; a syntax error is the one-line SweepError that names the file."""
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise SweepError(f"space {path.stem}: invalid TOML in {path}: {e}") from None


def space_logging(name_or_path: str) -> dict[str, Any]:
    """A space file's [logging] table (its own, not its includes'), checked: {} when it has none."""
    path = space_file(name_or_path)
    table = read_space_toml(path).get("logging", {})
    space = path.stem
    if not isinstance(table, dict):
        raise SweepError(f"space {space}: logging must be a table ([logging]), got {table!r}")
    unknown = sorted(set(table) - LOGGING_KEYS)
    if unknown:
        raise SweepError(f"space {space}: unknown key(s) {', '.join(unknown)} in [logging]; "
                         f"allowed: {', '.join(sorted(LOGGING_KEYS))}")
    loggers = table.get("loggers", [])
    if not isinstance(loggers, list) or not all(isinstance(k, str) for k in loggers):
        raise SweepError(f"space {space}: [logging] loggers must be a list of names, got {loggers!r}")
    for key in LOGGING_KEYS - {"loggers"}:
        if key in table and not isinstance(table[key], str):
            raise SweepError(f"space {space}: [logging] {key} must be a string, got {table[key]!r}")
    return dict(table)


def grid_hash(specs: list[CellSpec]) -> str:
    return stable_hash(sorted(s.cell_id for s in specs))[:16]
