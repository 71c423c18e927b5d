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

from asp_dist.data.mnist import PIXELS
from asp_dist.domains.contract import GameDomain, MetricInfo, PaperFacts, game_attribute, require

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

PAIRED_BLOCK = 256  # paired examples come from a pool drawn and encoded in blocks of this size


class VAEDomain(GameDomain):
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


def __getattr__(name: str) -> Any:
    """The game's names (VAE, vae_loss_terms, paired_error, train_images, ...), imported on first access."""
    return game_attribute(__name__, name)
