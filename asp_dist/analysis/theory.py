"""The paper's policy-space analysis: how many policies adversarial training leaves.

A deterministic one-step policy maps S equally likely states to A actions: A^S policies. An
adversary that matches the convention's action distribution p keeps only the policies that
send p_i·S states to action i: the multinomial coefficient S! / Π (p_i S)!. The log-ratio

    lr = ln( multinomial / A^S )

measures the pruning. This module computes it exactly (via lgamma, any distribution whose
p_i·S are counts, or real-valued through the gamma function) beside the paper's Stirling
approximation (the full form with its ½·ln(2πn) terms, whose leading terms cancel for the
uniform case) and the paper's final big-O expression ln S − A·ln(S/A).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence


def log_multinomial(counts: Sequence[float]) -> float:
    """ln( (Σ c)! / Π c_i! ), exact for integers, gamma-function extension for reals."""
    if any(c < 0 for c in counts):
        raise ValueError("counts must be >= 0")
    total = float(sum(counts))
    return math.lgamma(total + 1) - sum(math.lgamma(c + 1) for c in counts)


def uniform_counts(states: int, actions: int) -> list[float]:
    return [states / actions] * actions


def counts_from_probs(states: int, probs: Sequence[float]) -> list[float]:
    total = sum(probs)
    if total <= 0 or any(p < 0 for p in probs):
        raise ValueError("probabilities must be >= 0 and not all zero")
    return [states * p / total for p in probs]


def log_ratio_exact(states: int, actions: int, probs: Sequence[float] | None = None) -> float:
    """Exact lr = ln multinomial − S·ln A (uniform distribution when probs is None)."""
    validate(states, actions)
    counts = uniform_counts(states, actions) if probs is None else counts_from_probs(states, probs)
    if len(counts) != actions:
        raise ValueError(f"got {len(counts)} probabilities for {actions} actions")
    return log_multinomial(counts) - states * math.log(actions)


def log_ratio_stirling(states: int, actions: int, probs: Sequence[float] | None = None) -> float:
    """Stirling, ln n! ≈ n ln n − n + ½ ln(2πn), applied to every factorial.

    Uniform p: the n ln n − n terms cancel (the paper's Eq. 5 → 6), leaving
    ½ ln(2πS) − (A/2)·ln(2πS/A). General p: S·(H(p) − ln A) + ½ ln(2πS) − ½ Σ ln(2π S p_i)."""
    validate(states, actions)
    counts = uniform_counts(states, actions) if probs is None else counts_from_probs(states, probs)
    s = float(states)

    def stirling(n: float) -> float:
        return 0.0 if n == 0 else n * math.log(n) - n + 0.5 * math.log(2 * math.pi * n)

    return stirling(s) - sum(stirling(c) for c in counts) - s * math.log(actions)


def log_ratio_big_o(states: int, actions: int) -> float:
    """The paper's final form, ln S − A·ln(S/A), with the big-O's constants dropped (uniform p)."""
    validate(states, actions)
    return math.log(states) - actions * math.log(states / actions)


def validate(states: int, actions: int) -> None:
    if states < 1 or actions < 1:
        raise ValueError(f"states and actions must be >= 1 (got S={states}, A={actions})")


@dataclass(frozen=True)
class Pruning:
    states: int
    actions: int
    distribution: str
    log_all_policies: float
    log_adversarial_policies: float
    log_ratio_exact: float
    log_ratio_stirling: float
    log_ratio_big_o: float | None

    @property
    def fraction_kept(self) -> float:
        return math.exp(self.log_ratio_exact)


def analyse(states: int, actions: int, probs: Sequence[float] | None = None) -> Pruning:
    counts = uniform_counts(states, actions) if probs is None else counts_from_probs(states, probs)
    return Pruning(
        states=states, actions=actions,
        distribution="uniform" if probs is None else ",".join(f"{p:.3g}" for p in probs),
        log_all_policies=states * math.log(actions),
        log_adversarial_policies=log_multinomial(counts),
        log_ratio_exact=log_ratio_exact(states, actions, probs),
        log_ratio_stirling=log_ratio_stirling(states, actions, probs),
        log_ratio_big_o=log_ratio_big_o(states, actions) if probs is None else None,
    )


def skew_probs(actions: int, skew: float) -> list[float]:
    """The signaling game's token distribution, p_k ∝ exp(−skew·k)."""
    weights = [math.exp(-skew * k) for k in range(actions)]
    total = sum(weights)
    return [w / total for w in weights]
