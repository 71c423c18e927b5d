"""The machine a process runs on, as a row and a run's record name it. No torch, no Ray at import.

Float results reproduce bit for bit only on the CPU kind that made them (docs/decisions/0024-numerics-across-cpus.md,
0041-every-row-names-its-cpu.md), so every row says which CPU trained it and every run record which CPU drove it.
"""

from __future__ import annotations

import platform
from functools import lru_cache
from pathlib import Path


@lru_cache(maxsize=1)
def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo's first "model name"), else what `platform` knows, else "unknown"."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"
