"""The report's content model: a list of blocks that every output format renders in its own way.

report.py decides *what* the report says (headings, text, tables, figures) once; this module
renders it as Markdown, html_report.py as HTML. Text is written in a small Markdown subset
(paragraphs, ``- `` bullet lists, ``**bold**``, ``*em*``/``_em_``, ```code```, ``[text](url)``),
which Markdown keeps as it is and HTML translates, so no sentence exists twice.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from asp_dist.analysis.markdown import to_markdown

if TYPE_CHECKING:  # an annotation only: the model does not need matplotlib
    from asp_dist.analysis.plots import Figure


@dataclass(frozen=True)
class Heading:
    level: int  # 1 = the title, 2 = a section, 3 = a subsection
    text: str


@dataclass(frozen=True)
class Text:
    md: str  # one or more paragraphs or bullet lists in the subset above


@dataclass(frozen=True)
class Table:
    df: pd.DataFrame | None
    columns: Sequence[str] | None = None  # those shown, in this order (default: all)


@dataclass(frozen=True)
class Plot:
    figure: Figure  # a drawn figure: its PNG and SVG files are in figure.paths


Block = Heading | Text | Table | Plot


@dataclass
class Document:
    title: str
    out_dir: Path  # the directory the report is written to (figures are linked relative to it)
    blocks: list[Block] = field(default_factory=list)

    def add(self, *blocks: Block) -> None:
        self.blocks.extend(blocks)


def svg_path(figure: Figure) -> Path:
    return next(p for p in figure.paths if p.suffix == ".svg")


def png_path(figure: Figure) -> Path:
    return next(p for p in figure.paths if p.suffix == ".png")


def _block_markdown(block: Block, out_dir: Path) -> str:
    if isinstance(block, Heading):
        return "#" * block.level + " " + block.text
    if isinstance(block, Text):
        return block.md.strip("\n")
    if isinstance(block, Table):
        return to_markdown(block.df, block.columns).rstrip("\n")
    fig = block.figure
    png, svg = (os.path.relpath(p, out_dir) for p in (png_path(fig), svg_path(fig)))
    return f"### {fig.title}\n\n![{fig.title}]({png})\n\n{fig.caption} ([SVG]({svg}))"


def render_markdown(doc: Document) -> str:
    """The document as GitHub Markdown: blocks separated by one blank line."""
    return "\n\n".join(_block_markdown(b, doc.out_dir) for b in doc.blocks) + "\n"


def write_atomic(path: Path, text: str) -> Path:
    """Write through a temporary file in the same directory, so a reader never sees half a report."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return path
