"""Training without importing torch._dynamo, unless something else does (a plugin calling torch.compile).

torch.optim imports torch._dynamo -- sympy, the fx and export stacks: ≈ 2 CPU-s on the 2-core VM of
docs/performance.md, as much as torch itself -- at the first call of two kinds of wrapper, only to keep the
compiler out of the optimizer:

- ``torch._disable_dynamo`` around ``Optimizer.add_param_group`` (every optimizer's ``__init__`` calls it),
  ``zero_grad``, ``state_dict`` and ``load_state_dict``: "never compile this";
- ``_use_grad_for_differentiable`` around each optimizer's ``step``: grad mode set from ``differentiable``,
  and a ``torch._dynamo.graph_break()`` before and after.

Outside compilation both marks do nothing, and nothing compiles without torch._dynamo loaded; yet every Ray
worker, every `asp-dist cell` and every replay paid the import. ``keep_dynamo_unloaded`` (called where a base
or a unit starts training: bases.train_accepted_base, pipeline.run_unit) makes both kinds call
the method itself while torch._dynamo is not loaded and hand over to torch's own wrapping once anything has
loaded it (a plugin calling torch.compile): the first kind through the cache torch's wrapper looks in
(``fn.__dynamo_disable``, filled as torch would fill it at hand-over), the second by a ``step`` of the same
grad-mode rule in place of torch's wrapper. Each is applied only where torch's wrapper has the shape this
module knows (checked on its code, not assumed); any other torch pays the import as before.
tests/test_torch_runtime.py holds it to torch's own steps, bit for bit, before and after dynamo loads."""

from __future__ import annotations

import functools
import sys
from typing import Any, Callable, Iterator

import torch
import torch._compile
import torch.optim
from torch.optim import optimizer

CACHE_ATTRIBUTE = "__dynamo_disable"  # where torch._compile._disable_dynamo's wrapper caches its disabled function
COVERED = "_steps_directly_until_dynamo_loads"  # marks a step this module put in place of torch's wrapper


def keep_dynamo_unloaded() -> int:
    """Make torch's optimizers load torch._dynamo only once something else has (idempotent, ≈ 0.1 ms). Returns
    how many methods are covered (0: torch's wrappers are not the known shape; nothing was changed)."""
    covered = 0
    for fn, recursive in dynamo_disabled_methods():
        if getattr(fn, CACHE_ATTRIBUTE, None) is None:
            setattr(fn, CACHE_ATTRIBUTE, _called_directly_until_dynamo_loads(fn, recursive))
        covered += 1
    for cls, step in grad_mode_steps():
        if not getattr(step, COVERED, False):
            if getattr(vars(cls)["step"], "hooked", False):
                continue  # an optimizer of this class exists already: its hooks hold torch's step (pays the import)
            setattr(cls, "step", _stepped_directly_until_dynamo_loads(step))
        covered += 1
    return covered


# ---- torch._disable_dynamo ------------------------------------------------------------------------
def dynamo_disabled_methods() -> Iterator[tuple[Callable, bool]]:
    """(method, recursive) for each method of an optimizer class wrapped by torch._disable_dynamo."""
    wrapper = torch._compile._disable_dynamo(lambda: None).__code__
    if CACHE_ATTRIBUTE not in wrapper.co_consts or set(wrapper.co_freevars) != {"fn", "recursive"}:
        return  # another torch: its wrapper caches elsewhere, or not at all
    seen: set[int] = set()
    for cls in _subclasses(torch.optim.Optimizer):
        for value in vars(cls).values():
            if getattr(value, "__code__", None) is wrapper and id(value) not in seen:
                seen.add(id(value))
                cells = dict(zip(wrapper.co_freevars, (c.cell_contents for c in value.__closure__)))
                yield cells["fn"], bool(cells["recursive"])


def _called_directly_until_dynamo_loads(fn: Callable, recursive: bool) -> Callable:
    def call(*args: Any, **kwargs: Any) -> Any:
        if "torch._dynamo" not in sys.modules:
            return fn(*args, **kwargs)
        import torch._dynamo

        disabled = torch._dynamo.disable(fn, recursive, wrapping=False)  # what torch's wrapper builds and caches
        setattr(fn, CACHE_ATTRIBUTE, disabled)
        return disabled(*args, **kwargs)

    return call


# ---- _use_grad_for_differentiable -----------------------------------------------------------------
def grad_mode_steps() -> Iterator[tuple[type, Callable]]:
    """(class, its own step) for each optimizer class whose step is torch's grad-mode wrapper or this module's
    stand-in for it, seen through the hooks that the class's first __init__ wraps around it."""
    wrapper = optimizer._use_grad_for_differentiable(lambda: None).__code__
    if not ({"graph_break", "set_grad_enabled", "is_grad_enabled", "defaults"} <= set(wrapper.co_names)
            and "differentiable" in wrapper.co_consts):
        return  # another torch: its grad-mode rule may differ from the one below
    for cls in _subclasses(torch.optim.Optimizer):
        step = vars(cls).get("step")
        if getattr(step, "hooked", False):
            step = step.__wrapped__  # functools.wraps in Optimizer.profile_hook_step
        if getattr(step, "__code__", None) is wrapper or getattr(step, COVERED, False):
            yield cls, step


def _stepped_directly_until_dynamo_loads(torch_step: Callable) -> Callable:
    step = torch_step.__wrapped__  # functools.update_wrapper in torch's wrapper

    @functools.wraps(step)
    def _use_grad(self, *args: Any, **kwargs: Any) -> Any:
        if "torch._dynamo" in sys.modules:
            return torch_step(self, *args, **kwargs)
        with torch.set_grad_enabled(self.defaults["differentiable"]):  # torch's rule, without the graph breaks
            return step(self, *args, **kwargs)

    setattr(_use_grad, COVERED, True)
    return _use_grad


def _subclasses(cls: type) -> Iterator[type]:
    yield cls
    for sub in cls.__subclasses__():
        yield from _subclasses(sub)
