"""Methods: which terms of L = w_sp·L_sp + λ0·L_p + λ1·L_u a cell trains with, registered as plugins.

PC, OSP and ASP are the paper's three; each is a `Method` registered in the ``asp_dist.methods``
entry-point group (pyproject.toml), as a package of your own registers another (docs/extending.md). A
method is a choice of terms; their weights are the spec's knobs (λ0 = lambda_paired, λ1 =
lambda_unpaired), so every trainer — the reference one and the packed ones, which compose the same
weights — trains every registered method, and a new one changes no core file.

An *arm* ``<method>@<label>`` (``osp@default``) trains exactly as its method and is named apart
everywhere else (cell ids, rows, the store, a space's ``[methods."osp@default"]`` table), so one sweep
can run a method at two settings side by side. The arm labelled ``default`` is the method's *companion*:
the stats job compares it with its method (default_vs_tuned) and leaves it out of the main tests.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from asp_dist.errors import SpecError
from asp_dist.plugins import Registry

GROUP = "asp_dist.methods"


@dataclass(frozen=True)
class Method:
    """name         as in a spec and a row (``method = "asp"``)
    doc          one line for `asp-dist fields`
    self_play    train on self-play, L_sp (weight 1)
    paired       train on the paired set, L_p (weight λ0; none when the cell has no paired examples)
    adversarial  train against discriminators on unpaired base outputs, L_u (weight λ1, with its schedule).
                 A method without it records λ1 = 0 and a constant schedule, so its rows compare across
                 settings of the adversary."""

    name: str
    doc: str
    self_play: bool
    paired: bool = True
    adversarial: bool = False

    def problems(self, name: str) -> list[str]:
        out = []
        if "@" in name:
            out.append(f"its name {name!r} holds '@', which marks an arm (method@label); rename it")
        if self.name != name:
            out.append(f"it is registered as {name!r} but its Method.name is {self.name!r}")
        if not (self.self_play or self.paired or self.adversarial):
            out.append("it trains on no term (self_play, paired and adversarial all false)")
        if not isinstance(self.doc, str) or not self.doc.strip():
            out.append("it needs a one-line doc")
        return out


PC = Method("pc", "policy cloning: the paired loss only, no self-play", self_play=False)
OSP = Method("osp", "self-play + the paired loss, interleaved in every update", self_play=True)
ASP = Method("asp", "OSP + adversaries matching the base's unpaired outputs (λ1)", self_play=True, adversarial=True)


def _check(method: object, name: str) -> list[str]:
    if not isinstance(method, Method):
        return [f"it is a {type(method).__name__}, not an asp_dist.method_registry.Method"]
    return method.problems(name)


METHODS: Registry[Method] = Registry(GROUP, "method", lambda obj: obj, _check)
PAPER_ORDER = ("pc", "osp", "asp")  # how tables and figures order the paper's methods; others follow by name


ARM_LABEL = re.compile(r"[a-z0-9_-]{1,32}")
COMPANION_LABEL = "default"  # the arm that runs a method at its knobs' defaults beside its tuned setting


def split_arm(name: str) -> tuple[str, str | None]:
    """``"osp@default"`` -> ``("osp", "default")``; ``"osp"`` -> ``("osp", None)``. The label is not checked."""
    method, at, label = name.partition("@")
    return (method, label) if at else (name, None)


def arm_problem(name: str) -> str | None:
    """What is wrong with the label of arm `name` (one line), or None; the method part is not looked up."""
    label = split_arm(name)[1]
    if label is not None and not ARM_LABEL.fullmatch(label):
        return (f"method {name!r}: the label after '@' must be 1-32 of a-z, 0-9, _ and -, "
                f"got {label!r}")
    return None


def is_companion(method: str) -> bool:
    """Whether `method` is the ``@default`` arm of a method."""
    return split_arm(method)[1] == COMPANION_LABEL


def get_method(name: str) -> Method:
    """The registered method, or of an arm (``osp@default``) its method's."""
    problem = arm_problem(name)
    if problem is not None:
        raise SpecError(problem)
    return METHODS.lookup(split_arm(name)[0])


def method_order() -> list[str]:
    """Every registered method, the paper's three first."""
    return [m for m in PAPER_ORDER if m in METHODS] + sorted(m for m in METHODS if m not in PAPER_ORDER)
