"""The VAE cell's training update with hand-derived gradients: the fastest lone trainer of a VAE cell.

OnePassVAETrainer already runs each network once per update (self-play rows and P's rows in one batch). Through
autograd such an update still spent half its time or more outside its matmuls: the loss terms' forward values
(needed only in the recorded windows), the autograd engine, and the elementwise kernels of each term's
backward (bench/vae_roofline.py, docs/performance.md). This trainer computes the same gradients in closed form
(the base's, asp_dist.domains.vae.base_update, plus the paired and adversarial terms):

    self-play   w_sp · (recon + w_kl · kl)       as the base's update
    paired      w_p · (Σ|μ(P) − enc_P|² + Σ|σ(dec(enc_P)) − rec_P|²) / (rows, or rows · width: "mean")
    unpaired    w_u · L_u(D(fake)), fake = μ or z of the self-play rows: its gradient with respect to the
                fake codes from autograd through the small discriminator (the discriminators' own steps are
                the reference's Adversaries.step)

Only the self-play rows carry a gradient back through the decoder's first layer (P's encodings are data),
and no input gradient is formed for the images. The loss values are computed only for the updates whose
losses are recorded. The model's optimiser is the reference's torch.optim.Adam (the domain's fused options)
stepped on these gradients, so a checkpoint is the reference's (engine "autograd") and either trainer
resumes the other's. The draws are the reference's, in its order. tests/test_vae.py holds gradients,
weights, loss columns and draws to the reference Trainer's over a whole tiny training, for every method and
every value of the knobs below.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from asp_dist.data.mnist import PIXELS
from asp_dist.domains.vae.base_update import (
    code_grads,
    decode,
    decoder_backward,
    encode,
    encoder_backward,
    fused_adam_step,
    linear_layers,
    recon_grad_,
    sample,
)
from asp_dist.domains.vae.fast import OnePassVAETrainer
from asp_dist.domains.vae.game import self_play_batch
from asp_dist.knobs import ANY, BASE_ONLY, unimplemented
from asp_dist.spec import CellSpec
from asp_dist.training.methods import method_weights

# The knob values this update implements (asp_dist.knobs): every value of every VAE knob.
IMPLEMENTS = {
    "vae_latent_dim": ANY, "vae_hidden": ANY, "vae_kl_weight": ANY, "vae_train_images": ANY,
    "vae_recon_loss": ("bce", "mse"), "vae_adversary_input": ("mu", "z"), "vae_paired_reduction": ("sum", "mean"),
    "adversary_loss": ("neg_bce", "non_saturating"),
    "vae_base_lr": BASE_ONLY, "vae_base_batch": BASE_ONLY,
}


class HandDerivedVAETrainer(OnePassVAETrainer):
    # Capabilities (asp_dist.training.engines): a lone cell; its state_dict() is the reference Trainer's.
    implements = IMPLEMENTS

    @classmethod
    def unsupported(cls, spec: CellSpec) -> list[str]:
        """What of `spec` this trainer does not implement (empty: it trains it). Besides knob values: an adversary
        needs self-play rows for its fake codes, and without self-play or paired rows there is nothing to derive
        (the reference's zero loss); such cells train on the next trainer."""
        spec = spec.resolved()
        if spec.domain != "vae":
            return [f"domain={spec.domain!r}"]
        missing = unimplemented(cls.implements, spec)
        w = method_weights(spec)
        if not (w.needs_self_play or w.paired != 0.0):
            missing.append(f"method={spec.method!r} with paired={spec.paired} (nothing to learn)")
        elif w.needs_adversary and not w.needs_self_play:
            missing.append(f"method={spec.method!r} (an adversary without self-play)")
        return missing

    @classmethod
    def supports(cls, spec: CellSpec) -> bool:
        return not cls.unsupported(spec)

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.layers = linear_layers(self.agents)
        self.params = list(self.agents.parameters())
        self.grads = [torch.empty_like(p) for p in self.params]
        spec = self.spec
        # P is {} without paired examples (the pipeline samples none), and then λ0 is 0 (method_weights)
        self.n_paired = len(self.paired["image"]) if self.weights.paired != 0.0 else 0
        mean = spec.vae_paired_reduction == "mean"
        d = spec.vae_latent_dim
        self.enc_den, self.rec_den = (self.n_paired * d, self.n_paired * PIXELS) if mean else (self.n_paired,) * 2

    def train_step(self) -> None:
        spec, w = self.spec, self.weights_now()
        record = self.recording()
        vals: dict[str, float] | None = {} if record else None
        d, n_p, sp = spec.vae_latent_dim, self.n_paired, w.needs_self_play
        paired = self.paired

        # ---- forward: [self-play images; P's images] through the encoder, [z; P's encodings] through the decoder
        x = self_play_batch(spec, self.gen) if sp else None
        n = len(x) if sp else 0
        X = x if not n_p else paired["image"] if not sp else torch.cat([x, paired["image"]])
        h1, enc = encode(self.layers, X)
        if sp:
            mu, logvar, std, eps, z = sample(enc[:n], d, self.gen)
        D = z if not n_p else paired["encoding"] if not sp else torch.cat([z, paired["encoding"]])
        h3, logits = decode(self.layers, D)
        pixels = torch.sigmoid(logits)

        # ---- the adversary: its steps (the reference's), then L_u's gradient with respect to the fake codes
        unpaired_loss = disc_loss = g_fake = None
        if self.adversaries is not None:
            fake = (mu if spec.vae_adversary_input == "mu" else z).detach()
            for k in range(spec.disc_steps):
                real = {ch: u[torch.randint(len(u), (spec.unpaired_batch,), generator=self.gen)]
                        for ch, u in self.unpaired.items()}
                disc_loss = self.adversaries.step(real, {"latent": fake}, vals if k == 0 else None)
            leaf = fake.requires_grad_()
            with torch.enable_grad():
                unpaired_loss = self.adversaries.model_loss({"latent": leaf}, spec.adversary_loss)
                (g_fake,) = torch.autograd.grad(unpaired_loss, leaf)
            unpaired_loss = unpaired_loss.detach()
            g_fake.mul_(w.unpaired)

        if record:  # the loss values, only where they are recorded
            sp_loss = paired_loss = None
            if sp:
                if spec.vae_recon_loss == "bce":
                    recon = F.binary_cross_entropy_with_logits(logits[:n], x, reduction="sum") / n
                else:
                    recon = (pixels[:n] - x).pow(2).sum() / n
                kl = (-0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(-1)).mean()
                sp_loss = float(recon + spec.vae_kl_weight * kl)
            if n_p:
                paired_loss = float((enc[n:, :d] - paired["encoding"]).pow(2).sum() / self.enc_den
                                    + (pixels[n:] - paired["recon"]).pow(2).sum() / self.rec_den)
            total = sum(wt * v for wt, v in ((w.self_play, sp_loss), (w.paired, paired_loss),
                                             (w.unpaired, None if unpaired_loss is None else float(unpaired_loss)))
                        if wt != 0.0)
            for name, value in (("self_play", sp_loss), ("paired", paired_loss), ("unpaired", unpaired_loss),
                                ("disc", disc_loss), ("total", total)):
                if value is not None:
                    vals[name] = float(value)

        # ---- backward through the decoder (∂/∂logits in place of the pixels, not needed after this)
        if sp:
            recon_grad_(pixels[:n], x, w.self_play / n, spec.vae_recon_loss)
        if n_p:
            s = pixels[n:]
            s.copy_((s - paired["recon"]).mul_(2.0 * w.paired / self.rec_den).mul_(1.0 - s).mul_(s))
        g_h3 = decoder_backward(self.layers, self.grads, pixels, h3, D)

        # ---- into the encoder's outputs: self-play rows through z (and the KL term), P's rows from the paired term
        g_enc = torch.zeros_like(enc) if n_p else torch.empty_like(enc)
        if sp:
            g_z = torch.mm(g_h3[:n], self.layers[2][0])
            if g_fake is not None and spec.vae_adversary_input == "z":
                g_z.add_(g_fake)
            code_grads(g_z, mu, logvar, std, eps, w.self_play * spec.vae_kl_weight / n, g_enc[:n])
            if g_fake is not None and spec.vae_adversary_input == "mu":
                g_enc[:n, :d].add_(g_fake)
        if n_p:
            torch.mul(enc[n:, :d] - paired["encoding"], 2.0 * w.paired / self.enc_den, out=g_enc[n:, :d])
        encoder_backward(self.layers, self.grads, g_enc, h1, X)

        for p, grad in zip(self.params, self.grads):
            p.grad = grad
        fused_adam_step(self.opt)
        if record:
            self.record(vals)
        self.step += 1
        self.finish_curve_point()
