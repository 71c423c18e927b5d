"""A checkpoint callback for tests: what run_cell / run_pack hand to `checkpoint`, kept as bytes."""

from __future__ import annotations

import io
from typing import Any, Callable

import torch


def checkpoint_sink() -> tuple[list[bytes], Callable[[Any], None]]:
    """A list of saved checkpoints and the callback that fills it, through bytes as on disk."""
    saved: list[bytes] = []

    def keep(state) -> None:
        buf = io.BytesIO()
        torch.save(state, buf)
        saved.append(buf.getvalue())

    return saved, keep
