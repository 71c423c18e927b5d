"""K lever cells trained as one batched model: the packed counterpart of the single-cell path.

The reference is the single-cell Trainer (asp_dist.training.trainer.Trainer: autograd and
torch.optim.Adam): per update ε-greedy deep Q-learning on batch_size fresh games plus batch_size
replayed ones, the paired loss, and for ASP one discriminator per CommNet channel (f1, f2). run_cell
trains a single lever cell as a one-member pack of this trainer (`lone = True` below; 3.0× the
reference's update rate, docs/performance.md), as the particle world does. This trainer stacks the
parameters of K cells ("members") on a leading dimension and computes the same update for all of
them with batched ops and hand-derived gradients; one batched Adam step (torch._fused_adam_ over the
stacked buffer) updates every member's network, another every ASP member's two discriminators.

The same loss, computed with fewer operations (exact in real arithmetic, equal to the reference up
to float rounding):

- h1 = tanh(W1·embed(id) + b1) depends on the ID only, so it is computed once per ID (a V × H
  table) instead of per seat; so are W2's two halves applied to it, A = h1·W2aᵀ and C = h1·W2bᵀ.
  A seat's pre-activation of f2 is then W2·[h1, c1] + b2 = (A + b2 − C/2)[id] + Σ_seats (C/2)[id']
  (c1 is the mean of the two other seats): two small matmuls with one-hot matrices (a seat's ID,
  the IDs seated in its game), and their transposes give the gradient of the tables.
- The f1 discriminator sees h1 rows, one of V values each: it runs on the V per-ID rows with each
  row weighted by how often its ID is seated in the update's games (the same sums, regrouped).
- tanh of the seats' f2 block is computed as 2·σ(2x) − 1 (same value to 1.2e-7; torch.tanh is
  ~5x slower than sigmoid on CPU); the per-ID h1 table uses torch.tanh.
- Nothing is computed that the update does not use (the reference back-propagates the model's
  adversarial loss into the discriminators' parameters too, then discards it).

What stays per member, so that a member's result does not depend on its pack-mates:

- loss weights (PC / OSP / ASP differ only in them), λ0, λ1 and its schedule, the adversarial
  loss kind, the ε schedule, both learning rates: per-member columns;
- data: its own paired set (padded to the pack's largest, padded rows weighted 0), its own U
  (padded likewise; indices drawn in its own range), its own replay buffer;
- random streams: its own generator, seeded as Trainer seeds it, drawn in Trainer's order. No draw
  depends on a value: the fresh games, the replay indices (the buffer's fill level is a function of
  the update count), the ε-greedy exploration coins and random levers (drawn whether or not they
  are used) and the indices into U. So the draws of up to CHUNK updates are made ahead, member by
  member with that member's generator and in the single-cell order (rand for the games, randint for
  replay, randint for random levers, rand for the coins, then disc_steps × (f1, f2) randint into U),
  and the batched update consumes them. A generator ends training in the single-cell run's state.
- There is no target network: the lever game has one step, so the Q target is the reward itself
  (asp_dist.domains.levers.game.dqn_step); the replay buffer is the only Q-learning state.

Independence of pack-mates: no op mixes members (batched matmuls, gathers within a member's own
rows, elementwise ops, reductions along rows or features), and a frozen member keeps its place in
every call, so a member's arithmetic is bit for bit the same whatever its mates are as long as the
pack's shapes are the same (number of members, of ASP members, padded paired rows and U); with
other shapes some kernels may round differently, by float rounding. Over a whole cell such a
difference can flip a discrete choice - a greedy argmax between two equal-looking Q-values, or the
side of a discriminator's leaky-ReLU kink for a pre-activation within ~1e-8 of 0 - and send the
run down another trajectory; the same holds against the single-cell path. Measured at paper
settings (trial 0's 21 cells, 1,000 updates): the 14 PC and OSP rows equal run_cell's to 1e-4, the
7 ASP rows part from theirs after a few hundred updates (first event traced: one kink flip at
update 202 of a 300-update run). Rows are reproducible for a fixed packing.
tests/test_packed_levers.py checks both.

A member whose network gradient becomes non-finite (checked every update, before the Adam step),
whose discriminators' gradient does (checked before each discriminator step) or whose recorded loss
does is frozen: its gradients are zeroed and its momentum cleared, so Adam leaves its parameters
and its discriminators' at their last finite values, and it is reported failed.

Packs: any mix of methods, paired counts, trials and per-member knobs, provided the members agree
on the fields in SHARED (tensor shapes, replay capacity, the length of training). Mixed packs
compute the union of the members' work (a PC member rides along in the self-play rows with weight
0), so packs of one method are cheapest.

(About 510 lines, over the project's 500: one update's forward, hand-derived backward and draws are one
derivation, read against the reference line by line; most of the length is this note and the gradients.)
"""

from __future__ import annotations

from typing import Any, Sequence

import torch
import torch.nn.functional as F

from asp_dist.core.contract import Tensors
from asp_dist.domains.levers import AGENTS
from asp_dist.domains.levers.game import CommNet, epsilon
from asp_dist.knobs import ANY, BASE_ONLY
from asp_dist.spec import CellSpec
from asp_dist.training.stacked import (
    TERMS,
    PackedTrainer,
    StackedParams,
    asp_members_first,
    column,
    retain_freed_memory,
)

__all__ = ["PackedLeverTrainer", "pack_key", "IMPLEMENTS", "SHARED", "TERMS"]

_tanh_backward = torch.ops.aten.tanh_backward


def _tanh(x: torch.Tensor) -> torch.Tensor:
    """tanh(x) = 2·σ(2x) - 1, in place: torch.tanh is ~5x slower than sigmoid on CPU here, and the
    two agree to within 1.2e-7 (absolute), float rounding of values in [-1, 1]."""
    return torch.sigmoid_(x.mul_(2.0)).mul_(2.0).sub_(1.0)
_leaky_relu_backward = torch.ops.aten.leaky_relu_backward

# Fields every member of a pack shares: they fix the tensor shapes, the replay buffer and the loop.
SHARED = ("domain", "train_steps", "batch_size", "levers_hidden", "levers_num_ids", "levers_replay_size",
          "disc_hidden", "disc_layers", "unpaired_batch", "disc_steps")
CHANNELS = ("f1", "f2")  # Adversaries' order (sorted channel names)
CHUNK = 32  # updates whose random draws are made ahead
# The knob values this update implements (asp_dist.knobs): every one.
IMPLEMENTS = {
    "levers_hidden": ANY, "levers_num_ids": ANY, "levers_eps_start": ANY, "levers_eps_end": ANY,
    "levers_eps_decay_frac": ANY, "levers_replay_size": ANY,
    "levers_base_lr": BASE_ONLY, "levers_accept_reward": BASE_ONLY,
}


def explore(coins: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """dqn_step's `torch.rand(...) < eps` for pre-drawn coins and a float32 tensor of ε values: a
    Python float compared with a float32 tensor is rounded to float32 first, so the comparison must
    be in float32 too (in float64 a coin equal to float32(ε) < ε would explore where dqn_step does not)."""
    assert eps.dtype == torch.float32
    return coins < eps


class PackedLeverTrainer(PackedTrainer):
    """K lever cells as one batched model; train_step() is one update of every member.

    specs, paired, unpaired, agents: one entry per member, as Trainer gets them (run_cell: P and U
    from the member's base, a fresh CommNet). The agents' parameters are re-pointed into the pack's
    buffer. After training, member i's `members[i].agents` holds its trained weights,
    `loss_columns(i)` its row's loss_* columns and `members[i].curve` its learning curve (probes:
    set `members[i].probe` as run_cell sets Trainer.probe)."""

    # Capabilities (asp_dist.training.engines): packs, and a single lever cell trains as a pack of one
    # (3.0x the reference Trainer: docs/performance.md).
    domain = "levers"
    lone = True
    implements = IMPLEMENTS
    shared = SHARED  # the pack key (PackedTrainer.pack_key)
    member_order = staticmethod(asp_members_first)  # their rows of the pack are a prefix

    def __init__(self, specs: Sequence[CellSpec], paired: Sequence[Tensors], unpaired: Sequence[Tensors],
                 agents: Sequence[CommNet]):
        discs = self._init_members(specs, paired, unpaired, agents, paired_rows="ids")  # (f1, f2) each
        retain_freed_memory()
        mem = self.members
        s0 = mem[0].spec
        self.B, self.H, self.V, self.size = s0.batch_size, s0.levers_hidden, s0.levers_num_ids, s0.levers_replay_size
        M, B, H, V = self.M, self.B, self.H, self.V

        # ---- stacked parameters: the CommNets; the (f1, f2) discriminators of the ASP members ---------
        self.net = StackedParams(agents, [m.spec.lr for m in mem])
        self.E, self.W1, self.b1, self.W2, self.b2, self.Wq, self.bq = self.net.views
        (self.g_E, self.g_W1, self.g_b1, self.g_W2, self.g_b2, self.g_Wq, self.g_bq) = self.net.grad_views
        self.W1T, self.W2T, self.WqT = (w.transpose(1, 2) for w in (self.W1, self.W2, self.Wq))
        self.dnet = None
        if self.Ma:
            Ma = self.Ma
            # Channel-major: rows [0, Ma) are the f1 discriminators, [Ma, 2Ma) the f2 ones.
            self.dnet = StackedParams([d[0] for d in discs] + [d[1] for d in discs],
                                       [mem[i].spec.disc_lr for i in self.adv_rows] * 2)
            slopes = {m.negative_slope for m in discs[0][0].net if isinstance(m, torch.nn.LeakyReLU)}
            self.slope = slopes.pop() if slopes else 0.01
            v, g = self.dnet.views, self.dnet.grad_views
            self.dlayers = [[(v[2 * i][c * Ma:(c + 1) * Ma], v[2 * i][c * Ma:(c + 1) * Ma].transpose(1, 2),
                              v[2 * i + 1][c * Ma:(c + 1) * Ma], g[2 * i][c * Ma:(c + 1) * Ma],
                              g[2 * i + 1][c * Ma:(c + 1) * Ma]) for i in range(len(v) // 2)] for c in range(2)]

        # ---- per-ID tables: h1 per ID, and [h1, h1/2] block-diagonal for W2's two halves ------------
        self.H12 = torch.zeros(M, 2 * V, 2 * H)
        rows_max = (2 * B if self.any_self_play else 0) + max(m.n_paired for m in mem)
        self.seat_buf = torch.zeros(M, rows_max * AGENTS, V)  # one-hot ID of each seat
        self.game_buf = torch.zeros(M, rows_max, V)           # the IDs seated in each game

        # ---- paired data (padded to the largest set; padded rows weighted 0) ------------------------
        n_max = max(m.n_paired for m in mem)
        self.n = n_max
        self.p_ids = torch.arange(AGENTS).repeat(M, n_max, 1)  # padding: a valid game, weighted 0
        self.p_f1, self.p_f2 = torch.zeros(M, n_max, AGENTS, H), torch.zeros(M, n_max, AGENTS, H)
        self.p_onehot = torch.zeros(M, n_max, AGENTS, AGENTS)
        self.p_mask = torch.zeros(M, n_max, 1, 1)
        ce_w, mse_w = torch.zeros(M, n_max, 1, 1), torch.zeros(M, n_max, 1, 1)
        for i, (m, p) in enumerate(zip(mem, paired)):
            k = m.n_paired
            if k:
                self.p_ids[i, :k] = p["ids"]
                self.p_f1[i, :k], self.p_f2[i, :k] = p["f1"], p["f2"]
                self.p_onehot[i, :k] = F.one_hot(p["levers"], AGENTS).float()
                self.p_mask[i, :k] = 1.0
                ce_w[i, :k] = m.weights.paired / (k * AGENTS)          # cross_entropy: mean over n·3 rows
                mse_w[i, :k] = 2.0 * m.weights.paired / (k * AGENTS * H)  # mse_loss: mean over n·3·H
        self.p_ce_w, self.p_mse_w = ce_w, mse_w
        self.inv_n3 = column([1.0 / (max(m.n_paired, 1) * AGENTS) for m in mem])
        self.inv_n3H = column([1.0 / (max(m.n_paired, 1) * AGENTS * H) for m in mem])
        if n_max:
            # Scatter of the paired rows' h1 gradients into the per-ID table, as one batched matmul.
            self.p_scatter = F.one_hot(self.p_ids.view(M, -1), V).float().transpose(1, 2).contiguous()
            self.p_h1_index = (self.p_ids + (torch.arange(M) * V).view(M, 1, 1)).view(-1)

        # ---- self-play: replay buffers, the DQN loss scale ------------------------------------------
        self.r_ids = torch.zeros(M, self.size, AGENTS, dtype=torch.long)
        self.r_lev = torch.zeros(M, self.size, AGENTS, dtype=torch.long)
        self.r_rew = torch.zeros(M, self.size)
        self.r_offset = (torch.arange(M) * self.size).view(M, 1)
        self.pos = self.filled = 0
        # d(w_sp · mse(mean over seats of Q(chosen), reward)) / dQ(chosen) = (value - reward) · 2·w_sp / (3·G)
        self.sp_coef = {G: column([2.0 * m.weights.self_play / (AGENTS * G) for m in mem]) for G in (B, 2 * B)}

        # ---- discriminator data ----------------------------------------------------------------------
        if self.Ma:
            ub = self.ub
            sizes = [len(unpaired[i]["f1"]) for i in self.adv_rows]
            self.u_sizes, u_max = sizes, max(sizes)
            self.U = []
            for ch in CHANNELS:
                U = torch.zeros(self.Ma, u_max, H)
                for a, i in enumerate(self.adv_rows):
                    U[a, :sizes[a]] = unpaired[i][ch]
                self.U.append(U.view(self.Ma * u_max, H))
            self.u_offset = (torch.arange(self.Ma) * u_max).view(self.Ma, 1)
            kinds = [mem[i].spec.adversary_loss for i in self.adv_rows]
            self.ns_float = column([k == "non_saturating" for k in kinds])
            self.ns = self.ns_float.bool().view(-1)
            self.real_scale = torch.full((self.Ma, ub), 1.0 / ub)
            self.labels = {rows: torch.cat([torch.ones(ub), torch.zeros(rows)]).expand(self.Ma, ub + rows)
                           for rows in (V, AGENTS * B, 2 * AGENTS * B)}
            self.scales = {nf: torch.cat([torch.full((ub,), 1.0 / ub), torch.full((nf,), 1.0 / nf)]).expand(
                self.Ma, ub + nf) for nf in (AGENTS * B, 2 * AGENTS * B)}
            self.ones = torch.ones(self.Ma, 2 * AGENTS * B)

        # ---- bookkeeping, as Trainer's ----------------------------------------------------------------
        self._init_records()
        self._alloc_draws()

    # ---- random draws, made ahead per member in the single-cell order ---------------------------
    def _alloc_draws(self) -> None:
        M, B, V = self.M, self.B, self.V
        self.uniform = torch.zeros(CHUNK, B, V)                              # one member's game draws
        self.fresh = torch.arange(AGENTS).repeat(CHUNK, M, B, 1)             # (S, M, B, 3) fresh games
        self.rank = torch.arange(AGENTS).repeat(CHUNK, M, B, 1)              # their rank (reward rule)
        self.rep = torch.zeros(CHUNK, M, B, dtype=torch.long)                # replay indices
        self.rand_lev = torch.zeros(CHUNK, M, B, AGENTS, dtype=torch.long)   # random levers
        self.coins = torch.ones(CHUNK, M, B, AGENTS)                         # exploration coins
        self.eps = torch.zeros(CHUNK, M, 1, 1)
        self.real_idx = torch.zeros(CHUNK * self.disc_steps, 2, self.Ma, self.ub, dtype=torch.long)
        if self.Ma:
            self.lam_now = torch.zeros(CHUNK, self.Ma, dtype=torch.float64)     # λ1 of the update
            self.lam_signed = torch.zeros(CHUNK, self.Ma, dtype=torch.float64)  # d(λ1·L_u)/d(logit) · N / (σ - ns)

    def _filled_at(self, step: int) -> int:
        """Games in the replay buffer before update `step` (every self-play member adds batch_size)."""
        return min(step * self.B, self.size)

    def _draw_chunk(self) -> None:
        """The random draws of updates [step, step + CHUNK) (not past train_steps), member by member,
        with the calls dqn_step and Trainer.train_step make, in their order."""
        start, S, adv_slot = self._open_chunk(CHUNK)
        B, V, ub, ds = self.B, self.V, self.ub, self.disc_steps
        for i, m in enumerate(self.members):
            if not m.self_play:  # PC draws nothing
                continue
            gen, unif = m.gen, self.uniform[:S].unbind(0)
            reps, levs, coins = self.rep[:S, i].unbind(0), self.rand_lev[:S, i].unbind(0), self.coins[:S, i].unbind(0)
            idx = self.real_idx[:S * ds, :, adv_slot[i]].unbind(0) if m.adversary else ()
            high = m.spec.unpaired_size
            for s in range(S):
                torch.rand(B, V, generator=gen, out=unif[s])  # draw_games
                filled = self._filled_at(start + s)
                if filled > 0:
                    torch.randint(filled, (B,), generator=gen, out=reps[s])
                torch.randint(AGENTS, (B, AGENTS), generator=gen, out=levs[s])
                torch.rand(B, AGENTS, generator=gen, out=coins[s])
                for d in range(ds if m.adversary else 0):
                    for c in range(2):
                        torch.randint(high, (ub,), generator=gen, out=idx[s * ds + d][c])
                self.eps[s, i] = epsilon(m.spec, start + s, self.train_steps)
            games = self.uniform[:S].argsort(dim=-1)[..., :AGENTS]
            self.fresh[:S, i] = games
            self.rank[:S, i] = games.argsort(dim=-1).argsort(dim=-1)
        self.explore = explore(self.coins[:S], self.eps[:S])
        self.rep_flat = (self.rep[:S] + self.r_offset.unsqueeze(0)).view(S, -1)
        if self.Ma:
            self.real_flat = self.real_idx[:S * ds] + self.u_offset.unsqueeze(0).unsqueeze(0)
            self._lambda_chunk(start, S)
            for a, i in enumerate(self.adv_rows):
                now = self.lam_now[:S, a]
                self.lam_signed[:S, a] = now if self.members[i].spec.adversary_loss == "non_saturating" else -now

    # ---- one update of every member -------------------------------------------------------------
    @torch.no_grad()
    def train_step(self) -> None:
        j, vals = self._begin_update()
        record = vals is not None
        M, B, H, V, n = self.M, self.B, self.H, self.V, self.n

        # ---- games of this update: fresh, replayed (after the first update), paired ---------------
        G = 0
        parts = []
        if self.any_self_play:
            G = B if self.filled == 0 else 2 * B
            fresh = self.fresh[j]
            parts.append(fresh)
            if G > B:
                rep = self.rep_flat[j]
                parts.append(self.r_ids.view(-1, AGENTS).index_select(0, rep).view(M, B, AGENTS))
        if n:
            parts.append(self.p_ids)
        if not parts:  # nothing to learn in any member (PC without paired data): no update at all
            if record:
                self._record({}, j)
            self.step += 1
            self._finish_curve_point()
            return
        ids = parts[0] if len(parts) == 1 else torch.cat(parts, 1)  # (M, R, 3)
        R = ids.shape[1]

        # ---- forward: per-ID tables, then one-hot matmuls per seat and per game -------------------
        H1 = torch.baddbmm(self.b1, self.E, self.W1T).tanh_()             # (M, V, H): h1 of each ID
        H12 = self.H12
        H12[:, :V, :H] = H1
        torch.mul(H1, 0.5, out=H12[:, V:, H:])
        T = torch.bmm(H12, self.W2T)                                      # [h1·W2aᵀ ; (h1/2)·W2bᵀ]
        TA, TC = T[:, :V], T[:, V:]
        TA.add_(self.b2).sub_(TC)                                         # A + b2 - C/2
        seat = self.seat_buf[:, :R * AGENTS].zero_().scatter_(2, ids.view(M, R * AGENTS, 1), 1.0)  # (M, 3R, V)
        game = self.game_buf[:, :R].zero_().scatter_(2, ids, 1.0)                                # (M, R, V)
        h2 = torch.bmm(seat, TA).view(M, R, AGENTS, H)                    # (A + b2 - C/2)[id]
        h2 += torch.bmm(game, TC).unsqueeze(2)                            # + Σ_seats (C/2)[id']
        h2 = _tanh(h2)                                                    # (M, R, 3, H)
        q = torch.baddbmm(self.bq, h2.view(M, R * AGENTS, H), self.WqT).view(M, R, AGENTS, AGENTS)
        dq = torch.zeros_like(q)
        dh2_extra: list[tuple[slice, torch.Tensor]] = []

        # ---- self-play: ε-greedy levers of the fresh games, the DQN loss over fresh + replayed -------
        if G:
            greedy = q[:, :B].argmax(dim=-1)
            levers = torch.where(self.explore[j], self.rand_lev[j], greedy)
            reward = (levers == self.rank[j]).float().mean(dim=2)
            if G > B:
                all_lev = torch.cat([levers, self.r_lev.view(-1, AGENTS).index_select(0, rep).view(M, B, AGENTS)], 1)
                all_rew = torch.cat([reward, self.r_rew.view(-1).index_select(0, rep).view(M, B)], 1)
            else:
                all_lev, all_rew = levers, reward
            index = all_lev.unsqueeze(3)
            err = q[:, :G].gather(3, index).squeeze(3).mean(dim=2) - all_rew  # (M, G)
            dq[:, :G].scatter_(3, index, (err * self.sp_coef[G]).unsqueeze(2).unsqueeze(3).expand(M, G, AGENTS, 1))
            if record:
                vals["self_play"] = (err * err).mean(1)
            # the buffer after the update's own replay draw, as dqn_step writes it
            slots = (self.pos + torch.arange(B)) % self.size
            self.r_ids.index_copy_(1, slots, fresh)
            self.r_lev.index_copy_(1, slots, levers)
            self.r_rew.index_copy_(1, slots, reward)
            self.pos = (self.pos + B) % self.size
            self.filled = min(self.filled + B, self.size)

        # ---- paired: MSE on h1 and h2, cross-entropy of Q as logits on the base's levers ---------------
        dH1_direct = None
        if n:
            rows = slice(G, G + n)
            logp = q[:, rows].log_softmax(-1)
            dq[:, rows] = (logp.exp() - self.p_onehot) * self.p_ce_w
            d2 = h2[:, rows] - self.p_f2
            dh2_extra.append((rows, d2 * self.p_mse_w))
            h1p = H1.reshape(M * V, H).index_select(0, self.p_h1_index).view(M, n, AGENTS, H)
            d1 = h1p - self.p_f1
            dH1_direct = torch.bmm(self.p_scatter, (d1 * self.p_mse_w).view(M, n * AGENTS, H))
            if record:
                mask = self.p_mask
                mse1 = (d1 * d1 * mask).sum((1, 2, 3)).view(M, 1).mul_(self.inv_n3H)
                mse2 = (d2 * d2 * mask).sum((1, 2, 3)).view(M, 1).mul_(self.inv_n3H)
                ce = (logp * self.p_onehot * mask).sum((1, 2, 3)).view(M, 1).mul_(self.inv_n3)
                vals["paired"] = (mse1 + mse2 - ce).view(-1)

        # ---- ASP: discriminator steps, then the model's adversarial gradients -----------------------
        dh2 = torch.bmm(dq.view(M, R * AGENTS, AGENTS), self.Wq).view(M, R, AGENTS, H)
        for rows, d in dh2_extra:
            dh2[:, rows] += d
        if self.Ma:
            dX1, dX2 = self._adversarial(H1, h2, ids, G, j, vals)
            if dH1_direct is None:
                dH1_direct = torch.zeros(M, V, H)
            if self.adv_first:
                dh2[:self.Ma, :G] += dX2
                dH1_direct[:self.Ma] += dX1
            else:
                dh2[:, :G].index_add_(0, self.adv_idx, dX2)
                dH1_direct.index_add_(0, self.adv_idx, dX1)

        # ---- backward through q, the gathers, W2 and the per-ID f1 block -----------------------------
        torch.bmm(dq.view(M, R * AGENTS, AGENTS).transpose(1, 2), h2.view(M, R * AGENTS, H), out=self.g_Wq)
        torch.sum(dq.view(M, R * AGENTS, AGENTS), 1, out=self.g_bq)
        dpre2 = _tanh_backward(dh2, h2)
        dsum = dpre2[:, :, 0] + dpre2[:, :, 1]
        dsum += dpre2[:, :, 2]                                            # (M, R, H): Σ over a game's seats
        dTA = torch.bmm(seat.transpose(1, 2), dpre2.view(M, R * AGENTS, H))
        dTC = torch.bmm(game.transpose(1, 2), dsum)
        torch.sum(dTA, 1, out=self.g_b2)
        dT = torch.cat([dTA, dTC.sub_(dTA)], 1)                           # d/d(C/2) = dTC - dTA
        torch.bmm(dT.transpose(1, 2), H12, out=self.g_W2)
        dH12 = torch.bmm(dT, self.W2)                                     # (M, 2V, 2H)
        dH1 = torch.add(dH12[:, :V, :H], dH12[:, V:, H:], alpha=0.5)
        if dH1_direct is not None:
            dH1 += dH1_direct
        dpre1 = _tanh_backward(dH1, H1)
        torch.bmm(dpre1.transpose(1, 2), self.E, out=self.g_W1)
        torch.sum(dpre1, 1, out=self.g_b1)
        torch.bmm(dpre1, self.W1, out=self.g_E)

        # ---- one Adam step for every member (a member whose gradient is not finite frozen first) ------
        self._step_model(vals, j, record)

    def _adversarial(self, H1: torch.Tensor, h2: torch.Tensor, ids: torch.Tensor, G: int, j: int,
                     vals: dict | None) -> tuple[torch.Tensor, torch.Tensor]:
        """disc_steps BCE steps of each ASP member's two discriminators (f1 on the per-ID h1 rows, each
        weighted by its seat count; f2 on the self-play h2 rows), then d(λ1·L_u)/d(h1 per ID, h2 rows)
        through the updated ones."""
        Ma, ub, V, H, ds = self.Ma, self.ub, self.V, self.H, self.disc_steps
        nf = AGENTS * G  # fake rows of each channel (fresh and replayed games' seats)
        # Inputs of the two discriminators: ub real rows, then the fake ones (h1 per ID; h2 per seat).
        X = (torch.empty(Ma, ub + V, H), torch.empty(Ma, ub + nf, H))
        X[0][:, ub:] = self._adv(H1)
        X[1][:, ub:].view(Ma, G, AGENTS, H).copy_(self._adv(h2[:, :G]))
        counts = torch.zeros(Ma, V).scatter_add_(1, self._adv(ids[:, :G]).reshape(Ma, nf), self.ones[:, :nf])
        w1 = counts * (1.0 / nf)  # each per-ID f1 row stands for count seats of 1/nf each
        scales = (torch.cat([self.real_scale, w1], 1), self.scales[nf])
        labels = (self.labels[V], self.labels[nf])
        for k in range(ds):
            disc_loss, acc_real, acc_fake, d_fake = 0.0, 0.0, 0.0, 0.0
            for c in range(2):
                X[c][:, :ub] = self.U[c].index_select(0, self.real_flat[j * ds + k, c].view(-1)).view(Ma, ub, H)
                logits, inputs = self._disc_forward(c, X[c])
                self._disc_backward(c, (torch.sigmoid(logits) - labels[c]) * scales[c], inputs,
                                    params=True, input_grad=False)
                if vals is not None:  # as Trainer: the last step's loss, the first step's accuracies
                    disc_loss = disc_loss + F.binary_cross_entropy_with_logits(
                        logits, labels[c], reduction="none").mul(scales[c]).sum(1).double() / 2
                    if k == 0:
                        real_l, fake_l = logits[:, :ub], logits[:, ub:]
                        fw = scales[c][:, ub:]
                        acc_real = acc_real + (real_l > 0).float().mean(1).double() / 2
                        acc_fake = acc_fake + ((fake_l < 0).float() * fw).sum(1).double() / 2
                        d_fake = d_fake + (torch.sigmoid(fake_l) * fw).sum(1).double() / 2
            if vals is not None:
                vals["disc"] = disc_loss
                if k == 0:
                    vals["disc_acc_real"], vals["disc_acc_fake"], vals["d_fake"] = acc_real, acc_fake, d_fake
            self._step_discriminators()  # a member whose discriminators' gradient is not finite frozen first
        # The model's term: neg_bce -mean softplus(l) (d/dl = -σ/N), non-saturating mean softplus(-l)
        # (d/dl = (σ - 1)/N), times λ1 of this update.
        coef = (self.lam_signed[j] / nf).float().view(Ma, 1)
        grads, unpaired = [], 0.0
        for c in range(2):
            logits, inputs = self._disc_forward(c, X[c][:, ub:])
            dlogits = (torch.sigmoid(logits) - self.ns_float) * coef
            if c == 0:
                dlogits = dlogits * counts
            grads.append(self._disc_backward(c, dlogits, inputs, params=False, input_grad=True))
            if vals is not None:
                term = torch.where(self.ns.view(-1, 1), F.softplus(-logits), -F.softplus(logits))
                unpaired = unpaired + ((term * w1).sum(1) if c == 0 else term.mean(1)).double()
        if vals is not None:
            vals["unpaired"] = unpaired
        return grads[0], grads[1].view(Ma, G, AGENTS, H)

    def _adv(self, t: torch.Tensor) -> torch.Tensor:
        """The ASP members' rows of a member-stacked tensor (a view when they come first)."""
        return t[:self.Ma] if self.adv_first else t.index_select(0, self.adv_idx)

    def _disc_forward(self, c: int, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        inputs = [x]
        layers = self.dlayers[c]
        last = len(layers) - 1
        for i, (_, wT, b, _, _) in enumerate(layers):
            x = torch.baddbmm(b, x, wT)
            if i < last:
                x = F.leaky_relu(x, self.slope)
                inputs.append(x)
        return x.view(x.shape[0], -1), inputs

    def _disc_backward(self, c: int, dlogits: torch.Tensor, inputs: list[torch.Tensor], params: bool,
                       input_grad: bool) -> torch.Tensor | None:
        layers = self.dlayers[c]
        dy = dlogits.unsqueeze(2)
        for i in reversed(range(len(layers))):
            w, _, _, gw, gb = layers[i]
            if params:
                torch.bmm(dy.transpose(1, 2), inputs[i], out=gw)
                torch.sum(dy, 1, out=gb)
            if i == 0 and not input_grad:
                return None
            # the output layer has one unit: its input gradient is an outer product (exact as a product)
            dy = dy * w if dy.shape[2] == 1 else torch.bmm(dy, w)
            if i > 0:
                dy = _leaky_relu_backward(dy, inputs[i], self.slope, True)
        return dy

    # ---- failures and checkpoints (the rest in PackRecords) -------------------------------------
    def _freeze_params(self, rows: list[int]) -> None:
        self.net.freeze(rows)
        if self.dnet is not None:
            slots = [a for a, i in enumerate(self.adv_rows) if i in rows]
            self.dnet.freeze(slots + [self.Ma + a for a in slots])

    def state_dict(self) -> dict[str, Any]:
        """Everything to continue bit for bit (PackRecords._state), with the replay buffers."""
        return self._state(replay={"ids": self.r_ids.clone(), "levers": self.r_lev.clone(),
                                   "reward": self.r_rew.clone(), "pos": self.pos, "filled": self.filled})

    def load_state_dict(self, state: dict[str, Any]) -> None:
        replay = state["replay"]
        self.r_ids.copy_(replay["ids"])
        self.r_lev.copy_(replay["levers"])
        self.r_rew.copy_(replay["reward"])
        self.pos, self.filled = replay["pos"], replay["filled"]
        self._load_state(state)


pack_key = PackedLeverTrainer.pack_key  # cells with equal keys can share a pack
