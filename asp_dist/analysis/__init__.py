"""The analysis stage: a sweep's rows -> tables, figures and report.md (and the paper's policy-space theory).

The names below are all the CLI needs. They load on first use, so `asp_dist.analysis.theory`
stays as light as it is (no pandas, scipy or matplotlib).

Modules: rank_tests (statistics on arrays), paper (PaperFacts per domain), layout (conditions,
treatments, score), tables (StatsConfig and the tables), rliable_view (IQM, probability of
improvement, performance profiles), completeness (missing cells), job (compute, run_stats,
write_tables), markdown, plots, rliable_plots, report (what the report says, as a
document.Document), html_report (report.html), latex_tables (stats/*.tex), compare (are two runs
of a grid equivalent?), theory.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

_HOMES = {
    "StatsConfig": "tables",
    "run_stats": "job",
    "write_tables": "job",
    "plot_all": "plots",
    "write_report": "report",
    "paper_paired_ranges": "paper",
    "paper_thresholds": "paper",
}
__all__ = ["StatsConfig", "paper_paired_ranges", "paper_thresholds", "plot_all", "run_stats", "write_report",
           "write_tables"]

if TYPE_CHECKING:
    from asp_dist.analysis.job import run_stats, write_tables
    from asp_dist.analysis.paper import paper_paired_ranges, paper_thresholds
    from asp_dist.analysis.plots import plot_all
    from asp_dist.analysis.report import write_report
    from asp_dist.analysis.tables import StatsConfig


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{_HOMES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
