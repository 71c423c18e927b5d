"""Helpers shared by the bench/ scripts (run as `python bench/<script>.py`, so this module is on
sys.path as the script's own directory)."""

from __future__ import annotations

import resource
from typing import Any


def peak_rss_mib() -> float:
    """The process's peak resident set size so far (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def cell_timing(row: dict[str, Any]) -> str:
    """Where a run_cell row says its time went: per phase (wall), total wall and CPU."""
    return (f"train {row['time_train_wall_s']:.1f} s, eval {row['time_eval_wall_s']:.2f} s, "
            f"data {row['time_data_wall_s']:.2f} s, total {row['time_total_wall_s']:.1f} s wall / "
            f"{row['time_total_cpu_s']:.1f} s CPU")
