"""The Domain contract: what every domain provides, and a checker that tests run on each one.

A domain never knows which method trains it: it supplies the pieces (base training, paired
and unpaired data, the self-play loss, the paired loss, the convention outputs watched by the
adversaries, evaluation) and `asp_dist.training` composes them with the method's loss weights.

Randomness: every random choice goes through an explicit ``torch.Generator`` passed in, so
that a seed reproduces a domain's output bit for bit and checkpoints can capture RNG state.

A domain is a package of two halves (asp_dist/domains/<name>/): its ``__init__`` is the *card*,
the Domain subclass with everything a domain describes (knobs and defaults, metrics, paper facts,
validation, size bounds), which imports no torch; its ``game`` module holds the torch half
(networks, data, losses, self-play, evaluation), imported the first time a method needs it
(`Domain.game`). So `asp-dist --help`, `fields`, `status` and `query` never import torch. This
module too keeps torch to annotations and to the bodies of the functions that use it.
"""

from __future__ import annotations

import importlib
import importlib.util
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any, Callable, Protocol

from asp_dist.errors import SpecError
from asp_dist.knobs import Knob

if TYPE_CHECKING:
    import torch
    from torch import nn

ProgressFn = Callable[[str, int, int, dict], None]
"""progress(phase, done, total, info): called now and then by long loops."""

Tensors = dict[str, "torch.Tensor"]


class CellSpec(Protocol):
    """A resolved cell spec as a domain reads it: asp_dist.spec.CellSpec, every common knob and every
    registered domain's knob by attribute. Described here rather than imported: spec.py builds CellSpec
    from the registered domains' knobs, so the contract stays below it, with no import cycle, not even
    through annotations (tests/test_architecture.py). A domain's own modules import the real one."""

    domain: str
    method: str
    paired: int
    trial: int

    def __getattr__(self, name: str) -> Any: ...


@dataclass(frozen=True)
class MetricInfo:
    higher_is_better: bool
    doc: str


@dataclass(frozen=True)
class PaperFacts:
    """What the paper says about a domain; the stats job, the figures and the report read it
    from here so that no stage keeps its own per-domain table."""

    metric_label: str  # what eval_mixed measures, with its unit (axis label)
    claim: str  # the paper's finding for this domain, one sentence (in_paper False: the question it asks)
    test_paired: tuple[int, int] | None = None  # paired counts of the paper's Friedman test (None: all)
    threshold: tuple[float, str] | None = None  # data-efficiency threshold of eval_mixed, and where it comes from
    knob_labels: dict[str, str] = field(default_factory=dict)  # axis labels of this domain's swept knobs
    in_paper: bool = True  # False for a domain the paper does not study (a plugin's): `claim` is then its question


@dataclass
class SelfPlayOut:
    """One self-play update's loss and the convention outputs it produced (with grad)."""

    loss: torch.Tensor
    outputs: Tensors = field(default_factory=dict)
    info: dict[str, float] = field(default_factory=dict)


# What every domain's evaluate() returns (Domain.metrics declares them, with any others): a row counts as finished
# only with each of them finite (asp_dist.results.store reads no other as proof).
REQUIRED_METRICS = ("mixed", "self_play_new", "self_play_base")


class Domain(ABC):
    name: str = ""
    # This domain's own knobs (asp_dist.knobs.Knob: name, type, default, doc, choices, bound, ...), named
    # <name>_<knob>; each becomes a field of CellSpec and a column of the result row.
    knobs: tuple[Knob, ...] = ()
    # This domain's values of the common CellSpec knobs (train_steps, lr, λ0, λ1, ...): None fields of a
    # spec are filled from here (and its own knobs from their Knob.default).
    defaults: dict[str, Any] = {}
    # True for the domains whose knobs were CellSpec fields before domains were plugins: their knobs, even
    # unset, stay in every cell's identity, so that no recorded cell id moves. A new domain leaves it False:
    # its knobs then enter the identity of its own cells only, and installing it moves no other cell.
    legacy_identity: bool = False
    # The values of knobs whose default changed after the reproduction study's protocol was registered
    # (2026-11-24, docs/reproduction.md): `asp-dist select` counts changed knobs from these.
    protocol_defaults: dict[str, Any] = {}
    # Knob values that make a cell of this domain run in about a second: what `asp-dist check-domain` and the
    # registry-wide tests (tests/test_domain_registry.py) run it with.
    smoke: dict[str, Any] = {}
    # Convention channels watched by one adversary each (name -> output dimension given a spec).
    channels: tuple[str, ...] = ()
    # Metrics returned by evaluate(); must include "mixed", "self_play_new" and "self_play_base".
    metrics: dict[str, MetricInfo] = {}
    # The paper's statements about this domain (units, test range, thresholds, claim).
    paper: PaperFacts
    # Base acceptance: spec field holding the bar, and whether the base score must be >= it.
    accept_field: str | None = None
    # Spec fields besides the base's, paired count and |U| that shape U (what unpaired() returns), so
    # that a cache of U keys on them: e.g. the VAE's adversary input (μ or sampled z).
    unpaired_fields: tuple[str, ...] = ()
    # Spec fields besides the base's and the paired count that shape P (what paired() returns), likewise: e.g.
    # the VMAS domains' new agent (P holds that agent's observations and choices).
    paired_fields: tuple[str, ...] = ()
    # True for the one domain a spec that names no domain belongs to (CellSpec's default `domain`): the built-in
    # signaling game, for specs and spaces written before the domain had to be named. A plugin leaves it False.
    default_for_specs: bool = False
    # Extra keyword arguments for the Adam optimisers of the new agents and the discriminators,
    # e.g. {"fused": True}: one kernel for all parameters, several times faster per update on CPU
    # when a domain has many small parameter tensors and tiny batches.
    optimizer_options: dict[str, Any] = {}

    @property
    def knob_defaults(self) -> dict[str, Any]:
        """The defaults of this domain's optional knobs (what resolution fills a None knob with)."""
        return {k.name: k.default for k in self.knobs if k.optional}

    @property
    def upper_bounds(self) -> dict[str, int]:
        """Upper bounds of this domain's size-like knobs, checked by CellSpec with its common ones
        (spec.UPPER_BOUNDS)."""
        return {k.name: k.bound for k in self.knobs if k.bound is not None}

    @property
    def game(self) -> ModuleType:
        """The torch half of this domain: the module ``game`` of the card's package, imported on first use.

        Named rather than imported by the card, so that loading a card loads no torch, and the game may
        import the card's constants (POOL, AGENTS) without an import cycle. Not cached on the instance:
        Python's module cache makes the second call a dictionary lookup, and a domain stays picklable."""
        return importlib.import_module(f"{type(self).__module__}.game")

    def _sibling(self, name: str) -> ModuleType | None:
        """The module `name` of the card's package, imported on first use as `game` is; None where the
        package has none (or the card is not in a package)."""
        full = f"{type(self).__module__}.{name}"
        try:
            if importlib.util.find_spec(full) is None:
                return None
        except ModuleNotFoundError:  # the card's module is not a package
            return None
        return importlib.import_module(full)

    @property
    def trainers(self) -> tuple[type, ...]:
        """This domain's own trainers, fastest first (asp_dist.training.engines: classes with their
        capabilities as attributes; the reference Trainer, which trains any cell alone, follows them):
        ``TRAINERS`` of the module ``trainers`` of the card's package, or () where the package has none.
        A domain written as one module overrides this."""
        module = self._sibling("trainers")
        return tuple(module.TRAINERS) if module is not None else ()

    def draw_figures(self, payloads: list[tuple[dict, dict]], out_dir: Any) -> tuple[list, list[str]]:
        """The figures only this domain can draw, from its rows' figure_data (`payloads`: (row, decoded
        figure_data) pairs of its rows, every method and condition), written under `out_dir`: a list of
        asp_dist.analysis.plots.Figure and notes on what could not be drawn. Default: ``draw(payloads,
        out_dir)`` of the module ``figures`` of the card's package (the analysis helpers there:
        scatter_figures, pick_rows, save_figure), or nothing."""
        module = self._sibling("figures")
        return module.draw(payloads, out_dir) if module is not None else ([], [])

    def knob(self, spec: CellSpec, suffix: str) -> Any:
        """This domain's knob `suffix` of a spec: the field ``<name>_<suffix>`` (for cards whose subclasses
        name the domain, so the field name is not written out)."""
        return getattr(spec, f"{self.name}_{suffix}")

    def validate(self, spec: CellSpec) -> None:
        """Raise SpecError for a knob value this domain cannot run with."""

    def check_data(self, specs: list[CellSpec]) -> None:
        """Before any cell of `specs` (all of this domain) runs: load and verify the data set they read, so
        that a missing or corrupt copy is refused in one line before work starts. Domains without data: no-op."""

    def tensor_sizes(self, spec: CellSpec) -> dict[str, int]:
        """Numbers in the largest tensors a cell of `spec` allocates, by the knobs that set them (an estimate,
        {"signaling_states × signaling_tokens": S·A}); CellSpec refuses a cell above spec.MAX_TENSOR, so that
        a product of knobs each within its bound is refused before it exhausts memory."""
        return {}

    @abstractmethod
    def channel_dims(self, spec: CellSpec) -> dict[str, int]:
        """Width of each convention channel's output vectors."""

    # ---- the base convention ------------------------------------------------------------------
    @abstractmethod
    def train_base(self, spec: CellSpec, seed: int, progress: ProgressFn | None = None) -> tuple[nn.Module, float]:
        """Train one base candidate from `seed`; return (agents, score compared with the bar)."""

    def base_agents(self, spec: CellSpec) -> nn.Module:
        """An untrained module of the shape train_base returns for `spec`: a stored base is its weights (never a
        pickled object), loaded into this. By default new_agents' shape; a domain whose base has another
        shape overrides it (check_domain checks that a base's weights fit)."""
        return self.new_agents(spec, 0)

    @abstractmethod
    def paired(self, spec: CellSpec, base: nn.Module, n: int, gen: torch.Generator) -> Tensors:
        """P: n input-output tuples of the base. Sets for n < m must be prefixes of the set for m."""

    @abstractmethod
    def unpaired(self, spec: CellSpec, base: nn.Module, size: int, gen: torch.Generator) -> Tensors:
        """U: `size` base outputs per convention channel, with no inputs."""

    # ---- the new agents -------------------------------------------------------------------------
    @abstractmethod
    def new_agents(self, spec: CellSpec, seed: int) -> nn.Module:
        """Fresh agents, initialised from `seed`."""

    def init_self_play(self, spec: CellSpec, agents: nn.Module, gen: torch.Generator) -> Tensors:
        """State carried between self-play updates (environments, replay buffers); tensors only,
        so it checkpoints. Stateless domains return {}."""
        return {}

    @abstractmethod
    def self_play_step(self, spec: CellSpec, agents: nn.Module, state: Tensors, gen: torch.Generator) -> SelfPlayOut:
        """One self-play batch: the loss L_sp and the convention outputs (with grad). May update
        `state` in place."""

    @abstractmethod
    def paired_loss(self, spec: CellSpec, agents: nn.Module, paired: Tensors) -> torch.Tensor:
        """L_p on the full paired set."""

    @abstractmethod
    def convention_outputs(self, spec: CellSpec, agents: nn.Module, n: int, gen: torch.Generator) -> Tensors:
        """n outputs per channel of the agents on their own input distribution (with grad)."""

    @abstractmethod
    def evaluate(self, spec: CellSpec, base: nn.Module, agents: nn.Module, gen: torch.Generator) -> dict[str, float]:
        """Mixed-team scores (Eq. 1) and their components, self-play of new agents and of the base."""

    def figure_data(self, spec: CellSpec, base: nn.Module, agents: nn.Module) -> dict[str, Any] | None:
        """Arrays for the paper's figures (lists of numbers), when the domain has any."""
        return None



class GameDomain(Domain):
    """A Domain whose torch half is the sibling module ``game`` of its card's package (Domain.game), with
    one function per method, taking the method's arguments without ``self``: each method here calls it.
    The optional ones (init_self_play, figure_data) fall back to Domain's defaults where the game has no
    such function. The built-in domains are written this way; a domain may as well subclass Domain and
    implement the methods itself."""

    def train_base(self, spec, seed, progress=None):
        return self.game.train_base(spec, seed, progress)

    def paired(self, spec, base, n, gen):
        return self.game.paired(spec, base, n, gen)

    def unpaired(self, spec, base, size, gen):
        return self.game.unpaired(spec, base, size, gen)

    def new_agents(self, spec, seed):
        return self.game.new_agents(spec, seed)

    def init_self_play(self, spec, agents, gen):
        own = getattr(self.game, "init_self_play", None)
        return own(spec, agents, gen) if own is not None else super().init_self_play(spec, agents, gen)

    def self_play_step(self, spec, agents, state, gen):
        return self.game.self_play_step(spec, agents, state, gen)

    def paired_loss(self, spec, agents, paired):
        return self.game.paired_loss(spec, agents, paired)

    def convention_outputs(self, spec, agents, n, gen):
        return self.game.convention_outputs(spec, agents, n, gen)

    def evaluate(self, spec, base, agents, gen):
        return self.game.evaluate(spec, base, agents, gen)

    def figure_data(self, spec, base, agents):
        own = getattr(self.game, "figure_data", None)
        return own(spec, base, agents) if own is not None else super().figure_data(spec, base, agents)

def check_domain(domain: Domain, spec: CellSpec) -> None:
    """Contract checker (PettingZoo-style): same seed -> identical base, P, U, rollouts and scores.

    Raises ContractError (an AssertionError) naming the piece that broke the contract; not `assert`, so that
    it checks under ``python -O`` too. `asp-dist check-domain NAME` runs it on the domain's smoke spec."""
    import torch

    spec = spec.resolved()
    _holds(spec.domain == domain.name, "spec is for another domain")
    for metric in REQUIRED_METRICS:
        _holds(metric in domain.metrics, f"{domain.name}: metrics must declare {metric!r}")
    for knob in (*domain.defaults, *domain.knob_defaults):
        _holds(hasattr(spec, knob), f"{domain.name}: default for unknown field {knob!r}")

    base_a, score_a = domain.train_base(spec, seed=123)
    base_b, score_b = domain.train_base(spec, seed=123)
    _holds(score_a == score_b, "train_base: same seed gave different scores")
    assert_same_params(base_a, base_b, "train_base")
    _holds(_same_shapes(base_a, domain.base_agents(spec)),
           "train_base: the base's weights do not fit base_agents(spec) (names or shapes differ); a stored base is "
           "its weights, loaded into base_agents: override it where the base is not new_agents' shape")

    def gen(seed: int) -> torch.Generator:
        return torch.Generator().manual_seed(seed)

    n = max(spec.paired, 3)
    p1, p2 = domain.paired(spec, base_a, n, gen(1)), domain.paired(spec, base_a, n, gen(1))
    assert_same_tensors(p1, p2, "paired")
    prefix = domain.paired(spec, base_a, n - 1, gen(1))
    for k in p1:
        _holds(torch.equal(prefix[k], p1[k][: n - 1]), f"paired: set for n-1 is not a prefix of the set for n ({k})")
    u1, u2 = domain.unpaired(spec, base_a, 16, gen(2)), domain.unpaired(spec, base_a, 16, gen(2))
    assert_same_tensors(u1, u2, "unpaired")
    dims = domain.channel_dims(spec)
    _holds(set(u1) == set(domain.channels) == set(dims), "unpaired: one entry per convention channel")
    for ch, t in u1.items():
        _holds(t.shape == (16, dims[ch]), f"unpaired[{ch}] has shape {tuple(t.shape)}, expected (16, {dims[ch]})")

    agents_a, agents_b = domain.new_agents(spec, 7), domain.new_agents(spec, 7)
    assert_same_params(agents_a, agents_b, "new_agents")
    outs = []
    for agents in (agents_a, agents_b):
        g = gen(3)
        state = domain.init_self_play(spec, agents, g)
        step = [domain.self_play_step(spec, agents, state, g) for _ in range(2)][-1]
        conv = domain.convention_outputs(spec, agents, 5, g)
        outs.append((step, conv))
    _holds(torch.equal(outs[0][0].loss, outs[1][0].loss), "self_play_step: same seed gave different losses")
    assert_same_tensors(outs[0][0].outputs, outs[1][0].outputs, "self_play_step outputs")
    assert_same_tensors(outs[0][1], outs[1][1], "convention_outputs")
    for ch, t in outs[0][1].items():
        _holds(t.shape == (5, dims[ch]), f"convention_outputs[{ch}] has shape {tuple(t.shape)}")
        _holds(t.requires_grad, f"convention_outputs[{ch}] must carry gradients to the agents")
    _holds(domain.paired_loss(spec, agents_a, p1).requires_grad, "paired_loss must carry gradients")

    m1 = domain.evaluate(spec, base_a, agents_a, gen(4))
    m2 = domain.evaluate(spec, base_a, agents_a, gen(4))
    _holds(set(m1) == set(domain.metrics), f"evaluate returned {sorted(m1)}, declared {sorted(domain.metrics)}")
    problem = metric_problem(domain, m1)
    _holds(problem is None, f"evaluate: {problem}")
    _holds(m1 == m2, "evaluate: same seed gave different metrics")


def metric_problem(domain: Domain, metrics: dict[str, Any]) -> str | None:
    """What makes `metrics` (evaluate's result) unfit for a row, in a few words naming the metric; None if
    every declared metric is there and finite (a row is finished only then: asp_dist.training.row)."""
    import math

    for name in domain.metrics:
        if name not in metrics:
            return f"metric {name!r} is missing (evaluate returned {sorted(metrics) or 'nothing'})"
        value = metrics[name]
        try:
            number = float(value)
        except (TypeError, ValueError):
            return f"metric {name!r} is not a number ({type(value).__name__} {value!r:.40})"
        if math.isnan(number):
            return f"metric {name!r} is NaN"
        if math.isinf(number):
            return f"metric {name!r} is {number}"
    return None


def _same_shapes(a: nn.Module, b: nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(sa[k].shape == sb[k].shape and sa[k].dtype == sb[k].dtype for k in sa)


def assert_same_params(a: nn.Module, b: nn.Module, what: str) -> None:
    import torch

    sa, sb = a.state_dict(), b.state_dict()
    _holds(sa.keys() == sb.keys(), f"{what}: different parameter names")
    for k in sa:
        _holds(torch.equal(sa[k], sb[k]), f"{what}: parameter {k} differs between two runs of one seed")


def assert_same_tensors(a: Tensors, b: Tensors, what: str) -> None:
    import torch

    _holds(a.keys() == b.keys(), f"{what}: different keys")
    for k in a:
        _holds(torch.equal(a[k], b[k]), f"{what}: {k} differs between two runs of one seed")


class ContractError(AssertionError):
    """A domain breaks the contract (check_domain)."""


def _holds(condition: bool, message: str) -> None:
    if not condition:
        raise ContractError(message)


def require(condition: bool, message: str) -> None:
    if not condition:
        raise SpecError(message)


def game_attribute(package: str, name: str) -> Any:
    """A name of `package`'s game module, for the package's module-level ``__getattr__``: the torch half's
    public names stay importable from the package (``from asp_dist.domains.levers import CommNet``, and
    bases pickled before the split), while ``import asp_dist.domains.levers`` alone stays light."""
    if name.startswith("_"):  # dunder probes (pickle, inspect, pytest) must not import torch
        raise AttributeError(f"module {package!r} has no attribute {name!r}")
    game = importlib.import_module(f"{package}.game")
    try:
        return getattr(game, name)
    except AttributeError:
        raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
