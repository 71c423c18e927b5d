"""`asp-dist stats`: the stats job (tables, figures, report.md|html, LaTeX tables) and the checks of its flags."""

from __future__ import annotations

import argparse
import math
import os
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from asp_dist.commands.common import RESAMPLES, SEED, add_results, float_between, non_empty, non_empty_argument
from asp_dist.errors import DiskFull, SpecError, is_disk_full
from asp_dist.results import store
from asp_dist.results.location import is_remote


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
    from asp_dist.core.registry import DOMAINS

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

    if not out.strip():  # "" would be the current directory
        raise SpecError("--out is empty; name a directory or leave it out (the default: the sweep's directory)")
    path = Path(out).expanduser()
    inside = sweep_containing(path)
    if inside is not None:
        raise SpecError(f"--out {out} lies inside the sweep {inside}; write the stats to the sweep directory "
                        f"itself (the default) or outside it")
    if path.exists() and not path.is_dir():
        raise SpecError(f"cannot create the output directory {out}: a file of that name exists")
    return path


def stats_output_dir(inputs: Sequence[Path], out: str | None) -> tuple[Path, Path | None]:
    """--out, or the one sweep (or directory) given; the stats job never guesses among several inputs.
    A sweep's own directory may hold its stats (the default); a folder inside its tree may not.
    Returns it and the first directory of it that this run created (None: it existed), to remove on failure."""
    if out is not None:
        path = check_stats_out(out)
    elif len(inputs) == 1 and inputs[0].is_dir():
        path = inputs[0]
    else:
        raise SpecError("several inputs or single files: say where to write the stats with --out DIR")
    created = next((p for p in reversed([path, *path.parents]) if not p.exists()), None)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SpecError(f"cannot create the output directory {path} ({e.strerror or e})") from None
    if not os.access(path, os.W_OK):
        _remove_created(created, path)
        raise SpecError(f"output directory {path} is not writable; choose another with --out")
    return path, created


def _remove_created(created: Path | None, path: Path) -> None:
    """The empty directories this run made for --out, from `path` up to `created`."""
    if created is None:
        return
    for directory in [path, *path.parents]:
        try:
            directory.rmdir()
        except OSError:
            return
        if directory == created:
            return


def run_stats_job(sweeps: Sequence[str | Path], out: str | None = None, cfg=None, figures: bool = True,
                  results: str | Path = store.DEFAULT_RESULTS, command: str = "", log=print,
                  formats: Sequence[str] = REPORT_FORMATS) -> Path:
    """The whole stats job: read rows, compute tables, write stats/, figures/ and the report in `formats`
    (report.md, report.html, stats/*.tex). Returns report.md (else report.html, else stats/).
    For a single sweep on S3 (and no --out) they go beside it in the bucket."""
    from asp_dist.fsutil import staged_directory
    from asp_dist.results.query import find_inputs

    find_inputs(sweeps, results)  # a missing or empty input is the first thing to report
    located = [store.locate_sweep(s, results) for s in sweeps]
    scratch = upload_to = created = None
    if out is None and len(located) == 1 and is_remote(located[0]):
        # A sweep on S3 keeps its stats beside it in the bucket: written to scratch, then uploaded.
        import tempfile

        scratch = tempfile.TemporaryDirectory(prefix="asp-stats-")
        upload_to, out_dir = located[0], Path(scratch.name)
    else:
        out_dir, created = stats_output_dir(located, out)
    start = time.perf_counter()
    try:
        # Every file of this run is written to a stage and moved into out_dir only once all are written: a run
        # that fails midway (a full disk, an error, Ctrl-C) leaves out_dir exactly as it was.
        with staged_directory(out_dir) as stage:
            reports = _stats_job(located, stage, out_dir, cfg, figures, command, log, formats)
        return _finish(reports, out_dir, upload_to, log, formats, start)
    except BaseException as e:
        _remove_created(created, out_dir)
        if isinstance(e, OSError) and is_disk_full(e):
            raise DiskFull(f"no space left writing the stats to {out_dir}: nothing of this run was kept; free some "
                           f"space or choose another --out") from None
        raise
    finally:
        if scratch is not None:
            scratch.cleanup()


def _finish(reports: list[Path], out_dir: Path, upload_to, log, formats: Sequence[str], start: float) -> Path:
    """The reports in out_dir (uploaded beside an S3 sweep); report.md, else report.html, else stats/."""
    from asp_dist.results.s3 import upload_tree

    report = reports[0] if reports else out_dir / "stats"
    if upload_to is not None:
        written = upload_tree(out_dir, upload_to)
        log(f"uploaded {len(written)} files (stats/, figures/, {', '.join(p.name for p in reports) or 'no report'}) "
            f"to {upload_to}")
        report = upload_to / report.relative_to(out_dir).as_posix()
        reports = [upload_to / p.relative_to(out_dir).as_posix() for p in reports]
    log(f"report: {', '.join(str(p) for p in reports) or 'none (--formats ' + ','.join(formats) + ')'} "
        f"({time.perf_counter() - start:.1f} s in all)")
    return report


def _stats_job(located, stage: Path, out_dir: Path, cfg, figures: bool, command: str, log,
               formats: Sequence[str] = REPORT_FORMATS) -> list[Path]:
    """Every file of the job written under `stage` (the messages name out_dir, where they will be); the
    reports written, as paths in out_dir."""
    from asp_dist.analysis import plot_all, run_stats, write_tables
    from asp_dist.analysis.document import render_markdown, write_atomic
    from asp_dist.analysis.html_report import write_html
    from asp_dist.analysis.latex_tables import write_latex_tables
    from asp_dist.analysis.report import build_report
    from asp_dist.analysis.rliable_plots import plot_rliable
    from asp_dist.analysis.sequential_report import plot_decisions, read_decisions
    from asp_dist.analysis.tuning import plot_expected_best, plot_tuning, read_configurations

    start = time.perf_counter()
    result = run_stats(located, cfg)
    log(f"read and analysed {len(result.rows)} rows from {len(result.inputs.files)} files "
        f"({', '.join(sorted(result.layouts))}) in {time.perf_counter() - start:.1f} s")
    written = write_tables(result, stage)
    log(f"wrote {len(written)} tables to {out_dir / 'stats'}")
    latex = write_latex_tables(result, stage) if "latex" in formats else {}
    if latex:
        log(f"wrote {len(latex)} LaTeX tables ({', '.join(p.name for p in latex.values())}) to {out_dir / 'stats'}")
    figs, notes = plot_all(result, stage / "figures") if figures else ([], [])
    if figures:
        figs += plot_rliable(result, stage / "figures")
        configs = read_configurations(result)
        figs += plot_tuning(configs, stage / "figures")  # a tune run's search, per method
        figs += plot_expected_best(configs, stage / "figures")  # and its expected best against the budget
        figs += plot_decisions(read_decisions(result), stage / "figures")  # a decided sweep's looks
        log(f"wrote {len(figs)} figures (PNG + SVG) to {out_dir / 'figures'}")
    doc = build_report(result, stage, figs, notes, sources=[str(p) for p in located], command=command,
                       latex_tables=list(latex))
    reports = []
    if "md" in formats:
        reports.append(write_atomic(stage / "report.md", render_markdown(doc)))
    if "html" in formats:
        reports.append(write_html(doc))
    for note in result.tune_notes + result.notes + notes:
        log(f"note: {note}")
    return [out_dir / p.relative_to(stage) for p in reports]


def cmd_stats(args: argparse.Namespace) -> int:
    from asp_dist.analysis import StatsConfig

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


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stats", help="statistics, figures and report (md, html, LaTeX tables) of one or more sweeps",
                       description="Turn a sweep's rows into tables (stats/), figures (figures/), report.md and "
                                   "report.html, and LaTeX tables (stats/*.tex).")
    p.add_argument("sweeps", nargs="+", metavar="SWEEP", type=non_empty_argument,
                   help="sweep name (under --results) or directory, any directory or .parquet files; several merge")
    add_results(p)
    p.add_argument("--out", type=non_empty,
                   help="directory for stats/, figures/ and the report (default: the single sweep directory)")
    p.add_argument("--metric", default="eval_mixed", help="metric column to analyse (default: eval_mixed)")
    p.add_argument("--paired-range", action="append", default=[], metavar="DOMAIN=LO-HI",
                   help="paired counts of the Friedman test (defaults: the paper's per domain, others all)")
    p.add_argument("--threshold", action="append", default=[], metavar="DOMAIN=VALUE",
                   help="data-efficiency threshold of the metric (defaults: the paper's, else 90%% of base)")
    p.add_argument("--alpha", type=float_between(0, 1), default=0.05, help="significance level (default 0.05)")
    p.add_argument("--bootstrap", type=RESAMPLES, default=2000, help="bootstrap resamples (default 2000)")
    p.add_argument("--seed", type=SEED, default=0, help="bootstrap seed (default 0)")
    p.add_argument("--formats", default=",".join(REPORT_FORMATS), metavar="LIST",
                   help="report outputs, comma-separated: md (report.md), html (report.html, self-contained), "
                        "latex (stats/*.tex booktabs tables); default: md,html,latex")
    p.add_argument("--no-figures", action="store_true", help="tables and report only")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=cmd_stats)
