"""The MNIST VAE's torch half: the network, its loss, the data (MNIST images, P and U), the base,
evaluation and the figures' arrays. The card (asp_dist.domains.vae: knobs, metrics, validation,
sizes) calls the functions from "data" on, one per Domain method, and imports this module on first use.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.core.contract import SelfPlayOut
from asp_dist.data.mnist import PIXELS, load_mnist
from asp_dist.domains.vae import PAIRED_BLOCK, VAEDomain
from asp_dist.nn import seeded

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

FIGURE_LATENT_IMAGES = 1000  # test images whose codes are stored for the d = 2 scatter
FIGURE_DECIMALS = 4


class VAE(nn.Module):
    """Encoder 784→hidden→(μ, log σ²) and decoder d→hidden→784 (logits; sigmoid gives pixels)."""

    def __init__(self, latent_dim: int, hidden: int):
        super().__init__()
        self.latent_dim = latent_dim
        self.encoder = nn.Sequential(nn.Linear(PIXELS, hidden), nn.ReLU(), nn.Linear(hidden, 2 * latent_dim))
        self.decoder = nn.Sequential(nn.Linear(latent_dim, hidden), nn.ReLU(), nn.Linear(hidden, PIXELS))

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, logvar = self.encoder(x).chunk(2, dim=-1)
        return mu, logvar

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.decoder(z))

    def vae_loss(self, x: torch.Tensor, gen: torch.Generator, kl_weight: float,
                 recon_loss: str = "bce") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        """Loss per image: the reconstruction term summed over pixels — binary cross-entropy
        (Bernoulli decoder, as in the Keras VAE the paper builds on) or squared error (the
        paper's "often the mean squared error") — plus kl_weight · KL(q(z|x) || N(0, I)).
        Returns (loss, μ, the sampled z, info)."""
        mu, logvar = self.encode(x)
        z = sample_code(mu, logvar, gen)
        loss, info = vae_loss_terms(x, mu, logvar, self.decoder(z), kl_weight, recon_loss)
        return loss, mu, z, info

    def code(self, x: torch.Tensor, what: str, gen: torch.Generator) -> torch.Tensor:
        """What an adversary sees of x: the mean encoding μ, or a sampled code z ~ q(z|x)."""
        mu, logvar = self.encode(x)
        return mu if what == "mu" else sample_code(mu, logvar, gen)


def sample_code(mu: torch.Tensor, logvar: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """z ~ q(z|x) = N(μ, σ²), one draw of the generator per element."""
    return mu + torch.exp(0.5 * logvar) * torch.randn(mu.shape, generator=gen)


def vae_loss_terms(x: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor, logits: torch.Tensor,
                   kl_weight: float, recon_loss: str) -> tuple[torch.Tensor, dict]:
    """VAE.vae_loss from its forward pass (decoder logits of the sampled z): (loss, info)."""
    if recon_loss == "bce":
        recon = F.binary_cross_entropy_with_logits(logits, x, reduction="sum") / len(x)
    else:
        recon = (torch.sigmoid(logits) - x).pow(2).sum() / len(x)
    kl = (-0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(-1)).mean()
    return recon + kl_weight * kl, {"recon": float(recon.detach()), "kl": float(kl.detach())}


def paired_error(spec: CellSpec, encodings: torch.Tensor, recons: torch.Tensor, paired: dict) -> torch.Tensor:
    """The paired loss from the new VAE's μ of P's images and its reconstructions (pixels) of P's
    encodings: squared errors against the base's, summed over dimensions or averaged (vae_paired_reduction)."""
    reduce = (lambda e: e.sum(-1).mean()) if spec.vae_paired_reduction == "sum" else (lambda e: e.mean())
    return reduce((encodings - paired["encoding"]).pow(2)) + reduce((recons - paired["recon"]).pow(2))


def as_float(images: torch.Tensor) -> torch.Tensor:
    """uint8 pixels -> float32 in [0, 1]."""
    return images.to(torch.float32).div_(255.0)


def per_pixel_mse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).pow(2).mean())


# ---- data ----------------------------------------------------------------------------------
def train_images(spec: CellSpec) -> torch.Tensor:
    """uint8 training images (N x 784), the first vae_train_images of them when that is set."""
    images = load_mnist().train_images
    return images[: spec.vae_train_images] if spec.vae_train_images else images


def test_set(spec: CellSpec) -> tuple[torch.Tensor, torch.Tensor]:
    """The fixed evaluation subset: the first eval_episodes test images (float) and labels."""
    data = load_mnist()
    return as_float(data.test_images[: spec.eval_episodes]), data.test_labels[: spec.eval_episodes]


def image_rows(images: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """images[idx] for a 1-D index: index_select copies the rows directly, where advanced indexing
    costs ≈ 0.1 ms per batch of 128 on the machines of docs/performance.md (the same bytes)."""
    return images.index_select(0, idx)


def sample_indices(count: int, n: int, gen: torch.Generator) -> torch.Tensor:
    """`n` indices into `count` items: without replacement when possible."""
    if n <= count:
        return torch.randperm(count, generator=gen)[:n]
    return torch.randint(count, (n,), generator=gen)


# ---- the base convention -----------------------------------------------------------------------
def train_base(spec, seed, progress=None, *, reference=False):
    """A base VAE trained for base_train_steps updates from `seed`, and its score (per-pixel MSE of its
    own reconstructions of the test images). The updates' gradients are hand-derived
    (asp_dist.domains.vae.base_update); `reference=True` takes them from autograd instead, with
    torch.optim.Adam: the same draws and arithmetic up to float rounding."""
    from asp_dist.domains.vae.base_update import HandDerivedBaseUpdate

    images = train_images(spec)
    base = seeded(seed, lambda: VAE(spec.vae_latent_dim, spec.vae_hidden))
    gen = torch.Generator().manual_seed(seed)
    if reference:
        opt = torch.optim.Adam(base.parameters(), lr=spec.vae_base_lr, **VAEDomain.optimizer_options)
    else:
        update = HandDerivedBaseUpdate(base, spec.vae_base_lr, spec.vae_kl_weight, spec.vae_recon_loss)
    steps = spec.base_train_steps
    report_every = max(1, steps // 100)
    for step in range(steps):
        x = as_float(image_rows(images, torch.randint(len(images), (spec.vae_base_batch,), generator=gen)))
        if reference:
            loss, _, _, _ = base.vae_loss(x, gen, spec.vae_kl_weight, spec.vae_recon_loss)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        else:
            update.step(x, gen)
        if progress is not None and (step + 1) % report_every == 0:
            progress("base", step + 1, steps, {})
    base.eval()
    x_test, _ = test_set(spec)
    with torch.no_grad():
        score = per_pixel_mse(base.decode(base.encode(x_test)[0]), x_test)
    return base, score


def paired(spec, base, n, gen):
    """The first n tuples of a fixed pool. The base runs on blocks of PAIRED_BLOCK images so
    that an example's encoding does not depend on n (BLAS results vary with batch shape)."""
    images = train_images(spec)
    pool = PAIRED_BLOCK * max(1, math.ceil(n / PAIRED_BLOCK))
    idx = sample_indices(len(images), pool, gen)
    x = as_float(images[idx])
    with torch.no_grad():
        mu = torch.cat([base.encode(block)[0] for block in x.split(PAIRED_BLOCK)])
        recon = torch.cat([base.decode(block) for block in mu.split(PAIRED_BLOCK)])
    return {"image": x[:n], "encoding": mu[:n], "recon": recon[:n]}


def unpaired(spec, base, size, gen):
    images = train_images(spec)
    x = as_float(images[sample_indices(len(images), size, gen)])
    with torch.no_grad():
        return {"latent": base.code(x, spec.vae_adversary_input, gen)}


# ---- the new agents ---------------------------------------------------------------------------
def new_agents(spec, seed):
    return seeded(seed, lambda: VAE(spec.vae_latent_dim, spec.vae_hidden))


def self_play_batch(spec, gen) -> torch.Tensor:
    """The images of one self-play update (the update's first draw of the generator)."""
    images = train_images(spec)
    return as_float(image_rows(images, torch.randint(len(images), (spec.batch_size,), generator=gen)))


def self_play_out(spec, loss, mu, z, info) -> SelfPlayOut:
    return SelfPlayOut(loss=loss, outputs={"latent": mu if spec.vae_adversary_input == "mu" else z}, info=info)


def self_play_step(spec, agents, state, gen):
    x = self_play_batch(spec, gen)
    return self_play_out(spec, *agents.vae_loss(x, gen, spec.vae_kl_weight, spec.vae_recon_loss))


def paired_loss(spec, agents, paired):
    return paired_error(spec, agents.encode(paired["image"])[0], agents.decode(paired["encoding"]), paired)


def convention_outputs(spec, agents, n, gen):
    images = train_images(spec)
    x = as_float(image_rows(images, torch.randint(len(images), (n,), generator=gen)))
    return {"latent": agents.code(x, spec.vae_adversary_input, gen)}


# ---- evaluation -------------------------------------------------------------------------------
def evaluate(spec, base, agents, gen):
    x, _ = test_set(spec)
    with torch.no_grad():
        mu_base, mu_new = base.encode(x)[0], agents.encode(x)[0]
        base_to_new = per_pixel_mse(agents.decode(mu_base), x)
        new_to_base = per_pixel_mse(base.decode(mu_new), x)
        return {
            "mixed": (base_to_new + new_to_base) / 2,
            "mixed_base_encoder": base_to_new,
            "mixed_new_encoder": new_to_base,
            "self_play_new": per_pixel_mse(agents.decode(mu_new), x),
            "self_play_base": per_pixel_mse(base.decode(mu_base), x),
            "latent_mse": per_pixel_mse(mu_new, mu_base),
        }


def figure_data(spec, base, agents) -> dict[str, Any]:
    """Reconstructions of the first test image of each digit (pixels as 0..255 ints) for every
    encoder→decoder pairing; with d = 2 also both encoders' codes of a fixed test subset."""
    data = load_mnist()
    labels = data.test_labels
    picks = torch.stack([torch.nonzero(labels == digit)[0, 0] for digit in range(10)])
    x = as_float(data.test_images[picks])
    to_ints = lambda t: (t * 255).round().to(torch.uint8).tolist()  # noqa: E731
    with torch.no_grad():
        mu_base, mu_new = base.encode(x)[0], agents.encode(x)[0]
        recon = {
            "test_index": picks.tolist(), "labels": labels[picks].tolist(), "side": 28,
            "original": to_ints(x),
            "base": to_ints(base.decode(mu_base)),
            "new": to_ints(agents.decode(mu_new)),
            "base_encoder_new_decoder": to_ints(agents.decode(mu_base)),
            "new_encoder_base_decoder": to_ints(base.decode(mu_new)),
        }
        out: dict[str, Any] = {"kind": "vae_recon", "recon": recon}
        if spec.vae_latent_dim == 2:
            n = min(FIGURE_LATENT_IMAGES, len(labels))
            xs = as_float(data.test_images[:n])
            out.update({
                "kind": "latent2d",
                "base": base.encode(xs)[0].round(decimals=FIGURE_DECIMALS).tolist(),
                "new": agents.encode(xs)[0].round(decimals=FIGURE_DECIMALS).tolist(),
                "labels": labels[:n].tolist(),
            })
    return out
