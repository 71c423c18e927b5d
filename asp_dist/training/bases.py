"""Base models: train one per (domain, trial, base settings), retrying until it meets the bar.

The sweep service shares one base between all cells of a trial through a content-addressed
cache keyed by ``CellSpec.base_key``; this module only knows how to train and (de)serialise.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from asp_dist.domains import get_domain
from asp_dist.domains.contract import ProgressFn
from asp_dist.spec import CellSpec
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


def base_to_bytes(base: BaseModel) -> bytes:
    buf = io.BytesIO()
    torch.save(base, buf)
    return buf.getvalue()


def base_from_bytes(data: bytes) -> BaseModel:
    return torch.load(io.BytesIO(data), weights_only=False)
