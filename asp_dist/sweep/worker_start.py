"""A trainable worker of the embedded Ray starts with what it needs and nothing more.

Every Ray worker that trains cells is a fresh Python process that imports Ray, Tune and torch (≈ 5 CPU-s)
before its first cell. Two more costs came with Tune and do nothing for a sweep; both are skipped here:

- **Tune's runtime env.** Tune registers each trainable with a runtime env that only sets environment
  variables (``ray.tune.execution.class_cache``: ``PL_DISABLE_FORK=1`` and the driver's ``AWS_*`` and Ray
  Train switches). A worker with a non-empty runtime env starts through Ray's ``setup_worker.py``, a Python
  process that imports Ray only to exec the real worker (≈ 0.7 CPU-s a worker). On the embedded Ray the
  workers are children of this process's raylet and inherit its environment, so ``inherited_tune_env``
  puts the variables there before ``ray.init`` and ``trainables_without_runtime_env`` registers the
  trainable without the runtime env whenever every variable Tune would set already has that value in the
  workers' environment (else Tune's way, e.g. AWS keys set after Ray started). A joined cluster's workers
  inherit their node's environment, not the driver's: there Tune's runtime env stays.
- **IPython.** ``Trainable.__init__`` calls ``disable_ipython()``, which imports IPython (≈ 0.5 CPU-s
  where it is installed) to clear a shell instance that a Ray worker never has. ``skip_ipython_import``
  calls Tune's function only when IPython is already loaded, where it does what it always did.

Both patch a Ray internal by name and do nothing if a Ray release renames it (the cost comes back, nothing
breaks). tests/test_worker_start.py checks each rule and its fallbacks; tests/test_sweep.py's
test_ray_workers_start_lean checks a real sweep's processes and their environments. (The head's unused
daemons: ray_host._head_without_unused_daemons.)
"""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from typing import Iterator

# What the embedded Ray's workers inherit from this process (set by inherited_tune_env at ray.init).
_INHERITED: dict[str, str] = {}


def tune_env_vars() -> dict[str, str] | None:
    """The environment variables Tune's runtime env would give a trainable now (None: not this Ray's layout)."""
    try:
        from ray.tune.execution import class_cache
    except ImportError:
        return None
    defaults = getattr(class_cache, "DEFAULT_ENV_VARS", None)
    propagated = getattr(class_cache, "ENV_VARS_TO_PROPAGATE", None)
    if not isinstance(defaults, dict) or propagated is None:
        return None
    return {**defaults, **{k: os.environ[k] for k in propagated if k in os.environ}}


@contextmanager
def inherited_tune_env() -> Iterator[None]:
    """Around the embedded ``ray.init``: Tune's default variables in this process's environment (a value the
    user set is kept), so that the raylet and every worker it starts have them; put back afterwards."""
    wanted = tune_env_vars() or {}
    added = [k for k in wanted if k not in os.environ]
    for key in added:
        os.environ[key] = wanted[key]
    _INHERITED.clear()
    _INHERITED.update({k: os.environ[k] for k in wanted})
    try:
        yield
    finally:
        _INHERITED.clear()
        for key in added:
            os.environ.pop(key, None)


@contextmanager
def trainables_without_runtime_env() -> Iterator[None]:
    """While Tune runs on the embedded Ray: trainables registered without Tune's env-vars-only runtime env
    when the workers inherit every one of those variables already (no setup_worker.py process a worker)."""
    import ray
    from ray.tune.execution import class_cache

    cache_cls = getattr(class_cache, "_ActorClassCache", None)
    original = getattr(cache_cls, "get", None)
    if original is None or tune_env_vars() is None:
        yield
        return

    def get(self, trainable_cls):
        wanted = tune_env_vars() or {}
        if not _INHERITED or not wanted.items() <= _INHERITED.items():
            return original(self, trainable_cls)
        cache = self._cache
        if trainable_cls not in cache:
            cache[trainable_cls] = ray.remote(trainable_cls)
        return cache[trainable_cls]

    cache_cls.get = get
    try:
        yield
    finally:
        cache_cls.get = original


def skip_ipython_import() -> None:
    """Tune's trainables call ``disable_ipython()`` when they start; it imports IPython to clear a shell that
    exists only if IPython is loaded. Called where a worker unpickles the trial function (before the
    trainable starts); the check is the same wherever it runs."""
    trainable = sys.modules.get("ray.tune.trainable.trainable")
    original = getattr(trainable, "disable_ipython", None)
    if original is None or getattr(original, "asp_dist_guard", False):
        return

    def disable_ipython() -> None:
        if "IPython" in sys.modules:
            original()

    disable_ipython.asp_dist_guard = True
    trainable.disable_ipython = disable_ipython
