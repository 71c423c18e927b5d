"""The VAE's training update with one pass through each network: the fast path.

In an OSP or ASP update the reference path runs the new VAE's encoder twice (the self-play batch,
then P's images) and its decoder twice (the sampled codes, then P's encodings). Every weight is
then used by two graphs, and autograd accumulates each weight's two gradients with an extra
tensor add: 13 adds of up to 400k floats per update, memory-bound (a third of an update's time in a
profile on the loaded machine: docs/decisions/0019-vae-fused-adam-one-pass.md). This
trainer stacks the self-play rows and P's rows into one batch per network, so each weight is used
once: the same loss terms, the same random draws in the same order, one matmul per layer and no
accumulation. Idle, an OSP update takes 11 % and an ASP update 9 % less CPU than the reference's
(bench/bench_packing.py, docs/performance.md). Rows are computed by the same
kernels; the weight gradients sum the rows in one matmul instead of two, so results equal the
reference's up to float rounding (tests/test_vae.py checks gradients, weights and loss columns
over a whole tiny training, and the draws for equality).

Cells without both self-play and paired loss (PC, or 0 paired) have nothing to merge and run the
reference update unchanged.
"""

from __future__ import annotations

import torch

from asp_dist.core.contract import SelfPlayOut
from asp_dist.domains.vae.game import paired_error, sample_code, self_play_batch, self_play_out, vae_loss_terms
from asp_dist.spec import CellSpec
from asp_dist.training.methods import LossWeights
from asp_dist.training.trainer import Trainer


class OnePassVAETrainer(Trainer):
    @classmethod
    def supports(cls, spec: CellSpec) -> bool:
        return spec.domain == "vae"  # every VAE knob: the pieces are the domain's own

    def model_terms(self, w: LossWeights) -> tuple[SelfPlayOut | None, torch.Tensor | None]:
        if not (w.needs_self_play and w.paired != 0.0 and len(self.paired["image"])):
            return super().model_terms(w)
        spec, vae, paired = self.spec, self.agents, self.paired
        x = self_play_batch(spec, self.gen)
        n = len(x)
        mu_all, logvar_all = vae.encoder(torch.cat([x, paired["image"]])).chunk(2, dim=-1)
        mu, logvar = mu_all[:n], logvar_all[:n]
        z = sample_code(mu, logvar, self.gen)
        logits_all = vae.decoder(torch.cat([z, paired["encoding"]]))
        loss, info = vae_loss_terms(x, mu, logvar, logits_all[:n], spec.vae_kl_weight, spec.vae_recon_loss)
        sp_out = self_play_out(spec, loss, mu, z, info)
        return sp_out, paired_error(spec, mu_all[n:], torch.sigmoid(logits_all[n:]), paired)
