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

and back through the two ReLU layers of each network with the weights as nn.Linear stores them, then one step
of the reference's optimiser (torch.optim.Adam with VAEDomain.optimizer_options) through fused_adam_step. The
random draws are the reference's, in its order (the batch's indices, then ε). The reference, train_base(...,
reference=True), is the autograd loop; tests/test_vae.py holds the two to float rounding, gradients and
weights. The result is an ordinary VAE module.

The pieces below (forward halves, the reconstruction's and the codes' gradients, each network's backward, the
Adam step) are also the cell's update (asp_dist.domains.vae.hand_derived), which adds P's rows and the
adversary's term to them.
"""

from __future__ import annotations

import torch
from torch import nn

from asp_dist.domains.vae import VAEDomain

Layer = tuple[torch.Tensor, torch.Tensor]  # (weight as nn.Linear stores it, bias), outside autograd


def linear_layers(vae: nn.Module) -> list[Layer]:
    """The VAE's four Linear layers (encoder in, out; decoder in, out) as detached views: Adam updates the
    parameters in place and the views see it. Raises if the VAE has other parameters."""
    modules = (vae.encoder[0], vae.encoder[2], vae.decoder[0], vae.decoder[2])
    if [p.data_ptr() for m in modules for p in (m.weight, m.bias)] != [p.data_ptr() for p in vae.parameters()]:
        raise ValueError("a hand-derived VAE update needs a VAE whose parameters are its four Linear layers")
    return [(m.weight.detach(), m.bias.detach()) for m in modules]


def encode(layers: list[Layer], x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(hidden, [μ, log σ²]) of rows x."""
    (w1, b1), (w2, b2) = layers[:2]
    h1 = torch.addmm(b1, x, w1.t()).clamp_(min=0)
    return h1, torch.addmm(b2, h1, w2.t())


def sample(enc: torch.Tensor, d: int, gen: torch.Generator) -> tuple[torch.Tensor, ...]:
    """μ, log σ², σ, ε and z = μ + σ ε of encoder outputs `enc` (as game.sample_code draws ε)."""
    mu, logvar = enc[:, :d], enc[:, d:]
    std = torch.exp(0.5 * logvar)
    eps = torch.randn(mu.shape, generator=gen)
    return mu, logvar, std, eps, mu + std * eps


def decode(layers: list[Layer], codes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(hidden, logits) of codes."""
    (w3, b3), (w4, b4) = layers[2:]
    h3 = torch.addmm(b3, codes, w3.t()).clamp_(min=0)
    return h3, torch.addmm(b4, h3, w4.t())


def recon_grad_(pixels: torch.Tensor, x: torch.Tensor, scale: float, kind: str) -> torch.Tensor:
    """∂(scale · Σ reconstruction loss)/∂logits, in place of `pixels` = σ(logits): BCE or squared error. Each
    product in autograd's order, so that the gradients round as the reference's do."""
    if kind == "bce":
        return pixels.sub_(x).mul_(scale)
    return pixels.copy_((pixels - x).mul_(2.0).mul_(scale).mul_(1.0 - pixels).mul_(pixels))


def code_grads(g_z: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor, std: torch.Tensor, eps: torch.Tensor,
               kl_scale: float, out: torch.Tensor) -> None:
    """Into out = [∂/∂μ, ∂/∂log σ²]: z's gradient g_z (consumed) through z = μ + σ ε, plus kl_scale times the
    KL term's."""
    d = mu.shape[1]
    torch.add(g_z, mu, alpha=kl_scale, out=out[:, :d])
    torch.add(g_z.mul_(eps).mul_(std).mul_(0.5), torch.exp(logvar).sub_(1.0), alpha=0.5 * kl_scale, out=out[:, d:])


def decoder_backward(layers: list[Layer], grads: list[torch.Tensor], g: torch.Tensor, h3: torch.Tensor,
                     codes: torch.Tensor) -> torch.Tensor:
    """The decoder's weight and bias gradients (grads[4:8]) from ∂/∂logits `g`; returns ∂/∂(its hidden layer's
    input), before the first layer's weight (the caller takes the rows it needs through it)."""
    (_, _), (w4, _) = layers[2:]
    gw3, gb3, gw4, gb4 = grads[4:]
    torch.mm(g.t(), h3, out=gw4)
    torch.sum(g, 0, out=gb4)
    g_h3 = torch.ops.aten.threshold_backward(torch.mm(g, w4), h3, 0.0)
    torch.mm(g_h3.t(), codes, out=gw3)
    torch.sum(g_h3, 0, out=gb3)
    return g_h3


def encoder_backward(layers: list[Layer], grads: list[torch.Tensor], g_enc: torch.Tensor, h1: torch.Tensor,
                     x: torch.Tensor) -> None:
    """The encoder's weight and bias gradients (grads[0:4]) from ∂/∂[μ, log σ²]; no gradient for the images."""
    (_, _), (w2, _) = layers[:2]
    gw1, gb1, gw2, gb2 = grads[:4]
    torch.mm(g_enc.t(), h1, out=gw2)
    torch.sum(g_enc, 0, out=gb2)
    g_h1 = torch.ops.aten.threshold_backward(torch.mm(g_enc, w2), h1, 0.0)
    torch.mm(g_h1.t(), x, out=gw1)
    torch.sum(g_h1, 0, out=gb1)


def fused_adam_step(opt: torch.optim.Optimizer) -> None:
    """opt.step() of a fused torch.optim.Adam with one parameter group and no options beyond lr, betas and
    eps: the same state entries and the same two kernels (the step counts' add, then torch._fused_adam_), without
    the Python around them (≈ 0.15 ms per VAE update on the machines of docs/performance.md). Anything else
    is stepped by opt.step() itself."""
    (group,) = opt.param_groups if len(opt.param_groups) == 1 else (None,)
    plain = group is not None and isinstance(opt, torch.optim.Adam) and group["fused"] and not (
        group["amsgrad"] or group["weight_decay"] or group["maximize"] or group["capturable"]
        or group["differentiable"] or group.get("decoupled_weight_decay") or torch.is_tensor(group["lr"]))
    if not plain:
        opt.step()
        return
    params = group["params"]
    states = [opt.state[p] for p in params]
    for p, state in zip(params, states):
        if not state:  # Adam._init_group's entries for a fused group
            state["step"] = torch.zeros((), dtype=torch.float32)
            state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
    steps = [st["step"] for st in states]
    torch._foreach_add_(steps, 1)
    beta1, beta2 = group["betas"]
    torch._fused_adam_(params, [p.grad for p in params], [st["exp_avg"] for st in states],
                       [st["exp_avg_sq"] for st in states], [], steps, amsgrad=False, lr=group["lr"], beta1=beta1,
                       beta2=beta2, weight_decay=0.0, eps=group["eps"], maximize=False)


class HandDerivedBaseUpdate:
    """One base update on `vae` (asp_dist.domains.vae.game.VAE) in place per call of step(x, gen), with the
    reference's optimiser."""

    def __init__(self, vae: nn.Module, lr: float, kl_weight: float, recon_loss: str):
        if recon_loss not in ("bce", "mse"):
            raise ValueError(f"unknown vae_recon_loss {recon_loss!r}")
        self.layers = linear_layers(vae)
        self.params = list(vae.parameters())
        self.grads = [torch.empty_like(p) for p in self.params]
        for p, g in zip(self.params, self.grads):
            p.grad = g
        self.opt = torch.optim.Adam(self.params, lr=lr, **VAEDomain.optimizer_options)
        self.d, self.kl_weight, self.recon_loss = vae.latent_dim, kl_weight, recon_loss

    def gradients(self, x: torch.Tensor, gen: torch.Generator) -> list[torch.Tensor]:
        """The loss's gradient for each parameter (in the VAE's parameter order), into self.grads."""
        n = len(x)
        h1, enc = encode(self.layers, x)  # the reference's forward, without the loss values
        mu, logvar, std, eps, z = sample(enc, self.d, gen)
        h3, logits = decode(self.layers, z)
        g = recon_grad_(torch.sigmoid(logits), x, 1.0 / n, self.recon_loss)
        g_h3 = decoder_backward(self.layers, self.grads, g, h3, z)
        g_enc = torch.empty_like(enc)
        code_grads(torch.mm(g_h3, self.layers[2][0]), mu, logvar, std, eps, self.kl_weight / n, g_enc)
        encoder_backward(self.layers, self.grads, g_enc, h1, x)
        return self.grads

    @torch.no_grad()
    def step(self, x: torch.Tensor, gen: torch.Generator) -> None:
        self.gradients(x, gen)
        fused_adam_step(self.opt)
