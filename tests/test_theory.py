import math

import pytest

from asp_dist.analysis import theory


def test_exact_log_ratio_small_case_by_hand():
    # S=4, A=2, uniform: 4!/(2!2!) = 6 of 2^4 = 16 policies survive.
    assert theory.log_ratio_exact(4, 2) == pytest.approx(math.log(6 / 16))


def test_non_uniform_distribution():
    # S=4, A=2, p=(3/4, 1/4): 4!/(3!1!) = 4 of 16.
    assert theory.log_ratio_exact(4, 2, [0.75, 0.25]) == pytest.approx(math.log(4 / 16))
    # a delta distribution keeps a single policy
    assert theory.log_ratio_exact(5, 3, [1, 0, 0]) == pytest.approx(-5 * math.log(3))


def test_uniform_is_the_worst_case():
    uniform = theory.log_ratio_exact(60, 3)
    for probs in ([0.5, 0.3, 0.2], [0.8, 0.1, 0.1], [1 / 3 + 0.01, 1 / 3, 1 / 3 - 0.01]):
        assert theory.log_ratio_exact(60, 3, probs) < uniform


def test_stirling_tracks_exact_and_improves_with_s():
    for a in (2, 4, 10):
        errs = [abs(theory.log_ratio_stirling(s, a) - theory.log_ratio_exact(s, a)) for s in (a * 10, a * 100, a * 1000)]
        assert errs[0] > errs[1] > errs[2] and errs[2] < 1e-3


def test_log_ratio_decreases_with_states():
    values = [theory.log_ratio_exact(s, 4) for s in (8, 40, 400, 4000)]
    assert values == sorted(values, reverse=True)


def test_bad_input():
    with pytest.raises(ValueError):
        theory.log_ratio_exact(0, 2)
    with pytest.raises(ValueError):
        theory.log_ratio_exact(10, 2, [0.5, 0.25, 0.25])
