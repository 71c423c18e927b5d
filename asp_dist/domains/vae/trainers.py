"""The VAE's trainers, fastest first (asp_dist.training.engines; the reference Trainer follows): a lone
cell on hand-derived gradients, or (cells it does not support) on the one-pass autograd update; packs
(engines.run_pack; kept out of sweeps: PackedVAETrainer.in_sweeps) batched."""

from asp_dist.domains.vae.fast import OnePassVAETrainer
from asp_dist.domains.vae.hand_derived import HandDerivedVAETrainer
from asp_dist.domains.vae.packed import PackedVAETrainer

TRAINERS = (HandDerivedVAETrainer, OnePassVAETrainer, PackedVAETrainer)
