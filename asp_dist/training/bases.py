"""Base models: train one per (domain, trial, base settings), retrying until it meets the bar.

The sweep service shares one base between all cells of a trial through a content-addressed
cache keyed by ``CellSpec.base_key``; this module only knows how to train and (de)serialise.
A stored base is its weights and its facts (asp_dist.training.artefacts: no pickled object), loaded into
the module its domain builds for the spec (Domain.base_agents).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from torch import nn

from asp_dist.core.contract import ProgressFn
from asp_dist.core.registry import get_domain
from asp_dist.spec import CellSpec
from asp_dist.training import artefacts
from asp_dist.training.float_mode import denormals_flushed
from asp_dist.training.torch_runtime import keep_dynamo_unloaded


class BaseRejected(RuntimeError):
    """No attempt reached the domain's acceptance bar within base_max_attempts."""


@dataclass
class BaseModel:
    agents: nn.Module
    key: str
    score: float
    attempts: int
    seed: int
    attempt_scores: list[float] = field(default_factory=list)
    train_wall_s: float = 0.0
    train_cpu_s: float = 0.0

    def meta(self) -> dict[str, Any]:
        return {"base_key": self.key, "base_score": self.score, "base_attempts": self.attempts,
                "base_seed": self.seed, "base_attempt_scores": list(self.attempt_scores)}


def train_accepted_base(spec: CellSpec, progress: ProgressFn | None = None) -> BaseModel:
    """Train base candidates with seeds seed, seed+1, ... until one meets the domain's bar.
    Attempt k trains base_train_steps · base_steps_growth^k updates, so that a retry is not
    just another draw of a budget that was too small."""
    import time

    keep_dynamo_unloaded()
    spec = spec.resolved()
    domain = get_domain(spec.domain)
    bar = getattr(spec, domain.accept_field) if domain.accept_field else None
    first_seed = spec.seed_for("base")
    scores: list[float] = []
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for attempt in range(spec.base_max_attempts):
        seed = first_seed + attempt
        steps = attempt_steps(spec.base_train_steps, spec.base_steps_growth, attempt)
        attempt_spec = spec if steps == spec.base_train_steps else spec.replace(base_train_steps=steps)
        with denormals_flushed():
            agents, score = domain.train_base(attempt_spec, seed, progress)
        scores.append(float(score))
        if bar is None or score >= bar:
            return BaseModel(agents=agents, key=spec.base_key, score=float(score), attempts=attempt + 1,
                             seed=seed, attempt_scores=scores,
                             train_wall_s=time.perf_counter() - wall0, train_cpu_s=time.process_time() - cpu0)
    raise BaseRejected(f"{spec.domain} base for trial {spec.trial}: no attempt of {spec.base_max_attempts} "
                       f"reached {domain.accept_field} = {bar} (scores {[round(s, 3) for s in scores]}); "
                       f"raise base_train_steps or base_max_attempts")


def attempt_steps(base_steps: int, growth: float, attempt: int) -> int:
    return int(round(base_steps * growth**attempt))


BASE_FORMAT = "asp-dist base"
# 2: weights and facts, read with weights_only (1: the pickled BaseModel, refused: docs/decisions/0057)
BASE_FORMAT_VERSION = 2


def base_to_bytes(base: BaseModel) -> bytes:
    """The stored form of a base: its facts, its agents' weights and which of their modules are in training
    mode (a base is usually stored in eval mode, and dropout or batch norm would act on it otherwise)."""
    return artefacts.to_bytes({
        "format": BASE_FORMAT, "version": BASE_FORMAT_VERSION, "key": base.key, "score": float(base.score),
        "attempts": int(base.attempts), "seed": int(base.seed),
        "attempt_scores": [float(s) for s in base.attempt_scores],
        "train_wall_s": float(base.train_wall_s), "train_cpu_s": float(base.train_cpu_s),
        "weights": base.agents.state_dict(),
        "training": {name: module.training for name, module in base.agents.named_modules()}})


def base_from_bytes(data: bytes, spec: CellSpec, what: str = "base file") -> BaseModel:
    """The base stored by base_to_bytes for `spec` (its base_key), its weights loaded into the module the spec's
    domain builds; artefacts.DamagedArtefact (one line) for a file that is not that base, whatever is wrong."""
    spec = spec.resolved()
    state = artefacts.from_bytes(data, what)
    need = artefacts.require
    need(isinstance(state, dict) and state.get("format") == BASE_FORMAT, what, "is not an asp-dist base")
    need(state.get("version") == BASE_FORMAT_VERSION, what,
         f"is a base of format version {state.get('version')!r}, not {BASE_FORMAT_VERSION}")
    need(state.get("key") == spec.base_key, what, f"holds base {state.get('key')!r}, expected {spec.base_key}")
    agents = get_domain(spec.domain).base_agents(spec)
    weights, training = state.get("weights"), state.get("training")
    need(isinstance(weights, dict) and isinstance(training, dict), what, "lacks its weights")
    try:
        agents.load_state_dict(weights, strict=True)
    except (RuntimeError, TypeError, ValueError) as err:  # names, shapes or dtypes other than the domain's
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise artefacts.DamagedArtefact(f"{what} does not fit a {spec.domain} base for these settings "
                                        f"({first[:200]})") from None
    modules = dict(agents.named_modules())
    need(set(training) == set(modules), what, "names other modules than the domain's base")
    for name, module in modules.items():
        module.training = bool(training[name])
    try:
        return BaseModel(agents=agents, key=state["key"], score=float(state["score"]),
                         attempts=int(state["attempts"]), seed=int(state["seed"]),
                         attempt_scores=[float(s) for s in state["attempt_scores"]],
                         train_wall_s=float(state["train_wall_s"]), train_cpu_s=float(state["train_cpu_s"]))
    except (KeyError, TypeError, ValueError) as err:
        raise artefacts.DamagedArtefact(f"{what} lacks a base's facts ({type(err).__name__}: {err})") from None
