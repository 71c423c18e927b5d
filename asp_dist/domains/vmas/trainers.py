"""The VMAS domains' trainers, fastest first (asp_dist.training.engines; the reference Trainer follows): each
domain's packed trainer, for `--pack` sweeps (a lone cell trains on the reference)."""

from asp_dist.domains.vmas.packed import TRAINERS_OF  # noqa: F401  (VMASDomain.trainers reads it)
