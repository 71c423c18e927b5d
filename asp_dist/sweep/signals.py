"""SIGTERM handled as Ctrl-C from a sweep command's first line on, so that a sweep stopped by a scheduler
(Slurm, systemd, `kill`) stops as an interrupted one does: Tune saves its experiment, the lock is released,
Ray's processes end, and `resume` continues. No Ray import.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator

interrupted_by: int | None = None  # the last signal that interrupted a sweep (SIGTERM); None for Ctrl-C


def _sigterm(signum, frame) -> None:
    """SIGTERM is Ctrl-C: while a Tune run goes on, Tune's SIGINT handler (a graceful stop that saves the
    experiment; a second signal interrupts at once), else KeyboardInterrupt."""
    global interrupted_by
    interrupted_by = signum
    handler = signal.getsignal(signal.SIGINT)
    if callable(handler) and handler is not signal.default_int_handler and not getattr(handler, "asp_interrupt", False):
        handler(signal.SIGINT, frame)  # Tune's
        return
    raise KeyboardInterrupt  # also where SIGINT is ignored (a background job): SIGTERM must still stop the sweep


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within: SIGTERM stops the sweep as Ctrl-C does, at any stage, with the same cleanup (the lock,
    Ray's processes). Only the main thread can own signals; elsewhere, and when already set, a no-op."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) is _sigterm:
        yield
        return
    global interrupted_by
    interrupted_by = None
    previous = signal.signal(signal.SIGTERM, _sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
