"""report.html, the self-contained report: what it holds, checked in the file and in a real browser.

The browser check drives Debian's Chromium (headless) over the DevTools protocol on a pipe
(``--remote-debugging-pipe``: NUL-separated JSON on file descriptors 3 and 4, so no port, no
websocket and nothing outside the standard library). It records every console message of level
error, every uncaught exception and every browser log entry of level error (a blocked or failed
load among them), then measures each figure's <svg> as laid out and asks for a PDF, as printing
would. It is skipped, saying why, where no chromium is installed (scripts/install.sh installs it
as root where apt-get is available).
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import re
import select
import shutil
import subprocess
import sys
import time
from html.parser import HTMLParser
from pathlib import Path

import pytest

from asp_dist.cli import main

REPO = Path(__file__).resolve().parents[1]
SWEEP = REPO / "results" / "examples" / "confirm-levers"  # a committed confirmatory sweep, with learning curves


def chromium_binary() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    """The stats job on a copy of a committed sweep (never written into results/), all formats."""
    sweep = tmp_path_factory.mktemp("html") / SWEEP.name
    shutil.copytree(SWEEP, sweep)
    assert main(["stats", str(sweep), "--bootstrap", "200", "--quiet"]) == 0
    return sweep / "report.html"


class Page(HTMLParser):
    """What the static checks need from the page: ids, tags, references, figures, table and heading text."""

    def __init__(self) -> None:
        super().__init__()
        self.ids: list[str] = []
        self.tags: list[str] = []
        self.refs: list[str] = []
        self.figures = self.svgs_in_figures = self.tables = 0
        self.headings: list[str] = []
        self.meta: dict[str, str] = {}
        self._in_figure = self._heading = 0
        self._text: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        if "id" in a:
            self.ids.append(a["id"])
        self.refs += [a[k] for k in ("src", "href", "xlink:href") if a.get(k)]
        if tag == "meta" and "name" in a:
            self.meta[a["name"]] = a.get("content", "")
        if tag == "figure":
            self.figures += 1
            self._in_figure = 1
        if tag == "svg" and self._in_figure:
            self.svgs_in_figures += 1
        if tag == "table":
            self.tables += 1
        if re.fullmatch(r"h[1-3]", tag):
            self._heading, self._text = 1, []

    def handle_endtag(self, tag):
        if tag == "figure":
            self._in_figure = 0
        if re.fullmatch(r"h[1-3]", tag) and self._heading:
            self.headings.append("".join(self._text).strip())
            self._heading = 0

    def handle_data(self, data):
        if self._heading:
            self._text.append(data)


def stated_figure_count(text: str) -> int:
    """The number of figures the report says it holds ('12 figures, each also …' or 'No figures')."""
    m = re.search(r"(\d+) figures?, each also as PNG and SVG", text)
    return int(m.group(1)) if m else 0 if "No figures" in text else -1


@pytest.mark.xdist_group("report-html")  # shares a module fixture (one stats job): one worker
def test_report_html_is_one_self_contained_file_with_the_content_of_report_md(report):
    html = report.read_text(encoding="utf-8")
    md = report.with_name("report.md").read_text(encoding="utf-8")
    page = Page()
    page.feed(html)
    svg_files = sorted((report.parent / "figures").glob("*.svg"))
    assert len(svg_files) >= 8  # the paper's figures, learning curves and the rliable view
    # every figure inline, as many as the report says, and as many as figures/ holds
    assert page.figures == page.svgs_in_figures == len(svg_files) == stated_figure_count(md)
    assert int(page.meta["figure-count"]) == len(svg_files) == stated_figure_count(html)
    # self-contained: no script, no stylesheet or image to fetch, only links inside the page
    assert "script" not in page.tags and "img" not in page.tags and "link" not in page.tags
    assert all(ref.startswith("#") for ref in page.refs), [r for r in page.refs if not r.startswith("#")][:5]
    assert "default-src 'none'" in html
    # the ids of the inlined figures (figure_1, DejaVuSans-30, …) are prefixed per figure: unique in the page
    assert len(page.ids) == len(set(page.ids)) > 100
    # the same document as report.md: every heading and every table, the verdicts, the command and inputs
    md_headings = [re.sub(r"[`*]", "", line.lstrip("#").strip()) for line in md.splitlines()
                   if re.match(r"#{1,3} ", line)]
    assert page.headings == md_headings
    assert page.tables == sum(1 for line in md.splitlines() if line.startswith("|---"))
    for needle in ("At a glance: did ASP beat OSP and PC?", "ASP beat PC and OSP", "The rliable view",
                   "P(ASP &gt; OSP)", "Command: <code>asp-dist stats", "Inputs: <code>", "@media print"):
        assert needle in html, needle


# ---- the browser ---------------------------------------------------------------------------------------

class Chromium:
    """Headless Chromium driven over --remote-debugging-pipe (DevTools protocol, JSON + NUL on fds 3/4)."""

    def __init__(self, binary: str, profile: Path, timeout: float = 60.0):
        # the child's ends, moved above fd 9 so that placing them on 3 and 4 below cannot clobber one another
        commands_r, self._commands = os.pipe()
        self._replies, replies_w = os.pipe()
        commands_r, replies_w = (self._above_nine(fd) for fd in (commands_r, replies_w))
        args = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
                "--disable-extensions", "--remote-debugging-pipe", f"--user-data-dir={profile}",
                "--window-size=1280,900", "about:blank"]
        # the child reads commands on fd 3 and writes replies on fd 4: a tiny exec wrapper puts them there
        place = ("import os, sys; os.dup2(int(sys.argv[1]), 3); os.dup2(int(sys.argv[2]), 4); "
                 "os.execv(sys.argv[3], sys.argv[3:])")
        self.proc = subprocess.Popen([sys.executable, "-c", place, str(commands_r), str(replies_w), binary, *args],
                                     pass_fds=(commands_r, replies_w), stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        os.close(commands_r)
        os.close(replies_w)
        self.timeout, self._buf, self._id, self.events = timeout, b"", 0, []

    @staticmethod
    def _above_nine(fd: int) -> int:
        high = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
        os.close(fd)
        return high

    def _next(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._replies], [], [], left)[0]:
                raise TimeoutError("chromium did not answer in time")
            chunk = os.read(self._replies, 1 << 20)
            if not chunk:
                raise EOFError("chromium closed the pipe")
            self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        return json.loads(raw)

    def call(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}} | ({"sessionId": session} if session else {})
        os.write(self._commands, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        while True:
            reply = self._next(deadline)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)

    def wait_for(self, method: str) -> dict:
        deadline = time.monotonic() + self.timeout
        for i, event in enumerate(self.events):
            if event.get("method") == method:
                return self.events.pop(i)
        while True:
            event = self._next(deadline)
            if event.get("method") == method:
                return event
            self.events.append(event)

    def close(self) -> None:
        try:
            self.call("Browser.close")
        except (EOFError, TimeoutError, RuntimeError, OSError):
            pass
        try:
            self.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._commands, self._replies):
            os.close(fd)

    def errors(self) -> list[str]:
        """Console errors, uncaught exceptions and browser log errors seen so far."""
        out = []
        for e in self.events:
            p = e.get("params", {})
            if e.get("method") == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                out.append("console: " + " ".join(str(a.get("value", a.get("description"))) for a in p["args"]))
            elif e.get("method") == "Runtime.exceptionThrown":
                out.append("exception: " + json.dumps(p.get("exceptionDetails", {}))[:300])
            elif e.get("method") == "Log.entryAdded" and p["entry"]["level"] == "error":
                out.append(f"log: {p['entry']['text']} {p['entry'].get('url', '')}")
        return out


MEASURE = """JSON.stringify({
  figures: [...document.querySelectorAll('figure.plot')].map(f => {
    const s = f.querySelector('svg'), box = s.getBBox(), r = s.getBoundingClientRect();
    return {id: f.id, bbox: [box.width, box.height], shown: [r.width, r.height],
            drawn: s.querySelectorAll('path, use').length};
  }),
  text: document.body.innerText,
  resources: performance.getEntriesByType('resource').map(e => e.name),
  width: document.documentElement.scrollWidth
})"""


@pytest.mark.skipif(chromium_binary() is None,
                    reason="no chromium on PATH (Debian: apt-get install chromium; scripts/install.sh does it as root)")
@pytest.mark.xdist_group("report-html")  # shares a module fixture (one stats job): one worker
def test_report_html_loads_in_headless_chromium_without_errors_and_every_figure_renders(report, tmp_path):
    browser = Chromium(chromium_binary(), tmp_path / "profile")
    try:
        target = browser.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = browser.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            browser.call(f"{domain}.enable", session=session)
        browser.call("Page.navigate", {"url": report.as_uri()}, session)
        browser.wait_for("Page.loadEventFired")
        seen = json.loads(browser.call("Runtime.evaluate", {"expression": MEASURE, "returnByValue": True},
                                       session)["result"]["value"])
        pdf = base64.b64decode(browser.call("Page.printToPDF", {"preferCSSPageSize": True}, session)["data"])
        errors = browser.errors()
    finally:
        browser.close()
    assert errors == []
    assert seen["resources"] == []  # nothing fetched: the page is the file
    figures = seen["figures"]
    assert len(figures) == stated_figure_count(seen["text"]) == len(list((report.parent / "figures").glob("*.svg")))
    for fig in figures:
        assert min(fig["bbox"]) > 0 and min(fig["shown"]) > 0 and fig["drawn"] > 10, fig
        assert fig["shown"][0] <= 1280, fig  # scaled into the page, not wider than the window
    assert pdf.startswith(b"%PDF") and pdf.count(b"/Type /Page") >= 5  # printable, several pages
