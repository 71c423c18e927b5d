"""The sequential tests (asp_dist.analysis.sequential): blocked AdaStop and the betting e-value, on scores whose
answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asp_dist.analysis.sequential import (CONTINUE, EQUAL, LARGER, SMALLER, blocked_adastop, e_value,
                                          TESTS, permutation_draws, run_test, trial_scores)

NAMES = ["pc", "osp", "asp"]
PAIRS = [(2, 1), (2, 0)]  # asp vs osp, asp vs pc
COMPARISONS = [("asp", "osp"), ("asp", "pc")]
AO, AP = "asp vs osp", "asp vs pc"


def noise(trials: int, seed: int, k: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(trials, k))


def looks(trials: int, stage: int) -> list[int]:
    return list(range(stage, trials + 1, stage))


def adastop(y, stage=5, beta=0.0, permutations=1000, seed=0, pairs=PAIRS, names=NAMES, alpha=0.05):
    lk = looks(len(y), stage)
    return blocked_adastop(y, lk, pairs, names, len(lk), alpha, beta, permutations, seed)


# --- permutation draws -------------------------------------------------------------------------------------------

def test_draw_zero_is_the_identity_and_every_draw_permutes_within_a_trial():
    present = np.ones((12, 3), dtype=bool)
    draws = permutation_draws(present, 200, seed=3)
    assert (draws[0] == np.arange(3)).all()
    assert (np.sort(draws, axis=2) == np.arange(3)).all()
    assert not (draws[1:] == np.arange(3)).all()  # the others are not all the identity


def test_a_trials_draws_do_not_depend_on_the_trials_that_follow():
    present = np.ones((40, 3), dtype=bool)
    long = permutation_draws(present, 300, seed=7)
    assert np.array_equal(permutation_draws(present[:10], 300, seed=7), long[:, :10])
    assert np.array_equal(permutation_draws(present[:25], 300, seed=7), long[:, :25])
    assert not np.array_equal(permutation_draws(present[:10], 300, seed=8), long[:, :10])


def test_an_absent_treatment_is_never_moved_and_a_trials_draws_depend_on_its_own_row_only():
    present = np.ones((20, 3), dtype=bool)
    thinned = present.copy()
    thinned[8:, 0] = False  # pc dropped from trial 8 on
    full, part = permutation_draws(present, 300, 1), permutation_draws(thinned, 300, 1)
    assert np.array_equal(full[:, :8], part[:, :8])
    assert (part[:, 8:, 0] == 0).all()  # pc stays in its column
    assert (np.sort(part[:, 8:, 1:], axis=2) == [1, 2]).all()


# --- blocked AdaStop ---------------------------------------------------------------------------------------------

def test_same_inputs_same_looks():
    y = noise(30, 0)
    y[:, 2] += 0.6
    first = adastop(y, seed=5)
    again = adastop(y.copy(), seed=5)
    assert [l.as_dict() for l in first.looks] == [l.as_dict() for l in again.looks]
    via = run_test("blocked-adastop", y, looks(30, 5), COMPARISONS, NAMES, 6, 0.05, permutations=1000, seed=5)
    assert [l.as_dict() for l in via.looks] == [l.as_dict() for l in first.looks]
    ev = [l.as_dict() for l in e_value(y, looks(30, 5), PAIRS, NAMES, 6).looks]
    assert ev == [l.as_dict() for l in e_value(y.copy(), looks(30, 5), PAIRS, NAMES, 6).looks]


@pytest.mark.parametrize("sign, expected", [(1.0, LARGER), (-1.0, SMALLER)])
def test_a_large_clear_effect_is_decided_at_the_first_look(sign, expected):
    y = noise(30, 1)
    y[:, 2] += sign * 50
    result = adastop(y, stage=10)  # 10-trial stages: 3 treatments on 5 trials have too few relabellings
    assert result.looks[0].trials == 10
    assert result.decisions == {AO: expected, AP: expected}
    assert result.decided_at() == {AO: 10, AP: 10}
    assert len(result.looks) == 1 and result.finished


def test_identical_columns_end_equal_at_the_last_planned_look_and_never_reject():
    y = noise(30, 2)
    y[:, 1] = y[:, 2]  # osp's scores are asp's, exactly
    for seed in range(5):
        result = adastop(y, seed=seed)
        assert len(result.looks) == 6
        assert all(l.decision[AO] == CONTINUE for l in result.looks[:-1])
        assert result.decisions[AO] == EQUAL
        assert all(l.statistic[AO] == 0 for l in result.looks)
    ev = e_value(y, looks(30, 5), PAIRS, NAMES, 6)
    assert [l.decision[AO] for l in ev.looks] == [CONTINUE] * 5 + [EQUAL]
    assert all(l.statistic[AO] == 0 for l in ev.looks)  # no bet is ever placed: the wealth stays 1


def test_step_down_rejects_the_largest_statistic_first():
    """At every look the comparisons decided are the open ones of largest |sum of differences|: a weaker one is
    never decided while a stronger open one is not."""
    seen_split = False
    for seed in range(30):
        y = noise(30, 100 + seed)
        y[:, 2] += 0.5 + 0.1 * (seed % 5)
        y[:, 0] -= 0.3 * (seed % 3)
        result = adastop(y, seed=seed, permutations=500)
        open_ = {AO, AP}
        for look in result.looks:
            decided = {c for c in open_ if look.decision[c] in (LARGER, SMALLER)}
            for c in decided:
                assert all(abs(look.statistic[o]) <= abs(look.statistic[c]) for o in open_ - decided)
            seen_split |= 0 < len(decided) < len(open_)
            open_ -= {c for c in open_ if look.decision[c] != CONTINUE}
    assert seen_split  # some look decided the stronger comparison and left the weaker open


def test_the_stronger_comparison_is_decided_first_and_the_weaker_later():
    rng = np.random.default_rng(4)
    y = rng.normal(size=(30, 3))
    y[:, 2] += 1.0
    y[:, 0] -= 20.0  # asp vs pc: overwhelming; asp vs osp: a moderate effect
    result = adastop(y, stage=10)
    at = result.decided_at()
    assert result.decisions[AP] == LARGER and at[AP] == 10
    assert at[AO] is None or at[AO] >= at[AP]
    first = result.looks[0]
    assert first.boundary[AP] >= first.boundary[AO]  # step-down: the rest are held to a boundary no higher


def test_two_looks_boundaries_match_a_hand_computation_from_the_draws():
    """One comparison, looks at 20 and 40 of 2 planned: alpha/2 spent at the first, the rest at the second among
    the draws the first did not stop (AdaStop's conditioning). (20 trials: 2^20 relabellings, so 400 draws hold
    no ties, where the rule counts a tied draw at the boundary as above it: conservative.)"""
    rng = np.random.default_rng(12)
    y = rng.normal(size=(40, 2))
    y[:, 1] += 0.3
    B, alpha = 400, 0.05
    draws = permutation_draws(np.ones((40, 2), dtype=bool), B, seed=3)
    sign = np.where(draws[:, :, 1] == 1, 1.0, -1.0)  # a relabelled trial's difference is +-(asp - osp)
    sums = np.cumsum(sign * (y[:, 1] - y[:, 0]), axis=1)
    t1, t2 = np.abs(sums[:, 19]), np.abs(sums[:, 39])
    assert len(np.unique(t1)) == B and len(np.unique(t2)) == B
    b1 = min(v for v in t1 if (t1 > v).sum() / B <= alpha / 2)
    spent, alive = (t1 > b1).sum() / B, t1 <= b1
    b2 = min(v for v in t2[alive] if spent + (t2[alive] > v).sum() / B <= alpha)
    result = blocked_adastop(y, [20, 40], [(1, 0)], ["osp", "asp"], 2, alpha, permutations=B, seed=3)
    assert result.looks[0].decision[AO] == CONTINUE
    assert result.looks[0].boundary[AO] == pytest.approx(b1)
    assert result.looks[1].boundary[AO] == pytest.approx(b2)
    assert result.decisions[AO] == (LARGER if t2[0] > b2 else EQUAL)


def test_beta_lets_an_exactly_null_comparison_stop_equal_early_and_beta_zero_does_not():
    y = noise(40, 6, k=2)
    size = np.random.default_rng(6).uniform(0.5, 2.0, size=20)
    d = np.stack([size, -size], axis=1).ravel()  # asp - osp: +s1, -s1, +s2, -s2, ...: the sum is 0 at every even
    y[:, 1] = y[:, 0] + d                        # look, where few relabellings' sums are (their |sums| spread)
    pairs, names = [(1, 0)], ["osp", "asp"]
    early = adastop(y, stage=10, beta=0.5, pairs=pairs, names=names, seed=2)
    assert early.decisions[AO] == EQUAL and early.decided_at()[AO] < 40
    never = adastop(y, stage=10, beta=0.0, pairs=pairs, names=names, seed=2)
    assert [l.decision[AO] for l in never.looks] == [CONTINUE] * 3 + [EQUAL]


def test_a_comparisons_null_does_not_involve_a_third_treatments_scores():
    """Each comparison's relabellings swap its own two treatments only (as AdaStop permutes within a pair): the
    scores of a treatment it does not compare change nothing of its statistic, boundary or decision."""
    y = noise(30, 8)
    y[:, 2] += 0.7
    other = y.copy()
    other[:, 0] = 1000 * noise(30, 80)[:, 0]  # pc anywhere, with any spread
    pairs = [(2, 1)]  # asp vs osp only
    first, second = (adastop(v, pairs=pairs, seed=4) for v in (y, other))
    assert [l.as_dict() for l in first.looks] == [l.as_dict() for l in second.looks]


def test_a_dropped_column_leaves_earlier_looks_and_the_open_comparison_alone():
    """pc is not trained after asp vs pc is decided. Every look up to the drop is as with pc trained; later,
    pc's scores (whatever they are) do not enter asp vs osp. With pc NaN the trial's draws are permutations of
    the two treatments it has, other draws than with three: the same null, not the same numbers."""
    y = noise(30, 9)
    y[:, 2] += 0.4
    y[:, 0] -= 30.0
    full = adastop(y, stage=10, seed=1)
    assert full.decided_at()[AP] == 10 and full.decided_at()[AO] != 10
    scrambled = y.copy()
    scrambled[10:, 0] = 500 * noise(20, 90)[:, 0]  # anything after the drop
    assert [l.as_dict()["decision"] for l in adastop(scrambled, stage=10, seed=1).looks] == \
        [l.decision for l in full.looks]
    assert [l.boundary[AO] for l in adastop(scrambled, stage=10, seed=1).looks] == \
        [l.boundary[AO] for l in full.looks]
    thinned = y.copy()
    thinned[10:, 0] = np.nan
    part = adastop(thinned, stage=10, seed=1)
    assert part.looks[0].as_dict() == full.looks[0].as_dict()
    for a, b in zip(part.looks, full.looks):
        assert a.statistic[AO] == pytest.approx(b.statistic[AO])
        assert a.decision[AP] == LARGER
    # the e-value reads a comparison's own two columns: its decisions do not change at all
    ev_full, ev_part = (e_value(v, looks(30, 10), PAIRS, NAMES, 3) for v in (y, thinned))
    assert [l.decision[AO] for l in ev_part.looks] == [l.decision[AO] for l in ev_full.looks]


def test_rank_scores_of_a_trial_with_a_dropped_treatment_rank_the_rest():
    blocks = np.array([[[1.0, 5.0, 3.0], [2.0, 1.0, 3.0]], [[np.nan, 4.0, 7.0], [np.nan, 2.0, 1.0]]])
    ranks = trial_scores(blocks, "rank")
    assert ranks[0].tolist() == [1.5, 2.0, 2.5]
    assert np.isnan(ranks[1, 0]) and ranks[1, 1:].tolist() == [1.5, 1.5]
    assert trial_scores(blocks, "mean")[0].tolist() == [1.5, 3.0, 3.0]


# --- e-value -----------------------------------------------------------------------------------------------------

def test_e_value_wealth_matches_a_hand_computation():
    d = np.array([2.0, 1.0, -1.0, 3.0])
    y = np.stack([np.zeros(4), d], axis=1)  # columns b, a: a - b = d
    # trial 0: no earlier trials, no bet. trial 1: scale |2| = 2, x1 = tanh(1/2); no earlier x, lambda 0.
    x1 = math.tanh(0.5)
    # trial 2: scale median(2, 1) = 1.5, x2 = tanh(-1/1.5); lambda = x1 / (0 + x1^2) > 1/2: the long bettor
    # stakes 1/2, the short one nothing.
    x2 = math.tanh(-1 / 1.5)
    w_long = 1 + 0.5 * x2
    # trial 3: scale median(2, 1, 1) = 1, x3 = tanh(3); mean of (x1, x2) < 0: lambda = mu / (var + mu^2) < 0,
    # so the short bettor stakes -lambda.
    x3 = math.tanh(3.0)
    mu, var = (x1 + x2) / 2, ((x1 - x2) / 2) ** 2
    lam = mu / (var + mu * mu)
    assert -0.5 < lam < 0
    w_short = 1 - (-lam) * x3
    result = e_value(y, [2, 3, 4], [(1, 0)], ["b", "a"], planned_looks=3, alpha=0.05)
    assert [l.trials for l in result.looks] == [2, 3, 4]
    assert result.looks[0].statistic["a vs b"] == pytest.approx(0.0)
    assert result.looks[1].statistic["a vs b"] == pytest.approx(math.log(0.5 * (w_long + 1)))
    assert result.looks[2].statistic["a vs b"] == pytest.approx(math.log(0.5 * (w_long + w_short)))
    assert result.looks[2].boundary["a vs b"] == pytest.approx(math.log(1 / 0.05))
    assert result.decisions == {"a vs b": EQUAL}


def test_e_value_rejects_a_steady_effect_in_its_direction():
    y = noise(60, 11)
    y[:, 2] += 3.0
    result = e_value(y, looks(60, 5), PAIRS, NAMES, 12)
    assert result.decisions == {AO: LARGER, AP: LARGER}
    assert result.looks[0].boundary[AO] == pytest.approx(math.log(2 / 0.05))  # Bonferroni over 2 comparisons
    y[:, 2] -= 6.0
    assert e_value(y, looks(60, 5), PAIRS, NAMES, 12).decisions == {AO: SMALLER, AP: SMALLER}


# --- error and power by simulation -------------------------------------------------------------------------------

def simulated(runs: int, effect: float, test: str) -> list[dict[str, str]]:
    out = []
    for run in range(runs):
        y = noise(30, 1000 + run)
        y[:, 2] += effect
        lk = looks(30, 5)
        out.append(run_test(test, y, lk, COMPARISONS, NAMES, len(lk), 0.05, permutations=300, seed=run).decisions)
    return out


@pytest.mark.parametrize("test", ["blocked-adastop", "e-value"])
def test_exchangeable_null_rejects_rarely(test):
    runs = simulated(200, 0.0, test)
    false_positives = sum(any(d in (LARGER, SMALLER) for d in r.values()) for r in runs)
    assert false_positives < 25  # P(X >= 25) < 1e-4 for X ~ Binomial(200, 0.05)
    assert all(d != CONTINUE for r in runs for d in r.values())


@pytest.mark.parametrize("test", ["blocked-adastop", "e-value"])
def test_a_real_effect_is_found_most_of_the_time(test):
    runs = simulated(100, 1.5, test)
    found = sum(r[AO] == LARGER and r[AP] == LARGER for r in runs)
    assert found >= 80
    assert not any(d == SMALLER for r in runs for d in r.values())


@pytest.mark.parametrize("test", TESTS)
def test_a_lost_trial_changes_no_statistic(test):
    """A trial without any score (its base met no bar) adds nothing: the statistics at a look that includes it
    are those of the other trials alone (blocked AdaStop: its differences are zero in every draw; e-value: no bet)."""
    y = np.random.default_rng(5).normal(size=(30, 2)) + np.array([0.4, 0.0])
    lost = np.insert(y, 10, np.nan, axis=0)
    kept = run_test(test, y, [30], [("a", "b")], ["a", "b"], 1, 0.05, permutations=500)
    with_lost = run_test(test, lost, [31], [("a", "b")], ["a", "b"], 1, 0.05, permutations=500)
    assert with_lost.looks[0].statistic == pytest.approx(kept.looks[0].statistic)
    assert with_lost.looks[0].decision == kept.looks[0].decision
