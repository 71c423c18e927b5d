"""What asp_dist/sweep/worker_start.py changes about Tune's trainables, and when it leaves Tune's way alone.
(On a real sweep: tests/test_sweep.py::test_ray_workers_start_lean.)"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from asp_dist.sweep import worker_start

class_cache = pytest.importorskip("ray.tune.execution.class_cache")


class Trainable:  # stands for Tune's generated trainable class
    pass


def runtime_env(actor_cls):
    return actor_cls._default_options.get("runtime_env")


def test_trainables_inherit_tunes_variables_instead_of_a_runtime_env(monkeypatch):
    monkeypatch.delenv("PL_DISABLE_FORK", raising=False)
    monkeypatch.setenv("AWS_SESSION_TOKEN", "at-start")
    tunes = {"PL_DISABLE_FORK": "1", "AWS_SESSION_TOKEN": "at-start"}
    assert worker_start.tune_env_vars() == tunes | {k: os.environ[k] for k in class_cache.ENV_VARS_TO_PROPAGATE
                                                    if k in os.environ and k != "AWS_SESSION_TOKEN"}
    tunes_get = class_cache._ActorClassCache.get
    # Outside the embedded Ray's start, Tune's own way: its runtime env.
    assert runtime_env(class_cache._ActorClassCache().get(Trainable))["env_vars"].items() >= tunes.items()
    with worker_start.inherited_tune_env():
        assert os.environ["PL_DISABLE_FORK"] == "1"  # what the raylet, and every worker it starts, inherits
        with worker_start.trainables_without_runtime_env():
            cache = class_cache._ActorClassCache()
            assert runtime_env(cache.get(Trainable)) is None and cache.get(Trainable) is cache.get(Trainable)
            # A variable changed after Ray started is not in the workers' environment: Tune's runtime env again.
            monkeypatch.setenv("AWS_SESSION_TOKEN", "later")
            env_vars = runtime_env(class_cache._ActorClassCache().get(Trainable))["env_vars"]
            assert env_vars["AWS_SESSION_TOKEN"] == "later"
        assert class_cache._ActorClassCache.get is tunes_get  # put back
    assert "PL_DISABLE_FORK" not in os.environ  # put back as it was
    with worker_start.trainables_without_runtime_env():  # outside the embedded Ray: Tune's runtime env
        assert runtime_env(class_cache._ActorClassCache().get(Trainable)) is not None


def test_a_users_own_value_is_kept_and_then_tunes_runtime_env_sets_its_own(monkeypatch):
    monkeypatch.setenv("PL_DISABLE_FORK", "0")
    with worker_start.inherited_tune_env(), worker_start.trainables_without_runtime_env():
        assert os.environ["PL_DISABLE_FORK"] == "0"
        assert runtime_env(class_cache._ActorClassCache().get(Trainable))["env_vars"]["PL_DISABLE_FORK"] == "1"
    assert os.environ["PL_DISABLE_FORK"] == "0"


def test_a_trainable_imports_ipython_only_if_it_is_loaded_already():
    """In a fresh interpreter, as a Ray worker unpickling train_cell: Tune's disable_ipython() no longer imports
    IPython, and once IPython is loaded it clears the shell as before."""
    pytest.importorskip("IPython")
    script = textwrap.dedent("""
        import sys
        import asp_dist.sweep.trial  # noqa: F401  (what a worker imports to unpickle the trial function)
        from ray.tune.trainable import trainable
        trainable.disable_ipython()
        print("IPython" in sys.modules)
        from IPython.core.interactiveshell import InteractiveShell
        cleared = []
        InteractiveShell.clear_instance = classmethod(lambda cls: cleared.append(cls))
        trainable.disable_ipython()
        print(len(cleared))
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.stdout.split() == ["False", "1"], run.stderr[-2000:]
