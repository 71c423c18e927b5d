"""Sequential verdicts: tests that may be run after every stage of a growing sweep with the family-wise error
rate still controlled, for the paper's blocked design (a trial's paired counts share its base; treatments
are compared within trials).

Input: per-trial scores ``y`` (trials x treatments, larger is better; a trial's score of a treatment is the
mean over its paired counts in the registered range, or the mean within-block rank with ``statistic="rank"``)
in the order the trials were added, and the trial counts at which the test looked (``looks``, ascending).
NaN marks a treatment a trial did not train because every comparison it is in was decided before.

Two tests, chosen between by measurement (bench/sequential_error.py, docs/decisions/0059):

    blocked-adastop   AdaStop (Mathieu et al. 2023) on blocks: the statistic of comparison (a, b) is the sum
                      over trials of y[a] - y[b]; its null distribution is that of the same sum with the
                      labels of a and b swapped or not *within each trial* (a swap when the trial's draw puts
                      them in the other order: the sign of its difference flips), from `permutations` draws
                      fixed by `seed` for every trial the registration may add. As AdaStop permutes within
                      each comparison's pair, a comparison's null involves its two treatments alone, so it is
                      exact under its own H0 (a and b exchangeable within a trial) whatever the other
                      treatments score. Alpha is spent linearly over the `looks` planned (alpha
                      * k / K at look k); at each look the undecided comparisons are tested step-down on the
                      max-|T| statistic over the draws not stopped at an earlier look (AdaStop's conditioning),
                      which controls the family-wise error in the strong sense. With beta > 0 a comparison may
                      also stop as "equal" early (power spent linearly, as AdaStop's beta).
    e-value           a betting e-process per comparison (Waudby-Smith & Ramdas 2023): wealth multiplies by
                      1 + lambda * tanh(d / s) at each trial, d = y[a] - y[b], s the median |d| of the earlier
                      trials, lambda predictable (aGRAPA, clipped to [-1/2, 1/2]); two-sided as the mean of a
                      long and a short bettor; reject when the wealth reaches m / alpha (Bonferroni over the m
                      comparisons). Valid at any look, so the stage size does not matter; no early "equal".

The same inputs give the same decisions: a stage's verdict is recomputed from the rows after a crash, never
redrawn. Each look's record holds the statistic and its boundary, for the report's figure.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

TESTS = ("blocked-adastop", "e-value")
STATISTICS = ("mean", "rank")
CONTINUE, LARGER, SMALLER, EQUAL = "continue", "larger", "smaller", "equal"


@dataclass(frozen=True)
class Look:
    """What the test saw and said at one look: per comparison its statistic, the boundary it was held to,
    and its decision (continue | larger: a better | smaller: b better | equal)."""

    trials: int
    statistic: dict[str, float]
    boundary: dict[str, float]
    decision: dict[str, str]

    def as_dict(self) -> dict:
        """As JSON keeps it: a statistic or boundary that is not a finite number (a comparison decided earlier,
        a boundary no draw reaches) is None."""
        def finite(values: dict[str, float]) -> dict[str, float | None]:
            return {k: (float(v) if np.isfinite(v) else None) for k, v in values.items()}

        return {"trials": self.trials, "statistic": finite(self.statistic), "boundary": finite(self.boundary),
                "decision": dict(self.decision)}


@dataclass(frozen=True)
class SequentialResult:
    comparisons: tuple[tuple[str, str], ...]
    looks: tuple[Look, ...] = field(default_factory=tuple)

    @property
    def decisions(self) -> dict[str, str]:
        return dict(self.looks[-1].decision) if self.looks else {label(c): CONTINUE for c in self.comparisons}

    @property
    def finished(self) -> bool:
        return all(d != CONTINUE for d in self.decisions.values())

    def decided_at(self) -> dict[str, int | None]:
        """Per comparison, the trial count of the look that decided it (None: still open)."""
        out: dict[str, int | None] = {label(c): None for c in self.comparisons}
        for look in self.looks:
            for c, d in look.decision.items():
                if d != CONTINUE and out[c] is None:
                    out[c] = look.trials
        return out


def label(comparison: tuple[str, str]) -> str:
    return f"{comparison[0]} vs {comparison[1]}"


def trial_scores(blocks: np.ndarray, statistic: str = "mean") -> np.ndarray:
    """trials x blocks-per-trial x treatments scores -> trials x treatments: the mean over a trial's blocks of
    the score, or of the within-block rank (1 = worst; ties share their mean rank)."""
    if statistic not in STATISTICS:
        raise ValueError(f"statistic must be one of {STATISTICS}, got {statistic!r}")
    if statistic == "rank":
        from scipy.stats import rankdata

        blocks = rankdata(blocks, axis=2, nan_policy="omit")  # an untrained treatment stays NaN
    return blocks.mean(axis=1)


def permutation_draws(present: np.ndarray, permutations: int, seed: int) -> np.ndarray:
    """draws x trials x treatments: each draw's permutation of the treatments within each trial, among those
    the trial has (`present`, trials x treatments booleans: a treatment no open comparison needs any more is
    not trained in later trials). Draw 0 is the identity (the observed data), as in AdaStop. A trial's draws
    depend only on the seed, its position and what it has, so a run that grows repeats a shorter one's draws."""
    n, k = present.shape
    out = np.broadcast_to(np.arange(k, dtype=np.int8), (permutations, n, k)).copy()
    for t in range(n):
        cols = np.flatnonzero(present[t])
        keys = np.random.default_rng([seed, t, k]).random((permutations, len(cols)))
        out[:, t, cols] = cols[np.argsort(keys, axis=1)]
    out[0] = np.arange(k)
    return out


def blocked_adastop(y: np.ndarray, looks: Sequence[int], comparisons: Sequence[tuple[int, int]], names: Sequence[str],
                    planned_looks: int, alpha: float = 0.05, beta: float = 0.0, permutations: int = 10_000,
                    seed: int = 0, draws: np.ndarray | None = None) -> SequentialResult:
    """The blocked AdaStop test at each of `looks` (trial counts) of `planned_looks`; see the module doc."""
    y = np.asarray(y, dtype=float)
    n = y.shape[0]
    if draws is None:
        draws = permutation_draws(~np.isnan(y), permutations, seed)
    B = draws.shape[0]
    labels = [label((names[a], names[b])) for a, b in comparisons]
    # per draw, per trial, per comparison: the difference, its sign flipped where the draw swaps the pair's order.
    # (Permuting all the treatments would put a third one's scores into the comparison's null: not exact under
    # its H0, and far too wide where that treatment is far off.)
    order = np.argsort(draws[:, :n, :], axis=2)  # where each treatment's score goes
    diffs = np.stack([np.where((order[:, :, a] < order[:, :, b]) == (a < b), 1.0, -1.0) * (y[:, a] - y[:, b])
                      for a, b in comparisons], axis=2)  # B x n x m
    diffs[:, np.isnan(y).all(axis=1), :] = 0.0  # a lost trial (no base met its bar) adds nothing, observed or drawn
    cums = np.cumsum(diffs, axis=1)
    alive = np.ones(B, dtype=bool)  # draws not stopped at an earlier look (AdaStop's conditioning)
    open_ = list(range(len(comparisons)))
    decision = {lab: CONTINUE for lab in labels}
    level_spent = power_spent = 0.0
    out = []
    for k_look, trials in enumerate(looks, start=1):
        T = np.abs(cums[:, trials - 1, :])  # B x m: |sum of differences| so far, draw 0 observed
        observed = cums[0, trials - 1, :]
        clevel = alpha * min(k_look, planned_looks) / planned_looks
        dlevel = beta * min(k_look, planned_looks) / planned_looks
        bound_sup = {lab: float("nan") for lab in labels}
        stat = {labels[c]: float(observed[c]) for c in range(len(labels))}
        last_sup = np.inf
        level_add = 0.0
        while open_:  # step-down: reject the largest, test the rest again at the same level
            tmax = T[alive][:, open_].max(axis=1)
            values = np.sort(tmax)
            upper_tail = (len(values) - 1 - np.arange(len(values))) / B  # P(T > v) among all draws
            ok = level_spent + upper_tail <= clevel
            last_sup = values[ok][0] if ok.any() else np.inf
            level_add = upper_tail[ok][0] if ok.any() else 0.0
            for c in open_:
                bound_sup[labels[c]] = float(last_sup)
            top = max(open_, key=lambda c: T[0, c])
            if T[0, top] > last_sup:
                decision[labels[top]] = LARGER if observed[top] > 0 else SMALLER
                open_.remove(top)
                continue
            break
        if open_ and beta > 0:  # early accept: comparisons whose |T| is below the power-spending boundary
            tmax = T[alive][:, open_].max(axis=1)
            values = np.sort(tmax)
            lower = np.arange(len(values)) / B
            ok = power_spent + lower < dlevel
            if ok.any():
                bound_inf = values[ok][-1]
                power_spent += lower[ok][-1]
                for c in list(open_):
                    if T[0, c] < bound_inf:
                        decision[labels[c]] = EQUAL
                        open_.remove(c)
        if open_:
            level_spent += level_add
            alive &= T[:, open_].max(axis=1) <= last_sup
        if k_look >= planned_looks:
            for c in open_:
                decision[labels[c]] = EQUAL
            open_ = []
        out.append(Look(trials, stat, bound_sup, dict(decision)))
        if not open_:
            break
    return SequentialResult(tuple((names[a], names[b]) for a, b in comparisons), tuple(out))


def e_value(y: np.ndarray, looks: Sequence[int], comparisons: Sequence[tuple[int, int]], names: Sequence[str],
            planned_looks: int, alpha: float = 0.05) -> SequentialResult:
    """The betting e-process test at each of `looks`; see the module doc. `planned_looks` only ends it: at the
    last planned look an open comparison is "equal" (not shown different)."""
    y = np.asarray(y, dtype=float)
    m = len(comparisons)
    labels = [label((names[a], names[b])) for a, b in comparisons]
    threshold = m / alpha
    wealth = {}
    for (a, b), lab in zip(comparisons, labels):
        d = y[:, a] - y[:, b]
        w_long = w_short = 1.0
        path = []
        xs: list[float] = []
        for i, di in enumerate(d):
            if np.isnan(di):  # a lost trial (no base met its bar): no bet
                path.append((w_long, w_short))
                continue
            prior = d[:i][~np.isnan(d[:i])]
            scale = float(np.median(np.abs(prior))) if prior.size else 0.0
            if scale > 0:
                x = float(np.tanh(di / scale))
                mu = float(np.mean(xs)) if xs else 0.0
                var = float(np.var(xs)) if xs else 1.0
                lam = mu / (var + mu * mu) if (var + mu * mu) > 0 else 0.0
                lam_long, lam_short = min(max(lam, 0.0), 0.5), min(max(-lam, 0.0), 0.5)
                w_long *= 1.0 + lam_long * x
                w_short *= 1.0 - lam_short * x
                xs.append(x)
            path.append((w_long, w_short))
        wealth[lab] = path
    decision = {lab: CONTINUE for lab in labels}
    out = []
    for k_look, trials in enumerate(looks, start=1):
        stat, bound = {}, {}
        for lab in labels:
            w_long, w_short = wealth[lab][trials - 1]
            w = 0.5 * (w_long + w_short)
            stat[lab], bound[lab] = float(np.log(w)), float(np.log(threshold))
            if decision[lab] == CONTINUE:
                # Ville's inequality holds at any stopping time: a crossing between looks is seen at this one.
                # The long bettor's winnings say a is better, the short one's b.
                if max(0.5 * (lo + sh) for lo, sh in wealth[lab][:trials]) >= threshold:
                    decision[lab] = LARGER if w_long >= w_short else SMALLER
                elif k_look >= planned_looks:
                    decision[lab] = EQUAL
        out.append(Look(trials, stat, bound, dict(decision)))
        if all(d != CONTINUE for d in decision.values()):
            break
    return SequentialResult(tuple((names[a], names[b]) for a, b in comparisons), tuple(out))


def run_test(test: str, y: np.ndarray, looks: Sequence[int], comparisons: Sequence[tuple[str, str]],
             treatments: Sequence[str], planned_looks: int, alpha: float, beta: float = 0.0,
             permutations: int = 10_000, seed: int = 0) -> SequentialResult:
    """`test` on trials x treatments scores `y` (columns in `treatments` order) at `looks`."""
    index = {t: i for i, t in enumerate(treatments)}
    pairs = [(index[a], index[b]) for a, b in comparisons]
    if test == "blocked-adastop":
        return blocked_adastop(y, looks, pairs, list(treatments), planned_looks, alpha, beta, permutations, seed)
    if test == "e-value":
        return e_value(y, looks, pairs, list(treatments), planned_looks, alpha)
    raise ValueError(f"test must be one of {TESTS}, got {test!r}")
