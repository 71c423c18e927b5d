"""Packed trainers: K cells of one domain that share tensor shapes, trained as ONE batched model
(parameters stacked on a leading member dimension, one batched update and one Adam step for all).

Each member keeps its own loss weights, data, initial weights and random streams, so that its
result is the one its single-cell run gives (up to float rounding) whatever its pack-mates are.
Only the particle world has a packed trainer so far (particles.py)."""

from __future__ import annotations

from asp_dist.training.packed.particles import (
    PackedParticleTrainer,
    PackedResult,
    pack_key,
    run_pack,
    supports,
)

__all__ = ["PackedParticleTrainer", "PackedResult", "pack_key", "run_pack", "supports"]
