import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import pytest  # noqa: E402
import torch  # noqa: E402
from budgets import tiny_spec  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture
def tiny():
    """tiny(domain, **changes): a CellSpec of `domain` with every budget shrunk (tests/budgets.py)."""
    return tiny_spec


@pytest.fixture
def tiny_signaling():
    """A signaling cell shrunk to run in a fraction of a second."""
    return tiny_spec("signaling", method="asp", paired=2, trial=0)
