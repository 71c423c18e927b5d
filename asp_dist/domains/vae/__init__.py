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

from asp_dist.core.contract import GameDomain, MetricInfo, PaperFacts, game_attribute, require
from asp_dist.data.mnist import PIXELS
from asp_dist.knobs import Knob, choice

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
    knobs = (  # name, type, default, doc; choices, neutral value, base-shaping, bound
        Knob('vae_latent_dim', int, 32, 'Latent size d (paper: 32; grid 2..128).', bound=16_384),
        Knob('vae_hidden', int, 512, 'Hidden units of encoder and decoder (paper: 512).', bound=16_384),
        Knob('vae_kl_weight', float, 1.0, 'Weight of the KL term of the VAE loss.'),
        Knob('vae_base_lr', float, 0.001, 'Adam learning rate of the base VAE.'),
        Knob('vae_base_batch', int, 128, 'Batch size of base VAE training (paper: 128).', bound=1_000_000),
        Knob('vae_train_images', int, 0, 'Use only the first N training images (0 = all 60k); for tests.'),
        Knob('vae_recon_loss', str, 'bce',
             'Reconstruction term of the VAE loss: bce (Bernoulli, summed over pixels) | mse (squared error summed '
             'over pixels).', choices=('bce', 'mse'), neutral='bce', optional=False),
        Knob('vae_adversary_input', str, 'mu',
             'What the adversary compares: mu (mean encodings) | z (sampled codes).', choices=('mu', 'z'),
             neutral='mu', shapes_base=False, optional=False, search=choice('mu', 'z', needs=('adversarial',))),
        Knob('vae_paired_reduction', str, 'sum',
             'Paired MSE summed over latent dims and pixels (sum) or averaged (mean).', choices=('sum', 'mean'),
             neutral='sum', shapes_base=False, optional=False, search=choice('sum', 'mean', needs=('paired',))),
    )
    legacy_identity = True  # knobs recorded as CellSpec fields before domains were plugins
    protocol_defaults = dict(lambda_unpaired=1.0)  # before the reproduction study changed them
    # A cell in about a second (asp-dist check-domain, the registry-wide tests)
    smoke = dict(vae_train_images=300, vae_hidden=64, vae_latent_dim=4, base_train_steps=40, vae_base_batch=32,
                 train_steps=20, batch_size=32, unpaired_size=64, eval_episodes=200, disc_hidden=16)
    defaults = dict(
        base_train_steps=5000,
        train_steps=1000, batch_size=64, lr=1e-3,
        # λ1 = 10: at 1 the discriminator wins outright and the saturating -BCE gives the model ~1 % of
        # its gradient (reproduction study: docs/reproduction.md,
        # docs/decisions/0021-domain-defaults-from-reproduction-study.md).
        lambda_paired=1.0, lambda_unpaired=10.0, unpaired_size=2048,
        disc_hidden=64, disc_layers=2, disc_lr=1e-3,
        eval_episodes=10_000,
    )
    # One Adam kernel for all parameters: 0.48 ms per step of the 853k-parameter VAE against 2.6 ms
    # for torch's default per-tensor loop (one thread; docs/decisions/0019-vae-fused-adam-one-pass.md), a
    # quarter of an OSP update.
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


    def check_data(self, specs: list[CellSpec]) -> None:
        from asp_dist.data.mnist import load_mnist

        load_mnist()  # verifies the copy (MNISTError names what is wrong)

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
