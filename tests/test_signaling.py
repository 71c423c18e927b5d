import pytest
import torch

from asp_dist.core.registry import get_domain
from asp_dist.domains.signaling import class_sizes, state_classes
from asp_dist.spec import CellSpec


@pytest.mark.parametrize("states, tokens, skew", [(32, 4, 0.0), (32, 4, 1.0), (10, 3, 5.0), (100, 7, 0.3)])
def test_class_sizes_sum_and_follow_the_skew(states, tokens, skew):
    sizes = class_sizes(states, tokens, skew)
    assert sum(sizes) == states and min(sizes) >= 1
    assert sizes == sorted(sizes, reverse=True)
    if skew == 0.0:
        assert max(sizes) - min(sizes) <= 1


def test_base_is_a_perfect_bijection_and_varies_with_trial():
    domain = get_domain("signaling")
    spec = CellSpec(domain="signaling").resolved()
    bases = [domain.train_base(spec, seed)[0] for seed in range(6)]
    for base in bases:
        assert domain.evaluate(spec, base, base, torch.Generator())["self_play_new"] == 1.0
        tokens = base.greedy_tokens()
        classes = state_classes(spec)
        assert len(set(zip(classes.tolist(), tokens.tolist()))) == spec.signaling_tokens
    assert len({tuple(b.greedy_tokens().tolist()) for b in bases}) > 1


@pytest.mark.slow
def test_adversary_resolves_a_skewed_convention_without_paired_data():
    """The analysis' claim in miniature: with distinct class sizes, matching the token
    marginal identifies the convention; with a uniform distribution it cannot."""
    from asp_dist.training.cell import run_cell

    def median_mixed(method, skew):
        scores = sorted(run_cell(CellSpec(domain="signaling", method=method, paired=0, trial=t,
                                          signaling_skew=skew, train_steps=200))["eval_mixed"] for t in range(8))
        return (scores[3] + scores[4]) / 2

    asp_skewed = median_mixed("asp", 1.0)  # once: 8 cells (it was trained twice, for each comparison)
    assert asp_skewed > median_mixed("osp", 1.0)
    assert asp_skewed > median_mixed("asp", 0.0)
