"""The particle world's training update with hand-derived gradients: the fast path.

At the paper's batch of 8, an update of the reference path (asp_dist.training.trainer.Trainer driving
particles.a2c_update, paired_loss and training.adversary.Adversaries through autograd and
torch.optim.Adam) is ~500 tiny tensor ops, and its time is per-op overhead: graph
building, two backward passes, two optimisers walking their parameter lists. This trainer
computes the *same* update (same terms, same order, same random draws) with explicit forward
and backward passes over flat parameter buffers (FlatAdam): about a
fifth of the ops and no graph. tests/test_particles_fused.py checks its gradients against
autograd on the reference path, for every method and both adversarial losses.

The order of one update is the reference's:
  1. self-play rollout (A2C, messages kept) and the paired forward pass;
  2. ASP: one BCE step of the discriminator on U (real) vs. the rollout's messages (fake);
  3. the model's gradient of  w_sp·L_sp + λ0·L_p + λ1·L_u, with L_u through the updated
     discriminator; one Adam step.
The paired rows ride along with the first rollout step, so each layer sees one batch.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from asp_dist.domains.particles import BOX, N_ACTIONS, REWARD_SCALE, critic_features, env_step, spawn
from asp_dist.training.adversary import disc_diagnostics
from asp_dist.training.fast.flat_adam import FlatAdam
from asp_dist.training.trainer import Trainer

_tanh_backward = torch.ops.aten.tanh_backward
_threshold_backward = torch.ops.aten.threshold_backward
_leaky_relu_backward = torch.ops.aten.leaky_relu_backward


def linear_backward(dy: torch.Tensor, x: torch.Tensor, weight: torch.Tensor, grad_weight: torch.Tensor | None,
                    grad_bias: torch.Tensor | None, need_input_grad: bool = True) -> torch.Tensor | None:
    """y = x·Wᵀ + b: write dW and db into their gradient views and return dx."""
    if grad_weight is not None:
        torch.mm(dy.t(), x, out=grad_weight)
        torch.sum(dy, 0, out=grad_bias)
    return dy.mm(weight) if need_input_grad else None


class FusedDiscriminator:
    """Forward and backward of adversary.Discriminator (Linear/LeakyReLU stack) on its flat views."""

    def __init__(self, disc: torch.nn.Module, opt: FlatAdam):
        linears = [m for m in disc.net if isinstance(m, torch.nn.Linear)]
        slopes = {m.negative_slope for m in disc.net if isinstance(m, torch.nn.LeakyReLU)}
        self.slope = slopes.pop() if slopes else 0.01
        views, grads = opt.param_views, opt.grad_views
        self.layers = [(views[2 * i], views[2 * i + 1], grads[2 * i], grads[2 * i + 1]) for i in range(len(linears))]

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Logits (N,) and the input of every layer (post-activation), kept for backward."""
        inputs = [x]
        for i, (w, b, _, _) in enumerate(self.layers):
            x = torch.addmm(b, x, w.t())
            if i < len(self.layers) - 1:
                x = F.leaky_relu(x, self.slope)
                inputs.append(x)
        return x.view(-1), inputs

    def backward(self, dlogits: torch.Tensor, inputs: list[torch.Tensor], params: bool, input_grad: bool):
        """Backpropagate d(loss)/d(logits): into the parameter gradient views if `params`, and
        return d(loss)/d(input) if `input_grad`."""
        dy = dlogits.view(-1, 1)
        for i in reversed(range(len(self.layers))):
            w, _, gw, gb = self.layers[i]
            need_dx = i > 0 or input_grad
            dy = linear_backward(dy, inputs[i], w, gw if params else None, gb if params else None, need_dx)
            if i > 0:
                dy = _leaky_relu_backward(dy, inputs[i], self.slope, True)
        return dy if input_grad else None


class Rollout(NamedTuple):
    """What the backward pass needs from one update's forward pass. Speaker and listener rows
    are [step 0's B envs, the n paired rows, steps 1..K-1's envs]; the rest has the K·B env rows."""

    speaker_in: torch.Tensor
    speaker_hidden: torch.Tensor
    message: torch.Tensor
    listener_in: torch.Tensor
    listener_hidden: torch.Tensor
    logp: torch.Tensor
    actions: torch.Tensor
    values: torch.Tensor
    returns: torch.Tensor
    critic_in: torch.Tensor
    critic_hidden: torch.Tensor


class FusedParticleTrainer(Trainer):
    """Trainer with the same construction, checkpoints and loss diagnostics as the generic one,
    whose train_step is the hand-derived update described in the module docstring."""

    @classmethod
    def supports(cls, spec) -> bool:
        """The hand-derived update implements the on-policy update with the listener term in the
        paired loss; the replay buffer and the speaker-only paired loss run on the reference trainer."""
        return spec.particles_replay_size == 0 and spec.particles_paired_listener

    def make_optimizer(self, params, lr: float) -> FlatAdam:
        return FlatAdam(params, lr=lr)

    def __init__(self, spec, domain, agents, paired, unpaired, weights):
        super().__init__(spec, domain, agents, paired, unpaired, weights)
        (self.sw1, self.sb1, self.sw2, self.sb2, self.lw1, self.lb1, self.lw2, self.lb2,
         self.cw1, self.cb1, self.cw2, self.cb2) = self.opt.param_views
        (self.g_sw1, self.g_sb1, self.g_sw2, self.g_sb2, self.g_lw1, self.g_lb1, self.g_lw2, self.g_lb2,
         self.g_cw1, self.g_cb1, self.g_cw2, self.g_cb2) = self.opt.grad_views
        self.n_paired = len(paired["state"]) if weights.paired != 0.0 else 0
        if self.n_paired:
            self.paired_x = paired["state"] * (1.0 / BOX)
            self.paired_msg = paired["message"]
            self.paired_onehot = F.one_hot(paired["action"], N_ACTIONS).float()
        self.disc = None
        if self.adversaries is not None:
            (channel, disc), = self.adversaries.discs.items()
            disc_opt = self.adversaries.optims[channel]
            self.disc, self.disc_opt, self.real = FusedDiscriminator(disc, disc_opt), disc_opt, unpaired[channel]
            n_real, n_fake = spec.unpaired_batch, spec.batch_size * spec.particles_rollout_len
            # BCE targets and 1/N weights of the real rows then the fake rows.
            self.disc_labels = torch.cat([torch.ones(n_real), torch.zeros(n_fake)])
            self.disc_scale = torch.cat([torch.full((n_real,), 1.0 / n_real), torch.full((n_fake,), 1.0 / n_fake)])

    # ---- forward pieces ----------------------------------------------------------------------
    def speak(self, x):
        h = torch.addmm(self.sb1, x, self.sw1.t()).relu_()
        return h, torch.addmm(self.sb2, h, self.sw2.t()).tanh_()

    def listen(self, m):
        h = torch.addmm(self.lb1, m, self.lw1.t()).relu_()
        return h, torch.addmm(self.lb2, h, self.lw2.t()).log_softmax(-1)

    @torch.no_grad()
    def train_step(self) -> None:
        spec, w = self.spec, self.weights_now()
        n, B, K = self.n_paired, spec.batch_size, spec.particles_rollout_len
        record = self.recording()
        losses: dict[str, float] = {}
        if not w.needs_self_play and not n:
            # PC with no paired data: nothing to learn (the reference takes no optimiser step).
            if record:
                self.record({"total": 0.0})
            self.step += 1
            self.finish_curve_point()
            return

        # ---- 1. forward: rollout rows (B per step) with the paired rows after step 0's ----------
        if w.needs_self_play:
            ro = self.rollout(n)
            x, h, m, li, hl, logp = ro.speaker_in, ro.speaker_hidden, ro.message, ro.listener_in, ro.listener_hidden, ro.logp
        else:
            x, li = self.paired_x, self.paired_msg
            (h, m), (hl, logp) = self.speak(x), self.listen(li)
        probs = logp.exp()

        # ---- d(loss)/d(logits) of the listener and d(loss)/d(message) of the speaker --------------
        dz = torch.empty_like(logp)
        N = B * K if w.needs_self_play else 0
        sp_rows = [slice(0, B), slice(B + n, B + n + N - B)] if N else []
        p_rows = slice(B, B + n) if N else slice(0, n)
        if N:
            sp_logp, sp_probs = self._rows(logp, sp_rows), self._rows(probs, sp_rows)
            td = ro.returns - ro.values
            onehot = F.one_hot(ro.actions, N_ACTIONS).float()
            plogp = sp_probs * sp_logp
            # -log π(a)·A (A detached) and the entropy bonus Σ p log p, both per row, over N rows.
            dz_sp = ((sp_probs - onehot) * td.unsqueeze(1)
                     + spec.particles_entropy * (plogp - sp_probs * plogp.sum(1, keepdim=True))) * (w.self_play / N)
            self._put_rows(dz, sp_rows, dz_sp)
            dv = td * (-2.0 * spec.particles_value_coef * w.self_play / N)
            if record:
                losses["self_play"] = float((-(sp_logp * onehot).sum(1) * td + spec.particles_value_coef * td * td
                                             + spec.particles_entropy * plogp.sum(1)).mean())
        if n:
            dz[p_rows] = (probs[p_rows] - self.paired_onehot) * (w.paired / n)

        # Listener backward (its input grad matters for rollout rows only: paired inputs are data).
        dhl = _threshold_backward(linear_backward(dz, hl, self.lw2, self.g_lw2, self.g_lb2), hl, 0.0)
        dm = linear_backward(dhl, li, self.lw1, self.g_lw1, self.g_lb1)
        if n:
            dm[p_rows] = (m[p_rows] - self.paired_msg) * (2.0 * w.paired / (n * m.shape[1]))
            if record:
                losses["paired"] = float(F.mse_loss(m[p_rows], self.paired_msg)
                                         - (logp[p_rows] * self.paired_onehot).sum(1).mean())

        # ---- 2. ASP: discriminator step, then the model's adversarial gradient -------------------
        if self.disc is not None:
            fake = self._rows(m, sp_rows)
            d_adv = self.adversarial_grad(fake, w, losses if record else None)
            for rows, part in zip(sp_rows, (d_adv[:B], d_adv[B:])):
                if rows.stop > rows.start:
                    dm[rows] += part

        # Speaker backward.
        dh = _threshold_backward(linear_backward(_tanh_backward(dm, m), h, self.sw2, self.g_sw2, self.g_sb2), h, 0.0)
        linear_backward(dh, x, self.sw1, self.g_sw1, self.g_sb1, need_input_grad=False)
        if N:  # critic backward
            hc = ro.critic_hidden
            dhc = _threshold_backward(linear_backward(dv.unsqueeze(1), hc, self.cw2, self.g_cw2, self.g_cb2), hc, 0.0)
            linear_backward(dhc, ro.critic_in, self.cw1, self.g_cw1, self.g_cb1, need_input_grad=False)

        # ---- 3. one Adam step ---------------------------------------------------------------------
        self.opt.step()
        if record:
            losses["total"] = (w.self_play * losses.get("self_play", 0.0) + w.paired * losses.get("paired", 0.0)
                               + w.unpaired * losses.get("unpaired", 0.0))
            self.record(losses)
        self.step += 1
        self.finish_curve_point()

    def rollout(self, n: int) -> "Rollout":
        """particles.a2c_update's rollout and returns, without a graph; the paired rows join step 0."""
        spec, gen = self.spec, self.gen
        T, K, B = spec.particles_episode_len, spec.particles_rollout_len, spec.batch_size
        state, target = self.sp_state, self.sp_state["target"]
        pos, t = state["pos"], state["t"]
        spk_x, spk_h, spk_m, lis_in, lis_h, lis_logp = [], [], [], [], [], []
        acts, feats, rews, dones = [], [], [], []
        for k in range(K):
            x = pos * (1.0 / BOX)
            if k == 0 and n:
                x = torch.cat([x, self.paired_x])
            h, m = self.speak(x)
            li = torch.cat([m[:B], self.paired_msg]) if k == 0 and n else m
            hl, logp = self.listen(li)
            a = torch.multinomial(logp[:B].exp(), 1, generator=gen)
            feats.append(critic_features(pos, t, T))
            pos, r = env_step(pos, a.view(-1), target)
            t = t + 1
            done = t >= T
            if bool(done.any()):
                pos = torch.where(done.unsqueeze(1), spawn(len(pos), gen), pos)
                t = t.masked_fill_(done, 0)
            for store, value in ((spk_x, x), (spk_h, h), (spk_m, m), (lis_in, li), (lis_h, hl), (lis_logp, logp)):
                store.append(value)
            acts.append(a.view(-1))
            rews.append(r)
            dones.append(done)
        state["pos"], state["t"] = pos, t
        feats.append(critic_features(pos, t, T))
        feats = torch.cat(feats)
        hc = torch.addmm(self.cb1, feats, self.cw1.t()).relu_()
        values = torch.addmm(self.cb2, hc, self.cw2.t()).view(-1)
        ret = values[K * B:]
        returns = []
        for k in reversed(range(K)):
            ret = rews[k] * REWARD_SCALE + spec.particles_gamma * ret.masked_fill(dones[k], 0.0)
            returns.append(ret)
        cat = (lambda xs: xs[0] if len(xs) == 1 else torch.cat(xs))
        # The bootstrap rows of the critic get no gradient: keep the visited rows only.
        return Rollout(cat(spk_x), cat(spk_h), cat(spk_m), cat(lis_in), cat(lis_h), cat(lis_logp), cat(acts),
                       values[:K * B], cat(returns[::-1]), feats[:K * B], hc[:K * B])

    def adversarial_grad(self, fake: torch.Tensor, w, losses: dict | None) -> torch.Tensor:
        """disc_steps BCE steps of the discriminator (real = 1: a fresh batch of U each, fake = 0),
        then λ1·d(L_u)/d(fake) through the updated discriminator."""
        spec = self.spec
        for k in range(spec.disc_steps):
            real = self.real[torch.randint(len(self.real), (spec.unpaired_batch,), generator=self.gen)]
            logits, inputs = self.disc.forward(torch.cat([real, fake]))
            self.disc.backward((torch.sigmoid(logits) - self.disc_labels) * self.disc_scale, inputs, params=True,
                               input_grad=False)
            if losses is not None:  # as the reference: the last step's loss, the first step's accuracies
                losses["disc"] = float(F.binary_cross_entropy_with_logits(logits, self.disc_labels, reduction="none")
                                       .mul(self.disc_scale).sum())
                if k == 0:
                    losses.update(disc_diagnostics(logits[:len(real)], logits[len(real):]))
            self.disc_opt.step()
        logits, inputs = self.disc.forward(fake)
        sig = torch.sigmoid(logits)
        if spec.adversary_loss == "neg_bce":  # L_u = -BCE(D(fake), 0) = -mean softplus(logit)
            dlogits = sig * (-w.unpaired / len(fake))
            if losses is not None:
                losses["unpaired"] = float(-F.softplus(logits).mean())
        else:  # non_saturating: L_u = BCE(D(fake), 1) = mean softplus(-logit)
            dlogits = (sig - 1.0) * (w.unpaired / len(fake))
            if losses is not None:
                losses["unpaired"] = float(F.softplus(-logits).mean())
        return self.disc.backward(dlogits, inputs, params=False, input_grad=True)

    @staticmethod
    def _rows(t: torch.Tensor, rows: list[slice]) -> torch.Tensor:
        parts = [t[r] for r in rows if r.stop > r.start]
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    @staticmethod
    def _put_rows(dst: torch.Tensor, rows: list[slice], src: torch.Tensor) -> None:
        offset = 0
        for r in rows:
            size = r.stop - r.start
            if size > 0:
                dst[r] = src[offset:offset + size]
                offset += size
