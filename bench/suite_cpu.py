"""Where the test suite's CPU goes, test by test, counting every process a test starts (the CLI subprocesses,
Ray's daemons and workers, moto) -- and correct while another job loads the machine, where wall times are not.

    python bench/suite_cpu.py [--json FILE] [--top N] [-- PYTEST ARGS...]
    python bench/suite_cpu.py --json docs/bench-results/suite-cpu.json -- -m "not slow"

pytest runs in this process, one test at a time (-n 0), inside a cgroup of its own (root, cgroup v2 or v1's
cpuacct): a process inherits its parent's cgroup, so a test's CPU is the cgroup's counter after it minus before
it. A module fixture counts towards the first test that uses it; a process that outlives its test (a Ray
daemon on its way out) counts towards the next. Without a usable cgroup it falls back to getrusage of this
process and its reaped children, which misses the daemons, and says so.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from _common import machine_info  # noqa: E402


class CgroupClock:
    """CPU seconds used by every process of a fresh cgroup that this process moved itself into."""

    def __init__(self, name: str):
        self.dir = self.counter = self.parent = None
        mounts = [line.split() for line in Path("/proc/self/mounts").read_text().splitlines()]
        for _, where, kind, options, *_ in mounts:
            if kind == "cgroup2":
                self._try(Path(where), "cpu.stat", name)
            elif kind == "cgroup" and "cpuacct" in options.split(","):
                self._try(Path(where), "cpuacct.usage", name)
            if self.dir:
                return

    def _try(self, root: Path, counter: str, name: str) -> None:
        v2 = counter == "cpu.stat"
        # /proc/self/cgroup: "ID:CONTROLLERS:PATH"; cgroup v2's line has no controllers, v1's names cpuacct.
        here = None
        for line in Path("/proc/self/cgroup").read_text().splitlines():
            _, controllers, path = line.split(":", 2)
            if (controllers == "") if v2 else ("cpuacct" in controllers.split(",")):
                here = path
        if here is None:
            return
        parent = root / here.lstrip("/")
        group = parent / name
        try:
            group.mkdir(exist_ok=True)
            (group / "cgroup.procs").write_text(str(os.getpid()))
        except OSError:
            try:
                group.rmdir()
            except OSError:
                pass
            return
        self.dir, self.counter, self.parent = group, group / counter, parent

    def seconds(self) -> float:
        text = self.counter.read_text()
        if self.counter.name == "cpu.stat":
            usec = next(int(line.split()[1]) for line in text.splitlines() if line.startswith("usage_usec"))
            return usec / 1e6
        return int(text) / 1e9

    def close(self) -> str | None:
        """Move back to the parent cgroup and remove this one; a reason when it cannot be removed."""
        (self.parent / "cgroup.procs").write_text(str(os.getpid()))
        try:
            self.dir.rmdir()
        except OSError as e:
            return f"cgroup {self.dir} left in place ({e.strerror}: a test left a process running)"
        return None


def rusage_seconds() -> float:
    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                  resource.getrusage(resource.RUSAGE_CHILDREN)))


class PerTestCpu:
    """pytest plugin: wall and CPU seconds of each test's whole protocol (setup, call, teardown)."""

    def __init__(self, clock):
        self.clock, self.records = clock, []

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item, nextitem):
        c0, t0 = self.clock(), time.perf_counter()
        yield
        self.records.append({"test": item.nodeid, "slow": item.get_closest_marker("slow") is not None,
                             "cpu_s": round(self.clock() - c0, 2), "wall_s": round(time.perf_counter() - t0, 2)})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write the per-test records and the machine here")
    parser.add_argument("--top", type=int, default=30, help="list the N tests that use the most CPU")
    parser.add_argument("pytest_args", nargs="*", help="passed to pytest after `--` (default: the whole suite)")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    cgroup = CgroupClock(f"asp-suite-cpu-{os.getpid()}")
    clock = cgroup.seconds if cgroup.dir else rusage_seconds
    how = (f"cgroup {cgroup.counter}" if cgroup.dir else
           "getrusage (no writable cgroup: Ray's daemons and other grandchildren are not counted)")
    print(f"suite_cpu: counting CPU with {how}", file=sys.stderr)
    plugin = PerTestCpu(clock)
    load_before, t0, c0 = os.getloadavg(), time.perf_counter(), clock()
    code = pytest.main(["-q", "-n", "0", "-p", "no:cacheprovider", *args.pytest_args], plugins=[plugin])
    wall, cpu, load_after = time.perf_counter() - t0, clock() - c0, os.getloadavg()
    left = cgroup.close() if cgroup.dir else None
    if left:
        print(f"suite_cpu: {left}", file=sys.stderr)

    records = sorted(plugin.records, key=lambda r: -r["cpu_s"])
    by_file: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0])
    for r in records:
        f = by_file[r["test"].split("::")[0]]
        f[0] += r["cpu_s"]
        f[1] += r["wall_s"]
        f[2] += 1
    tier = {slow: sum(r["cpu_s"] for r in records if r["slow"] == slow) for slow in (False, True)}
    print(f"\n{len(records)} tests, {wall / 60:.1f} min wall, {cpu / 60:.1f} CPU-min "
          f"(fast tier {tier[False] / 60:.1f}, slow {tier[True] / 60:.1f}); load {load_before[0]:.2f} -> "
          f"{load_after[0]:.2f}")
    print(f"\n{'CPU s':>7} {'wall s':>7}  the {args.top} tests that use the most CPU")
    for r in records[:args.top]:
        print(f"{r['cpu_s']:7.1f} {r['wall_s']:7.1f}  {r['test']}{'  [slow]' if r['slow'] else ''}")
    print(f"\n{'CPU s':>7} {'wall s':>7} {'tests':>5}  per file")
    for name, (c, w, n) in sorted(by_file.items(), key=lambda kv: -kv[1][0]):
        print(f"{c:7.1f} {w:7.1f} {n:5d}  {name}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "machine": machine_info(),
            "counter": how, "pytest_args": args.pytest_args, "exit": int(code), "wall_s": round(wall, 1),
            "cpu_s": round(cpu, 1), "load_before": load_before, "load_after": load_after, "tests": records},
            indent=1) + "\n")
    return int(code)


if __name__ == "__main__":
    sys.exit(main())
