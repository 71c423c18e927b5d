"""report.html: the sweep report as one self-contained file, to e-mail, open offline and print.

It renders the same document.Document as report.md (report.build_report), so both always say the
same thing. Self-contained means: the figures are the SVG that matplotlib wrote for figures/*.svg
(``savefig(format="svg")``), inlined; the style sheet is inline; there is no script and nothing to
fetch (a Content-Security-Policy of ``default-src 'none'`` makes a browser refuse any fetch, so a
stray reference shows up as a console error in the headless-browser test, tests/test_report_html.py).
"""

from __future__ import annotations

import html
import re
from pathlib import Path

import pandas as pd

from asp_dist.analysis.document import Document, Heading, Plot, Table, Text, png_path, svg_path, write_atomic
from asp_dist.analysis.markdown import format_value

CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:"

CSS = """
:root { color-scheme: light; }
body { font: 15px/1.5 system-ui, "Segoe UI", "DejaVu Sans", Arial, sans-serif; color: #1b1b1b;
       max-width: 76rem; margin: 0 auto; padding: 1.2rem 1.5rem 3rem; }
h1 { font-size: 1.65rem; margin: 0 0 .4rem; }
h2 { font-size: 1.3rem; margin: 2.2rem 0 .6rem; padding-bottom: .2rem; border-bottom: 1px solid #d8d8d8; }
h3 { font-size: 1.05rem; margin: 1.4rem 0 .4rem; }
p, ul { margin: .5rem 0; }
li { margin: .15rem 0; }
code { font: .88em ui-monospace, "DejaVu Sans Mono", monospace; background: #f2f2f2; padding: 0 .2em;
       border-radius: 3px; overflow-wrap: anywhere; }
nav.toc { font-size: .9rem; margin: .6rem 0 1rem; padding: .4rem .7rem; background: #f7f7f7;
          border-radius: 4px; }
nav.toc ol { margin: 0; padding: 0; list-style: none; display: flex; flex-wrap: wrap; gap: .2rem 1.2rem; }
nav.toc a { color: #1d4f91; text-decoration: none; }
.table-wrap { overflow-x: auto; margin: .6rem 0 1rem; }
table { border-collapse: collapse; font-size: .84rem; }
th, td { padding: .22rem .55rem; text-align: left; vertical-align: top; border-bottom: 1px solid #e4e4e4; }
th { background: #f5f5f5; border-bottom: 2px solid #9a9a9a; white-space: nowrap; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
figure.plot { margin: 1.4rem 0 2rem; }
figure.plot h3 { margin-top: 0; }
figure.plot svg { display: block; max-width: 100%; height: auto; }
figcaption { font-size: .9rem; color: #404040; margin-top: .3rem; }
figcaption .files { color: #707070; }
@media print {
  @page { size: A4; margin: 14mm 12mm; }
  body { max-width: none; padding: 0; font-size: 9.5pt; }
  nav.toc { display: none; }
  h2, h3 { break-after: avoid; }
  figure.plot, tr, li { break-inside: avoid; }
  .table-wrap { overflow: visible; }
  table { font-size: 7pt; }
  th { white-space: normal; }
  code { background: none; padding: 0; }
  a { color: inherit; text-decoration: none; }
}
"""

_CODE = re.compile(r"`([^`]+)`")
_LINK = re.compile(r"\[([^\]]+)\]\(([^)\s]+)\)")
_STRONG = re.compile(r"\*\*(.+?)\*\*")
_EM_STAR = re.compile(r"(?<![\w*])\*(?=\S)(.+?)(?<=\S)\*(?![\w*])")
_EM_UNDERSCORE = re.compile(r"(?<![\w_])_(?=\S)(.+?)(?<=\S)_(?![\w_])")
_KEPT = re.compile("\x00(\\d+)\x00")


def inline(md: str) -> str:
    """The report's inline Markdown (code, links, bold, emphasis) as escaped HTML."""
    codes: list[str] = []

    def keep(m: re.Match) -> str:
        codes.append(m.group(1))
        return f"\x00{len(codes) - 1}\x00"

    s = html.escape(_CODE.sub(keep, md), quote=False)
    s = _LINK.sub(lambda m: f'<a href="{m.group(2).replace(chr(34), "&quot;")}">{m.group(1)}</a>', s)
    s = _STRONG.sub(r"<strong>\1</strong>", s)
    s = _EM_STAR.sub(r"<em>\1</em>", s)
    s = _EM_UNDERSCORE.sub(r"<em>\1</em>", s)
    return _KEPT.sub(lambda m: f"<code>{html.escape(codes[int(m.group(1))], quote=False)}</code>", s)


def text_html(md: str) -> str:
    """Paragraphs and ``- `` bullet lists (an item runs on over following lines until a blank line)."""
    out: list[str] = []
    para: list[str] = []
    items: list[str] | None = None

    def flush() -> None:
        nonlocal items
        if para:
            out.append(f"<p>{inline(' '.join(para))}</p>")
            para.clear()
        if items is not None:
            out.append("<ul>" + "".join(f"<li>{inline(i)}</li>" for i in items) + "</ul>")
            items = None

    for line in md.split("\n"):
        if not line.strip():
            flush()
        elif line.startswith("- "):
            if para:
                flush()
            items = (items or []) + [line[2:].strip()]
        elif items is not None:
            items[-1] += " " + line.strip()
        else:
            para.append(line.strip())
    flush()
    return "\n".join(out)


def table_html(df: pd.DataFrame | None, columns=None) -> str:
    """A table with every value rounded as in the Markdown tables; numeric columns right-aligned."""
    if df is None or df.empty:
        return "<p><em>(none)</em></p>"
    cols = [c for c in (columns or df.columns) if c in df.columns]
    numeric = {c for c in cols if pd.api.types.is_numeric_dtype(df[c]) and not pd.api.types.is_bool_dtype(df[c])}
    head = "".join(f"<th>{inline(str(c))}</th>" for c in cols)
    body = []
    for rec in df[cols].itertuples(index=False, name=None):
        cells = "".join(f'<td class="num">{inline(format_value(v))}</td>' if c in numeric
                        else f"<td>{inline(format_value(v))}</td>" for c, v in zip(cols, rec))
        body.append(f"<tr>{cells}</tr>")
    return (f'<div class="table-wrap"><table><thead><tr>{head}</tr></thead>'
            f"<tbody>{''.join(body)}</tbody></table></div>")


_BEFORE_SVG = re.compile(r"\A.*?(?=<svg\b)", re.DOTALL)
_METADATA = re.compile(r"<metadata>.*?</metadata>\s*", re.DOTALL)
_ID = re.compile(r'\bid="([^"]+)"')
_HREF = re.compile(r'((?:xlink:)?href)="#([^"]+)"')
_URL = re.compile(r"url\(#([^)]+)\)")


def inline_svg(svg: str, prefix: str, label: str) -> str:
    """matplotlib's SVG file as an element of the page: no XML prolog, no metadata, and every id (and
    reference to it) prefixed, since each figure reuses ids such as figure_1 or DejaVuSans-30."""
    svg = _METADATA.sub("", _BEFORE_SVG.sub("", svg, count=1))
    svg = _ID.sub(lambda m: f'id="{prefix}{m.group(1)}"', svg)
    svg = _HREF.sub(lambda m: f'{m.group(1)}="#{prefix}{m.group(2)}"', svg)
    svg = _URL.sub(lambda m: f"url(#{prefix}{m.group(1)})", svg)
    return svg.replace("<svg ", f'<svg role="img" aria-label="{html.escape(label)}" ', 1).strip()


def slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "section"


def render_html(doc: Document) -> str:
    """The whole page: head with the inline style, a contents line of the sections, then every block."""
    body: list[str] = []
    sections: list[tuple[str, str]] = []
    used: set[str] = set()
    figure_no = 0
    for block in doc.blocks:
        if isinstance(block, Heading):
            anchor = slug(re.sub(r"[`*_]", "", block.text))
            while anchor in used:
                anchor += "-x"
            used.add(anchor)
            if block.level == 2:
                sections.append((anchor, block.text))
            level = min(max(block.level, 1), 6)
            body.append(f'<h{level} id="{anchor}">{inline(block.text)}</h{level}>')
            if block.level == 1:
                body.append("<!--contents-->")
        elif isinstance(block, Text):
            body.append(text_html(block.md))
        elif isinstance(block, Table):
            body.append(table_html(block.df, block.columns))
        elif isinstance(block, Plot):
            figure_no += 1
            fig = block.figure
            svg = inline_svg(svg_path(fig).read_text(encoding="utf-8"), f"f{figure_no}-", fig.title)
            files = ", ".join(p.relative_to(doc.out_dir).as_posix() if p.is_relative_to(doc.out_dir) else p.name
                              for p in (png_path(fig), svg_path(fig)))
            body.append(f'<figure class="plot" id="fig-{slug(fig.name)}"><h3>{inline(fig.title)}</h3>\n{svg}\n'
                        f'<figcaption>{inline(fig.caption)} <span class="files">({html.escape(files)})</span>'
                        "</figcaption></figure>")
    toc = ('<nav class="toc"><ol>' + "".join(f'<li><a href="#{a}">{inline(t)}</a></li>' for a, t in sections)
           + "</ol></nav>") if sections else ""
    page = "\n".join(body).replace("<!--contents-->", toc, 1)
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f'<meta http-equiv="Content-Security-Policy" content="{CSP}">\n'
            '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
            '<meta name="generator" content="asp-dist stats">\n'
            f'<meta name="figure-count" content="{figure_no}">\n'
            f"<title>{html.escape(doc.title)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n<main>\n"
            f"{page}\n</main>\n</body>\n</html>\n")


def write_html(doc: Document) -> Path:
    """report.html beside report.md in the document's output directory."""
    return write_atomic(doc.out_dir / "report.html", render_html(doc))
