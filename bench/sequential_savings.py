"""What the sequential tests would have saved on the committed confirmatory studies: each study's rows replayed in
trial order as the decide loop would have run them.

    python bench/sequential_savings.py [--studies confirm-levers ...] [--stage 5] [--beta 0]
        [--out docs/bench-results/sequential-savings-<date>.json]

Per study: its complete trials in trial order, the paper's paired range, the paper's three methods (a validated
study's @default arms are compared apart), the comparisons "asp vs osp" and "asp vs pc" at alpha 0.05, stages of
--stage trials up to the study's registered size (its trial range: a trial that failed is missing from the
replay, as it would have been from the run). As in the decide loop, a treatment whose comparisons are all decided
trains no later trial (bench/sequential_error.py run_sequential). Each test (blocked-adastop and the e-value, each
with statistic mean and rank; the registered 10,000 permutation draws, seed 0) gives per comparison its verdict
and the trials it took; beside it the fixed-size verdict of the paper's test (Friedman, then Nemenyi:
asp_dist.analysis.power.rejects, each direction) on all the study's trials, and whether the two agree. Savings:
the trials at stop over the registered size, and the cells trained over the fixed run's (a dropped treatment's
later trials are not trained). The target: on average no more than 60 % of the trials.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from sequential_error import DEFAULT_STUDIES, EXAMPLES, fixed_verdicts, load_study, run_sequential

VARIANTS = (("blocked-adastop", "mean"), ("blocked-adastop", "rank"), ("e-value", "mean"), ("e-value", "rank"))


def replay(name: str, stage: int, alpha: float, beta: float, permutations: int, seed: int) -> list[dict]:
    study = load_study(EXAMPLES / name)
    n, _, k = study.blocks.shape
    fixed = fixed_verdicts(study.blocks, study.treatments, study.comparisons, alpha)
    out = []
    for test, statistic in VARIANTS:
        result, present = run_sequential(study.blocks, study.treatments, study.comparisons, test, statistic,
                                         study.registered, stage, alpha, beta if test == "blocked-adastop" else 0.0,
                                         permutations, seed)
        stop = result.looks[-1].trials
        at = result.decided_at()
        comps = {c: {"sequential": d, "trials": at[c], "fixed": fixed[c], "agree": d == fixed[c]}
                 for c, d in result.decisions.items()}
        out.append({"study": name, "domain": study.domain, "condition": study.condition,
                    "paired": list(study.paired), "trials_available": n, "registered": study.registered,
                    "test": test, "statistic": statistic, "comparisons": comps, "trials_at_stop": stop,
                    "trials_fraction": stop / study.registered,
                    "cells_fraction": float(present[:stop].sum()) / (study.registered * k),
                    "looks": [look.as_dict() for look in result.looks]})
    return out


def table(rows: list[dict]) -> str:
    lines = [(f"{'study':<26}{'test':<16}{'asp vs osp (trials) / fixed':<34}{'asp vs pc (trials) / fixed':<34}"
              f"{'stop':>9}{'trials':>8}{'cells':>7}")]
    for r in rows:
        name = f"{'adastop' if r['test'] == 'blocked-adastop' else 'e-value'}-{r['statistic']}"
        cells = []
        for c in ("asp vs osp", "asp vs pc"):
            v = r["comparisons"][c]
            cells.append(f"{v['sequential']} ({v['trials']}) / {v['fixed']}{'' if v['agree'] else ' *'}")
        lines.append(f"{r['study']:<26}{name:<16}{cells[0]:<34}{cells[1]:<34}"
                     f"{r['trials_at_stop']:>4}/{r['registered']:<4}{r['trials_fraction']:>8.2f}{r['cells_fraction']:>7.2f}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--studies", nargs="+", default=list(DEFAULT_STUDIES))
    ap.add_argument("--stage", type=int, default=5)
    ap.add_argument("--alpha", type=float, default=0.05)
    ap.add_argument("--beta", type=float, default=0.0)
    ap.add_argument("--permutations", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=f"docs/bench-results/sequential-savings-{dt.date.today().isoformat()}.json")
    args = ap.parse_args(argv)
    rows = [r for name in args.studies for r in replay(name, args.stage, args.alpha, args.beta, args.permutations,
                                                         args.seed)]
    summary = {}
    for test, statistic in VARIANTS:
        mine = [r for r in rows if r["test"] == test and r["statistic"] == statistic]
        verdicts = [v for r in mine for v in r["comparisons"].values()]
        summary[f"{test}/{statistic}"] = {
            "mean_trials_fraction": float(np.mean([r["trials_fraction"] for r in mine])),
            "mean_cells_fraction": float(np.mean([r["cells_fraction"] for r in mine])),
            "agree": sum(v["agree"] for v in verdicts), "comparisons": len(verdicts)}
    record = {"bench": "sequential_savings",
              "command": "python bench/sequential_savings.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "date": dt.date.today().isoformat(), "stage": args.stage, "alpha": args.alpha, "beta": args.beta,
              "permutations": args.permutations, "seed": args.seed, "target_mean_trials_fraction": 0.6,
              "summary": summary, "studies": rows}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(table(rows))
    print()
    for key, s in summary.items():
        print(f"{key:<24} mean trials fraction {s['mean_trials_fraction']:.2f}, cells {s['mean_cells_fraction']:.2f}, "
              f"agrees with the fixed test on {s['agree']} of {s['comparisons']}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
