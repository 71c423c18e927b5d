"""Error rates and power of the sequential tests (asp_dist.analysis.sequential) by simulation on committed rows.

    python bench/sequential_error.py [--studies confirm-levers confirm-tuned-particles ...] [--sims 1000]
        [--seed 0] [--max-trials 30 60] [--modes shuffle shift shift-mean effect] [--aa SWEEP_DIR]
        [--out docs/bench-results/sequential-error-<date>.json] [--merge]

The committed figures ran one study and two modes a command (each under 3 minutes on two loaded cores), merged:
    for s in confirm-levers confirm-particles confirm-tuned-levers confirm-tuned-particles \
             confirm-validated-levers confirm-vae; do
      python bench/sequential_error.py --studies $s --modes shuffle shift --merge
      python bench/sequential_error.py --studies $s --modes shift-mean effect --merge
    done
A smoke check of --aa before an A/A sweep exists (not a figure): synthetic_aa() below writes one method's rows
twice, the copy's trials rotated by one, e.g. to /tmp/aa.parquet; then --studies --aa /tmp/aa.parquet --sims 100.

Each simulated run is a registration like the real ones: comparisons "asp vs osp" and "asp vs pc", alpha 0.05,
stages of 5 trials, at most 30 or 60 trials, run as the decide loop runs it: after each stage the test looks at
every trial so far, and a treatment whose comparisons are all decided trains no later trial (its later trials
are NaN: with the rank statistic the others are ranked among themselves). Its trials are drawn with replacement
from a study's complete trials (each with all its blocks in the paper's paired range); the same draw serves
every mode, test and size of one simulation (a 30-trial run uses the first 30 of the 60 drawn).

Modes:
    shuffle   the effect removed by permuting the treatments' labels within each drawn trial (all its blocks
              alike): the treatments are exchangeable within a trial, the null the permutation test is exact for
    shift     each treatment's scores shifted by the median over the study's trials of ASP's per-trial
              difference from it (per-trial score: the mean over the trial's blocks), so those medians are zero:
              a null in the median that is not exchangeable (spreads and shapes still differ): robustness. Where
              the differences are skewed their mean is not zero, and a test of the mean is right to reject
    shift-mean  the same with the mean difference: zero mean, not exchangeable (the mean statistic's null
              without the permutation test's assumption)
    effect    the rows as they are: power and the trials a run takes
    aa        (--aa) an A/A sweep's rows, one method under two names: a null by construction

Tests: blocked-adastop with statistic mean and rank (permutation draws: --permutations, 2,000 by default
against the registered 10,000: a Monte Carlo permutation test is exact for any number of draws, and 2,000
keeps a study's 1,000 runs within minutes on two cores) and the e-value (statistic mean). Beside them the
paper's fixed test (Friedman, then Nemenyi; Wilcoxon for two treatments: asp_dist.analysis.power.rejects) on
the same drawn trials at the maximum size. A false positive is a run with any comparison decided different
(either direction); its rate comes with a 95 % Clopper-Pearson interval.

Seeded: the study's draws depend on (--seed, the run's index, the study's name) only, so a study's figures
do not change with the other studies run beside it; the permutation draws' seed is (--seed, run index).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from asp_dist.analysis import power
from asp_dist.analysis.layout import domain_layout, label_rows, treatment_order
from asp_dist.analysis.paper import paper_paired_ranges
from asp_dist.analysis.sequential import (CONTINUE, EQUAL, LARGER, SMALLER, SequentialResult, blocked_adastop,
                                          e_value, label, permutation_draws, trial_scores)
from asp_dist.results.store import read_rows

EXAMPLES = Path("results/examples")
MAIN = ("pc", "osp", "asp")
COMPARISONS = (("asp", "osp"), ("asp", "pc"))
VARIANTS = (("blocked-adastop", "mean"), ("blocked-adastop", "rank"), ("e-value", "mean"))
DEFAULT_STUDIES = ("confirm-levers", "confirm-particles", "confirm-tuned-levers", "confirm-tuned-particles",
                   "confirm-validated-levers", "confirm-vae")


@dataclass
class Study:
    """A study's complete trials in trial order: blocks (trials x blocks per trial x treatments, score: larger is
    better) over its paired range, and what its registration compares."""

    name: str
    domain: str
    condition: str
    paired: tuple[int, int]
    treatments: list[str]
    comparisons: list[tuple[str, str]]
    trials: list[int]
    blocks: np.ndarray
    registered: int  # the trial count the study was registered with (its trial range)
    dropped_trials: list[int]  # trials without every block (left out)


def load_rows(path: str | Path) -> pd.DataFrame:
    path = Path(path)
    return pd.read_parquet(path) if path.suffix == ".parquet" else read_rows(path)


def load_study(path: str | Path, treatments: Sequence[str] | None = None,
               comparisons: Sequence[tuple[str, str]] | None = None, name: str | None = None) -> Study:
    """The study at `path` (a sweep directory or a Parquet file of rows) among `treatments` (default: the paper's
    three methods; the @default arms of a validated study are compared apart). Of several conditions the one
    with the most paired counts is taken (VAE: the paired-count grid at d = 32)."""
    rows = load_rows(path)
    domains = rows["domain"].unique()
    if len(domains) != 1:
        raise SystemExit(f"{path}: rows of {len(domains)} domains; one expected")
    domain = str(domains[0])
    labelled = label_rows(rows, domain_layout(rows, "eval_mixed"), "eval_mixed")
    counts = labelled.groupby("condition")["paired"].nunique()
    condition = str(counts.idxmax())
    treatments = list(treatments or MAIN)
    comparisons = list(comparisons or COMPARISONS)
    paired = paper_paired_ranges().get(domain)
    comp = power.comparison(rows, domain, comparisons[0][0], comparisons[0][1], paired, condition, treatments)
    cols = list(comp.blocks.columns)
    per_trial = {t: comp.blocks.xs(t, level="trial").to_numpy() for t in comp.trials}
    size = max(len(v) for v in per_trial.values())
    keep = [t for t in comp.trials if len(per_trial[t]) == size]
    trial_ids = labelled["trial"]
    return Study(name or Path(path).name.removesuffix(".parquet"), domain, condition, comp.paired, cols,
                 comparisons, keep, np.stack([per_trial[t] for t in keep]),
                 int(trial_ids.max() - trial_ids.min() + 1), [t for t in comp.trials if t not in keep])


class Draws:
    """One seed's permutation draws for trials x k treatments, for any pattern of present treatments: a trial's
    draws depend only on the seed, its position and what it has (sequential.permutation_draws), so a pattern's
    draws are computed once for every trial and a run's are put together trial by trial."""

    def __init__(self, seed: int, permutations: int, trials: int):
        self.seed, self.permutations, self.trials = seed, permutations, trials
        self.cache: dict[tuple[bool, ...], np.ndarray] = {}

    def pattern(self, present: tuple[bool, ...]) -> np.ndarray:
        if present not in self.cache:
            self.cache[present] = permutation_draws(np.tile(np.array(present), (self.trials, 1)),
                                                    self.permutations, self.seed)
        return self.cache[present]

    def get(self, present: np.ndarray) -> np.ndarray:
        n, k = present.shape
        patterns, which = np.unique(present, axis=0, return_inverse=True)
        if len(patterns) == 1:
            return self.pattern(tuple(bool(v) for v in patterns[0]))[:, :n]
        out = np.empty((self.permutations, n, k), dtype=np.int8)
        for i, pattern in enumerate(patterns):
            rows = np.flatnonzero(which.ravel() == i)
            out[:, rows, :] = self.pattern(tuple(bool(v) for v in pattern))[:, rows, :]
        return out


def looks_for(n: int, stage: int) -> list[int]:
    """The trial counts a run of n trials looks at: every full stage, and n if the last stage is short."""
    looks = list(range(stage, n + 1, stage))
    return looks if looks and looks[-1] == n else looks + [n]


def run_sequential(blocks: np.ndarray, treatments: Sequence[str], comparisons: Sequence[tuple[str, str]], test: str,
                   statistic: str, max_trials: int, stage: int = 5, alpha: float = 0.05, beta: float = 0.0,
                   permutations: int = 10_000, seed: int = 0,
                   draws: Draws | None = None) -> tuple[SequentialResult, np.ndarray]:
    """The decide loop on these trials (in order; at most max_trials of them): the result and which treatments
    each trial trained (trials x treatments booleans). A treatment whose comparisons are all decided at a look
    trains no later trial; the test is run again on the rows so thinned, which leaves every earlier look as it
    was (a trial's draws and scores do not depend on later trials), until no further treatment drops out."""
    blocks = np.array(blocks[:max_trials], dtype=float)
    n, _, k = blocks.shape
    looks = looks_for(n, stage)
    planned = math.ceil(max_trials / stage)
    index = {t: i for i, t in enumerate(treatments)}
    pairs = [(index[a], index[b]) for a, b in comparisons]
    labels = [label(c) for c in comparisons]
    members = {j: [labels[c] for c, p in enumerate(pairs) if j in p] for j in range(k)}
    present = np.ones((n, k), dtype=bool)
    if draws is None and test == "blocked-adastop":
        draws = Draws(seed, permutations, n)
    while True:
        y = trial_scores(blocks, statistic)
        if test == "blocked-adastop":
            result = blocked_adastop(y, looks, pairs, list(treatments), planned, alpha, beta, permutations, seed,
                                     draws=draws.get(present))
        elif test == "e-value":
            result = e_value(y, looks, pairs, list(treatments), planned, alpha)
        else:
            raise ValueError(test)
        drops = first_drops(result, present, members, n)
        if not drops:
            return result, present
        if test == "e-value" and statistic == "mean":
            # an e-value reads its comparison's two columns only: the thinned rerun would decide as this run did
            for trials, j in drops:
                present[trials:, j] = False
            return result, present
        trials, j = drops[0]
        present[trials:, j] = False
        blocks[trials:, :, j] = np.nan


def first_drops(result: SequentialResult, present: np.ndarray, members: dict[int, list[str]],
                n: int) -> list[tuple[int, int]]:
    """(trial count, treatment) of each treatment still trained whose comparisons are all decided at a look
    before the run's last, in the order of those looks."""
    out, seen = [], set()
    for look in result.looks[:-1]:  # after the last look nothing trains
        if look.trials >= n:
            break
        for j, comps in members.items():
            if (j not in seen and present[look.trials, j] and comps
                    and all(look.decision[c] != CONTINUE for c in comps)):
                out.append((look.trials, j))
                seen.add(j)
    return out


def fixed_verdicts(blocks: np.ndarray, treatments: Sequence[str], comparisons: Sequence[tuple[str, str]],
                   alpha: float = 0.05) -> dict[str, str]:
    """The paper's fixed test on all these trials' blocks, per comparison: larger | smaller | equal (Friedman then
    Nemenyi with three or more treatments, Wilcoxon with two: power.rejects, each direction)."""
    scores = blocks.reshape(-1, blocks.shape[2])
    test = "friedman-nemenyi" if scores.shape[1] >= 3 else "wilcoxon-holm"
    out = {}
    for a, b in comparisons:
        ia, ib = treatments.index(a), treatments.index(b)
        out[label((a, b))] = (LARGER if power.rejects(scores, ia, ib, test, alpha)
                              else SMALLER if power.rejects(scores, ib, ia, test, alpha) else EQUAL)
    return out


def clopper_pearson(x: int, n: int, level: float = 0.95) -> tuple[float, float]:
    from scipy.stats import beta

    tail = (1 - level) / 2
    lo = 0.0 if x == 0 else float(beta.ppf(tail, x, n - x + 1))
    hi = 1.0 if x == n else float(beta.ppf(1 - tail, x + 1, n - x))
    return lo, hi


def study_seed(name: str) -> int:
    return zlib.crc32(name.encode())


MODES = ("shuffle", "shift", "shift-mean", "effect")


def modes_of(study: Study, aa: bool, chosen: Sequence[str] = MODES) -> dict[str, np.ndarray | None]:
    if aa:
        return {"aa": None}
    y = study.blocks.mean(axis=1)  # trials x treatments
    ia = study.treatments.index("asp")
    out: dict[str, np.ndarray | None] = {}
    for mode in chosen:
        if mode in ("shift", "shift-mean"):
            centre = np.median if mode == "shift" else np.mean
            shift = np.array([centre(y[:, ia] - y[:, j]) for j in range(len(study.treatments))])
            out[mode] = study.blocks + shift[None, None, :]
        else:
            out[mode] = None
    return out


def simulate(study: Study, sims: int, seed: int, max_sizes: Sequence[int], variants, permutations: int,
             alpha: float, beta: float, stage: int, aa: bool = False, modes: Sequence[str] = MODES,
             log=print) -> list[dict]:
    """Every mode x variant x size's tallies over `sims` runs of one study."""
    modes = modes_of(study, aa, modes)
    labels = [label(c) for c in study.comparisons]
    n_max, k = max(max_sizes), len(study.treatments)
    tallies: dict[tuple, dict] = {}
    t0 = time.perf_counter()
    for sim in range(sims):
        rng = np.random.default_rng([seed, sim, study_seed(study.name)])
        picks = rng.integers(len(study.trials), size=n_max)
        shuffles = np.argsort(rng.random((n_max, k)), axis=1)  # one permutation of the labels per drawn trial
        draws = Draws(int(np.random.default_rng([seed, sim]).integers(2**31)), permutations, n_max)
        for mode, source in modes.items():
            data = (study.blocks if source is None else source)[picks]
            if mode == "shuffle":
                data = np.take_along_axis(data, shuffles[:, None, :], axis=2)
            for size in max_sizes:
                fixed = fixed_verdicts(data[:size], study.treatments, study.comparisons, alpha)
                t = tallies.setdefault((mode, "fixed", "friedman-nemenyi" if k >= 3 else "wilcoxon", size),
                                       {"decisions": {c: [] for c in labels}, "stop": [], "cells": []})
                for c in labels:
                    t["decisions"][c].append(fixed[c])
                t["stop"].append(size)
                t["cells"].append(1.0)
                for test, statistic in variants:
                    result, present = run_sequential(data, study.treatments, study.comparisons, test, statistic,
                                                     size, stage, alpha, beta, permutations, draws.seed, draws)
                    stop = result.looks[-1].trials
                    t = tallies.setdefault((mode, test, statistic, size),
                                           {"decisions": {c: [] for c in labels}, "stop": [], "cells": []})
                    for c in labels:
                        t["decisions"][c].append(result.decisions[c])
                    t["stop"].append(stop)
                    t["cells"].append(float(present[:stop].sum()) / (size * k))
        if (sim + 1) % max(1, sims // 10) == 0:
            log(f"  {study.name}: {sim + 1}/{sims} runs, {time.perf_counter() - t0:.0f} s")
    out = []
    for (mode, test, statistic, size), t in tallies.items():
        runs = len(t["stop"])
        decided = np.array([[d in (LARGER, SMALLER) for d in t["decisions"][c]] for c in labels])
        fp = int(decided.any(axis=0).sum())
        lo, hi = clopper_pearson(fp, runs)
        out.append({"study": study.name, "mode": mode, "test": test, "statistic": statistic, "max_trials": size,
                    "runs": runs, "any_decided": fp, "any_decided_rate": fp / runs, "ci95": [lo, hi],
                    "per_comparison": {c: {d: t["decisions"][c].count(d) / runs for d in (LARGER, SMALLER, EQUAL,
                                                                                          CONTINUE)}
                                       for c in labels},
                    "trials_at_stop_mean": float(np.mean(t["stop"])), "trials_at_stop_median": float(np.median(t["stop"])),
                    "cells_fraction_mean": float(np.mean(t["cells"]))})
    return out


def synthetic_aa(rows: pd.DataFrame, method: str = "osp", twin: str = "osp@twin") -> pd.DataFrame:
    """A smoke-check A/A frame (not a figure to report): `method`'s rows, and a copy named `twin` whose trials are
    rotated by one (trial i's scores under trial i+1's id), so the two share a distribution but not draws."""
    base = rows[rows["method"] == method].copy()
    trials = sorted(base["trial"].unique())
    rotate = dict(zip(trials, trials[1:] + trials[:1]))
    copy = base.copy()
    copy["method"] = twin
    copy["trial"] = copy["trial"].map(rotate)
    if "cell_id" in copy:
        copy["cell_id"] = copy["cell_id"].astype(str) + "-twin"
    return pd.concat([base, copy], ignore_index=True)


def aa_study(path: str) -> Study:
    rows = load_rows(path)
    labelled = label_rows(rows, domain_layout(rows, "eval_mixed"), "eval_mixed")
    names = treatment_order(labelled["treatment"].unique())
    if len(names) != 2:
        raise SystemExit(f"{path}: an A/A sweep holds one method under two names; found {names}")
    base, twin = sorted(names, key=lambda t: ("@" in t, t))
    return load_study(path, [base, twin], [(twin, base)], name=f"aa:{Path(path).name}")


def table(results: list[dict]) -> str:
    header = (f"{'study':<30}{'mode':<11}{'test':<24}{'max':>4}{'runs':>6}{'any decided [95 % CI]':>26}"
              f"{'larger/smaller per comparison':>40}{'trials mean/median':>20}{'cells':>7}")
    lines = [header]
    for r in results:
        name = (f"fixed ({r['statistic']})" if r["test"] == "fixed"
                else "e-value" if r["test"] == "e-value" else f"adastop-{r['statistic']}")
        lo, hi = r["ci95"]
        split = "  ".join(f"{v[LARGER]:.3f}/{v[SMALLER]:.3f}" for v in r["per_comparison"].values())
        lines.append(f"{r['study'][:29]:<30}{r['mode']:<11}{name:<24}{r['max_trials']:>4}{r['runs']:>6}"
                     f"{r['any_decided_rate']:>10.3f} [{lo:.3f}, {hi:.3f}]{split:>40}"
                     f"{r['trials_at_stop_mean']:>12.1f} / {r['trials_at_stop_median']:<5.0f}"
                     f"{r['cells_fraction_mean']:>7.2f}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--studies", nargs="*", default=list(DEFAULT_STUDIES),
                    help="committed studies under results/examples (none: only --aa)")
    ap.add_argument("--aa", help="an A/A sweep directory (or a Parquet file of rows): one method under two names")
    ap.add_argument("--sims", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-trials", type=int, nargs="+", default=[30, 60])
    ap.add_argument("--stage", type=int, default=5)
    ap.add_argument("--alpha", type=float, default=0.05)
    ap.add_argument("--beta", type=float, default=0.0)
    ap.add_argument("--permutations", type=int, default=2000)
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--out", default=f"docs/bench-results/sequential-error-{dt.date.today().isoformat()}.json")
    ap.add_argument("--merge", action="store_true",
                    help="keep the results already in --out of the (study, mode)s not run now (a long run in parts)")
    args = ap.parse_args(argv)
    results = []
    for name in args.studies:
        study = load_study(EXAMPLES / name)
        print(f"{name}: {study.domain} ({study.condition}), paired {study.paired[0]}-{study.paired[1]}, "
              f"{len(study.trials)} trials x {study.blocks.shape[1]} blocks, treatments {study.treatments}"
              + (f"; left out (incomplete): {study.dropped_trials}" if study.dropped_trials else ""), flush=True)
        results += simulate(study, args.sims, args.seed, args.max_trials, VARIANTS, args.permutations, args.alpha,
                            args.beta, args.stage, modes=args.modes, log=lambda s: print(s, flush=True))
    if args.aa:
        study = aa_study(args.aa)
        print(f"{study.name}: {study.treatments}, {len(study.trials)} trials x {study.blocks.shape[1]} blocks", flush=True)
        results += simulate(study, args.sims, args.seed, args.max_trials, VARIANTS, args.permutations, args.alpha,
                            args.beta, args.stage, aa=True, log=lambda s: print(s, flush=True))
    out_path = Path(args.out)
    record = {"bench": "sequential_error", "command": "python bench/sequential_error.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "date": dt.date.today().isoformat(), "seed": args.seed, "sims": args.sims,
              "permutations": args.permutations, "stage": args.stage, "alpha": args.alpha, "beta": args.beta,
              "comparisons": [label(c) for c in COMPARISONS], "results": results}
    if args.merge and out_path.exists():
        old = json.loads(out_path.read_text())
        ran = {(r["study"], r["mode"]) for r in results}
        record["results"] = [r for r in old.get("results", []) if (r["study"], r["mode"]) not in ran] + results
        record["commands"] = old.get("commands", [old.get("command")]) + [record["command"]]
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(record, indent=1) + "\n")
    print(table(results))
    print(f"wrote {out_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
