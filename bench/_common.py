"""Helpers shared by the bench/ scripts (run as `python bench/<script>.py`, so this module is on
sys.path as the script's own directory)."""

from __future__ import annotations

import os
import platform
import resource
import statistics
import time
from typing import Any, Callable


def peak_rss_mib() -> float:
    """The process's peak resident set size so far (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def cell_timing(row: dict[str, Any]) -> str:
    """Where a run_cell row says its time went: per phase (wall), total wall and CPU."""
    return (f"train {row['time_train_wall_s']:.1f} s, eval {row['time_eval_wall_s']:.2f} s, "
            f"data {row['time_data_wall_s']:.2f} s, total {row['time_total_wall_s']:.1f} s wall / "
            f"{row['time_total_cpu_s']:.1f} s CPU")


def timed(step: Callable[[], Any], updates: int) -> tuple[float, float]:
    """(wall, CPU) seconds of `updates` calls of `step`."""
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(updates):
        step()
    return time.perf_counter() - t0, time.process_time() - c0


def machine_info() -> dict[str, Any]:
    """What a benchmark figure was measured on: host, CPU model (/proc/cpuinfo), cores, memory,
    torch version and the CPU capability its kernels were dispatched for."""
    import torch

    info: dict[str, Any] = {"host": platform.node(), "machine": platform.machine(), "cores": os.cpu_count(),
                            "python": platform.python_version(), "torch": torch.__version__,
                            "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
                            "torch_threads": torch.get_num_threads(),
                            "omp_num_threads": os.environ.get("OMP_NUM_THREADS")}
    for path, key, field in (("/proc/cpuinfo", "cpu_model", "model name"), ("/proc/meminfo", "memory", "MemTotal")):
        try:
            with open(path) as f:
                info[key] = next((line.split(":", 1)[1].strip() for line in f if line.startswith(field)), None)
        except OSError:
            info[key] = None
    if info["memory"] and info["memory"].endswith(" kB"):
        info["memory"] = f"{int(info['memory'].split()[0]) / 2**20:.1f} GiB"
    return info


def cpu_per_call(call: Callable[[], Any], repeats: int = 3, min_s: float = 1.0) -> float:
    """Median over `repeats` blocks of the CPU seconds of one call (each block at least min_s of CPU)."""
    out = []
    for _ in range(repeats):
        n, start = 0, time.process_time()
        while True:
            call()
            n += 1
            spent = time.process_time() - start
            if spent >= min_s:
                break
        out.append(spent / n)
    return statistics.median(out)


def vmas_random_steps_per_cpu_s(n: int, repeats: int = 3, min_s: float = 1.0) -> float:
    """World-steps per CPU-second of n VMAS worlds of asp-dist's speaker–listener (asp_dist.domains.vmas.world.Worlds)
    under fixed random choices, no gradients, every world reset after 25 steps."""
    import torch

    from asp_dist.domains.vmas.world import WorldOptions, Worlds

    worlds = Worlds(n, WorldOptions())
    worlds.reset(0)
    choices = [{"say": torch.eye(3)[torch.randint(3, (n,))]}, {"move": torch.eye(5)[torch.randint(5, (n,))]}]

    def step():
        with torch.no_grad():
            worlds.step(choices)
        if worlds.t >= 25:
            worlds.reset(1)

    return n / cpu_per_call(step, repeats, min_s)


def mpe2_random_steps_per_cpu_s(n: int, repeats: int = 3, min_s: float = 1.0) -> float:
    """World-steps per CPU-second of n copies of mpe2's speaker–listener through asp-dist's PettingZoo adapter
    (EnvBatch, a Python loop over copies) under random actions, every copy reset after 25 steps."""
    import numpy as np

    from asp_dist.core.registry import get_domain
    from asp_dist.domains.pettingzoo.envs import EnvBatch
    from asp_dist.spec import CellSpec

    name = "mpe_speaker_listener"
    batch = EnvBatch(get_domain(name).facts(CellSpec(domain=name, method="osp").resolved()), n)
    batch.reset(range(n), range(n))
    rng = np.random.default_rng(0)

    def step():
        batch.step([rng.integers(3, size=(n, 1)).astype(float), rng.integers(5, size=(n, 1)).astype(float)])
        if batch.t[0] >= 25:
            batch.reset(range(n), range(n))

    try:
        return n / cpu_per_call(step, repeats, min_s)
    finally:
        batch.close()

