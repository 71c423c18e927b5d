"""The base VAE's training update with hand-derived gradients: how train_base trains a base.

The bases are more than half of the paper grid's arithmetic (232 of 420 TFLOP: 5,000 updates at batch 128 for
each of 70 bases). Through autograd an update spent 55 % of its time in its eleven matmuls and 10 % in Adam; the
rest went to the loss's forward terms that no gradient needs (the base's loss value is never reported), the
autograd engine, and small elementwise kernels (bench/vae_roofline.py, docs/performance.md). This update
computes the same gradients in closed form:

    recon  = Σ BCE(logits, x) / B       → ∂/∂logits = (σ(logits) − x) / B
           (or Σ (σ(logits) − x)² / B   → 2 (σ − x) σ (1 − σ) / B)
    kl     = mean_b −½ Σ (1 + lv − μ² − e^lv)  → ∂/∂μ = w μ / B,  ∂/∂lv = ½ w (e^lv − 1) / B
    z      = μ + e^{lv/2} ε                → ∂z/∂μ = 1,  ∂z/∂lv = ½ e^{lv/2} ε

and back through the two ReLU layers of each network with the weights as nn.Linear stores them, then one fused
Adam step (torch.optim.Adam's kernel and defaults, as VAEDomain.optimizer_options asks for). The random
draws are the reference's, in its order (the batch's indices, then ε). The reference, train_base(...,
reference=True), is the autograd loop; tests/test_vae.py holds the two to float rounding, gradients and
weights. The result is an ordinary VAE module.
"""

from __future__ import annotations

import torch
from torch import nn

BETAS, EPS = (0.9, 0.999), 1e-8  # torch.optim.Adam's defaults: what the reference base trains with


class HandDerivedBaseUpdate:
    """One base update on `vae` (asp_dist.domains.vae.game.VAE) in place per call of step(x, gen). The Adam
    state lives here."""

    def __init__(self, vae: nn.Module, lr: float, kl_weight: float, recon_loss: str):
        if recon_loss not in ("bce", "mse"):
            raise ValueError(f"unknown vae_recon_loss {recon_loss!r}")
        enc_in, enc_out = vae.encoder[0], vae.encoder[2]
        dec_in, dec_out = vae.decoder[0], vae.decoder[2]
        self.layers = [(m.weight.data, m.bias.data) for m in (enc_in, enc_out, dec_in, dec_out)]
        self.params = [t for pair in self.layers for t in pair]
        self.grads = [torch.empty_like(p) for p in self.params]
        self.exp_avgs = [torch.zeros_like(p) for p in self.params]
        self.exp_avg_sqs = [torch.zeros_like(p) for p in self.params]
        self.steps = torch.zeros(())  # one step count for every tensor, as fused Adam keeps it (float)
        self.d, self.lr, self.kl_weight, self.recon_loss = vae.latent_dim, lr, kl_weight, recon_loss

    def gradients(self, x: torch.Tensor, gen: torch.Generator) -> list[torch.Tensor]:
        """The loss's gradient for each parameter (in self.params' order), into self.grads."""
        (w1, b1), (w2, b2), (w3, b3), (w4, b4) = self.layers
        gw1, gb1, gw2, gb2, gw3, gb3, gw4, gb4 = self.grads
        n, d = len(x), self.d
        # forward: the reference's ops, without the loss values
        h1 = torch.addmm(b1, x, w1.t()).clamp_(min=0)
        enc = torch.addmm(b2, h1, w2.t())
        mu, logvar = enc[:, :d], enc[:, d:]
        std = torch.exp(0.5 * logvar)
        eps = torch.randn(mu.shape, generator=gen)
        z = mu + std * eps
        h3 = torch.addmm(b3, z, w3.t()).clamp_(min=0)
        logits = torch.addmm(b4, h3, w4.t())
        # backward
        # each product in autograd's order, so that the gradients round as the reference's do
        pixels = torch.sigmoid(logits)
        if self.recon_loss == "bce":
            g = pixels.sub_(x).mul_(1.0 / n)
        else:
            g = (pixels - x).mul_(2.0).mul_(1.0 / n).mul_(1.0 - pixels).mul_(pixels)
        torch.mm(g.t(), h3, out=gw4)
        torch.sum(g, 0, out=gb4)
        g_h3 = torch.ops.aten.threshold_backward(torch.mm(g, w4), h3, 0.0)
        torch.mm(g_h3.t(), z, out=gw3)
        torch.sum(g_h3, 0, out=gb3)
        g_z = torch.mm(g_h3, w3)
        g_enc = torch.empty_like(enc)
        kl_scale = self.kl_weight / n
        torch.add(g_z, mu, alpha=kl_scale, out=g_enc[:, :d])
        torch.add(g_z.mul_(eps).mul_(std).mul_(0.5), torch.exp(logvar).sub_(1.0), alpha=0.5 * kl_scale,
                  out=g_enc[:, d:])
        torch.mm(g_enc.t(), h1, out=gw2)
        torch.sum(g_enc, 0, out=gb2)
        g_h1 = torch.ops.aten.threshold_backward(torch.mm(g_enc, w2), h1, 0.0)
        torch.mm(g_h1.t(), x, out=gw1)
        torch.sum(g_h1, 0, out=gb1)
        return self.grads

    @torch.no_grad()
    def step(self, x: torch.Tensor, gen: torch.Generator) -> None:
        self.gradients(x, gen)
        self.steps.add_(1)
        torch._fused_adam_(self.params, self.grads, self.exp_avgs, self.exp_avg_sqs, [],
                           [self.steps] * len(self.params), lr=self.lr, beta1=BETAS[0], beta2=BETAS[1],
                           weight_decay=0.0, eps=EPS, amsgrad=False, maximize=False)
