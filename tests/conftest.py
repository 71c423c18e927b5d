import getpass
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
# Under pytest-xdist each worker's sweeps get an embedded Ray temp dir of their own (the CLI's default,
# ASP_DIST_RAY_TEMP_DIR): two Rays sharing one would share its session_latest link and pruning.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("ASP_DIST_RAY_TEMP_DIR", f"/tmp/asp-ray-{getpass.getuser()}-{os.environ['PYTEST_XDIST_WORKER']}")

import pytest  # noqa: E402
import torch  # noqa: E402
from budgets import tiny_spec  # noqa: E402

torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    """Slow tests first (stable otherwise): with `-n 2` the longest ones start early and the short ones fill
    the gaps, instead of two long sweeps meeting at the end (longest-processing-time-first scheduling)."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture(scope="session", autouse=True)
def expected_rows_shared_by_workers(tmp_path_factory):
    """Under xdist, the rows of uninterrupted runs (harness.expected_rows) are computed by one worker and read by
    the others, through the run's common temp dir (pytest keeps the last three)."""
    import harness

    if os.environ.get("PYTEST_XDIST_WORKER"):
        harness.SHARED_EXPECTED_DIR = tmp_path_factory.getbasetemp().parent / "expected-rows"
    yield
    harness.SHARED_EXPECTED_DIR = None


@pytest.fixture
def tiny():
    """tiny(domain, **changes): a CellSpec of `domain` with every budget shrunk (tests/budgets.py)."""
    return tiny_spec


@pytest.fixture
def tiny_signaling():
    """A signaling cell shrunk to run in a fraction of a second."""
    return tiny_spec("signaling", method="asp", paired=2, trial=0)
