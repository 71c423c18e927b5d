"""The MNIST VAE domain: the latent code is the convention.

A base VAE (encoder 784→512→(μ, log σ²), decoder d→512→784 with a sigmoid) is trained on MNIST.
A new VAE must adopt the base's mapping between images and codes, so that its encoder works
with the base decoder and its decoder with the base encoder (the paper's "Autoencoder").

- Self-play of the new VAE is its own VAE loss on a batch of MNIST training images.
- Paired set P: (image, base encoding μ, base reconstruction decode(μ)) tuples; image→encoding
  trains the new encoder, encoding→reconstruction the new decoder (squared error).
- Unpaired set U and the convention channel ``"latent"``: μ, the encoder's mean. μ (not a
  sample z) because μ is what the mixed teams exchange at evaluation and what P's encodings
  are, so the adversary, the paired loss and the metric all look at the same quantity; a sample
  would add noise of the model's own σ that the discriminator could key on instead of the map.
- Metrics (lower is better), per-pixel MSE on MNIST test images in [0, 1], decoding μ:
  base-encoder→new-decoder, new-encoder→base-decoder, their mean (``mixed``, the paper's Eq. 1),
  the new VAE's own reconstruction and the base's.

Losses are sums over pixels (and latent dimensions), averaged over examples, the usual VAE
scale: one paired example then weighs about as much as one self-play image when λ0 = 1.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.data.mnist import PIXELS, load_mnist
from asp_dist.domains.contract import Domain, MetricInfo, PaperFacts, SelfPlayOut, require
from asp_dist.nn import seeded

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

FIGURE_LATENT_IMAGES = 1000  # test images whose codes are stored for the d = 2 scatter
FIGURE_DECIMALS = 4
PAIRED_BLOCK = 256  # paired examples come from a pool drawn and encoded in blocks of this size


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


class VAEDomain(Domain):
    name = "vae"
    channels = ("latent",)
    accept_field = None  # every base is kept; its test MSE is recorded as base_score
    paper = PaperFacts(
        metric_label="mixed reconstruction MSE per pixel",
        claim="ASP better reconstructions than OSP and PC at intermediate paired counts; robust to latent size",
        test_paired=(8, 32),
        threshold=(0.06, "paper: MSE 0.06 ~ right digit"),
        knob_labels={"vae_latent_dim": "latent size d (dimensions)"},
    )
    defaults = dict(
        vae_latent_dim=32, vae_hidden=512, vae_kl_weight=1.0, vae_base_lr=1e-3, vae_base_batch=128,
        vae_train_images=0,
        base_train_steps=5000,
        train_steps=1000, batch_size=64, lr=1e-3,
        # λ1 = 10: at 1 the discriminator wins outright and the saturating -BCE gives the model ~1 % of
        # its gradient (reproduction study: docs/reproduction.md, docs/decisions.md).
        lambda_paired=1.0, lambda_unpaired=10.0, unpaired_size=2048,
        disc_hidden=64, disc_layers=2, disc_lr=1e-3,
        eval_episodes=10_000,
    )
    # One Adam kernel for all parameters: 0.48 ms per step of the 853k-parameter VAE against 2.6 ms
    # for torch's default per-tensor loop (one thread; docs/decisions.md), a quarter of an OSP update.
    optimizer_options = {"fused": True}
    unpaired_fields = ("vae_adversary_input",)  # U holds the base's μ or sampled z
    metrics = {
        "mixed": MetricInfo(False, "Eq. 1: mean of the two mixed MSEs (base enc→new dec, new enc→base dec)"),
        "mixed_base_encoder": MetricInfo(False, "per-pixel test MSE of base encoder → new decoder"),
        "mixed_new_encoder": MetricInfo(False, "per-pixel test MSE of new encoder → base decoder"),
        "self_play_new": MetricInfo(False, "per-pixel test MSE of the new VAE on its own (μ decoded)"),
        "self_play_base": MetricInfo(False, "per-pixel test MSE of the base VAE on its own (μ decoded)"),
        "latent_mse": MetricInfo(False, "mean squared difference per latent dimension of new and base μ on test images"),
    }

    # ---- spec --------------------------------------------------------------------------------
    def validate(self, spec: CellSpec) -> None:
        require(spec.vae_latent_dim >= 1, f"vae_latent_dim must be >= 1, got {spec.vae_latent_dim}")
        require(spec.vae_hidden >= 1, f"vae_hidden must be >= 1, got {spec.vae_hidden}")
        require(spec.vae_base_batch >= 1, f"vae_base_batch must be >= 1, got {spec.vae_base_batch}")
        require(spec.vae_base_lr > 0, f"vae_base_lr must be > 0, got {spec.vae_base_lr}")
        require(spec.vae_train_images <= 60_000, f"vae_train_images must be 0 (all) or at most 60000, got {spec.vae_train_images}")
        require(spec.eval_episodes <= 10_000, f"eval_episodes (test images) must be at most 10000, got {spec.eval_episodes}")

    # [the paper's values in brackets] widths of the weight matrices; images of a base batch (784 pixels each)
    upper_bounds = {"vae_latent_dim": 16_384, "vae_hidden": 16_384, "vae_base_batch": 1_000_000}  # [128, 512, 128]

    def tensor_sizes(self, spec: CellSpec) -> dict[str, int]:
        width = max(PIXELS, spec.vae_hidden, 2 * spec.vae_latent_dim)  # an image, a hidden layer or (μ, log σ²)
        rows = {"batch_size": spec.batch_size, "vae_base_batch": spec.vae_base_batch,
                "paired": PAIRED_BLOCK * max(1, math.ceil(spec.paired / PAIRED_BLOCK)),
                "unpaired_size": spec.unpaired_size, "unpaired_batch": spec.unpaired_batch,
                "eval_episodes": spec.eval_episodes}
        return {"vae_hidden × 784 pixels": spec.vae_hidden * PIXELS,
                "vae_hidden × vae_latent_dim": 2 * spec.vae_hidden * spec.vae_latent_dim,
                **{f"{knob} × width {width}": n * width for knob, n in rows.items()}}

    def channel_dims(self, spec: CellSpec) -> dict[str, int]:
        return {"latent": spec.vae_latent_dim}

    # ---- data ----------------------------------------------------------------------------------
    @staticmethod
    def train_images(spec: CellSpec) -> torch.Tensor:
        """uint8 training images (N x 784), the first vae_train_images of them when that is set."""
        images = load_mnist().train_images
        return images[: spec.vae_train_images] if spec.vae_train_images else images

    @staticmethod
    def test_set(spec: CellSpec) -> tuple[torch.Tensor, torch.Tensor]:
        """The fixed evaluation subset: the first eval_episodes test images (float) and labels."""
        data = load_mnist()
        return as_float(data.test_images[: spec.eval_episodes]), data.test_labels[: spec.eval_episodes]

    @staticmethod
    def sample_indices(count: int, n: int, gen: torch.Generator) -> torch.Tensor:
        """`n` indices into `count` items: without replacement when possible."""
        if n <= count:
            return torch.randperm(count, generator=gen)[:n]
        return torch.randint(count, (n,), generator=gen)

    # ---- the base convention -----------------------------------------------------------------------
    def train_base(self, spec, seed, progress=None):
        images = self.train_images(spec)
        base = seeded(seed, lambda: VAE(spec.vae_latent_dim, spec.vae_hidden))
        gen = torch.Generator().manual_seed(seed)
        opt = torch.optim.Adam(base.parameters(), lr=spec.vae_base_lr, **self.optimizer_options)
        steps = spec.base_train_steps
        report_every = max(1, steps // 100)
        for step in range(steps):
            x = as_float(images[torch.randint(len(images), (spec.vae_base_batch,), generator=gen)])
            loss, _, _, _ = base.vae_loss(x, gen, spec.vae_kl_weight, spec.vae_recon_loss)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if progress is not None and (step + 1) % report_every == 0:
                progress("base", step + 1, steps, {})
        base.eval()
        x_test, _ = self.test_set(spec)
        with torch.no_grad():
            score = per_pixel_mse(base.decode(base.encode(x_test)[0]), x_test)
        return base, score

    def paired(self, spec, base, n, gen):
        """The first n tuples of a fixed pool. The base runs on blocks of PAIRED_BLOCK images so
        that an example's encoding does not depend on n (BLAS results vary with batch shape)."""
        images = self.train_images(spec)
        pool = PAIRED_BLOCK * max(1, math.ceil(n / PAIRED_BLOCK))
        idx = self.sample_indices(len(images), pool, gen)
        x = as_float(images[idx])
        with torch.no_grad():
            mu = torch.cat([base.encode(block)[0] for block in x.split(PAIRED_BLOCK)])
            recon = torch.cat([base.decode(block) for block in mu.split(PAIRED_BLOCK)])
        return {"image": x[:n], "encoding": mu[:n], "recon": recon[:n]}

    def unpaired(self, spec, base, size, gen):
        images = self.train_images(spec)
        x = as_float(images[self.sample_indices(len(images), size, gen)])
        with torch.no_grad():
            return {"latent": base.code(x, spec.vae_adversary_input, gen)}

    # ---- the new agents ---------------------------------------------------------------------------
    def new_agents(self, spec, seed):
        return seeded(seed, lambda: VAE(spec.vae_latent_dim, spec.vae_hidden))

    def self_play_batch(self, spec, gen) -> torch.Tensor:
        """The images of one self-play update (the update's first draw of the generator)."""
        images = self.train_images(spec)
        return as_float(images[torch.randint(len(images), (spec.batch_size,), generator=gen)])

    @staticmethod
    def self_play_out(spec, loss, mu, z, info) -> SelfPlayOut:
        return SelfPlayOut(loss=loss, outputs={"latent": mu if spec.vae_adversary_input == "mu" else z}, info=info)

    def self_play_step(self, spec, agents, state, gen):
        x = self.self_play_batch(spec, gen)
        return self.self_play_out(spec, *agents.vae_loss(x, gen, spec.vae_kl_weight, spec.vae_recon_loss))

    def paired_loss(self, spec, agents, paired):
        return paired_error(spec, agents.encode(paired["image"])[0], agents.decode(paired["encoding"]), paired)

    def convention_outputs(self, spec, agents, n, gen):
        images = self.train_images(spec)
        x = as_float(images[torch.randint(len(images), (n,), generator=gen)])
        return {"latent": agents.code(x, spec.vae_adversary_input, gen)}

    # ---- evaluation -------------------------------------------------------------------------------
    def evaluate(self, spec, base, agents, gen):
        x, _ = self.test_set(spec)
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

    def figure_data(self, spec, base, agents) -> dict[str, Any]:
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
