"""K particle cells trained as one batched model, with hand-derived gradients; a single cell is a pack of one.

A particle cell is 25,000 updates of batch 8 through networks of a few thousand weights; its
cost is the number of tensor operations, not arithmetic. At batch 8 an update of the reference
path (asp_dist.training.trainer.Trainer driving particles.a2c_update, paired_loss and
training.adversary.Adversaries through autograd and torch.optim.Adam) is ~500 tiny tensor ops,
and its time is per-op overhead: graph building, two backward passes, two optimisers. This
trainer computes the same update (same terms, same order, same random draws) with explicit
forward and backward passes and no graph, and stacks the parameters of K cells ("members") on a
leading dimension, so that each tensor op serves K cells (batched matmuls); one batched Adam step
(torch._fused_adam_, one pass over the stacked buffer) updates them all. run_cell trains a
particle cell as a one-member pack of it (`lone = True`, asp_dist.training.engines), which
is faster than the single-cell hand-derived kernel it replaced
(docs/decisions/0018-lone-particle-cell-is-a-pack-of-one.md). tests/test_packed_particles.py checks the
one-member pack against the autograd reference, tests/test_packed.py packs of every size.

The order of one update is the reference's:
  1. self-play rollout (A2C, messages kept) and the paired forward pass;
  2. ASP: disc_steps BCE steps of the discriminator on U (real) vs. the rollout's messages (fake);
  3. the model's gradient of  w_sp·L_sp + λ0·L_p + λ1·L_u, with L_u through the updated
     discriminator; one Adam step.
The paired rows ride along with the first rollout step, so each layer sees one batch.

What stays per member, so that a member's result does not depend on its pack-mates:

- loss weights (PC / OSP / ASP differ only in them), λ0, λ1 and its schedule, the adversarial
  loss kind, γ, the entropy and value coefficients, both learning rates: per-member columns;
- data: its own paired set (padded to the pack's largest, padded rows weighted 0), its own U,
  its own trial's target;
- random streams: its own generator, seeded as the reference Trainer seeds it, drawn in its
  order. torch.multinomial(p, 1) *is* argmax(p / Exp(1)) with the Exp(1) draws
  taken from the generator (ATen's one-sample path), so the draws of up to CHUNK updates
  (Exp(1) per action, uniform re-spawns when an episode ends, indices into U) are made ahead,
  member by member with that member's generator and in the order the reference update makes
  them, and the batched update consumes them; episode ends are known in advance (the envs
  start staggered and advance one step per rollout step), so nothing in the draws depends on
  values. A generator ends training in the state the reference Trainer leaves it in.

Independence of pack-mates: no op mixes members (batched matmuls, elementwise ops, reductions
along rows or features), padded rows add exact zeros, and a frozen member keeps its place in
every call. So a member's arithmetic is bit for bit the same whatever its mates are (method,
data, trial, divergence) as long as the pack's shapes are the same (number of members, padded
paired rows); with other shapes a few kernels round differently (a batched matmul with one
member and one output column takes a gemv path; the last elements of a vectorised elementwise
op over the whole stack take the scalar path), and the member's weights then differ from their
run in another pack by float rounding (about 1e-7 after 100 updates), as they differ from the
reference Trainer's. Over a whole cell such a difference can flip a sampled action and send the
run down another, equally likely, trajectory: rows are reproducible for a fixed packing, not
across packings (a single cell is the packing of one). tests/test_packed.py checks both.

A member whose gradient becomes non-finite (checked every update, before the Adam step) or
whose recorded loss does is frozen: its gradients are zeroed and its momentum cleared, so Adam
leaves its parameters at their last finite values, and it is reported failed. Its rows are
still computed (the shapes and the calls stay the same, so nothing changes for the others)
but never read by another member.

Packs: any mix of methods, paired counts, trials and per-member knobs, provided the members
agree on the fields in SHARED (tensor shapes, the length of training). Mixed packs compute
the union of the members' work (a PC member rides along in the rollout with weight 0), so
packs of one method are cheapest. Knob values this update does not implement (replay buffer,
speaker-only paired loss) are not packable (IMPLEMENTS); the reference Trainer runs those cells.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Sequence

import torch
import torch.nn.functional as F

from asp_dist.core.contract import Tensors
from asp_dist.core.registry import get_domain
from asp_dist.domains.particles.game import BOX, N_ACTIONS, REWARD_SCALE, ParticleAgents, env_step, target_for
from asp_dist.knobs import ANY, BASE_ONLY
from asp_dist.spec import CellSpec
from asp_dist.training.stacked import PackedTrainer, StackedParams, column

_tanh_backward = torch.ops.aten.tanh_backward
_threshold_backward = torch.ops.aten.threshold_backward
_leaky_relu_backward = torch.ops.aten.leaky_relu_backward

# Fields every member of a pack shares: they fix the tensor shapes and the loop.
SHARED = ("domain", "train_steps", "batch_size", "particles_episode_len", "particles_rollout_len",
          "particles_message_dim", "particles_hidden", "disc_hidden", "disc_layers", "unpaired_batch", "disc_steps")
CHUNK = 128  # updates whose random draws are made ahead
# The knob values this update implements (asp_dist.knobs): the replay buffer and the speaker-only paired
# loss are the reference Trainer's alone.
IMPLEMENTS = {
    "particles_message_dim": ANY, "particles_hidden": ANY, "particles_episode_len": ANY, "particles_gamma": ANY,
    "particles_entropy": ANY, "particles_value_coef": ANY, "particles_rollout_len": ANY,
    "particles_replay_size": (0,), "particles_paired_listener": (True,),
    "particles_base_envs": BASE_ONLY, "particles_base_lr": BASE_ONLY, "particles_accept_return": BASE_ONLY,
}


class _Rollout(NamedTuple):
    """What the backward pass needs from one update's forward pass, per member (leading dimension).
    Speaker and listener rows are [step 0's B envs, the n paired rows, steps 1..K-1's envs]; the
    rest has the K·B env rows."""

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


def _lin_back(dy: torch.Tensor, x: torch.Tensor, weight: torch.Tensor, grad_weight: torch.Tensor | None,
              grad_bias: torch.Tensor | None, need_input_grad: bool = True) -> torch.Tensor | None:
    """Batched y = x·Wᵀ + b: write dW and db into their (member-stacked) gradient views, return dx."""
    if grad_weight is not None:
        torch.bmm(dy.transpose(1, 2), x, out=grad_weight)
        torch.sum(dy, 1, out=grad_bias)
    return torch.bmm(dy, weight) if need_input_grad else None


class PackedParticleTrainer(PackedTrainer):
    """K particle cells as one batched model; train_step() is one update of every member.

    specs, paired, unpaired, agents: one entry per member, as a single cell's trainer gets them
    (asp_dist.training.cell.run_cell: P and U from the member's base, agents freshly initialised).
    The agents' parameters are re-pointed into the pack's buffer. After training, member i's
    `members[i].agents` holds its trained weights, `loss_columns(i)` its row's loss_* columns and
    `members[i].curve` its learning curve (probes: set `members[i].probe` as run_cell sets
    Trainer.probe)."""

    # Capabilities (asp_dist.training.engines): packs, and a single particle cell trains as a pack of one
    # (faster than the single-cell kernel it replaced:
    # docs/decisions/0018-lone-particle-cell-is-a-pack-of-one.md). Members in the order given.
    domain = "particles"
    lone = True
    implements = IMPLEMENTS
    shared = SHARED  # the pack key (PackedTrainer.pack_key)

    def __init__(self, specs: Sequence[CellSpec], paired: Sequence[Tensors], unpaired: Sequence[Tensors],
                 agents: Sequence[ParticleAgents]):
        discs = [d for (d,) in self._init_members(specs, paired, unpaired, agents, paired_rows="state")]
        domain = get_domain("particles")
        mem = self.members
        s0 = mem[0].spec
        self.B, self.T = s0.batch_size, s0.particles_episode_len
        self.Kr, self.D = s0.particles_rollout_len, s0.particles_message_dim
        M, B, T, D = self.M, self.B, self.T, self.D
        # the self-play state of each member, drawn from its generator as Trainer.__init__ draws it
        states = [domain.init_self_play(m.spec, m.agents, m.gen) if m.self_play else {} for m in mem]

        # ---- stacked parameters: speaker, listener, critic; discriminators of the ASP members --------
        self.net = StackedParams(agents, [m.spec.lr for m in mem])
        (self.sw1, self.sb1, self.sw2, self.sb2, self.lw1, self.lb1, self.lw2, self.lb2,
         self.cw1, self.cb1, self.cw2, self.cb2) = self.net.views
        (self.g_sw1, self.g_sb1, self.g_sw2, self.g_sb2, self.g_lw1, self.g_lb1, self.g_lw2, self.g_lb2,
         self.g_cw1, self.g_cb1, self.g_cw2, self.g_cb2) = self.net.grad_views
        self.sw1T, self.sw2T, self.lw1T, self.lw2T, self.cw1T, self.cw2T = (
            w.transpose(1, 2) for w in (self.sw1, self.sw2, self.lw1, self.lw2, self.cw1, self.cw2))
        self.dnet = None
        if self.Ma:
            self.dnet = StackedParams(discs, [mem[i].spec.disc_lr for i in self.adv_rows])
            slopes = {m.negative_slope for m in discs[0].net if isinstance(m, torch.nn.LeakyReLU)}
            self.slope = slopes.pop() if slopes else 0.01
            v, g = self.dnet.views, self.dnet.grad_views
            self.dlayers = [(v[2 * i], v[2 * i].transpose(1, 2), v[2 * i + 1], g[2 * i], g[2 * i + 1])
                            for i in range(len(v) // 2)]

        # ---- per-member constants of the update (the reference's Python scalars) ---------------------
        n_max = max(m.n_paired for m in mem)
        self.n = n_max
        N = B * self.Kr
        self.paired_x, self.paired_msg = torch.zeros(M, n_max, 2), torch.zeros(M, n_max, D)
        self.paired_onehot = torch.zeros(M, n_max, N_ACTIONS)
        self.action_ids = torch.arange(N_ACTIONS)
        self.row_mask = torch.zeros(M, n_max)
        pw, pmw = torch.zeros(M, n_max, 1), torch.zeros(M, n_max, 1)
        for i, (m, p) in enumerate(zip(mem, paired)):
            k = m.n_paired
            if k:
                self.paired_x[i, :k] = p["state"] * (1.0 / BOX)
                self.paired_msg[i, :k] = p["message"]
                self.paired_onehot[i, :k] = F.one_hot(p["action"], N_ACTIONS).float()
                self.row_mask[i, :k] = 1.0
                pw[i, :k] = m.weights.paired / k
                pmw[i, :k] = 2.0 * m.weights.paired / (k * D)
        self.pw, self.pmw = pw, pmw
        self.inv_n = column([1.0 / max(m.n_paired, 1) for m in mem])
        self.inv_nD = column([1.0 / (max(m.n_paired, 1) * D) for m in mem])
        sp = [m.spec for m in mem]
        self.sp_scale = column([m.weights.self_play / N for m in mem], dims=3)
        self.ent3 = column([s.particles_entropy for s in sp], dims=3)
        self.ent2 = column([s.particles_entropy for s in sp])
        self.vc2 = column([s.particles_value_coef for s in sp])
        self.dv_scale = column([-2.0 * s.particles_value_coef * m.weights.self_play / N for s, m in zip(sp, mem)])
        self.gamma = column([s.particles_gamma for s in sp])

        # ---- self-play state: positions (M, B, 2), targets, the shared episode clock -----------------
        self.pos = torch.zeros(M, B, 2)
        for i, st in enumerate(states):
            if st:
                self.pos[i] = st["pos"]
        self.target = torch.stack([target_for(s) for s in sp]).view(M, 1, 2)
        t0 = next((st["t"] for st in states if st), torch.arange(B) * T // B)
        # Envs advance one step per rollout step, so the clock at env step g is (t0 + g) mod T for
        # every member; tfeat[φ] is critic_features' time column and done[φ] the episode ends at phase φ.
        clock = [(t0 + ph) % T for ph in range(T)]
        self.tfeat = [((T - t).unsqueeze(1) * (1.0 / T)).expand(M, B, 1) for t in clock]
        self.done = [(t + 1) >= T for t in clock]
        self.done_any = [bool(d.any()) for d in self.done]
        self.done3 = [d.view(1, B, 1) for d in self.done]

        # ---- discriminator data --------------------------------------------------------------------
        if self.Ma:
            ub = self.ub
            sizes = [len(unpaired[i]["message"]) for i in self.adv_rows]
            self.u_sizes, u_max = sizes, max(sizes)
            U = torch.zeros(self.Ma, u_max, D)
            for a, i in enumerate(self.adv_rows):
                U[a, :sizes[a]] = unpaired[i]["message"]
            self.U = U.view(self.Ma * u_max, D)
            self.u_offset = (torch.arange(self.Ma) * u_max).view(1, self.Ma, 1)
            self.disc_labels = torch.cat([torch.ones(ub), torch.zeros(N)]).expand(self.Ma, ub + N)
            self.disc_scale = torch.cat([torch.full((ub,), 1.0 / ub), torch.full((N,), 1.0 / N)])
            kinds = [mem[i].spec.adversary_loss for i in self.adv_rows]
            self.ns_float = column([k == "non_saturating" for k in kinds])
            self.ns = self.ns_float.bool()
            self.any_ns = any(k == "non_saturating" for k in kinds)
            self.adv_spread = torch.zeros(M, N, D)

        # ---- bookkeeping, as Trainer's -------------------------------------------------------------
        self._init_records()
        self._alloc_draws()

    # ---- random draws, made ahead per member in the reference Trainer's order -------------------
    def _alloc_draws(self) -> None:
        M, B, Kr = self.M, self.B, self.Kr
        self.E = torch.ones(CHUNK * Kr, M, B, N_ACTIONS)    # Exp(1) per action (1 for members without self-play)
        self.respawn_u = torch.zeros(CHUNK * Kr, M, B, 2)  # uniforms of spawn()
        self.real_idx = torch.zeros(CHUNK * self.disc_steps, self.Ma, self.ub, dtype=torch.long)
        if self.Ma:
            self.lam_coef = torch.zeros(CHUNK, self.Ma, 1)      # d(λ1·L_u)/d(logit) factor, float32
            self.lam_now = torch.zeros(CHUNK, self.Ma, dtype=torch.float64)  # λ1 of the update (for 'total')

    def _draw_chunk(self) -> None:
        """The random draws of updates [step, step + CHUNK) (not past train_steps), member by member:
        per rollout step the Exp(1) of torch.multinomial and, when episodes end, spawn()'s uniforms;
        then the disc_steps batches of indices into U. The same calls the reference Trainer makes."""
        start, S, adv_slot = self._open_chunk(CHUNK)
        Kr, B, T, ub, ds = self.Kr, self.B, self.T, self.ub, self.disc_steps
        for i, m in enumerate(self.members):
            if not m.self_play:  # PC draws nothing
                continue
            gen = m.gen
            exps, unis = self.E[:S * Kr, i].unbind(0), self.respawn_u[:S * Kr, i].unbind(0)
            idx = self.real_idx[:S * ds, adv_slot[i]].unbind(0) if m.adversary else ()
            high = m.spec.unpaired_size
            for s in range(S):
                for k in range(Kr):
                    j = s * Kr + k
                    exps[j].exponential_(generator=gen)
                    if self.done_any[((start + s) * Kr + k) % T]:
                        torch.rand(B, 2, generator=gen, out=unis[j])
                for d in range(ds if m.adversary else 0):
                    torch.randint(high, (ub,), generator=gen, out=idx[s * ds + d])
        self.respawn = (self.respawn_u[:S * Kr] * 2 - 1) * BOX
        if self.Ma:
            self.real_flat = (self.real_idx[:S * ds].view(S, ds, self.Ma, ub) + self.u_offset.unsqueeze(0)).view(
                S * ds, self.Ma * ub)
            self._lambda_chunk(start, S)
            N = B * Kr
            for a, i in enumerate(self.adv_rows):
                now = self.lam_now[:S, a]
                ns = self.members[i].spec.adversary_loss == "non_saturating"
                self.lam_coef[:S, a, 0] = (now / N if ns else -now / N).float()

    # ---- forward pieces (member-stacked) --------------------------------------------------------
    def _speak(self, x):
        h = torch.baddbmm(self.sb1, x, self.sw1T).relu_()
        return h, torch.baddbmm(self.sb2, h, self.sw2T).tanh_()

    def _listen(self, m):
        h = torch.baddbmm(self.lb1, m, self.lw1T).relu_()
        return h, torch.baddbmm(self.lb2, h, self.lw2T).log_softmax(-1)

    def _rollout(self, j: int) -> _Rollout:
        """particles.a2c_update's rollout and returns for every member, without a graph; the paired
        rows join step 0."""
        M, B, Kr, T, n = self.M, self.B, self.Kr, self.T, self.n
        pos = self.pos
        spk_x, spk_h, spk_m, lis_in, lis_h, lis_logp, acts, feats, rews, dones = ([] for _ in range(10))
        for k in range(Kr):
            phase = (self.step * Kr + k) % T
            x = pos * (1.0 / BOX)
            xs = torch.cat([x, self.paired_x], 1) if k == 0 and n else x
            h, m = self._speak(xs)
            li = torch.cat([m[:, :B], self.paired_msg], 1) if k == 0 and n else m
            hl, logp = self._listen(li)
            a = (logp[:, :B].exp() / self.E[j * Kr + k]).argmax(-1)  # = torch.multinomial(probs, 1, generator)
            feats.append(torch.cat([x, self.tfeat[phase]], 2))
            pos, r = env_step(pos, a, self.target)
            if self.done_any[phase]:
                pos = torch.where(self.done3[phase], self.respawn[j * Kr + k], pos)
            for store, value in ((spk_x, xs), (spk_h, h), (spk_m, m), (lis_in, li), (lis_h, hl), (lis_logp, logp)):
                store.append(value)
            acts.append(a)
            rews.append(r)
            dones.append(self.done[phase])
        self.pos = pos
        feats.append(torch.cat([pos * (1.0 / BOX), self.tfeat[(self.step * Kr + Kr) % T]], 2))
        feats = torch.cat(feats, 1)
        hc = torch.baddbmm(self.cb1, feats, self.cw1T).relu_()
        values = torch.baddbmm(self.cb2, hc, self.cw2T).view(M, -1)
        ret = values[:, Kr * B:]
        returns = []
        for k in reversed(range(Kr)):
            ret = rews[k] * REWARD_SCALE + self.gamma * ret.masked_fill(dones[k], 0.0)
            returns.append(ret)
        cat = (lambda xs: xs[0] if len(xs) == 1 else torch.cat(xs, 1))
        return _Rollout(cat(spk_x), cat(spk_h), cat(spk_m), cat(lis_in), cat(lis_h), cat(lis_logp), cat(acts),
                        values[:, :Kr * B], cat(returns[::-1]), feats[:, :Kr * B], hc[:, :Kr * B])

    # ---- one update of every member -------------------------------------------------------------
    @torch.no_grad()
    def train_step(self) -> None:
        j, vals = self._begin_update()
        record = vals is not None
        B, Kr, n = self.B, self.Kr, self.n

        # ---- 1. forward: rollout rows (B per step) with the paired rows after step 0's ------------
        if self.any_self_play:
            ro = self._rollout(j)
            x, h, m, li, hl, logp = (ro.speaker_in, ro.speaker_hidden, ro.message, ro.listener_in,
                                     ro.listener_hidden, ro.logp)
        else:
            x, li = self.paired_x, self.paired_msg
            (h, m), (hl, logp) = self._speak(x), self._listen(li)
        probs = logp.exp()

        # ---- d(loss)/d(logits) of the listener and d(loss)/d(message) of the speaker --------------
        dz = torch.empty_like(logp)
        N = B * Kr if self.any_self_play else 0
        sp_rows = [slice(0, B), slice(B + n, B + n + N - B)] if N else []
        p_rows = slice(B, B + n) if N else slice(0, n)
        if N:
            sp_logp, sp_probs = self._rows(logp, sp_rows), self._rows(probs, sp_rows)
            td = ro.returns - ro.values
            onehot = (ro.actions.unsqueeze(2) == self.action_ids).float()  # F.one_hot without its checks
            plogp = sp_probs * sp_logp
            dz_sp = ((sp_probs - onehot) * td.unsqueeze(2)
                     + self.ent3 * (plogp - sp_probs * plogp.sum(2, keepdim=True))) * self.sp_scale
            self._put_rows(dz, sp_rows, dz_sp)
            dv = td * self.dv_scale
            if record:
                vals["self_play"] = (-(sp_logp * onehot).sum(2) * td + self.vc2 * td * td
                                     + self.ent2 * plogp.sum(2)).mean(1)
        if n:
            dz[:, p_rows] = (probs[:, p_rows] - self.paired_onehot) * self.pw

        # Listener backward (its input grad matters for rollout rows only: paired inputs are data).
        dhl = _threshold_backward(_lin_back(dz, hl, self.lw2, self.g_lw2, self.g_lb2), hl, 0.0)
        dm = _lin_back(dhl, li, self.lw1, self.g_lw1, self.g_lb1)
        if n:
            diff = m[:, p_rows] - self.paired_msg
            dm[:, p_rows] = diff * self.pmw
            if record:
                # MSE over each member's own rows minus their mean log-likelihood (padded rows masked).
                mse = ((diff * diff).sum(2) * self.row_mask).sum(1, keepdim=True).mul_(self.inv_nD)
                loglik = ((logp[:, p_rows] * self.paired_onehot).sum(2) * self.row_mask).sum(1, keepdim=True)
                vals["paired"] = (mse - loglik.mul_(self.inv_n)).view(-1)

        # ---- 2. ASP: discriminator step, then the model's adversarial gradient -------------------
        if self.Ma:
            fake = self._rows(m, sp_rows)
            d_adv = self._adversarial(fake if self.all_adv else fake.index_select(0, self.adv_idx), j, vals)
            if not self.all_adv:  # spread the ASP members' rows over the pack (the others' stay 0)
                d_adv = self.adv_spread.index_copy_(0, self.adv_idx, d_adv)
            for rows, part in zip(sp_rows, (d_adv[:, :B], d_adv[:, B:])):
                if rows.stop > rows.start:
                    dm[:, rows] += part

        # Speaker backward.
        dh = _threshold_backward(_lin_back(_tanh_backward(dm, m), h, self.sw2, self.g_sw2, self.g_sb2), h, 0.0)
        _lin_back(dh, x, self.sw1, self.g_sw1, self.g_sb1, need_input_grad=False)
        if N:  # critic backward
            hc = ro.critic_hidden
            dv3 = dv.unsqueeze(2)
            torch.bmm(dv3.transpose(1, 2), hc, out=self.g_cw2)
            torch.sum(dv, 1, keepdim=True, out=self.g_cb2)
            dhc = _threshold_backward(dv3 * self.cw2, hc, 0.0)
            _lin_back(dhc, ro.critic_in, self.cw1, self.g_cw1, self.g_cb1, need_input_grad=False)

        # ---- 3. one Adam step for every member (a member whose gradient is not finite frozen first) ---
        self._step_model(vals, j, record)

    def _adversarial(self, fake: torch.Tensor, j: int, vals: dict | None) -> torch.Tensor:
        """disc_steps BCE steps of each ASP member's discriminator, then λ1·d(L_u)/d(fake) through
        the updated one. `fake`: the ASP members' rollout messages (Ma, N, D)."""
        Ma, ub, D = self.Ma, self.ub, self.D
        for k in range(self.disc_steps):
            real = self.U.index_select(0, self.real_flat[j * self.disc_steps + k]).view(Ma, ub, D)
            logits, inputs = self._disc_forward(torch.cat([real, fake], 1))
            self._disc_backward((torch.sigmoid(logits) - self.disc_labels) * self.disc_scale, inputs,
                                params=True, input_grad=False)
            if vals is not None:  # as the reference: the last step's loss, the first step's accuracies
                vals["disc"] = F.binary_cross_entropy_with_logits(logits, self.disc_labels, reduction="none") \
                    .mul(self.disc_scale).sum(1)
                if k == 0:
                    real_l, fake_l = logits[:, :ub], logits[:, ub:]
                    vals["disc_acc_real"] = (real_l > 0).float().mean(1)
                    vals["disc_acc_fake"] = (fake_l < 0).float().mean(1)
                    vals["d_fake"] = torch.sigmoid(fake_l).mean(1)
            self.dnet.step()
        logits, inputs = self._disc_forward(fake)
        sig = torch.sigmoid(logits)
        coef = self.lam_coef[j]
        dlogits = (sig - self.ns_float) * coef if self.any_ns else sig * coef  # neg_bce: σ·(-λ/N); else (σ-1)·λ/N
        if vals is not None:
            vals["unpaired"] = torch.where(self.ns.view(-1), F.softplus(-logits).mean(1), -F.softplus(logits).mean(1))
        return self._disc_backward(dlogits, inputs, params=False, input_grad=True)

    def _disc_forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        inputs = [x]
        last = len(self.dlayers) - 1
        for i, (_, wT, b, _, _) in enumerate(self.dlayers):
            x = torch.baddbmm(b, x, wT)
            if i < last:
                x = F.leaky_relu(x, self.slope)
                inputs.append(x)
        return x.view(x.shape[0], -1), inputs

    def _disc_backward(self, dlogits: torch.Tensor, inputs: list[torch.Tensor], params: bool, input_grad: bool):
        dy = dlogits.unsqueeze(2)
        for i in reversed(range(len(self.dlayers))):
            w, _, _, gw, gb = self.dlayers[i]
            dy = _lin_back(dy, inputs[i], w, gw if params else None, gb if params else None, i > 0 or input_grad)
            if i > 0:
                dy = _leaky_relu_backward(dy, inputs[i], self.slope, True)
        return dy if input_grad else None

    # ---- failures and checkpoints (the rest in PackRecords) -------------------------------------
    def _freeze_params(self, rows: list[int]) -> None:
        self.net.freeze(rows)
        if self.dnet is not None:
            self.dnet.freeze([a for a, i in enumerate(self.adv_rows) if i in rows])

    def state_dict(self) -> dict[str, Any]:
        """Everything to continue bit for bit (PackRecords._state), with the rollout positions."""
        return self._state(pos=self.pos.clone())

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.pos = state["pos"].clone()
        self._load_state(state)

    # ---- helpers -------------------------------------------------------------------------------
    @staticmethod
    def _rows(t: torch.Tensor, rows: list[slice]) -> torch.Tensor:
        parts = [t[:, r] for r in rows if r.stop > r.start]
        return parts[0] if len(parts) == 1 else torch.cat(parts, 1)

    @staticmethod
    def _put_rows(dst: torch.Tensor, rows: list[slice], src: torch.Tensor) -> None:
        offset = 0
        for r in rows:
            size = r.stop - r.start
            if size > 0:
                dst[:, r] = src[:, offset:offset + size]
                offset += size


pack_key = PackedParticleTrainer.pack_key  # cells with equal keys can share a pack
