"""How fast the commands that only describe or read answer: `asp-dist --help`, `fields` and `status` on a
sweep of the paper's size, each run in a fresh interpreter (what a user waits for), median of N runs.

    python bench/bench_cli.py --repeats 5 [--query] [--json out.json] [--dir DIR]

What it builds (once, in a temporary directory unless --dir names one to keep and reuse): a results root
holding sweep `paper`, the manifest of the paper grid (asp_dist.sweep.spaces.expand("paper"), 1,470 cells)
and one cell file per row of results/examples/paper-packed-2.parquet (the 1,470 rows of that grid, written
with store.write_row: the layout `status` reads). `--rows N` writes only the first N rows (the rest pending).

It also times `status replicate-particles` on the committed 1,800-cell replication
(results/examples/replicate-particles: 1,782 rows, 18 failed cells; no verdict index there, so every footer
is parsed, what a user meets on a copied sweep), with and without `--failed`.

Rows of the table: `python -c pass` (the interpreter's own start, the floor), `--help`, `fields`,
`fields --domain vae`, `status paper` twice: with no verdict index (every cell file's footer is parsed: a
sweep whose files some other process wrote) and after the index a sweep's driver keeps (cells/.verified.json,
written when a sweep starts and ends: what a user meets after `sweep` or `resume`), and with --query `query paper --sql "SELECT count(*) FROM cells"`
(pandas and DuckDB: slower). Targets on an idle machine: --help <= 0.5 s, status <= 1 s. None of these
commands imports torch or Ray (tests/test_cli_imports.py); the numbers say what that buys.
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

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "results" / "examples" / "paper-packed-2.parquet"
REPLICATION = REPO / "results" / "examples" / "replicate-particles"  # a finished sweep directory, read only
SWEEP = "paper"


def build_sweep(root: Path, rows: int | None) -> dict[str, int]:
    """The paper grid's manifest and (up to `rows`) cell files under root/paper; kept if already complete."""
    import pyarrow.parquet as pq

    from asp_dist.results import store
    from asp_dist.sweep import ledger
    from asp_dist.sweep.spaces import expand

    sweep_dir = root / SWEEP
    specs = expand("paper")
    if store.read_manifest(sweep_dir) is None:
        store.write_manifest(sweep_dir, ledger.new_manifest(SWEEP, "paper", specs))
    table = pq.read_table(EXAMPLE)
    written = 0
    for row in table.to_pylist()[:rows]:
        written += store.write_row(sweep_dir, row, sweep_id=row["sweep_id"] or SWEEP)  # False: already there
    return {"cells": len(specs), "rows": len(table) if rows is None else min(rows, len(table)), "written": written}


def store_index(root: Path) -> Path:
    from asp_dist.results import store

    return store.cells_dir(root / SWEEP) / store.VERDICTS_FILE


def remember_verdicts(root: Path) -> None:
    """What the sweep's driver does when it starts and ends: count the cells and keep the verdicts."""
    from asp_dist.results import store

    store.done_cell_ids(root / SWEEP, remember=True)


def time_command(argv: list[str], repeats: int) -> list[float]:
    """Wall seconds of `python -m asp_dist ARGV` (or of `python ARGV` for the floor), each in a fresh process."""
    cmd = [sys.executable, *argv] if argv[:1] == ["-c"] else [sys.executable, "-m", "asp_dist", *argv]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
        times.append(time.perf_counter() - t0)
        if out.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} exited {out.returncode}:\n{out.stderr[-2000:]}")
    return times


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="runs per command (default 5)")
    ap.add_argument("--rows", type=int, default=None, help="cell files to write (default: all 1,470)")
    ap.add_argument("--dir", default=None, help="results root to build in and keep (default: a temporary one)")
    ap.add_argument("--query", action="store_true", help="also time `query ... --sql 'SELECT count(*) FROM cells'`")
    ap.add_argument("--json", default=None, metavar="FILE", help="write the results here")
    args = ap.parse_args(argv)

    scratch = tempfile.TemporaryDirectory(prefix="asp-bench-cli-") if args.dir is None else None
    root = Path(args.dir or scratch.name).resolve()
    try:
        t0 = time.perf_counter()
        built = build_sweep(root, args.rows)
        print(f"sweep {root / SWEEP}: {built['cells']} cells in the manifest, {built['rows']} rows "
              f"({built['written']} written now, {time.perf_counter() - t0:.1f} s)")
        commands = {
            "python -c pass": ["-c", "pass"],
            "--help": ["--help"],
            "fields": ["fields"],
            "fields --domain vae": ["fields", "--domain", "vae"],
            f"status {SWEEP} (no index)": ["status", SWEEP, "--results", str(root)],
            f"status {SWEEP}": ["status", SWEEP, "--results", str(root)],
        }
        if REPLICATION.is_dir():
            commands["status replicate-particles (1,800 cells)"] = ["status", REPLICATION.name, "--results",
                                                                    str(REPLICATION.parent)]
            commands["status replicate-particles --failed"] = ["status", REPLICATION.name, "--results",
                                                               str(REPLICATION.parent), "--failed"]
        if args.query:
            commands[f"query {SWEEP} --sql count(*)"] = ["query", SWEEP, "--results", str(root),
                                                         "--sql", "SELECT count(*) FROM cells"]
        load_before = os.getloadavg()
        results = {}
        index = store_index(root)
        for name, command in commands.items():
            if name.endswith("(no index)"):
                index.unlink(missing_ok=True)
            elif name.startswith(f"status {SWEEP}"):
                remember_verdicts(root)
            times = time_command(command, args.repeats)
            results[name] = {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times),
                             "runs": times}
        load_after = os.getloadavg()
    finally:
        if scratch is not None:
            scratch.cleanup()

    print(f"\n{'command':<44}{'median s':>10}{'min s':>9}{'max s':>9}   ({args.repeats} runs each, fresh processes)")
    for name, r in results.items():
        print(f"{name:<44}{r['median_s']:>10.3f}{r['min_s']:>9.3f}{r['max_s']:>9.3f}")
    print(f"load average (1, 5, 15 min): before {load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f}, "
          f"after {load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f}; {os.cpu_count()} cores")
    if args.json:
        Path(args.json).write_text(json.dumps({
            "sweep": {"cells": built["cells"], "rows": built["rows"]}, "repeats": args.repeats,
            "python": sys.version.split()[0], "cores": os.cpu_count(),
            "load_average_before": load_before, "load_average_after": load_after, "results": results}, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
