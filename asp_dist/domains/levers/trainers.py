"""The lever game's trainers, fastest first (asp_dist.training.engines; the reference Trainer follows)."""

from asp_dist.domains.levers.packed import PackedLeverTrainer

TRAINERS = (PackedLeverTrainer,)
