import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture
def tiny_signaling():
    """A signaling cell shrunk to run in a fraction of a second."""
    from asp_dist.spec import CellSpec

    return CellSpec(domain="signaling", method="asp", paired=2, trial=0, train_steps=60, batch_size=16,
                    unpaired_size=128)
