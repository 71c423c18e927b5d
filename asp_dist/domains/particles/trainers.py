"""The particle world's trainers, fastest first (asp_dist.training.engines; the reference Trainer follows)."""

from asp_dist.domains.particles.packed import PackedParticleTrainer

TRAINERS = (PackedParticleTrainer,)
