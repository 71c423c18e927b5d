"""The reproduction study's pre-registered selection and power rules (docs/reproduction.md).

A calibration sweep holds several *settings* of a domain: each is a combination of knob values.
An ASP setting is judged against the PC and OSP cells of the same *protocol*: the knobs that also
change PC and OSP (a replay buffer, the VAE's KL weight or budget …), but not the ones only an
adversary has (ASP_ONLY). Blocks are (trial, paired) over the paper's paired range.

    score    ASP's mean Friedman rank among (PC, OSP, ASP) over the blocks, 1 = best
    winner   the best score; within TIE of it, the setting that changes fewest knobs from the
             domain's defaults
    power    resample the winner's trials with replacement to n; the rate at which the Friedman
             test rejects at α and ASP has the best mean rank; the smallest n with rate ≥ 0.8
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from asp_dist.analysis.layout import NOT_KNOBS
from asp_dist.analysis.paper import paper_paired_ranges
from asp_dist.analysis.power import resampled
from asp_dist.analysis.rank_tests import friedman_each, mean_ranks, mean_ranks_each
from asp_dist.core.registry import DOMAINS, get_domain
from asp_dist.spec import CellSpec

METHODS = ("pc", "osp", "asp")
# Knobs that only shape the adversary: PC and OSP cells record them at 0 / their default, so a
# protocol ignores them when it looks for an ASP setting's PC and OSP cells. A domain's own are the fields
# that shape its unpaired data (Domain.unpaired_fields: the VAE's adversary input).
ASP_ONLY = frozenset({"lambda_unpaired", "adversary_loss", "lambda_unpaired_schedule", "lambda_schedule_frac",
                      "disc_steps", "disc_lr", "disc_hidden", "disc_layers", "unpaired_size", "unpaired_batch",
                      *(f for name in DOMAINS for f in DOMAINS[name].unpaired_fields)})
TIE = 0.05
POWER_SIZES = (10, 15, 20, 30, 40, 60, 80, 100)
# Columns a row carries that are not knobs of what was trained.
_NOT_SETTING = NOT_KNOBS | {"eval_episodes", "base_max_attempts"}


@dataclass
class Setting:
    knobs: dict  # the knob values that vary in the sweep, for this setting
    protocol: dict  # the subset that PC and OSP share with it
    blocks: pd.DataFrame  # (trial, paired) x (pc, osp, asp), oriented so that larger is better
    changed: int  # knobs differing from the domain's defaults
    score: float = float("nan")
    median_gain: float = float("nan")
    extra: dict = field(default_factory=dict)


def varying_knobs(rows: pd.DataFrame) -> list[str]:
    from asp_dist.spec import FIELD_NAMES

    knobs = [c for c in FIELD_NAMES if c in rows.columns and c not in _NOT_SETTING]
    return [c for c in knobs if rows[c].astype(str).nunique() > 1]


def _defaults(domain: str) -> dict:
    """The defaults the pre-registered protocol counts changed knobs from: today's, overlaid with the values
    a domain had when the protocol was registered, where they changed since (Domain.protocol_defaults), so
    that `asp-dist select` on the calibration rows gives what it gave."""
    return CellSpec(domain=domain, **get_domain(domain).protocol_defaults).resolved().to_dict()


def settings(rows: pd.DataFrame, domain: str, metric: str = "eval_mixed") -> list[Setting]:
    """Every ASP setting of `domain` in `rows`, with its blocks over the paper's paired range."""
    rows = rows[rows["domain"] == domain]
    lo, hi = paper_paired_ranges().get(domain, (rows["paired"].min(), rows["paired"].max()))
    rows = rows[(rows["paired"] >= lo) & (rows["paired"] <= hi)]
    sign = 1.0 if get_domain(domain).metrics[metric.removeprefix("eval_")].higher_is_better else -1.0
    knobs = varying_knobs(rows)
    protocol_knobs = [k for k in knobs if k not in ASP_ONLY]
    defaults = _defaults(domain)
    out = []
    asp = rows[rows["method"] == "asp"]
    for values, group in asp.groupby(knobs, dropna=False, sort=True) if knobs else [((), asp)]:
        values = values if isinstance(values, tuple) else (values,)
        setting = dict(zip(knobs, values))
        protocol = {k: setting[k] for k in protocol_knobs}
        mask = np.ones(len(rows), dtype=bool)
        for k, v in protocol.items():
            mask &= (rows[k].astype(str) == str(v)).to_numpy()
        others = rows[mask & rows["method"].isin(["pc", "osp"]).to_numpy()]
        wide = pd.concat([others, group]).pivot_table(index=["trial", "paired"], columns="method", values=metric)
        wide = wide.reindex(columns=list(METHODS)).dropna() * sign
        changed = sum(str(v) != str(defaults.get(k)) for k, v in setting.items())
        s = Setting(setting, protocol, wide, changed)
        if len(wide):
            s.score = float(mean_ranks(wide.to_numpy())[2])
            s.median_gain = float((wide["asp"] - wide["osp"]).median())
        out.append(s)
    return out


def select(candidates: list[Setting]) -> Setting:
    """The pre-registered rule: best (lowest) mean rank of ASP; within TIE, fewest changed knobs."""
    scored = [s for s in candidates if s.score == s.score]
    if not scored:
        raise ValueError("no setting has complete (PC, OSP, ASP) blocks")
    best = min(s.score for s in scored)
    near = [s for s in scored if s.score <= best + TIE]
    return min(near, key=lambda s: (s.changed, s.score))


def power(blocks: pd.DataFrame, sizes=POWER_SIZES, alpha: float = 0.05, resamples: int = 5000,
          seed: int = 0) -> dict[int, float]:
    """Rejection rate of the Friedman test with ASP best, resampling whole trials to n (all resamples of one n
    tested at once: asp_dist.analysis.power.resampled)."""
    rng = np.random.default_rng(seed)
    trials = sorted(blocks.index.get_level_values("trial").unique())
    per_trial = [blocks.xs(t, level="trial").to_numpy() for t in trials]
    out = {}
    for n in sizes:
        picks = [rng.integers(len(per_trial), size=n) for _ in range(resamples)]
        hits = 0
        for scores in resampled(per_trial, picks):
            ranks = mean_ranks_each(scores)
            hits += int(((friedman_each(scores) < alpha) & (ranks[:, 2] < ranks[:, :2].min(axis=1))).sum())
        out[n] = hits / resamples
    return out


def needed_trials(rates: dict[int, float], target: float = 0.8) -> int | None:
    """The smallest n whose rate reaches `target`, or None when none does."""
    return next((n for n in sorted(rates) if rates[n] >= target), None)


def report(rows: pd.DataFrame, domain: str, resamples: int = 5000) -> str:
    """The selection table, the winner and its power, as Markdown."""
    cands = settings(rows, domain)
    lines = [f"### {domain}: ASP settings (mean rank of ASP among PC, OSP, ASP over the paper's range; 1 = best)",
             "", "| setting | blocks | ASP mean rank | median ASP − OSP (oriented) | knobs changed |", "|---|---:|---:|---:|---:|"]
    for s in sorted(cands, key=lambda s: (s.score != s.score, s.score)):
        name = ", ".join(f"{k}={v}" for k, v in s.knobs.items()) or "(defaults)"
        lines.append(f"| {name} | {len(s.blocks)} | {s.score:.3f} | {s.median_gain:.4g} | {s.changed} |")
    win = select(cands)
    rates = power(win.blocks, resamples=resamples)
    n = needed_trials(rates)
    lines += ["", f"Selected: {', '.join(f'{k}={v}' for k, v in win.knobs.items()) or '(defaults)'}", "",
              "Power (Friedman p < 0.05 with ASP best) by trials: "
              + ", ".join(f"{k}: {v:.2f}" for k, v in rates.items()),
              f"Trials needed for 0.8: {n if n is not None else 'not reached by 100'}"]
    return "\n".join(lines)
