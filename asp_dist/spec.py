"""CellSpec: every knob of one training cell, typed, documented and validated.

A cell is one (domain, method, paired, trial) training run plus the domain's own knobs.
Fields left as ``None`` take the domain's default when the spec is *resolved*; a resolved
spec is what runs, what is hashed into ``cell_id`` and what is written to the result row.

The common knobs are declared here. A domain's own knobs are declared by the domain
(``Domain.knobs``, asp_dist.knobs.Knob) and become fields of CellSpec when the registered domains are
first asked for: this module names no domain. They carry their domain's name as a prefix
(``vae_latent_dim``) so that one flat, pinned schema serves every domain: a particle row simply has
``vae_*`` = null.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from dataclasses import dataclass, field, fields, make_dataclass
from typing import Any, get_type_hints

from asp_dist.core.registry import DOMAINS, get_domain
from asp_dist.errors import SpecError
from asp_dist.hashing import stable_hash
from asp_dist.knobs import UNSET, Range, choice, integers, log_uniform, uniform
from asp_dist.method_registry import METHODS, arm_problem, get_method, split_arm

__all__ = ["CellSpec", "SpecError", "stable_hash", "FIELD_NAMES", "FIELD_DOCS", "coerce_field", "field_type"]

ADVERSARY_LOSSES = ("neg_bce", "non_saturating")
LAMBDA_SCHEDULES = ("constant", "warmup", "anneal")
CHOICES: dict[str, tuple[str, ...]] = {  # and every domain knob's Knob.choices (added below)
    "adversary_loss": ADVERSARY_LOSSES,
    "lambda_unpaired_schedule": LAMBDA_SCHEDULES,
}


def knob(default: Any = None, doc: str = "", search: Range | None = None) -> Any:
    """A common knob: its default, its one-line doc, and where `asp-dist tune` may look for its value."""
    return field(default=default, metadata={"doc": doc, "search": search})


ADVERSARY = ("adversarial",)  # Range.needs: the knob matters to methods that train against an adversary


@dataclass(frozen=True)
class _CommonKnobs:
    """The knobs every cell has, and every method of CellSpec; CellSpec adds the domains' knobs (below)."""

    # --- identity of the cell -------------------------------------------------------------
    # Its default is the registered domain that says `default_for_specs` (CellSpec below): specs and spaces
    # written before domains were plugins leave the domain out. This module names no domain.
    domain: str = knob(None, "Domain, as registered (asp-dist fields lists them).")
    method: str = knob("asp", "Method, as registered: pc (paired only) | osp (self-play + paired) | asp (osp + "
                              "adversary) | a plugin's (asp_dist.method_registry); an arm, method@label (osp@default), "
                              "trains as its method under a name of its own.")
    paired: int = knob(0, "Number of paired (input, output) examples of the base convention, |P|.")
    trial: int = knob(0, "Trial index: selects the base model and all seeds of the cell.")
    root_seed: int = knob(0, "Global seed; every seed of the cell is derived from (root_seed, trial, ...).")
    common_seeds: bool = knob(False, "Train and eval seeds hash only the base, paired count and method (arm label "
                                     "dropped), not the other knobs: every setting of a method trains on the same "
                                     "draws (common random numbers).")

    # --- the loss L = w_sp*L_sp + lambda_paired*L_p + lambda_unpaired*L_u ------------------
    # λ0 is tuned where another term weighs against it (alone, Adam makes a loss's scale almost irrelevant)
    lambda_paired: float | None = knob(None, "λ0: weight of the paired (supervised) loss.",
                                       log_uniform(0.1, 10.0, needs=("paired", "self_play")))
    lambda_unpaired: float | None = knob(None, "λ1: weight of the adversarial (unpaired) loss; ASP only.",
                                         log_uniform(0.01, 1.0, needs=ADVERSARY))
    adversary_loss: str = knob("neg_bce", "Model's adversarial term: neg_bce (paper: -BCE) | non_saturating (-log D(fake)).",
                               choice("neg_bce", "non_saturating", needs=ADVERSARY))
    unpaired_size: int | None = knob(None, "|U|: number of unpaired base outputs per convention channel.")
    unpaired_batch: int | None = knob(None, "Unpaired samples shown to each discriminator per update (default: batch_size).")
    lambda_unpaired_schedule: str | None = knob(None, "λ1 over training: constant | warmup (0 → λ1 over the first "
                                                      "lambda_schedule_frac of updates) | anneal (λ1 → 0 over that "
                                                      "fraction). ASP only; PC and OSP resolve it to constant.",
                                                choice("constant", "warmup", "anneal", needs=ADVERSARY))
    lambda_schedule_frac: float | None = knob(None, "Fraction of the updates over which a λ1 warm-up or anneal runs.",
                                              uniform(0.1, 1.0, needs=ADVERSARY))
    disc_steps: int = knob(1, "Discriminator updates per model update (each on a fresh batch of U, the same fakes).",
                           integers(1, 3, needs=ADVERSARY))

    # --- optimisation of the new agents ---------------------------------------------------
    train_steps: int | None = knob(None, "Number of training updates (batches) of the new agents.")
    batch_size: int | None = knob(None, "Self-play batch size per update (domain's unit: envs, images, games).")
    lr: float | None = knob(None, "Adam learning rate of the new agents.", log_uniform(1e-4, 1e-2))
    disc_hidden: int | None = knob(None, "Hidden units of each discriminator's MLP.")
    disc_layers: int | None = knob(None, "Hidden layers of each discriminator's MLP.")
    disc_lr: float | None = knob(None, "Adam learning rate of the discriminators.", log_uniform(1e-4, 1e-2, needs=ADVERSARY))

    # --- base model and evaluation ----------------------------------------------------------
    base_train_steps: int | None = knob(None, "Training updates of the base model.")
    base_max_attempts: int | None = knob(None, "Base retrained with the next seed at most this many times if it misses "
                                               "the bar.")
    base_steps_growth: float | None = knob(None, "Attempt k (from 0) of a base trains base_train_steps · growth^k "
                                                 "updates: retries escalate the budget instead of repeating it.")
    eval_episodes: int | None = knob(None, "Evaluation size per mixed-team composition (episodes, images or games).")
    record_figure_data: bool = knob(False, "Store figure arrays (latent codes, communication vectors) in the row.")

    # ------------------------------------------------------------------------------------------
    def replace(self, **changes: Any) -> "CellSpec":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Every field, except the unset knobs of domains other than the legacy four and this cell's own
        (Domain.legacy_identity): a cell's dict, manifest entry and row do not change when a plugin is installed."""
        # Every field is a scalar, so a plain read is dataclasses.asdict without its deep copies (~0.6 ms a cell).
        return {k: v for k in FIELD_NAMES if not ((v := getattr(self, k)) is None and k in _SPARSE_IDENTITY)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "CellSpec":
        unknown = sorted(set(data) - set(FIELD_NAMES))
        if unknown:
            raise SpecError(f"unknown cell field(s) {', '.join(unknown)}; run `asp-dist fields` for the list")
        return cls(**{k: coerce_field(k, v) for k, v in data.items()})

    def resolved(self) -> "CellSpec":
        """Fill every None knob with the domain's default and validate the result.

        Resolution happens once: the spec it returns is marked resolved (`is_resolved`), resolving it again
        returns it as it is, and its identity (cell_id, base_key, seeds) is computed once and kept on it. A
        spec made from it by replace() is a new spec, resolved anew."""
        if self.is_resolved:
            return self
        self.validate_identity()
        domain = get_domain(self.domain)
        defaults = {**COMMON_DEFAULTS, **domain.defaults, **domain.knob_defaults}
        changes = {k: v for k, v in defaults.items() if getattr(self, k) is None}

        def now(name: str) -> Any:  # a field's value with the changes so far (one replace() for them all)
            return changes[name] if name in changes else getattr(self, name)

        if not get_method(self.method).adversarial:
            # λ1 and its schedule have no meaning without an adversary; keep them in the row at their
            # neutral values (0, constant) so that PC and OSP rows stay comparable across settings.
            changes.update(lambda_unpaired_schedule="constant",
                           lambda_schedule_frac=HASH_NEUTRAL["lambda_schedule_frac"])
            if now("lambda_unpaired") not in (None, 0, 0.0):
                changes["lambda_unpaired"] = 0.0
        if now("unpaired_batch") is None:
            changes["unpaired_batch"] = now("batch_size")
        spec = dataclasses.replace(self, **changes)
        spec.validate_resolved()
        object.__setattr__(spec, "_identity", {})  # frozen: the mark and the cache are not fields
        return spec

    @property
    def is_resolved(self) -> bool:
        """Whether this spec is one that resolved() returned (its knobs filled and validated)."""
        return "_identity" in self.__dict__

    def _cached(self, key: str, compute) -> Any:
        """`compute(resolved spec)`, computed once per resolved spec."""
        spec = self.resolved()
        cache = spec.__dict__["_identity"]
        if key not in cache:
            cache[key] = compute(spec)
        return cache[key]

    # ---- validation --------------------------------------------------------------------------
    def validate_types(self) -> None:
        """Every field holds a value of its type: text, true/false, an integer (never a bool, within
        int64) or a finite number (never a bool, NaN or ±inf); None only where the field is optional."""
        for name in FIELD_NAMES:
            value = getattr(self, name)
            if value is None:
                if name not in _OPTIONAL:
                    raise SpecError(f"{name} must have a value (it is not optional), got None")
                continue
            t = field_type(name)
            if t is str:
                ok = isinstance(value, str)
            elif t is bool:
                ok = isinstance(value, bool)
            elif t is int:
                ok = isinstance(value, int) and not isinstance(value, bool) and -INT64_MAX - 1 <= value <= INT64_MAX
            else:
                ok = (isinstance(value, (int, float)) and not isinstance(value, bool)
                      and math.isfinite(float(value)))
            if not ok:
                raise SpecError(f"{name} must be {_TYPE_WORDS[t]}, got {_short_repr(value)}")

    def validate_identity(self) -> None:
        for name in ("domain", "method"):
            if not isinstance(getattr(self, name), str):
                raise SpecError(f"{name} must be text, got {_short_repr(getattr(self, name))}")
        if self.domain not in DOMAINS:
            if isinstance(self.domain, str) and self.domain in DOMAINS.problems():
                get_domain(self.domain)  # the set-aside plugin's one line (e.g. which extra to install)
            raise SpecError(f"unknown domain {_short_repr(self.domain)}; choose one of {', '.join(sorted(DOMAINS))}")
        problem = arm_problem(self.method)
        if problem is not None:
            raise SpecError(problem)
        method, label = split_arm(self.method)
        if method not in METHODS:
            if method in METHODS.problems():
                get_method(method)  # the set-aside plugin's one line
            arm = f" (of arm {_short_repr(self.method)})" if label is not None else ""
            raise SpecError(f"unknown method {_short_repr(method)}{arm}; choose one of {', '.join(METHODS)}")
        for name, allowed in CHOICES.items():
            if getattr(self, name) is not None and getattr(self, name) not in allowed:
                raise SpecError(f"{name} must be one of {', '.join(allowed)}, got {_short_repr(getattr(self, name))}")
        for name in ("paired", "trial", "root_seed"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= INT64_MAX:
                raise SpecError(f"{name} must be an integer >= 0 (in the int64 range), got {_short_repr(value)}")
        self.validate_types()
        # Checked as given, before resolved() sets PC's and OSP's λ1 and schedule aside: a bad value is refused
        # whatever the method.
        self.refuse_negatives()
        if self.lambda_schedule_frac is not None and not 0.0 < self.lambda_schedule_frac <= 1.0:
            raise SpecError(f"lambda_schedule_frac must be in (0, 1], got {self.lambda_schedule_frac!r}")

    def refuse_negatives(self) -> None:
        for name in FIELD_NAMES:
            value = getattr(self, name)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and value < 0:
                raise SpecError(f"{name} must be >= 0, got {value!r}")

    def validate_resolved(self) -> None:
        own = {*_COMMON_NAMES, *(k.name for k in get_domain(self.domain).knobs)}
        unset = [name for name in FIELD_NAMES if name in own and getattr(self, name) is None]
        if unset:  # a domain (a plugin's, say) that gives no default for a knob its cells need
            raise SpecError(f"{', '.join(unset)} {'has' if len(unset) == 1 else 'have'} no value for domain "
                            f"{self.domain!r}: set {'it' if len(unset) == 1 else 'them'}, or give the domain a "
                            f"default (Domain.defaults or Knob.default)")
        self.validate_types()  # again: domain defaults and the replacements of resolved() are values too
        self.refuse_negatives()
        for name in ("train_steps", "batch_size", "unpaired_size", "unpaired_batch", "eval_episodes",
                     "disc_hidden", "disc_layers", "base_max_attempts", "disc_steps"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise SpecError(f"{name} must be >= 1, got {value!r}")
        for name in ("lr", "disc_lr", "base_steps_growth"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise SpecError(f"{name} must be > 0, got {value!r}")
        if not 0.0 < self.lambda_schedule_frac <= 1.0:
            raise SpecError(f"lambda_schedule_frac must be in (0, 1], got {self.lambda_schedule_frac!r}")
        domain = get_domain(self.domain)
        for name, bound in {**UPPER_BOUNDS, **domain.upper_bounds}.items():
            if getattr(self, name) > bound:
                raise SpecError(f"{name} must be <= {bound}, got {getattr(self, name)!r}")
        # Computed in logs: growth^attempts overflows a float long before it is refused.
        last_attempt = (math.log(self.base_train_steps or 1)
                        + (self.base_max_attempts - 1) * math.log(self.base_steps_growth))
        if last_attempt > math.log(UPPER_BOUNDS["base_train_steps"]):
            raise SpecError(f"base_train_steps · base_steps_growth^(base_max_attempts - 1) (the last base attempt's "
                            f"updates) must be <= {UPPER_BOUNDS['base_train_steps']}, got {self.base_train_steps} · "
                            f"{self.base_steps_growth!r}^{self.base_max_attempts - 1}")
        domain.validate(self)
        sizes = {**self.common_tensor_sizes(domain.channel_dims(self)), **domain.tensor_sizes(self)}
        label, numbers = max(sizes.items(), key=lambda item: item[1])
        if numbers > MAX_TENSOR:
            raise SpecError(f"out of memory for this cell: one tensor of {label} = {numbers} numbers, above the "
                            f"budget of {MAX_TENSOR} (1 GiB of float32) per tensor")

    def common_tensor_sizes(self, widths: dict[str, int]) -> dict[str, int]:
        """Numbers in the largest tensors of U and the discriminators, by the knobs that set them."""
        sizes = {"disc_hidden × disc_hidden": self.disc_hidden ** 2 if self.disc_layers > 1 else 0,
                 "unpaired_batch × disc_hidden": self.unpaired_batch * self.disc_hidden}
        for channel, width in widths.items():
            sizes[f"unpaired_size × {channel} width {width}"] = self.unpaired_size * width
            sizes[f"unpaired_batch × {channel} width {width}"] = self.unpaired_batch * width
            sizes[f"disc_hidden × {channel} width {width}"] = self.disc_hidden * width
        return sizes

    # ---- identity ----------------------------------------------------------------------------
    def identity_dict(self) -> dict[str, Any]:
        """The fields that identify what runs: every field, except knobs added after the first
        results were recorded while they hold the value that reproduces the earlier behaviour
        (HASH_NEUTRAL), and the unset knobs of domains other than the legacy four (Domain.legacy_identity).
        Adding a knob or installing a domain therefore changes no existing cell id, seed or base key."""
        return {k: v for k, v in self.to_dict().items() if not (k in HASH_NEUTRAL and v == HASH_NEUTRAL[k])}

    @property
    def cell_id(self) -> str:
        """Readable, stable id: same resolved spec -> same id, on every machine."""
        def compute(spec: CellSpec) -> str:
            digest = stable_hash(spec.identity_dict())[:10]
            return f"{spec.domain}-{spec.method}-p{spec.paired}-t{spec.trial}-{digest}"

        return self._cached("cell_id", compute)

    def base_fields(self) -> dict[str, Any]:
        """The fields the base model depends on; cells agreeing on these share one base."""
        def compute(spec: CellSpec) -> dict[str, Any]:
            prefix = spec.domain + "_"
            return {k: v for k, v in spec.identity_dict().items()
                    if shapes_base(k, prefix)}

        return dict(self._cached("base_fields", compute))

    @property
    def base_key(self) -> str:
        return self._cached("base_key", lambda spec: stable_hash(spec.base_fields())[:16])

    def seed_for(self, purpose: str) -> int:
        """Derived seeds. 'base' depends on the base fields only; 'data' (P and U) and 'init'
        (new agents) on (domain, trial, paired) but not the method, so PC/OSP/ASP of one
        block see the same paired set, unpaired set and initial weights (common random numbers).
        'train' and 'eval' add the method and every knob; with common_seeds only the method, its
        arm label dropped, so every setting of a method draws the same batches and evaluation."""
        return self._cached(f"seed:{purpose}", lambda spec: spec._seed(purpose))

    def _seed(self, purpose: str) -> int:
        spec = self
        if purpose == "base":
            material: Any = self.base_fields()
        elif purpose in ("data", "init"):
            material = {"base": self.base_fields(), "paired": spec.paired}
        elif purpose in ("train", "eval") and spec.common_seeds:
            # A setting's effect is then measured on the same draws (osp against osp@default, lr against lr).
            material = {"base": self.base_fields(), "paired": spec.paired, "method": split_arm(spec.method)[0],
                        "common": True}
        elif purpose in ("train", "eval"):
            # Output-only switches must not change what is trained.
            material = {k: v for k, v in spec.identity_dict().items() if k not in OUTPUT_ONLY_FIELDS}
        else:
            raise ValueError(f"unknown seed purpose {purpose!r}")
        return int(stable_hash({"purpose": purpose, "material": material})[:12], 16)


# Knobs every domain uses, with the value a domain gets unless its `defaults` say otherwise
# (particles: robust bases and a λ1 warm-up, chosen by the reproduction study;
# docs/decisions/0021-domain-defaults-from-reproduction-study.md).
COMMON_DEFAULTS: dict[str, Any] = {
    "lambda_unpaired_schedule": "constant", "lambda_schedule_frac": 0.5,
    "base_max_attempts": 5, "base_steps_growth": 1.0,
}

# Knobs added after rows were first recorded, with the value that reproduces the behaviour
# before them. At that value they are left out of cell ids, seeds and base keys (identity_dict).
# (Here the common ones; a domain knob's is its Knob.neutral, added below.)
HASH_NEUTRAL: dict[str, Any] = {
    "lambda_unpaired_schedule": "constant", "lambda_schedule_frac": 0.5, "disc_steps": 1,
    "base_steps_growth": 1.0, "common_seeds": False,
}

# Fields that change what a cell records, never what it trains or how it is evaluated.
OUTPUT_ONLY_FIELDS = frozenset({"record_figure_data"})

# Upper bounds of the size-like knobs every domain has (a domain adds its own: Domain.upper_bounds). Far
# above the paper (its largest value in brackets) and a laptop, below what exhausts memory or time; a
# product of knobs that would still not fit is refused by MAX_TENSOR. Validation only: no cell id changes.
UPPER_BOUNDS: dict[str, int] = {
    "paired": 100_000,  # [64] P is held whole and its loss taken on every update
    "unpaired_size": 1_000_000,  # [4096] U is held whole
    "unpaired_batch": 1_000_000, "batch_size": 1_000_000, "eval_episodes": 1_000_000,  # [256, 256, 10000] rows
    "disc_hidden": 16_384,  # [64] a disc_hidden² weight matrix (1 GiB of float32 at the bound)
    "disc_layers": 100, "disc_steps": 1_000, "base_max_attempts": 1_000,  # [2, 2, 10]
    # [25000, 5000] a billion updates is weeks of CPU even at the fastest cells' ~1 ms per update
    "train_steps": 10**9, "base_train_steps": 10**9,
}
# Numbers in any one tensor of a cell, as Domain.tensor_sizes estimates them: 2^28 (1 GiB of float32) is
# ~30x the largest tensor of a paper cell (the VAE's 10000 test images x 784 pixels) and fits a laptop.
MAX_TENSOR = 2**28

_COMMON_NAMES = tuple(f.name for f in fields(_CommonKnobs))


def _domain_knobs() -> list[Any]:
    """The knobs of every registered domain, by domain name; a domain whose knob collides with a common knob
    or another domain's is set aside (registry.DOMAINS.refuse), the others keep working."""
    common = {f.name for f in fields(_CommonKnobs)}
    owner: dict[str, str] = {}
    knobs = []
    for name in list(DOMAINS):
        domain = DOMAINS[name]
        clash = next((k.name for k in domain.knobs if k.name in common or k.name in owner), None)
        if clash is not None:
            what = "a common CellSpec field" if clash in common else f"a knob of domain {owner[clash]!r}"
            DOMAINS.refuse(name, f"its knob {clash!r} collides with {what}; rename it")
            continue
        owner.update((k.name, name) for k in domain.knobs)
        knobs += domain.knobs
    return knobs


def _knob_field(k: Any) -> tuple[str, Any, Any]:
    hint = k.type | None if k.optional else k.type
    return k.name, hint, field(default=None if k.optional else k.default, metadata={"doc": k.doc})


_KNOBS = _domain_knobs()
# The domain of a spec that names none: the registered domain whose card says default_for_specs (the built-in
# signaling game), or None, and then a spec must name its domain.
DEFAULT_DOMAIN = next((name for name in sorted(DOMAINS) if getattr(DOMAINS.get(name), "default_for_specs", False)),
                      None)
_DOMAIN_FIELD = ("domain", str, knob(DEFAULT_DOMAIN, "Domain, as registered (asp-dist fields lists them)."))
CellSpec = make_dataclass("CellSpec", [_DOMAIN_FIELD, *(_knob_field(k) for k in _KNOBS)], bases=(_CommonKnobs,),
                          frozen=True,
                          namespace={"__module__": __name__, "__doc__": "Every knob of one training cell: the "
                                     "common ones (_CommonKnobs) and each registered domain's (Domain.knobs)."})
CHOICES.update({k.name: k.choices for k in _KNOBS if k.choices})
HASH_NEUTRAL.update({k.name: k.neutral for k in _KNOBS if k.neutral is not UNSET})
# Domain knobs that shape only how the new agents train: cells differing in them share a base.
NEW_AGENTS_ONLY = frozenset(k.name for k in _KNOBS if not k.shapes_base)
_SPARSE_IDENTITY = frozenset(k.name for name in DOMAINS if not DOMAINS[name].legacy_identity
                             for k in DOMAINS[name].knobs)

FIELD_NAMES: tuple[str, ...] = tuple(f.name for f in fields(CellSpec))
FIELD_DOCS: dict[str, str] = {f.name: f.metadata.get("doc", "") for f in fields(CellSpec)}
# Where `asp-dist tune` may look for a knob's value (asp_dist.knobs.Range): the common knobs' and every domain's.
SEARCH: dict[str, Range] = {**{f.name: f.metadata["search"] for f in fields(_CommonKnobs) if f.metadata.get("search")},
                            **{k.name: k.search for k in _KNOBS if k.search is not None}}
# The common fields a base depends on (CellSpec.base_fields); with a domain's base-shaping knobs, never tuned.
BASE_COMMON = frozenset({"domain", "trial", "root_seed", "base_train_steps", "base_max_attempts", "base_steps_growth"})


def shapes_base(name: str, domain_prefix: str) -> bool:
    """Whether field `name` is one a base depends on, for a cell of the domain whose knobs start with
    `domain_prefix` ("<domain>_"): the common base fields and the domain's knobs that shape its base."""
    return name in BASE_COMMON or (name.startswith(domain_prefix) and name not in NEW_AGENTS_ONLY)
_HINTS = get_type_hints(CellSpec)
_OPTIONAL = frozenset(name for name in FIELD_NAMES if "None" in str(_HINTS[name]))
INT64_MAX = 2**63 - 1  # integer knobs are stored as int64 in the result row
_TYPE_WORDS = {str: "text", bool: "true or false", int: "an integer in the int64 range (not a bool)",
               float: "a finite number (not NaN, inf or a bool)"}


def _is_bool(value: Any) -> bool:
    """True for Python and NumPy booleans (numpy.bool_ is no subclass of bool)."""
    return isinstance(value, bool) or type(value).__name__ in ("bool_", "bool")


def _short_repr(value: Any, width: int = 60) -> str:
    """A value for a one-line error message."""
    text = repr(value)
    return text if len(text) <= width else text[: width - 1] + "…"


@functools.cache  # looked up for every field of every spec validated
def field_type(name: str) -> type:
    """The scalar Python type of a field (int, float, str or bool)."""
    hint = str(_HINTS[name])
    for t in (bool, int, float, str):
        if t.__name__ in hint:
            return t
    raise TypeError(f"unsupported field type {hint} for {name}")


def coerce_field(name: str, value: Any) -> Any:
    """Convert text or numbers (from the CLI, YAML or JSON) into the field's type, with a clear error."""
    if name not in FIELD_DOCS:
        raise SpecError(f"unknown cell field {name!r}; run `asp-dist fields` for the list")
    if value is None:
        return None
    t = field_type(name)
    try:
        if t is bool:
            if isinstance(value, str):
                if value.strip().lower() in ("1", "true", "yes", "on"):
                    return True
                if value.strip().lower() in ("0", "false", "no", "off"):
                    return False
                if value.strip().lower() == "none" and name in _OPTIONAL:  # an unset optional switch, as numbers
                    return None
                raise ValueError
            if _is_bool(value) or (isinstance(value, numbers.Integral) and value in (0, 1)):
                return bool(value)
            raise ValueError  # 2, 0.5, a list: not a yes/no answer
        if _is_bool(value) and t in (int, float):
            raise ValueError  # `paired = true` in a space file is a mistake, not 1
        if t is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            if isinstance(value, str) and value.strip().lower() == "none":
                return None
            if not isinstance(value, (numbers.Integral, float, str)):
                raise ValueError
            return int(value)
        if t is float:
            if isinstance(value, str) and value.strip().lower() == "none":
                return None
            if not isinstance(value, (numbers.Real, str)):
                raise ValueError
            return float(value)
        if not isinstance(value, str):
            raise ValueError
        return value
    except (TypeError, ValueError, OverflowError):
        raise SpecError(f"{name} must be of type {t.__name__}, got {_short_repr(value)}") from None
