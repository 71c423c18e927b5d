"""The report's section for a decided sweep (`asp-dist decide`, decide.json): the registration, every look's
statistic against its boundary, and the verdict with the trials it took; a figure of the same."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from asp_dist.analysis.document import Block, Heading, Table, Text
from asp_dist.results.location import as_path
from asp_dist.sweep.ledger import DECIDE_FILE

WORDS = {"larger": "{a} better", "smaller": "{b} better", "equal": "no difference shown", "continue": "open"}


def read_decisions(result) -> list[tuple[str, dict]]:
    """(sweep name, decide.json) of every input sweep that `asp-dist decide` grew; unreadable ones are skipped
    (decide itself refuses them)."""
    out = []
    for sweep_dir in (result.inputs.sweep_dirs if result.inputs is not None else []):
        path = as_path(sweep_dir) / DECIDE_FILE
        if not path.exists():
            continue
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            continue
        if isinstance(record, dict) and isinstance(record.get("looks"), list) and record["looks"]:
            out.append((as_path(sweep_dir).name, record))
    return out


def _word(decision: str, comparison: str) -> str:
    a, _, b = comparison.partition(" vs ")
    return WORDS.get(decision, decision).format(a=a, b=b)


def verdict_sentence(record: dict) -> str:
    last = record["looks"][-1]
    parts = [f"{c}: **{_word(d, c)}**" for c, d in last["decision"].items()]
    state = ("decided" if record.get("finished") and all(d in ("larger", "smaller") for d in last["decision"].values())
             else "ended at the most it may use" if record.get("finished") else "still running")
    return (f"{'; '.join(parts)} — {state} after {last['trials']} of {record.get('max_trials', '?')} trials "
            f"({last['first_trial']}–{last['last_trial']}).")


def looks_table(record: dict) -> pd.DataFrame:
    rows = []
    for look in record["looks"]:
        for c, d in look["decision"].items():
            stat, bound = look["statistic"].get(c), look["boundary"].get(c)
            rows.append({"stage": look["stage"], "trials": look["trials"],
                         "trial_ids": f"{look['first_trial']}–{look['last_trial']}"
                         + (f" (lost: {', '.join(map(str, look['lost_trials']))})" if look.get("lost_trials") else ""),
                         "comparison": c,
                         "statistic": stat, "abs_statistic": None if stat is None else abs(stat),
                         "boundary": bound, "decision": _word(d, c), "trained": ", ".join(look.get("trained", []))})
    return pd.DataFrame(rows)


def decide_blocks(decisions: list[tuple[str, dict]]) -> list[Block]:
    """The section, or nothing when no input was grown by `asp-dist decide`."""
    if not decisions:
        return []
    blocks: list[Block] = [Heading(2, "Sequential verdict: the registered comparison")]
    for name, record in decisions:
        reg = record.get("registration", {})
        paired = reg.get("paired")
        blocks += [
            Heading(3, name),
            Text(verdict_sentence(record)),
            Text(f"Registered before the first stage ran (decide.json, fingerprint `{record.get('fingerprint')}`): "
                 f"{', '.join(reg.get('compare', []))}; test `{reg.get('test')}` on `{reg.get('metric')}` (a trial's "
                 f"{'mean score' if reg.get('statistic') == 'mean' else 'mean within-block rank'} over "
                 f"{'every paired count' if not paired else f'paired {paired[0]}–{paired[1]}'}), family-wise "
                 f"α = {reg.get('alpha')}, "
                 f"β = {reg.get('beta')}, stages of {reg.get('stage_trials')} trials up to "
                 f"{record.get('max_trials')} ({record.get('stages')} looks), {reg.get('permutations')} permutation "
                 f"draws, seed {reg.get('seed')}. A comparison is decided when |statistic| passes its boundary "
                 f"(blocked-adastop: the sum over trials of the score difference against its within-trial permutation "
                 f"boundary; e-value: the log wealth against log(m/α))."),
            Table(looks_table(record), ["stage", "trials", "trial_ids", "comparison", "abs_statistic", "boundary",
                                        "decision", "trained"]),
        ]
    return blocks


def plot_decisions(decisions: list[tuple[str, dict]], out_dir: Path) -> list:
    """One figure, a panel per decided sweep: each comparison's |statistic| at each look, and its boundary."""
    if not decisions:
        return []
    import matplotlib.pyplot as plt

    from asp_dist.analysis.plots import Figure, save_figure

    fig, axes = plt.subplots(1, len(decisions), figsize=(max(6.4, 4.6 * len(decisions)), 3.6), squeeze=False,
                             layout="constrained")
    for ax, (name, record) in zip(axes[0], decisions):
        table = looks_table(record)
        for i, (c, g) in enumerate(table.groupby("comparison", sort=False)):
            g = g[g["abs_statistic"].notna()]
            ax.plot(g["trials"], g["abs_statistic"], "o-", color=f"C{i}", label=f"{c}: |statistic|")
            b = g[g["boundary"].notna()]
            ax.plot(b["trials"], b["boundary"], "x--", color=f"C{i}", alpha=0.7, label=f"{c}: boundary")
        ax.set_xlabel("trials")
        ax.set_ylabel("|statistic|")
        ax.set_title(f"{name}: statistic against boundary", fontsize=10)
        ax.legend(fontsize=7)
    stem = "sequential_looks"
    caption = ("After each stage, each open comparison's |statistic| (solid) against the boundary it must pass to be "
               "decided (dashed); a comparison stops at the first look where it passes. The registration fixed the "
               "test, α, the stage size and the most trials before the first stage ran.")
    return [Figure(stem, "Sequential verdict: statistic against boundary at each look", caption,
                   save_figure(fig, out_dir, stem))]
