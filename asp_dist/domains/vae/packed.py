"""K VAE cells trained as one batched model: the packed counterpart of the one-pass single-cell trainer.

run_cell trains a single VAE cell on asp_dist.domains.vae.fast.OnePassVAETrainer (this trainer is not
`lone`): per update the self-play VAE loss of batch_size training images (BCE or squared
error summed over pixels, plus kl_weight·KL), the paired loss on P (squared errors of the new
encoder's μ against the base's encodings and of the new decoder's pixels against the base's
reconstructions, summed or averaged), and for ASP disc_steps BCE steps of a discriminator on U
(real) against the self-play batch's μ or z (fake), then λ1·L_u through the updated discriminator;
one fused Adam step. The one-pass trainer runs each network once per update on the self-play rows
and P's rows together. This trainer does the same for K cells ("members") at once: every parameter
is stacked on a leading member dimension (StackedParams: one flat buffer, one fused Adam step for
all), each layer is one batched matmul (torch.baddbmm) over the members' rows [self-play batch,
P's rows], and the gradient is plain autograd over the stacked parameters (leaves that share the
buffer's storage; the gradients are copied into its gradient buffer). The ASP members'
discriminators are stacked likewise (a second StackedParams, its own fused Adam step).

Unlike the particle and lever trainers, nothing is hand-derived: a VAE update is a few large
matmuls (784 × hidden per image), so autograd's per-op overhead is small against them, and what
stacking saves is the per-op overhead of the elementwise ops and of the Adam pass.

What stays per member, so that a member's result does not depend on its pack-mates:

- loss weights (PC / OSP / ASP differ only in them), λ0, λ1 and its schedule (methods.lambda_factor),
  the KL weight, the reconstruction loss (bce | mse), the adversary's input (μ | z), the paired
  reduction (sum | mean), the adversarial loss (neg_bce | non_saturating), both learning rates:
  per-member columns (a knob whose values differ within the pack is computed both ways and
  selected per member with torch.where, whose gradient to the branch not taken is exactly 0);
- data: its own P (padded to the pack's largest, padded rows masked out of the sums), its own U
  (the ASP members' sets concatenated, each member's indices drawn in its own range and offset),
  its own range of training images (vae_train_images);
- random streams: its own generator, seeded as Trainer seeds it, drawn in Trainer's order. No draw
  depends on a value (the self-play batch's image indices, z's normal noise, disc_steps batches of
  indices into U), so the draws of up to CHUNK updates are made ahead, member by member with that
  member's generator and in the single-cell order, and the batched update consumes them. A
  generator ends training in the single-cell run's state. PC members draw nothing (their
  self-play rows ride along with weight 0, on image 0 and zero noise, their log σ² replaced by 0 so
  that nothing of theirs can be non-finite: torch.where's gradient to them is exactly 0).

Independence of pack-mates: no op mixes members (batched matmuls, elementwise ops, reductions along
rows or features; the losses are summed over members only for autograd, whose gradient of a sum is
1 for every member whatever the values), padded rows add exact zeros, and a frozen member keeps its
place in every call. So a member's arithmetic is bit for bit the same whatever its mates are, as
long as the pack's shapes are the same (number of members and of ASP members, padded paired rows);
with other shapes some kernels round differently, by float rounding. The same holds against the
single-cell path: its matmuls have other shapes (2-D, and B + n rows instead of B + the pack's
largest n), so a member's weights differ from its single-cell run's by float rounding (~1e-7 per
update). The VAE has no discrete choice but ReLU and leaky-ReLU kinks, so such differences stay
small over a cell (tests/test_packed_vae.py).

A member whose network gradient becomes non-finite (checked every update, before the Adam step),
whose discriminator's gradient does (checked before each discriminator step) or whose recorded loss
does is frozen: its gradients are zeroed and its momentum cleared, so Adam leaves its parameters
and its discriminator's at their last finite values, and it is reported failed.

Packs: any mix of methods, paired counts, trials and per-member knobs, provided the members agree
on the fields in SHARED (tensor shapes, the length of training). Mixed packs compute the union of
the members' work (a PC member rides along in the self-play rows with weight 0), so packs of one
method are cheapest. Every VAE knob value is implemented (IMPLEMENTS).
"""

from __future__ import annotations

from typing import Any, Sequence

import torch
import torch.nn.functional as F

from asp_dist.core.contract import Tensors
from asp_dist.data.mnist import PIXELS
from asp_dist.domains.vae.game import VAE, train_images
from asp_dist.knobs import ANY, BASE_ONLY
from asp_dist.spec import CellSpec
from asp_dist.training.stacked import PackedTrainer, StackedParams, asp_members_first, column

__all__ = ["PackedVAETrainer", "pack_key", "IMPLEMENTS", "SHARED", "IN_SWEEPS"]

# Sweeps leave VAE cells single (PackedVAETrainer.in_sweeps, asp_dist.training.engines.sweep_packs): on the 2-core CPU machine a
# pack is slower per member-update than OnePassVAETrainer alone at every size and composition measured
# (0.3-0.95x; docs/performance.md, "Packed VAE trainer, measured"). Profiled (10 PC members): the
# batched matmuls of the backward pass take twice the 2-D matmuls' time for the same arithmetic, and
# copying autograd's gradients into the stacked buffer adds a quarter; a VAE update is already a few
# large matmuls, so there is little per-op overhead for stacking to save. Packs follow from the grid,
# the packing and this flag: setting it True regroups the VAE cells of an unfinished --pack sweep when
# it resumes, so finish such sweeps first.
IN_SWEEPS = False

# Fields every member of a pack shares: they fix the tensor shapes and the loop.
SHARED = ("domain", "train_steps", "batch_size", "vae_latent_dim", "vae_hidden", "disc_hidden", "disc_layers",
          "unpaired_batch", "disc_steps")
CHUNK = 32  # updates whose random draws are made ahead (z's noise: CHUNK·K·batch·d floats)
# The knob values this update implements (asp_dist.knobs): every one; a cell with another value is not
# packable and trains alone (OnePassVAETrainer).
IMPLEMENTS = {
    "vae_latent_dim": ANY, "vae_hidden": ANY, "vae_kl_weight": ANY, "vae_train_images": ANY,
    "vae_recon_loss": ("bce", "mse"), "vae_adversary_input": ("mu", "z"), "vae_paired_reduction": ("sum", "mean"),
    "adversary_loss": ("neg_bce", "non_saturating"),
    "vae_base_lr": BASE_ONLY, "vae_base_batch": BASE_ONLY,
}


def _bce(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return F.binary_cross_entropy_with_logits(logits, target, reduction="none")


class PackedVAETrainer(PackedTrainer):
    """K VAE cells as one batched model; train_step() is one update of every member.

    specs, paired, unpaired, agents: one entry per member, as Trainer gets them (run_cell: P and U
    from the member's base, a fresh VAE). The agents' parameters are re-pointed into the pack's
    buffer. After training, member i's `members[i].agents` holds its trained weights,
    `loss_columns(i)` its row's loss_* columns and `members[i].curve` its learning curve (probes:
    set `members[i].probe` as run_cell sets Trainer.probe)."""

    # Capabilities (asp_dist.training.engines): packs only; a lone VAE cell trains on OnePassVAETrainer.
    domain = "vae"
    in_sweeps = IN_SWEEPS
    implements = IMPLEMENTS
    shared = SHARED  # the pack key (PackedTrainer.pack_key)
    member_order = staticmethod(asp_members_first)  # their rows of the pack are a prefix

    def __init__(self, specs: Sequence[CellSpec], paired: Sequence[Tensors], unpaired: Sequence[Tensors],
                 agents: Sequence[VAE]):
        discs = [d for (d,) in self._init_members(specs, paired, unpaired, agents, paired_rows="image")]
        mem = self.members
        s0 = mem[0].spec
        self.B, self.d = s0.batch_size, s0.vae_latent_dim
        M, B, d = self.M, self.B, self.d

        self.sp_rows = [i for i, m in enumerate(mem) if m.self_play]
        # Members without self-play beside members with it: their self-play rows are computed (with
        # weight 0) on log σ² = 0, so nothing of theirs can overflow into a NaN gradient.
        self.sp_guard = None
        if self.any_self_play and len(self.sp_rows) < M:
            self.sp_guard = torch.tensor([m.self_play for m in mem]).view(M, 1, 1)

        # ---- training images: one tensor, each member's own range (vae_train_images) -----------------
        images = [train_images(m.spec) for m in mem]
        self.images = max(images, key=len)
        if any(im.data_ptr() != self.images.data_ptr() for im in images):
            raise ValueError("the members' training images are not prefixes of one set")
        self.image_counts = [len(im) for im in images]

        # ---- stacked parameters (autograd leaves sharing the buffers' storage) -----------------------
        self.net = StackedParams(agents, [m.spec.lr for m in mem])
        self.leaves = [v.detach().requires_grad_() for v in self.net.views]
        self.dnet = None
        if self.Ma:
            self.dnet = StackedParams(discs, [mem[i].spec.disc_lr for i in self.adv_rows])
            self.dleaves = [v.detach().requires_grad_() for v in self.dnet.views]
            slopes = {m.negative_slope for m in discs[0].net if isinstance(m, torch.nn.LeakyReLU)}
            self.slope = slopes.pop() if slopes else 0.01

        # ---- paired data (padded to the largest set; padded rows masked) ------------------------------
        n_max = max(m.n_paired for m in mem)
        self.n = n_max
        R = (B if self.any_self_play else 0) + n_max
        self.X = torch.zeros(M, R, PIXELS)  # encoder input: [self-play images, P's images]
        self.p_off = B if self.any_self_play else 0
        self.p_enc, self.p_rec = torch.zeros(M, n_max, d), torch.zeros(M, n_max, PIXELS)
        self.p_mask = torch.zeros(M, n_max)
        enc_den, rec_den = [1.0] * M, [1.0] * M
        for i, (m, p) in enumerate(zip(mem, paired)):
            k = m.n_paired
            if k:
                self.X[i, self.p_off:self.p_off + k] = p["image"]
                self.p_enc[i, :k], self.p_rec[i, :k] = p["encoding"], p["recon"]
                self.p_mask[i, :k] = 1.0
                mean = m.spec.vae_paired_reduction == "mean"
                enc_den[i], rec_den[i] = (k * d, k * PIXELS) if mean else (k, k)
        # paired_error divides by the row count (sum) or the element count (mean): the same divisions
        self.enc_den, self.rec_den = column(enc_den).view(-1), column(rec_den).view(-1)

        # ---- per-member constants of the update (the single-cell trainer's Python scalars) -----------
        sp = [m.spec for m in mem]
        self.w_sp = column([m.weights.self_play for m in mem]).view(-1)
        self.w_p = column([m.weights.paired for m in mem]).view(-1)
        self.klw = column([s.vae_kl_weight for s in sp]).view(-1)
        kinds = {s.vae_recon_loss for i, s in enumerate(sp) if i in self.sp_rows}
        self.recon_kind = kinds.pop() if len(kinds) == 1 else "mixed"
        self.recon_bce = torch.tensor([s.vae_recon_loss == "bce" for s in sp])

        # ---- discriminator data: the ASP members' U, concatenated ----------------------------------
        if self.Ma:
            ub = self.ub
            adv_specs = [mem[i].spec for i in self.adv_rows]
            self.u_sizes = [len(unpaired[i]["latent"]) for i in self.adv_rows]
            self.U = torch.cat([unpaired[i]["latent"] for i in self.adv_rows]).detach()
            starts = torch.tensor([0] + self.u_sizes[:-1]).cumsum(0)
            self.u_offset = starts.view(self.Ma, 1)
            inputs = {s.vae_adversary_input for s in adv_specs}
            self.adv_input = inputs.pop() if len(inputs) == 1 else "mixed"
            self.use_z = torch.tensor([s.vae_adversary_input == "z" for s in adv_specs]).view(self.Ma, 1, 1)
            losses = {s.adversary_loss for s in adv_specs}
            self.adv_loss = losses.pop() if len(losses) == 1 else "mixed"
            self.ns = torch.tensor([s.adversary_loss == "non_saturating" for s in adv_specs])
            self.disc_labels = torch.cat([torch.ones(ub), torch.zeros(B)]).expand(self.Ma, ub + B)
            self.fake_zeros, self.fake_ones = torch.zeros(self.Ma, B), torch.ones(self.Ma, B)

        # ---- bookkeeping, as Trainer's ----------------------------------------------------------------
        self._init_records()
        self._alloc_draws()

    # ---- random draws, made ahead per member in the single-cell order ---------------------------
    def _alloc_draws(self) -> None:
        M, B, d = self.M, self.B, self.d
        self.img_idx = torch.zeros(CHUNK, M, B, dtype=torch.long)  # self-play images (0 for members without)
        self.noise = torch.zeros(CHUNK, M, B, d)                    # z's noise (0 for members without)
        self.real_idx = torch.zeros(CHUNK * self.disc_steps, self.Ma, self.ub, dtype=torch.long)
        if self.Ma:
            self.lam_now = torch.zeros(CHUNK, self.Ma, dtype=torch.float64)  # λ1 of the update
            self.lam32 = torch.zeros(CHUNK, self.Ma)                          # its float32 rounding

    def _draw_chunk(self) -> None:
        """The random draws of updates [step, step + CHUNK) (not past train_steps), member by member,
        with the calls the single-cell trainer makes, in its order: the self-play batch's indices
        (randint), z's noise (randn), then disc_steps batches of indices into U (randint)."""
        start, S, adv_slot = self._open_chunk(CHUNK)
        B, d, ub, ds = self.B, self.d, self.ub, self.disc_steps
        for i, m in enumerate(self.members):
            if not m.self_play:  # PC draws nothing
                continue
            gen, count = m.gen, self.image_counts[i]
            idx, noise = self.img_idx[:S, i].unbind(0), self.noise[:S, i].unbind(0)
            real = self.real_idx[:S * ds, adv_slot[i]].unbind(0) if m.adversary else ()
            high = self.u_sizes[adv_slot[i]] if m.adversary else 0
            for s in range(S):
                torch.randint(count, (B,), generator=gen, out=idx[s])  # asp_dist.domains.vae.game.self_play_batch
                torch.randn((B, d), generator=gen, out=noise[s])       # vae.sample_code
                for k in range(ds if m.adversary else 0):
                    torch.randint(high, (ub,), generator=gen, out=real[s * ds + k])
        if self.Ma:
            self.real_flat = (self.real_idx[:S * ds] + self.u_offset.unsqueeze(0)).view(S * ds, -1)
            self._lambda_chunk(start, S)
            self.lam32[:S] = self.lam_now[:S].float()

    # ---- one update of every member -------------------------------------------------------------
    @torch.enable_grad()
    def train_step(self) -> None:
        j, vals = self._begin_update()
        record = vals is not None
        M, B, n = self.M, self.B, self.n
        if not self.any_self_play and not n:  # nothing to learn in any member (PC without paired data)
            if record:
                self._record({}, j)
            self.step += 1
            self._finish_curve_point()
            return

        We1, be1, We2, be2, Wd1, bd1, Wd2, bd2 = self.leaves
        X = self.X
        if self.any_self_play:  # this update's images into the self-play rows (VAEDomain.as_float)
            x = X[:, :B]
            x.copy_(self.images.index_select(0, self.img_idx[j].view(-1)).view(M, B, PIXELS)).div_(255.0)

        # ---- encoder and decoder, each once over [self-play rows, P's rows] --------------------------
        h = torch.relu(torch.baddbmm(be1, X, We1.transpose(1, 2)))
        mu_all, logvar_all = torch.baddbmm(be2, h, We2.transpose(1, 2)).chunk(2, dim=-1)
        codes = []
        if self.any_self_play:
            mu, logvar = mu_all[:, :B], logvar_all[:, :B]
            if self.sp_guard is not None:
                logvar = torch.where(self.sp_guard, logvar, 0.0)
            z = mu + torch.exp(0.5 * logvar) * self.noise[j]
            codes.append(z)
        if n:
            codes.append(self.p_enc)
        hd = torch.relu(torch.baddbmm(bd1, codes[0] if len(codes) == 1 else torch.cat(codes, 1), Wd1.transpose(1, 2)))
        logits = torch.baddbmm(bd2, hd, Wd2.transpose(1, 2))

        # ---- the loss terms, per member ----------------------------------------------------------------
        total = None
        if self.any_self_play:
            ls = logits[:, :B]
            if self.recon_kind == "bce":
                recon = _bce(ls, x).sum((1, 2)) / B
            elif self.recon_kind == "mse":
                recon = (torch.sigmoid(ls) - x).pow(2).sum((1, 2)) / B
            else:
                recon = torch.where(self.recon_bce, _bce(ls, x).sum((1, 2)) / B,
                                    (torch.sigmoid(ls) - x).pow(2).sum((1, 2)) / B)
            kl = (-0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(-1)).mean(1)
            sp_loss = recon + self.klw * kl
            total = (self.w_sp * sp_loss).sum()
            if record:
                vals["self_play"] = sp_loss.detach()
        if n:
            off = self.p_off
            enc_err = (mu_all[:, off:] - self.p_enc).pow(2).sum(-1)
            rec_err = (torch.sigmoid(logits[:, off:]) - self.p_rec).pow(2).sum(-1)
            paired_loss = (enc_err * self.p_mask).sum(1) / self.enc_den + (rec_err * self.p_mask).sum(1) / self.rec_den
            term = (self.w_p * paired_loss).sum()
            total = term if total is None else total + term
            if record:
                vals["paired"] = paired_loss.detach()

        # ---- ASP: discriminator steps, then the model's adversarial term through the updated ones -----
        if self.Ma:
            total = total + self._adversarial(self._adv(mu), self._adv(z), j, vals)

        # ---- gradient, then one Adam step for every member ---------------------------------------------
        grads = torch.autograd.grad(total, self.leaves, allow_unused=True)
        for g, out in zip(grads, self.net.grad_views):
            if g is None:
                out.zero_()
            else:
                out.copy_(g.view_as(out))
        # One Adam step for every member (a member whose gradient is not finite frozen first).
        self._step_model(vals, j, record)

    def _adversarial(self, mu: torch.Tensor, z: torch.Tensor, j: int, vals: dict | None) -> torch.Tensor:
        """disc_steps BCE steps of each ASP member's discriminator on U (real) against its self-play
        μ or z (fake), then Σ over the ASP members of λ1·L_u through the updated discriminator.
        `mu`, `z`: the ASP members' self-play rows (Ma, B, d)."""
        Ma, ub, ds = self.Ma, self.ub, self.disc_steps
        if self.adv_input == "mu":
            fake = mu
        elif self.adv_input == "z":
            fake = z
        else:
            fake = torch.where(self.use_z, z, mu)
        fake_d = fake.detach()
        for k in range(ds):
            real = self.U.index_select(0, self.real_flat[j * ds + k]).view(Ma, ub, self.d)
            logits = self._disc_forward(torch.cat([real, fake_d], 1), self.dleaves)
            bce = _bce(logits, self.disc_labels)
            loss = bce[:, :ub].mean(1) + bce[:, ub:].mean(1)
            grads = torch.autograd.grad(loss.sum(), self.dleaves)
            for g, out in zip(grads, self.dnet.grad_views):
                out.copy_(g.view_as(out))
            if vals is not None:  # as Trainer: the last step's loss, the first step's accuracies (before it)
                vals["disc"] = loss.detach()
                if k == 0:
                    real_l, fake_l = logits.detach()[:, :ub], logits.detach()[:, ub:]
                    vals["disc_acc_real"] = (real_l > 0).float().mean(1)
                    vals["disc_acc_fake"] = (fake_l < 0).float().mean(1)
                    vals["d_fake"] = torch.sigmoid(fake_l).mean(1)
            self._step_discriminators()  # a member whose discriminator's gradient is not finite frozen first
        # The model's term through the updated discriminators (their parameters as constants):
        # neg_bce -BCE(D(fake), 0), non-saturating BCE(D(fake), 1) (adversary.model_adversarial_loss).
        logits = self._disc_forward(fake, self.dnet.views)
        if self.adv_loss == "neg_bce":
            unpaired = -_bce(logits, self.fake_zeros).mean(1)
        elif self.adv_loss == "non_saturating":
            unpaired = _bce(logits, self.fake_ones).mean(1)
        else:
            unpaired = torch.where(self.ns, _bce(logits, self.fake_ones).mean(1), -_bce(logits, self.fake_zeros).mean(1))
        if vals is not None:
            vals["unpaired"] = unpaired.detach()
        return (self.lam32[j] * unpaired).sum()

    def _disc_forward(self, x: torch.Tensor, params: Sequence[torch.Tensor]) -> torch.Tensor:
        """The stacked discriminators (Linear, LeakyReLU, ..., Linear) on x (Ma, rows, d): logits (Ma, rows)."""
        last = len(params) // 2 - 1
        for i in range(last + 1):
            x = torch.baddbmm(params[2 * i + 1], x, params[2 * i].transpose(1, 2))
            if i < last:
                x = F.leaky_relu(x, self.slope)
        return x.squeeze(-1)

    def _adv(self, t: torch.Tensor) -> torch.Tensor:
        """The ASP members' rows of a member-stacked tensor (a view when they come first)."""
        return t[:self.Ma] if self.adv_first else t.index_select(0, self.adv_idx)

    # ---- failures and checkpoints (the rest in PackRecords) -------------------------------------
    def _freeze_params(self, rows: list[int]) -> None:
        self.net.freeze(rows)
        if self.dnet is not None:
            self.dnet.freeze([a for a, i in enumerate(self.adv_rows) if i in rows])

    def state_dict(self) -> dict[str, Any]:
        """Everything to continue bit for bit (PackRecords._state: parameters, Adam moments, the
        generators at the current chunk's start, the records)."""
        return self._state()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._load_state(state)


pack_key = PackedVAETrainer.pack_key  # cells with equal keys can share a pack
