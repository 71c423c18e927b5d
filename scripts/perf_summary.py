"""docs/performance.md's Summary table, made from the `<!-- summary: what | figure | target | machine, date -->`
line under each section's heading: a headline figure is written once, in the section that measured it, and the
table only gathers them (in the page's order). tests/test_docs.py fails when the table and the sections differ.

    python scripts/perf_summary.py          # rewrite the table in docs/performance.md
    python scripts/perf_summary.py --check  # exit 1 if it is stale
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

PAGE = Path(__file__).resolve().parents[1] / "docs" / "performance.md"
MARKER = re.compile(r"^<!-- summary: (.+) -->$", re.M)
HEADER = "| what | latest figure | target | machine, date |\n|---|---|---|---|\n"


def table(text: str) -> str:
    """The Summary table the page's markers give."""
    rows = []
    for found in MARKER.finditer(text):
        cells = [c.strip() for c in found.group(1).split(" | ")]
        if len(cells) != 4:
            raise ValueError(f"a summary marker needs 4 cells (what | figure | target | machine, date): {found.group(0)}")
        rows.append("| " + " | ".join(cells) + " |\n")
    return HEADER + "".join(rows)


def with_table(text: str) -> str:
    """The page with its Summary table (the first table after '## Summary', or a TABLE_PLACEHOLDER line) remade."""
    start = text.index("## Summary")
    end = text.index("\n## ", start)
    body = text[start:end]
    if "TABLE_PLACEHOLDER\n" in body:
        body = body.replace("TABLE_PLACEHOLDER\n", table(text))
    else:
        first = body.index(HEADER[:12])
        last = first + len("".join(line + "\n" for line in _table_lines(body[first:])))
        body = body[:first] + table(text) + body[last:]
    return text[:start] + body + text[end:]


def _table_lines(text: str) -> list[str]:
    lines = []
    for line in text.splitlines():
        if not line.startswith("|"):
            break
        lines.append(line)
    return lines


def main(argv: list[str]) -> int:
    text = PAGE.read_text()
    new = with_table(text)
    if "--check" in argv:
        if new != text:
            print(f"{PAGE}: the Summary table is stale; run python scripts/perf_summary.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
