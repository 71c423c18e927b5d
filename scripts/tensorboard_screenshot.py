"""The screenshot of docs/tracking.md: TensorBoard's scalars page while `asp-dist sweep smoke --logger tensorboard`
runs, taken with Debian's headless Chromium.

    python scripts/tensorboard_screenshot.py docs/figures/tensorboard-smoke.png

Starts the sweep into a fresh results directory and `tensorboard --logdir` on loopback beside it, waits until
some cells have finished and others are still running, then loads the scalars page (filtered to a few tags)
and saves it. Everything it starts is stopped at the end; the sweep is left to finish first.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "docs/figures/tensorboard-smoke.png").absolute()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("needs Debian's chromium (apt-get install chromium)")
    tmp = Path(tempfile.mkdtemp(prefix="tb-shot-"))
    logdir = tmp / "trackers" / "tensorboard"  # --logger-dir: the sweep's own directory must not exist before it
    env = dict(os.environ, OMP_NUM_THREADS="1")
    sweep = subprocess.Popen([sys.executable, "-m", "asp_dist.cli", "sweep", "smoke", "--results", str(tmp / "results"),
                              "--logger", "tensorboard", "--logger-dir", str(tmp / "trackers")], env=env, stdout=subprocess.DEVNULL,
                             stderr=open(tmp / "sweep.err", "w"), start_new_session=True)
    port = free_port()
    logdir.mkdir(parents=True, exist_ok=True)
    board = subprocess.Popen([str(Path(sys.executable).with_name("tensorboard")), "--logdir", str(logdir), "--host",
                              "127.0.0.1", "--port", str(port), "--load_fast", "false", "--reload_interval", "1"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:  # some cells done, the sweep still running
            cells = list((tmp / "results" / "smoke" / "cells").rglob("*.parquet"))
            if len(cells) >= 8 or sweep.poll() is not None:
                break
            time.sleep(0.2)
        if sweep.poll() is not None:
            raise SystemExit(f"the sweep ended before the screenshot: {(tmp / 'sweep.err').read_text()[-2000:]}")
        print(f"{len(cells)} of 18 cells done, the sweep running")
        time.sleep(3)  # TensorBoard reloads every second
        url = f"http://127.0.0.1:{port}/?darkMode=false#scalars&tagFilter=loss%2Ftotal%7Cprobe%2Fmixed%24"
        urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30).read()
        subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                        "--window-size=1400,1000", "--virtual-time-budget=15000", f"--screenshot={out}", url],
                       check=True, capture_output=True, timeout=120)
        print(f"wrote {out}")
        sweep.wait(timeout=300)
    finally:
        for proc in (board, sweep):
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
