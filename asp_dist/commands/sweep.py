"""`asp-dist sweep` and `asp-dist resume`: their shared run options (workers, Ray, packing, trackers), the
checks made before anything is written, SIGTERM as Ctrl-C, and what a finished run prints."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

from asp_dist.commands.common import MAX_FAILURES, WORKERS, add_results, check_data, int_between, non_empty, seconds
from asp_dist.errors import SpecError
from asp_dist.results import store
from asp_dist.results.location import as_path, is_remote
from asp_dist.results.s3 import first_answer_within

RAY_SOCKET_SUFFIX = 64  # len('/session_YYYY-MM-DD_HH-MM-SS_uuuuuu_<pid:7>/sockets/plasma_store')
DASHBOARD_MODULES = ("aiohttp", "aiohttp_cors", "grpc", "opencensus", "opentelemetry", "prometheus_client", "pydantic")


def check_run_flags(args: argparse.Namespace) -> None:
    """The flags of sweep and resume that need no grid, refused before anything is read or written."""
    from asp_dist.sweep.packing import check_packing
    from asp_dist.sweep.preflight import check_run_options, parse_address

    check_run_options(args.workers, args.max_failures, args.checkpoint_every, args.connect_timeout)
    check_packing(args.pack, args.pack_size)
    if args.address is not None and not args.address.strip():
        raise SpecError("--address is empty; give HOST:PORT of a Ray cluster or leave it out")
    if args.address is not None:
        parse_address(args.address)
        if args.dashboard:
            raise SpecError("--dashboard starts the embedded Ray's dashboard; a cluster's own is set by "
                            "`ray start` (leave out --address or --dashboard)")
    if args.dashboard:
        import importlib.util

        missing = [m for m in DASHBOARD_MODULES if importlib.util.find_spec(m) is None]
        if missing:
            raise SpecError(f"--dashboard needs Ray's dashboard packages ({', '.join(missing)} missing): "
                            f"pip install 'ray[default]', or leave out --dashboard")
    check_ray_temp_dir(args.ray_temp_dir)


def check_ray_temp_dir(ray_temp_dir: str | None) -> None:
    """--ray-temp-dir: a directory (or none yet) whose socket paths fit Ray's limit; refused in one line."""
    if ray_temp_dir is not None:
        temp = Path(ray_temp_dir).expanduser()
        if not str(ray_temp_dir).strip():
            raise SpecError("--ray-temp-dir is empty; name a directory or leave it out")
        if temp.exists() and not temp.is_dir():
            raise SpecError(f"--ray-temp-dir {temp} exists and is not a directory")
        # Ray puts Unix sockets at <dir>/session_<date>_<time>_<usec>_<pid>/sockets/plasma_store (64 more
        # characters at most), and a socket path may have 107 bytes: say so now, not in a traceback later.
        longest = len(os.fsencode(os.path.abspath(temp))) + RAY_SOCKET_SUFFIX
        if longest > 107:
            raise SpecError(f"--ray-temp-dir {temp} is too long for Ray's socket paths ({longest} > 107 bytes); "
                            f"use a directory of at most {107 - RAY_SOCKET_SUFFIX} characters, e.g. /tmp/asp-ray")


def _run_options(args: argparse.Namespace, tracking=None):
    from asp_dist.sweep.plan import RunOptions
    from asp_dist.tracking.base import TrackingSettings

    return RunOptions(results=args.results, workers=args.workers, address=args.address,
                      max_failures=args.max_failures, checkpoint_every_s=args.checkpoint_every,
                      ray_temp_dir=args.ray_temp_dir, dashboard=args.dashboard,
                      connect_timeout_s=args.connect_timeout, pack=args.pack, pack_size=args.pack_size,
                      tracking=tracking or TrackingSettings(), extend=getattr(args, "extend", False))


def tracking_settings(args: argparse.Namespace, name: str, defaults: dict | None):
    """The run's live trackers (asp_dist.tracking): the flags, else `defaults` (a space file's [logging], or on
    resume the sweep's last run's), resolved and checked -- one `asp-dist: error:` line before anything runs."""
    from asp_dist import tracking

    defaults = defaults or {}
    if args.logger is not None:
        loggers = tuple(k for given in args.logger for k in given.split(",") if k and k != "none")
    else:
        loggers = tuple(defaults.get("loggers", ()))
    settings = tracking.TrackingSettings(
        loggers, args.logger_dir or defaults.get("dir"), args.mlflow_uri or defaults.get("mlflow_uri"),
        args.wandb_project or defaults.get("wandb_project"), timeout_s=args.connect_timeout)
    if not loggers:
        return settings
    # File-based trackers write next to the sweep; a sweep on S3 has no local directory: ./asp-dist-trackers/NAME.
    default_dir = (Path("asp-dist-trackers") / name if is_remote(args.results)
                   else Path(args.results) / name / "trackers")
    settings = settings.resolved(default_dir)
    tracking.check(settings)
    return settings


def _interruptible(args: argparse.Namespace, name_of, run, again: str | None = None) -> int:
    """Run a sweep command with SIGTERM behaving as Ctrl-C from its first line on (signals.sigterm_as_interrupt):
    the sweep stops, its lock and Ray are released, finished cells stay. Exit 128 + the signal. `again`: the
    command that continues it (default: asp-dist resume NAME)."""
    import signal

    from asp_dist.sweep import signals

    # --connect-timeout also bounds the S3 endpoint's first answer (the other commands: ASP_DIST_S3_TIMEOUT).
    with signals.sigterm_as_interrupt(), first_answer_within(args.connect_timeout):
        try:
            return run()
        except (KeyboardInterrupt, SystemExit) as e:
            # ray.init answers SIGTERM with sys.exit(SIGTERM) while it starts, before its handler is replaced.
            if isinstance(e, SystemExit) and e.code != signal.SIGTERM:
                raise
            signum = signal.SIGTERM if isinstance(e, SystemExit) else (signals.interrupted_by or signal.SIGINT)
            name = name_of()
            hint = ""
            try:
                if name is not None and store.read_manifest(as_path(args.results) / name) is not None:
                    hint = f"; finished cells are kept: {again or f'asp-dist resume {name} --results {args.results}'}"
            except (OSError, SpecError):
                pass
            print(f"asp-dist: interrupted ({signal.Signals(signum).name}){hint}", file=sys.stderr)
            return 128 + signum


def _finish(result) -> int:
    """What a sweep left, and the commands that read it; exit 1 unless every cell finished."""
    cells = store.cells_dir(result.sweep_dir)
    print(f"{result.done}/{result.total} cells done, {result.failed} failed; rows in {cells}")
    print(f"  stats, figures and report: asp-dist stats {result.sweep_dir}")
    print(f"  query: asp-dist query {result.sweep_dir} --where \"method = 'asp'\" --columns paired,trial,eval_mixed")
    print(f"  read: python -c \"from asp_dist.results.store import read_rows; print(read_rows('{result.sweep_dir}'))\"")
    if not is_remote(result.sweep_dir):  # DuckDB would need its own S3 settings (httpfs) for a bucket
        print(f"   or: duckdb -c \"select method, paired, median(eval_mixed) from read_parquet('{cells}/**/*.parquet') "
              f"group by all order by all\"")
    if result.failed:
        print(f"  failed cells: asp-dist status {result.name} --results {result.sweep_dir.parent}", file=sys.stderr)
    return 0 if result.failed == 0 and result.done == result.total else 1


def cmd_sweep(args: argparse.Namespace) -> int:
    name: list[str] = []

    def run() -> int:
        from asp_dist.sweep.plan import Plan
        from asp_dist.sweep.preflight import check_address, check_can_start

        # Everything a user can get wrong is refused before paying for the Ray import, and nothing is written
        # until then: flags, space, name, results dir, an existing sweep's grid and lock, the data, a cluster
        # that does not answer.
        check_run_flags(args)
        plan = Plan.from_space(args.space, args.name)  # read and resolved once: the run takes this plan
        name.append(plan.name)
        manifest = check_can_start(args.results, plan.name, plan.specs, plan.space, args.pack, args.pack_size,
                                   args.extend)
        plan = dataclasses.replace(plan, manifest=manifest)  # what the run checks before its lock, not read again
        check_data(plan.specs)
        tracking = tracking_settings(args, plan.name, plan.logging)
        if args.address is not None:
            check_address(args.address, args.connect_timeout)
        from asp_dist.sweep.tune import run_plan

        return _finish(run_plan(plan, _run_options(args, tracking)))

    return _interruptible(args, lambda: name[0] if name else None, run)


def cmd_resume(args: argparse.Namespace) -> int:
    def run() -> int:
        from asp_dist.sweep.plan import Plan
        from asp_dist.sweep.preflight import check_address, check_can_resume

        check_run_flags(args)
        # an unknown or broken sweep too, and a packing other than its own, before the Ray import
        plan = Plan.from_manifest(args.name, check_can_resume(args.results, args.name, args.pack, args.pack_size))
        finished = nothing_to_resume(args.results, plan)
        if finished:
            print(finished, file=sys.stderr)
            return 0
        check_data(plan.specs)
        from asp_dist.sweep.provenance import last_tracking

        tracking = tracking_settings(args, plan.name, last_tracking(as_path(args.results) / args.name))
        if args.address is not None:
            check_address(args.address, args.connect_timeout)
        from asp_dist.sweep.tune import run_plan

        return _finish(run_plan(plan, _run_options(args, tracking)))

    return _interruptible(args, lambda: args.name, run)


def nothing_to_resume(results: str, plan) -> str | None:
    """The line that says so when every cell of the sweep has its row: resuming it would train nothing, so
    it starts no Ray, takes no lock and records nothing (no env/<n>/, locally or on S3). None otherwise
    (a failed or pending cell: the run retries it)."""
    from asp_dist.sweep.ledger import finished_and_failed, sweep_dir_for

    done, _ = finished_and_failed(sweep_dir_for(results, plan.name), [s.cell_id for s in plan.specs])
    if len(done) < len(plan.specs):
        return None
    return (f"sweep {plan.name}: all {len(plan.specs)} cells are done; nothing to resume "
            f"(asp-dist stats {plan.name} --results {results})")


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", type=WORKERS, default=2, help="concurrent cells, 1 CPU each (default 2)")
    p.add_argument("--address", default=None,
                   help="join an existing Ray cluster (e.g. 127.0.0.1:6379) instead of starting an embedded one")
    add_results(p)
    p.add_argument("--max-failures", type=MAX_FAILURES, default=2,
                   help="retries of a cell whose worker dies (default 2)")
    p.add_argument("--checkpoint-every", type=seconds(), default=30.0, metavar="SECONDS",
                   help="checkpoint interval of a running cell: at most this much work is lost on a crash")
    p.add_argument("--ray-temp-dir", type=non_empty, default=None,
                   help="temp dir of the embedded Ray (default /tmp/asp-ray-$USER)")
    p.add_argument("--connect-timeout", type=seconds(), default=20.0, metavar="SECONDS",
                   help="give up (exit 2, nothing written) if the cluster of --address, the S3 endpoint of "
                        "--results or a tracker's server (--logger mlflow, wandb online) does not answer within this "
                        "time; also bounds the wait for a silent S3 lease and each tracker call (default 20)")
    p.add_argument("--dashboard", action="store_true",
                   help="start the embedded Ray's dashboard, on 127.0.0.1 only (default: none)")
    p.add_argument("--pack", default=None, metavar="cell|trial|method",
                   help="train cells that share tensor shapes as one batched model per Tune trial: 'trial' packs "
                        "the cells of one trial, 'method' those of one method across trials; 'cell' (the default "
                        "of a new sweep) runs one cell per trial. Fixed when a sweep starts; resume keeps it")
    p.add_argument("--pack-size", type=int_between(1), default=None, metavar="N",
                   help="at most N cells per pack (default 21); larger groups split deterministically")
    p.add_argument("--logger", action="append", type=non_empty, default=None, metavar="tensorboard|mlflow|wandb|json",
                   help="watch every cell live in this tracker, one tracker run per cell (repeatable; default: the "
                        "space file's [logging], on resume the last run's; 'none': no tracker). See docs/tracking.md")
    p.add_argument("--logger-dir", type=non_empty, default=None, metavar="DIR",
                   help="where tensorboard, json, wandb and the default MLflow store write "
                        "(default RESULTS/NAME/trackers)")
    p.add_argument("--mlflow-uri", type=non_empty, default=None, metavar="URI",
                   help="MLflow tracking URI (default MLFLOW_TRACKING_URI, else sqlite:///DIR/mlflow.db)")
    p.add_argument("--wandb-project", type=non_empty, default=None, metavar="NAME",
                   help="W&B project (default WANDB_PROJECT, else asp-dist); offline unless W&B credentials or "
                        "WANDB_MODE say otherwise")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sweep", help="run a named grid of cells on Ray Tune",
                       description="Run (or continue) a sweep over a space from tune_spaces/ or a .toml path.")
    p.add_argument("space", help="space name (smoke, paper, paper-vae, ...) or path to a .toml file")
    p.add_argument("--name", default=None, help="sweep name (default: the space's name)")
    p.add_argument("--extend", action="store_true",
                   help="grow sweep NAME to this grid when it holds every stored cell: finished rows, failures and "
                        "bases are kept, only the new cells train (the grid's history goes to manifest.json)")
    _add_run_options(p)
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("resume", help="continue an interrupted sweep",
                       description="Continue sweep NAME from its manifest; failed cells are retried.")
    p.add_argument("name")
    _add_run_options(p)
    p.set_defaults(func=cmd_resume)
