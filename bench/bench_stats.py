"""How long `asp-dist stats` takes on the paper grid, today and at an older revision: each run a fresh
interpreter (what a user waits for), median of N runs, at one or more bootstrap sizes.

    python bench/bench_stats.py --repeats 3 --rev 'f34a278^' [--bootstrap 2000,10000] [--no-figures] [--json out.json]

Input: results/examples/paper-packed-2.parquet (the 1,470 rows of the paper grid: particles, levers, VAE),
copied to a temporary directory first; every run writes to a fresh `--out` directory there. The command is
`python -m asp_dist stats COPY --out DIR --bootstrap N` (plus `--no-figures` if asked), i.e. each
revision's default outputs: the working tree writes report.md, report.html, stats/*.tex and the rliable
view; revisions before f34a278 write the paper's tables, figures and report.md only.

`--rev REV` (repeatable) also times revision REV: `git worktree add --detach` of REV in the temporary
directory, the command run from there with PYTHONPATH pointing at it (checked: `asp_dist` imports from the
worktree), the worktree removed at the end. `f34a278^` is the revision before the rliable view (2026-12-01),
so "before" is the paper's tables alone. The working tree ("current") is always timed, after the revisions.
`--bootstrap` takes a comma-separated list; `--bootstrap 10000` sets the resamples of the rliable view
(and of the paper tables' median intervals: StatsConfig.n_boot is one number). The ratio lines compare the
working tree with the first --rev at every bootstrap size, and the working tree at the largest size with
the first --rev at each size. Besides the wall time of the process, the job's own log gives "tables s"
(`read and analysed … in X s`: reading the rows and computing every table, the rliable view included) and
"job s" (`… s in all`: the job without the interpreter's start and imports of the CLI).
The budget: the working tree at 10,000 resamples <= 2x before.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "results" / "examples" / "paper-packed-2.parquet"
CURRENT = "current"


def cpu_model() -> str:
    """`lscpu`'s Model name (else /proc/cpuinfo's model name)."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "?")
    except OSError:
        return "?"


def git(*args: str, cwd: Path = REPO) -> str:
    out = subprocess.run(["git", *args], check=False, cwd=cwd, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"git {' '.join(args)} exited {out.returncode}: {out.stderr.strip()}")
    return out.stdout.strip()


def add_worktree(rev: str, scratch: Path) -> tuple[Path, str]:
    """A detached worktree of REV under scratch; (its path, the full commit)."""
    commit = git("rev-parse", "--verify", f"{rev}^{{commit}}")
    path = scratch / f"rev-{commit[:12]}"
    git("worktree", "add", "--detach", "--quiet", str(path), commit)
    return path, commit


def remove_worktree(path: Path) -> None:
    subprocess.run(["git", "worktree", "remove", "--force", str(path)], check=False, cwd=REPO, capture_output=True)
    subprocess.run(["git", "worktree", "prune"], check=False, cwd=REPO, capture_output=True)


def environment(source: Path) -> dict[str, str]:
    """The environment of a run from `source`: PYTHONPATH first on it, and no bytecode written there."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(source), *filter(None, [env.get("PYTHONPATH")])])
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    env.setdefault("MPLBACKEND", "Agg")
    return env


def check_imports(source: Path) -> str:
    """Where `asp_dist` is imported from when run from source (must lie inside it)."""
    out = subprocess.run([sys.executable, "-c", "import asp_dist; print(asp_dist.__file__)"], check=False,
                         cwd=source, env=environment(source), capture_output=True, text=True)
    where = out.stdout.strip()
    if out.returncode != 0 or not Path(where).resolve().is_relative_to(source.resolve()):
        raise SystemExit(f"asp_dist imports from {where or out.stderr.strip()!r}, not from {source}")
    return where


def job_seconds(stderr: str) -> tuple[float | None, float | None]:
    """The stats job's own log: (read and analysed in X s, Y s in all), None where a line is missing."""
    analysed = re.search(r"read and analysed .* in ([0-9.]+) s$", stderr, re.MULTILINE)
    in_all = re.search(r"\(([0-9.]+) s in all\)$", stderr, re.MULTILINE)
    return (float(analysed.group(1)) if analysed else None, float(in_all.group(1)) if in_all else None)


def time_stats(source: Path, rows: Path, out_root: Path, label: str, n_boot: int, repeats: int,
               figures: bool) -> tuple[list[float], list[float | None], list[float | None]]:
    """Wall seconds of `python -m asp_dist stats ROWS --out DIR --bootstrap N`, a fresh process each, with the
    job's own figures from its log (the tables' computation; the job without the interpreter's start)."""
    times, analysed, in_all = [], [], []
    for i in range(repeats):
        out = out_root / f"{label}-b{n_boot}-{i}"
        cmd = [sys.executable, "-m", "asp_dist", "stats", str(rows), "--out", str(out), "--bootstrap", str(n_boot),
               *([] if figures else ["--no-figures"])]
        t0 = time.perf_counter()
        done = subprocess.run(cmd, check=False, cwd=source, env=environment(source), capture_output=True, text=True)
        times.append(time.perf_counter() - t0)
        if done.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} (from {source}) exited {done.returncode}:\n{done.stderr[-2000:]}")
        a, b = job_seconds(done.stderr)
        analysed.append(a)
        in_all.append(b)
        shutil.rmtree(out, ignore_errors=True)
    return times, analysed, in_all


def parse_boots(text: str) -> list[int]:
    try:
        boots = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(f"--bootstrap {text!r}: a comma-separated list of integers") from None
    if not boots or min(boots) < 100:
        raise SystemExit(f"--bootstrap {text!r}: every size must be at least 100 (asp-dist stats refuses fewer)")
    return boots


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="runs per revision and bootstrap size (default 3)")
    ap.add_argument("--rev", action="append", default=[], metavar="REV",
                    help="also time this revision from a git worktree (repeatable), e.g. 'f34a278^'")
    ap.add_argument("--bootstrap", default="10000", metavar="N[,N…]",
                    help="bootstrap resamples passed to stats --bootstrap (default 10000)")
    ap.add_argument("--input", default=str(EXAMPLE), help="rows to analyse (default: the paper grid's 1,470 rows)")
    ap.add_argument("--no-figures", action="store_true", help="pass --no-figures (tables and report only)")
    ap.add_argument("--json", default=None, metavar="FILE", help="write the results here")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        raise SystemExit("--repeats must be at least 1")
    boots = parse_boots(args.bootstrap)

    scratch = tempfile.TemporaryDirectory(prefix="asp-bench-stats-")
    root = Path(scratch.name)
    worktrees: list[Path] = []
    results: dict[str, dict] = {}
    try:
        rows = root / "input" / Path(args.input).name
        rows.parent.mkdir()
        shutil.copy2(args.input, rows)
        sources: list[tuple[str, Path, str]] = []
        for rev in args.rev:
            path, commit = add_worktree(rev, root)
            worktrees.append(path)
            sources.append((rev, path, commit))
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
        sources.append((CURRENT, REPO, git("rev-parse", "HEAD") + (" + uncommitted changes" if dirty else "")))
        for label, path, commit in sources:
            print(f"{label}: {commit}, asp_dist from {check_imports(path)}")
        print(f"input: {args.input} (copied to {rows}); figures {'off' if args.no_figures else 'on'}; "
              f"bootstrap {', '.join(map(str, boots))}; {args.repeats} runs each")
        load_before = os.getloadavg()
        for label, path, commit in sources:
            for n_boot in boots:
                key = f"{label} @ {n_boot}"
                slug = label.replace("^", "p").replace("/", "_")
                times, analysed, in_all = time_stats(path, rows, root / "out", slug, n_boot, args.repeats,
                                                     not args.no_figures)
                results[key] = {"rev": label, "commit": commit, "bootstrap": n_boot,
                                "median_s": statistics.median(times), "min_s": min(times), "max_s": max(times),
                                "runs": times, "analysed_s": analysed, "job_s": in_all,
                                "analysed_median_s": _median(analysed), "job_median_s": _median(in_all)}
                print(f"  {key}: median {results[key]['median_s']:.2f} s ({', '.join(f'{t:.2f}' for t in times)}); "
                      f"read + tables {_fmt(results[key]['analysed_median_s'])} s, "
                      f"job {_fmt(results[key]['job_median_s'])} s", flush=True)
        load_after = os.getloadavg()
    finally:
        for path in worktrees:
            remove_worktree(path)
        scratch.cleanup()

    print(f"\n{'revision @ bootstrap':<34}{'median s':>10}{'min s':>9}{'max s':>9}{'tables s':>10}{'job s':>8}   "
          f"({args.repeats} runs each, fresh processes)")
    for key, r in results.items():
        print(f"{key:<34}{r['median_s']:>10.2f}{r['min_s']:>9.2f}{r['max_s']:>9.2f}"
              f"{_fmt(r['analysed_median_s']):>10}{_fmt(r['job_median_s']):>8}")
    ratios = {}
    if args.rev:
        before = args.rev[0]
        for n_boot in boots:
            ratios[f"{CURRENT} @ {n_boot} / {before} @ {n_boot}"] = (
                results[f"{CURRENT} @ {n_boot}"]["median_s"] / results[f"{before} @ {n_boot}"]["median_s"])
        top = max(boots)
        for n_boot in boots:
            if n_boot != top:
                ratios[f"{CURRENT} @ {top} / {before} @ {n_boot}"] = (
                    results[f"{CURRENT} @ {top}"]["median_s"] / results[f"{before} @ {n_boot}"]["median_s"])
        for name, ratio in ratios.items():
            print(f"ratio {name}: {ratio:.2f}x")
    machine = cpu_model()
    print(f"machine: {machine}, {os.cpu_count()} cores; python {sys.version.split()[0]}")
    print(f"load average (1, 5, 15 min): before {load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f}, "
          f"after {load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({
            "input": args.input, "repeats": args.repeats, "bootstrap": boots, "figures": not args.no_figures,
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": machine, "cores": os.cpu_count(),
            "python": sys.version.split()[0], "load_average_before": load_before, "load_average_after": load_after,
            "results": results, "ratios": ratios}, indent=1))
        print(f"wrote {args.json}")
    return 0


def _median(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return statistics.median(known) if known else None


def _fmt(value: float | None) -> str:
    return "?" if value is None else f"{value:.1f}"


if __name__ == "__main__":
    raise SystemExit(main())
