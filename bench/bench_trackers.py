"""What do the live trackers cost? End-to-end wall time of the same sweep with no logger and with each one,
in one run on one machine (the budget: <= 5 % for tensorboard and json).

    python bench/bench_trackers.py --repeats 2 --json docs/bench-results/trackers-<date>.json

Workloads, each a fresh `asp-dist sweep` subprocess on the embedded Ray with 2 workers, into a new results
directory every time (so every run trains every cell):
  smoke              tune_spaces/smoke: 18 tiny signaling cells (a cell takes well under a second: the worst
                     case for a per-cell cost such as opening a tracker run)
  particles-packed   one paper particle trial pair (42 cells: paired 0..6 x 3 methods x 2 trials, short
                     budget) packed per trial: 2 packs of 21 members, each member its own tracker run

Rounds alternate the order of the variants (forward, then backward) so that a drifting load hits all of
them alike; the figure per variant is the median over rounds, and its overhead is against the median of
the no-logger runs. Beside it, the paired view: per round, the variant's time over that round's no-logger
time (so a slow round counts against both), the median of those ratios, and a 95 % bootstrap interval of
that median over rounds -- the figure to hold against a budget on a noisy machine. Beside wall time, the CPU
seconds the whole machine spent during each run (/proc/stat), with the same paired view: steadier than wall
time on a VM, and only meaningful on an otherwise idle machine. W&B runs offline (WANDB_MODE=offline). Record
the load average: figures taken on a busy machine say little.

`--against COMMIT` is the A/B of a change: every variant also runs on COMMIT's code (its asp_dist/ and
tune_spaces/ exported to a temporary directory, put first on PYTHONPATH of the sweep and its Ray workers), in the
same alternating rounds after one untimed warm-up run per code, and each variant is also compared round by round
with itself on COMMIT's code (this checkout's "json" over "json@COMMIT"). The JSON records both revisions.

    python bench/bench_trackers.py --repeats 8 --workloads smoke --variants none,json --against 223a963c
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_info  # noqa: E402

# "no-tune-logs": no tracker and no Tune JSON/CSV result logs either (ASP_DIST_TUNE_RESULT_LOGS=0), the cost of
# what makes Tune's readers work; every other variant keeps them, as every sweep does.
VARIANTS = ("none", "no-tune-logs", "tensorboard", "json", "mlflow", "wandb")
PARTICLES = """
description = "bench_trackers: one paper particle trial pair, short budget, packed per trial"
[[grid]]
[grid.fixed]
train_steps = 400
base_train_steps = 20
base_max_attempts = 1
particles_accept_return = 0.0
eval_episodes = 16
[grid.axes]
domain = ["particles"]
method = ["pc", "osp", "asp"]
paired = [0, 1, 2, 3, 4, 5, 6]
trial = { first = 0, last = 1 }
"""


def machine_cpu_seconds() -> float:
    """CPU time spent on this whole machine so far (/proc/stat: user, nice, system, irq, softirq), in seconds.
    Taken around a run on an otherwise idle machine, it is the CPU the run cost with every process it started
    (driver, Ray's daemons, workers, the tracker hub), which per-process accounting loses once Ray's workers
    are reparented; far steadier than wall time on a VM, and on a saturated two-core sweep wall ≈ CPU / 2."""
    fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    user, nice, system, _idle, _iowait, irq, softirq = (int(x) for x in fields[:7])
    return (user + nice + system + irq + softirq) / os.sysconf("SC_CLK_TCK")


def run_once(workload: str, variant: str, space: str, work: Path, code: Path | None = None) -> tuple[float, float]:
    """One fresh sweep; `code`: run another checkout's asp_dist (first on PYTHONPATH, and the working directory)."""
    results = Path(tempfile.mkdtemp(prefix=f"{workload}-{variant}-", dir=work))
    cmd = [sys.executable, "-m", "asp_dist.cli", "sweep", space, "--name", "b", "--results", str(results)]
    if workload == "particles-packed":
        cmd += ["--pack", "trial"]
    if variant not in ("none", "no-tune-logs"):
        cmd += ["--logger", variant]
    env = dict(os.environ, OMP_NUM_THREADS="1", WANDB_MODE="offline", WANDB_SILENT="true",
               ASP_DIST_TUNE_RESULT_LOGS="0" if variant == "no-tune-logs" else "1")
    if code is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(code), *filter(None, [os.environ.get("PYTHONPATH")])])
    start, cpu_start = time.perf_counter(), machine_cpu_seconds()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=code)
    seconds, cpu = time.perf_counter() - start, machine_cpu_seconds() - cpu_start
    if done.returncode != 0:
        raise SystemExit(f"{workload}/{variant} failed:\n{done.stderr[-2000:]}")
    return seconds, cpu


def paired_overhead(times: list[float], baseline: list[float], resamples: int = 10_000) -> dict:
    """Round by round, `times` over the same round's `baseline`: the median ratio - 1 and a percentile
    bootstrap 95 % interval of it over rounds (seeded: the same runs give the same interval)."""
    import numpy as np

    ratios = np.array(times) / np.array(baseline) - 1
    rng = np.random.default_rng(0)
    medians = np.median(rng.choice(ratios, size=(resamples, len(ratios))), axis=1)
    return {"paired_ratios": ratios.tolist(), "paired_overhead": float(np.median(ratios)),
            "paired_ci": [float(np.percentile(medians, 2.5)), float(np.percentile(medians, 97.5))]}


REPO = Path(__file__).resolve().parent.parent


def git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(REPO), *args], check=True, capture_output=True, text=True).stdout.strip()


def export(commit: str, where: Path) -> Path:
    """COMMIT's asp_dist/ and tune_spaces/ at `where` (what a sweep of it imports and reads), for --against."""
    where.mkdir()
    archive = subprocess.run(["git", "-C", str(REPO), "archive", commit, "asp_dist", "tune_spaces"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(where)], input=archive, check=True)
    return where


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2, help="rounds (alternating order); median per variant")
    ap.add_argument("--workloads", default="smoke,particles-packed")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--against", metavar="COMMIT", help="also run every variant on COMMIT's code (A/B of a change)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    load_before = os.getloadavg()
    dirty = bool(git("status", "--porcelain", "--untracked-files=no", "--", "asp_dist", "tune_spaces"))
    out = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": machine_info(), "load_before": load_before,
           "code": git("rev-parse", "HEAD") + (" with uncommitted changes" if dirty else ""),
           "against": git("rev-parse", args.against) if args.against else None, "workloads": {}}
    with tempfile.TemporaryDirectory(prefix="bench-trackers-") as tmp:
        work = Path(tmp)
        # arm name -> (logger variant, code to run: None = this checkout)
        arms: dict[str, tuple[str, Path | None]] = {v: (v, None) for v in args.variants.split(",")}
        if args.against:
            old = export(args.against, work / "against")
            arms.update({f"{v}@{args.against}": (v, old) for v in args.variants.split(",")})
        spaces = {"smoke": "smoke", "particles-packed": str(work / "particles.toml")}
        (work / "particles.toml").write_text(PARTICLES)
        for workload in args.workloads.split(","):
            if args.against:  # untimed: each code's bytecode and imports warm before the first timed round
                for code in (None, old):
                    run_once(workload, "none", spaces[workload], work, code)
            times: dict[str, list[float]] = {a: [] for a in arms}
            cpus: dict[str, list[float]] = {a: [] for a in arms}
            for r in range(args.repeats):
                for arm in list(arms) if r % 2 == 0 else list(arms)[::-1]:
                    variant, code = arms[arm]
                    wall, cpu = run_once(workload, variant, spaces[workload], work, code)
                    times[arm].append(wall)
                    cpus[arm].append(cpu)
                    print(f"{workload} {arm}: {wall:.1f} s wall, {cpu:.1f} s CPU", file=sys.stderr)
            out["workloads"][workload] = {arm: summary(arm, arms, times, cpus) for arm in arms}
    out["load_after"] = os.getloadavg()
    print(f"load average before {load_before[0]:.2f}, after {out['load_after'][0]:.2f}")
    print("| workload | logger | median wall (s) | overhead | paired wall: median of per-round ratios (95 % CI) "
          "| median CPU (s) | paired CPU (95 % CI) |\n|---|---|---|---|---|---|---|")

    def paired(rec: dict, prefix: str = "") -> str:
        if f"{prefix}paired_overhead" not in rec:
            return ""
        lo, hi = rec[f"{prefix}paired_ci"]
        return f"{100 * rec[f'{prefix}paired_overhead']:+.1f} % ({100 * lo:+.1f} … {100 * hi:+.1f} %)"

    for workload, by in out["workloads"].items():
        for arm, rec in by.items():
            over = "" if rec["overhead"] is None else f"{100 * rec['overhead']:+.1f} %"
            print(f"| {workload} | {arm} | {rec['median_s']:.1f} | {over} | {paired(rec)} | {rec['median_cpu_s']:.1f} "
                  f"| {paired(rec, 'cpu_')} |")
        if args.against:
            print(f"\n| workload | logger | this code over {args.against}: paired wall (95 % CI) | paired CPU (95 % CI) |"
                  "\n|---|---|---|---|")
            for arm, rec in by.items():
                if "change" in rec:
                    print(f"| {workload} | {arm} | {paired(rec['change'])} | {paired(rec['change'], 'cpu_')} |")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")


def summary(arm: str, arms: dict[str, tuple[str, Path | None]], times: dict[str, list[float]],
            cpus: dict[str, list[float]]) -> dict:
    """An arm's figures: medians, and round by round against the no-logger arm of the same code (and, for this
    checkout's arms under --against, against the same variant on the other code: "change")."""
    variant, code = arms[arm]
    base = next((a for a, (v, c) in arms.items() if v == "none" and c == code), None)
    rec = {"seconds": times[arm], "median_s": statistics.median(times[arm]), "cpu_seconds": cpus[arm],
           "median_cpu_s": statistics.median(cpus[arm]), "overhead": None}
    if base is not None and base != arm:
        rec["overhead"] = statistics.median(times[arm]) / statistics.median(times[base]) - 1
        rec.update(paired_overhead(times[arm], times[base]))
        rec.update({f"cpu_{k}": x for k, x in paired_overhead(cpus[arm], cpus[base]).items()})
    other = next((a for a, (v, c) in arms.items() if v == variant and c is not None), None)
    if code is None and other is not None:
        rec["change"] = {**paired_overhead(times[arm], times[other]),
                         **{f"cpu_{k}": x for k, x in paired_overhead(cpus[arm], cpus[other]).items()}}
    return rec


if __name__ == "__main__":
    main()
