"""What a sweep ran with, recorded at every start and resume: ``RESULTS/NAME/env/<n>/`` (n = 1, 2, ...).

    command.txt        the command line, as run
    space.toml         the space file as run (a resume: the grid hash and cell count it continues)
    git.txt            the asp_dist source's revision and whether its tree is dirty
    git.diff           `git diff HEAD` of the source tree, when it is dirty
    distributions.txt  every installed distribution, name==version, sorted
    tracking.json      the live trackers of the run (--logger, their directory and URIs): a resume's default
    machine.json       host, CPU model, cores, memory, Python, platform, thread settings (OMP/MKL/torch), the
                       run's start time, and its Ray nodes (node id, address, CPUs, memory) when Ray is up: a
                       row's ray_node_id names the run and node that made it (the row's cpu_model, its CPU)

A row already records five versions and a revision (asp_dist.training.row); this is the rest of what a
reviewer asks for. Written once per run and never overwritten (a new number per run); on S3 the same
files as objects. Never fatal: a sweep does not stop because git or /proc cannot be read (the entry says
so). No Ray import.
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

from asp_dist.machine import cpu_model
from asp_dist.results.location import AnyPath, write_replace

ENV_DIR = "env"
TRACKING = "tracking.json"  # the run's live trackers (asp_dist.tracking.base.TrackingSettings): resume's default
SOURCE = Path(__file__).resolve().parents[2]  # the checkout that holds asp_dist (a git work tree, usually)


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=SOURCE, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout if out.returncode == 0 else None


def _memory_gib() -> float | None:
    try:
        return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        return None


def distributions() -> list[str]:
    """Every installed distribution as name==version, sorted by name (case-insensitive)."""
    seen = {}
    for dist in metadata.distributions():
        meta = dist.metadata  # parsed at each access (dist.version too): once, as it is ≈ 1 ms a distribution
        name = meta.get("Name")
        if name:
            seen.setdefault(name.lower(), f"{name}=={meta.get('Version')}")
    return [seen[k] for k in sorted(seen)]


def machine(ray_nodes: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """This machine and the run's thread settings (and Ray's nodes when given)."""
    info: dict[str, Any] = {
        "host": platform.node(), "cpu_model": cpu_model(), "cores": os.cpu_count(), "memory_gib": _memory_gib(),
        "python": platform.python_version(), "platform": platform.platform(),
        "threads": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")},
        "started_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    torch = sys.modules.get("torch")  # the driver imports torch with Tune; report what it uses
    if torch is not None:
        info["threads"]["torch"] = torch.get_num_threads()
        info["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    if ray_nodes is not None:
        info["ray_nodes"] = [{"node_id": n.get("NodeID"), "address": n.get("NodeManagerAddress"),
                              "alive": n.get("Alive"),
                              "cpus": n.get("Resources", {}).get("CPU"),
                              "memory_gib": round(n.get("Resources", {}).get("memory", 0) / 2**30, 1)}
                             for n in ray_nodes]
    return info


def next_number(sweep_dir: AnyPath) -> int:
    root = sweep_dir / ENV_DIR
    taken = [int(p.name) for p in root.iterdir() if p.name.isdigit()] if root.is_dir() else []
    return max(taken, default=0) + 1


def last_tracking(sweep_dir: AnyPath) -> dict[str, Any] | None:
    """The trackers of the sweep's latest recorded run (its tracking.json), or None."""
    root = sweep_dir / ENV_DIR
    try:
        runs = sorted((int(p.name) for p in root.iterdir() if p.name.isdigit()), reverse=True) if root.is_dir() else []
        for n in runs:
            path = root / str(n) / TRACKING
            if path.exists():
                return json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return None


def record(sweep_dir: AnyPath, *, space_text: str | None, grid: str, argv: list[str] | None = None,
           ray_nodes: list[dict[str, Any]] | None = None, tracking: dict[str, Any] | None = None) -> AnyPath:
    """Write ``env/<n>/`` for this run of the sweep in `sweep_dir` and return it. `space_text`: the space
    file as run (None on resume); `grid`: one line on the grid (hash, cells) for a resume's space.toml."""
    where = sweep_dir / ENV_DIR / str(next_number(sweep_dir))
    argv = sys.argv if argv is None else argv
    revision = _git("rev-parse", "HEAD")
    status = _git("status", "--porcelain", "--", "asp_dist")
    dirty = bool(status and status.strip())
    files = {
        "command.txt": shlex.join(argv) + "\n",
        "space.toml": space_text if space_text is not None else f"# resumed from the manifest: {grid}\n",
        "git.txt": (f"revision {revision.strip()}\ndirty {str(dirty).lower()}\nsource {SOURCE}\n" if revision
                    else f"revision unknown (no git checkout at {SOURCE})\n"),
        "distributions.txt": "\n".join(distributions()) + "\n",
        "machine.json": json.dumps(machine(ray_nodes), indent=1, sort_keys=True) + "\n",
    }
    if tracking is not None:
        files[TRACKING] = json.dumps(tracking, indent=1, sort_keys=True) + "\n"
    if dirty:
        files["git.diff"] = _git("diff", "HEAD", "--", "asp_dist") or ""
    if isinstance(where, Path):
        where.mkdir(parents=True, exist_ok=False)  # a new number: nothing of an earlier run is overwritten
        for name, text in files.items():
            write_replace(where / name, text)
    else:  # on S3: objects, each put only where none is (If-None-Match)
        for name, text in files.items():
            where.joinpath(name).create(text.encode())
    return where
