"""The VAE's trainers, fastest first (asp_dist.training.engines; the reference Trainer follows): a lone
cell on the one-pass update, packs (engines.run_pack; kept out of sweeps: PackedVAETrainer.in_sweeps) batched."""

from asp_dist.domains.vae.fast import OnePassVAETrainer
from asp_dist.domains.vae.packed import PackedVAETrainer

TRAINERS = (OnePassVAETrainer, PackedVAETrainer)
