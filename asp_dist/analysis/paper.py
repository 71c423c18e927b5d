"""The paper's facts per domain, looked up in the domain registry (each domain's PaperFacts).

Analysis keeps no per-domain table of its own. Rows of a domain the registry does not know (an
old or renamed domain) get the generic behaviour: every paired count in the rank tests, the
generic efficiency threshold, the metric's column name as its label, no paper claim.
The facts describe ``eval_mixed``; another metric gets only the generic behaviour.
"""

from __future__ import annotations

from asp_dist.core.contract import PaperFacts
from asp_dist.core.registry import DOMAINS

PAPER_METRIC = "eval_mixed"  # the metric PaperFacts' label and threshold are about
GENERIC_KNOB_LABELS = {"paired": "paired examples |P| (count)"}


def paper_facts(domain: str) -> PaperFacts | None:
    found = DOMAINS.get(domain)
    return getattr(found, "paper", None) if found is not None else None


def paper_paired_ranges() -> dict[str, tuple[int, int]]:
    """domain -> paired counts of the paper's Friedman test; domains tested over every count are absent."""
    return {name: facts.test_paired for name in sorted(DOMAINS)
            if (facts := paper_facts(name)) is not None and facts.test_paired is not None}


def paper_thresholds() -> dict[str, float]:
    """domain -> the paper's data-efficiency threshold of eval_mixed; domains without one are absent."""
    return {name: facts.threshold[0] for name in sorted(DOMAINS)
            if (facts := paper_facts(name)) is not None and facts.threshold is not None}


def paper_threshold(domain: str, metric: str) -> tuple[float, str] | None:
    """(threshold, where it comes from) for `metric` of `domain`, when the paper gives one."""
    facts = paper_facts(domain)
    if metric != PAPER_METRIC or facts is None or facts.threshold is None:
        return None
    value, source = facts.threshold
    return float(value), source


def paper_claim(domain: str) -> str | None:
    """The report's line on what the paper found for `domain` (or, for a domain the paper does not
    study, the question the domain asks); None when the domain says nothing."""
    facts = paper_facts(domain)
    if facts is None or not facts.claim:
        return None
    return f"the paper reports: {facts.claim}" if facts.in_paper else f"not in the paper; the question: {facts.claim}"


def metric_label(domain: str, metric: str) -> str:
    """What the metric measures, with its unit; the column name when the domain does not say."""
    facts = paper_facts(domain)
    return facts.metric_label if metric == PAPER_METRIC and facts is not None else metric


def knob_label(domain: str, knob: str) -> str:
    """Axis label of a swept knob (or of the paired count); the knob's name when nobody labels it."""
    facts = paper_facts(domain)
    if facts is not None and knob in facts.knob_labels:
        return facts.knob_labels[knob]
    return GENERIC_KNOB_LABELS.get(knob, knob)
