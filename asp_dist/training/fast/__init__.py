"""Fast trainers: the same update as asp_dist.training.trainer.Trainer, computed with fewer
tensor ops. The trainer is chosen here, per cell, not by the domain: a fast trainer is used
only where one exists for the domain and it implements every knob value of the spec; the
reference trainer runs everything else."""

from __future__ import annotations

from asp_dist.domains.contract import Domain, Tensors
from asp_dist.spec import CellSpec
from asp_dist.training.fast.particles import FusedParticleTrainer
from asp_dist.training.fast.vae import OnePassVAETrainer
from asp_dist.training.methods import LossWeights
from asp_dist.training.trainer import Trainer

FAST_TRAINERS: dict[str, type[Trainer]] = {"particles": FusedParticleTrainer, "vae": OnePassVAETrainer}


def choose_trainer(spec: CellSpec, domain: Domain, agents, paired: Tensors, unpaired: Tensors,
                   weights: LossWeights) -> Trainer:
    fast = FAST_TRAINERS.get(domain.name)
    cls = fast if fast is not None and fast.supports(spec) else Trainer
    return cls(spec, domain, agents, paired, unpaired, weights)
