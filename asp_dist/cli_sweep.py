"""`asp-dist sweep | resume | status`: the sweep service's subcommands (registered by cli.py).

Ray is imported only when a sweep actually runs, so `asp-dist --help` and `status` stay fast.
"""

from __future__ import annotations

import argparse
import os
import sys

DEFAULT_RESULTS = "results"


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", type=int, default=2, help="concurrent cells, 1 CPU each (default 2)")
    p.add_argument("--address", default=None,
                   help="join an existing Ray cluster (e.g. 127.0.0.1:6379) instead of starting an embedded one")
    p.add_argument("--results", default=DEFAULT_RESULTS, help="results root; the sweep lives in RESULTS/NAME")
    p.add_argument("--max-failures", type=int, default=2, help="retries of a cell whose worker dies (default 2)")
    p.add_argument("--checkpoint-every", type=float, default=30.0, metavar="SECONDS",
                   help="checkpoint interval of a running cell: at most this much work is lost on a crash")
    p.add_argument("--ray-temp-dir", default=None, help="temp dir of the embedded Ray (default /tmp/asp-ray-$USER)")


def register(subparsers) -> None:
    p = subparsers.add_parser("sweep", help="run a named grid of cells on Ray Tune",
                              description="Run (or continue) a sweep over a space from tune_spaces/ or a .toml path.")
    p.add_argument("space", help="space name (smoke, paper, paper-vae, ...) or path to a .toml file")
    p.add_argument("--name", default=None, help="sweep name (default: the space's name)")
    _add_run_options(p)
    p.set_defaults(func=cmd_sweep)

    p = subparsers.add_parser("resume", help="continue an interrupted sweep",
                              description="Continue sweep NAME from its manifest; failed cells are retried.")
    p.add_argument("name")
    _add_run_options(p)
    p.set_defaults(func=cmd_resume)

    p = subparsers.add_parser("status", help="done / failed / pending cells of a sweep")
    p.add_argument("name")
    p.add_argument("--results", default=DEFAULT_RESULTS)
    p.set_defaults(func=cmd_status)


def _finish(result) -> int:
    cells = os.path.join(result.sweep_dir, "cells")
    print(f"{result.done}/{result.total} cells done, {result.failed} failed; rows in {cells}")
    print(f"  stats, figures and report: asp-dist stats {result.sweep_dir}")
    print(f"  query: asp-dist query {result.sweep_dir} --where \"method = 'asp'\" --columns paired,trial,eval_mixed")
    print(f"  read: python -c \"from asp_dist.results.store import read_rows; print(read_rows('{result.sweep_dir}'))\"")
    print(f"   or: duckdb -c \"select method, paired, median(eval_mixed) from read_parquet('{cells}/**/*.parquet') "
          f"group by all order by all\"")
    if result.failed:
        print(f"  failed cells: asp-dist status {result.name} --results {result.sweep_dir.parent}", file=sys.stderr)
    return 0 if result.failed == 0 and result.done == result.total else 1


def _run_kwargs(args) -> dict:
    return dict(results=args.results, workers=args.workers, address=args.address, max_failures=args.max_failures,
                checkpoint_every_s=args.checkpoint_every, ray_temp_dir=args.ray_temp_dir)


def cmd_sweep(args) -> int:
    from asp_dist.sweep.spaces import expand
    expand(args.space)  # reject a bad space before paying for the Ray import
    from asp_dist.sweep.tune import run_sweep
    return _finish(run_sweep(args.space, name=args.name, **_run_kwargs(args)))


def cmd_resume(args) -> int:
    from asp_dist.sweep.tune import resume_sweep
    return _finish(resume_sweep(args.name, **_run_kwargs(args)))


def cmd_status(args) -> int:
    from asp_dist.sweep.tune import sweep_status
    print(sweep_status(args.name, args.results))
    return 0
