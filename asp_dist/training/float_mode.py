"""Training runs with denormal floats flushed to zero (the CPU's FTZ/DAZ modes), as TensorFlow and XLA run CPU
kernels by default.

A float32 below 1.2e-38 (a denormal) costs x86 cores a microcode assist per operation. Adam's moving averages
of a weight whose gradient is exactly zero (a ReLU unit that stopped firing) decay by β1 = 0.9 per update and
pass through that range after about 700 updates: a paper-size VAE base update went from 3.9 to 5.6 ms CPU from
then on (docs/decisions/0056-vae-hand-derived-gradients.md), ≈ 40 % of the bases' time. Flushed, such a value
is zero a few updates early; a value that small moves no weight (its Adam step is ~1e-31). A particle, lever or
VAE cell trained either way gave the same evaluation metrics.

The mode belongs to the thread (a Ray trial trains in a thread of its own), so it is set where training starts
(pipeline.run_unit's loop, bases.train_accepted_base) and reset when it ends."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def denormals_flushed() -> Iterator[bool]:
    """Flush denormals on this thread inside the block (yields whether the CPU supports it); off again after
    (torch cannot tell whether it was on before: a caller that flushes them itself sets it again)."""
    supported = torch.set_flush_denormal(True)
    try:
        yield supported
    finally:
        if supported:
            torch.set_flush_denormal(False)
