"""Docs that cannot drift: docs/performance.md's Summary table is made from the headline line of each section
(scripts/perf_summary.py), so a figure is written once; docs/knobs.md is checked in tests/test_knobs.py."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _perf_summary():
    spec = importlib.util.spec_from_file_location("perf_summary", ROOT / "scripts" / "perf_summary.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_performance_summary_is_the_sections_headlines():
    perf = _perf_summary()
    text = perf.PAGE.read_text()
    assert perf.with_table(text) == text, "docs/performance.md's Summary is stale: python scripts/perf_summary.py"
    assert len(perf.MARKER.findall(text)) >= 10


def test_a_headline_changed_in_its_section_is_caught():
    perf = _perf_summary()
    text = perf.PAGE.read_text()
    changed = text.replace("<!-- summary: whole test suite | ", "<!-- summary: whole test suite | 99 min, ", 1)
    assert changed != text and perf.with_table(changed) != changed
    with pytest.raises(ValueError, match="4 cells"):
        perf.table("<!-- summary: only | three | cells -->")
