"""K cells of a VMAS domain trained as one batched program: one VMAS world batch holding every self-play
member's worlds, the members' networks stacked.

A VMAS cell's update is one episode of `batch_size` worlds through the differentiable world (game.py,
decision 0060): 25 steps of two small MLPs, a straight-through sample per choice and VMAS's World.step, then
autograd back through all of it. At 64 worlds every one of those calls is a fixed cost on tiny tensors
(docs/performance.md, `bench_vmas.py --profile`), so K cells cost K times the calls of one. This trainer makes
the calls once for the pack:

- **one world batch**: the self-play members' worlds side by side, K_sp × batch_size worlds in one VMAS
  World; member i's block is reset from member i's own episode seed (world.Worlds.reset with one seed per
  block), so it holds exactly the worlds its lone cell would play;
- **stacked networks**: every member's team is a slice of one parameter buffer (training.stacked
  .StackedParams); an agent's forward pass is three batched matmuls (baddbmm) over the members; autograd
  differentiates the pack's summed loss (each member's loss depends on its own slice only, so each member
  gets its own gradient), and one fused Adam step updates every member with its own moments and learning
  rate; the ASP members' discriminators likewise;
- **draws made ahead**: torch.multinomial(p, 1) is argmax(p / Exp(1)) with the Exp(1) draws taken from the
  generator (ATen's one-sample path), and nothing a cell draws depends on a value (the episode seed, one
  Exp(1) per choice per world and step, the indices into U), so the draws of up to CHUNK updates are made
  member by member with the member's own generator in the reference's order, and the batched update
  consumes them. A generator ends training in the state the reference Trainer leaves it in.

The update is the reference's (asp_dist.training.trainer.Trainer driving game.self_play_step, paired_loss and
training.adversary.Adversaries): w_sp·L_sp + λ0·L_p + λ1·L_u, the discriminators stepped disc_steps times on
the episode's channel choices before L_u is taken through the updated ones. A PC member plays no episode: it
has no worlds in the batch and only its paired loss is computed. Computed once where the reference computes
the same values again: a static agent's network (its observation is fixed all episode: the speaker's) once an
episode; the adversary's outputs from the episode's own probabilities, their gradient run back through the
role's actor by hand from the activations the episode kept (_ChannelProbs), not by re-running the actor.

Per member: loss weights, λ1 and its schedule, the adversarial loss kind, the entropy bonus, both learning
rates, its P (padded to the pack's largest, padded rows weighted 0), its U, its generator. Shared (the pack
key: `shared`, from COMMON_SHARED and KNOB_SHARED): the world's options, the team's shapes, the role and
channel, the discriminator's shape, the loop's length.

Independence of pack-mates: no op mixes members or worlds (batched matmuls, per-world physics, reductions
along a member's own rows), so a member's arithmetic is the same whatever its mates are as long as the pack's
shapes are (members, self-play members, ASP members, padded paired rows); other shapes round differently
(about 1e-7), which over a whole cell can flip a sampled choice: rows are reproducible for a fixed packing
(tests/test_packed.py).

A member whose network gradient, discriminator gradient or recorded loss becomes non-finite is frozen
(training.stacked.PackedTrainer) and reported failed; its worlds go on being stepped, read by no one else.
"""

from __future__ import annotations

from typing import Any, Sequence

import torch
import torch.nn.functional as F

from asp_dist.core.contract import Tensors
from asp_dist.domains.vmas import VMASDomain, VMASReference, VMASSpeakerListener
from asp_dist.domains.vmas.game import SEED_HIGH, Team, options, role, roles, straight_through, worlds
from asp_dist.domains.vmas.scenarios import AgentRole
from asp_dist.domains.vmas.world import Worlds
from asp_dist.knobs import ANY, BASE_ONLY
from asp_dist.spec import CellSpec
from asp_dist.training.methods import method_weights
from asp_dist.training.stacked import PackedTrainer, StackedParams, column, retain_freed_memory

CHUNK = 16  # updates whose random draws are made ahead
_tanh_backward = torch.ops.aten.tanh_backward  # grad · (1 − y²)
BASE_KNOBS = ("base_worlds", "base_lr", "accept_mi", "accept_drop")  # <domain>_<these> shape the base alone
# Common fields every member shares: the loop's length and the tensors' shapes.
COMMON_SHARED = ("domain", "train_steps", "batch_size", "disc_hidden", "disc_layers", "unpaired_batch", "disc_steps")
# Knobs of the domain every member shares (the rest, e.g. the entropy bonus, are per member).
KNOB_SHARED = ("new_agent", "channel", "goal_per_world", "force", "reward", "episode_len", "hidden")


class PackedVMASTrainer(PackedTrainer):
    """K cells of one VMAS domain as one batched program; train_step() is one update of every member.

    A subclass names its domain's card: `class PackedXTrainer(PackedVMASTrainer, card=XDomain)`; what it
    implements (every knob, the base's as BASE_ONLY) and shares follow from the card's knobs.

    specs, paired, unpaired, agents: one entry per member, as Trainer gets them; the agents' (Team) parameters
    are re-pointed into the pack's buffer, so after training member i's `members[i].agents` holds its weights."""

    # A lone cell stays on the reference Trainer: a pack of one is ~23 % faster per update, but the committed word
    # study's rows were trained on the reference, and `replay` retraces them there (docs/decisions/0061).
    lone = False

    def __init_subclass__(cls, card: type[VMASDomain] | None = None, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if card is None:
            return
        names = [k.name for k in card.knobs]
        cls.domain = card.name
        cls.implements = {n: BASE_ONLY if n.removeprefix(f"{card.name}_") in BASE_KNOBS else ANY for n in names}
        cls.shared = COMMON_SHARED + tuple(f"{card.name}_{k}" for k in KNOB_SHARED if f"{card.name}_{k}" in names)

    @classmethod
    def unsupported(cls, spec: CellSpec) -> list[str]:
        missing = super().unsupported(spec)
        weights = method_weights(spec)
        if weights.needs_adversary and not weights.needs_self_play:  # its fakes would come from convention_outputs
            missing.append(f"method={spec.method!r} (an adversary without self-play)")
        return missing

    @staticmethod
    def member_order(specs: Sequence[CellSpec]) -> list[int]:
        """ASP members first, then the other self-play members, then the rest: the self-play and ASP rows are
        prefixes of the pack (views, not gathers)."""
        def rank(i: int) -> int:
            w = method_weights(specs[i])
            return 0 if w.needs_adversary else 1 if w.needs_self_play else 2
        return sorted(range(len(specs)), key=rank)

    def __init__(self, specs: Sequence[CellSpec], paired: Sequence[Tensors], unpaired: Sequence[Tensors],
                 agents: Sequence[Team]):
        discs = [d for (d,) in self._init_members(specs, paired, unpaired, agents, paired_rows="obs")]
        retain_freed_memory()  # an episode's tensors are K × a cell's: without it, page faults on most of them
        mem, s0 = self.members, self.members[0].spec
        self.roles = roles(s0)
        self.role, self.part = role(s0)
        self.T, self.n = getattr(s0, f"{s0.domain}_episode_len"), s0.batch_size
        self.width = sum(size for agent in self.roles for _, size in agent.parts)  # Exp(1) draws per world-step

        # ---- stacked parameters: the teams (six per agent: three Linear layers); the ASP members' discriminators
        self.net = StackedParams(agents, [m.spec.lr for m in mem])
        self.leaves = [v.detach().requires_grad_() for v in self.net.views]  # autograd's leaves, on the buffer
        self.dnet = self.dleaves = None
        if self.Ma:
            self.dnet = StackedParams(discs, [mem[i].spec.disc_lr for i in self.adv_rows])
            self.dleaves = [v.detach().requires_grad_() for v in self.dnet.views]
            slopes = {m.negative_slope for m in discs[0].net if isinstance(m, torch.nn.LeakyReLU)}
            self.slope = slopes.pop() if slopes else 0.01

        # ---- who plays: the self-play members' worlds, block by block, in one batch ---------------------
        self.sp_rows = [i for i, m in enumerate(mem) if m.self_play]
        self.sp = _rows(self.sp_rows)
        self.sp_idx = torch.tensor(self.sp_rows, dtype=torch.long)
        self.adv = _rows(self.adv_rows)
        self.adv_in_sp = _rows([self.sp_rows.index(i) for i in self.adv_rows])  # ASP ⊂ self-play (unsupported)
        self.world: Worlds | None = worlds(len(self.sp_rows) * self.n, options(s0)) if self.sp_rows else None
        self.entropy = column([getattr(mem[i].spec, f"{s0.domain}_entropy") for i in self.sp_rows]).view(-1)
        self.w_sp = column([m.weights.self_play for m in mem]).view(-1)
        self.w_p = column([m.weights.paired for m in mem]).view(-1)
        self.neg_bce = torch.tensor([mem[i].spec.adversary_loss == "neg_bce" for i in self.adv_rows])

        # ---- paired data: the role's observations and choices, padded to the largest set (weight 0) -------
        width = self.roles[self.role].obs
        self.n_p = max(m.n_paired for m in mem)
        self.p_obs = torch.zeros(self.M, self.n_p, width)
        self.p_act = torch.zeros(self.M, self.n_p, len(self.roles[self.role].parts), dtype=torch.long)
        self.p_w = torch.zeros(self.M, self.n_p)  # 1/n on a member's rows: cross_entropy's mean
        for i, (m, p) in enumerate(zip(mem, paired)):
            if m.n_paired:
                self.p_obs[i, :m.n_paired], self.p_act[i, :m.n_paired] = p["obs"], p["action"]
                self.p_w[i, :m.n_paired] = 1.0 / m.n_paired
        self.p_members = torch.tensor([m.n_paired > 0 for m in mem])

        # ---- unpaired data of the ASP members (padded; indices drawn in each member's own range) ---------
        if self.Ma:
            u = [unpaired[i]["channel"] for i in self.adv_rows]
            self.u_len = [len(x) for x in u]
            self.u = torch.zeros(self.Ma, max(self.u_len), u[0].shape[1])
            for a, x in enumerate(u):
                self.u[a, :len(x)] = x
            self.lam_now = torch.zeros(CHUNK, self.Ma, dtype=torch.float64)
        self._init_records()

    # ---- the networks, batched over members ----------------------------------------------------------
    def _weights(self, rows: slice | torch.Tensor, agent: int) -> tuple[torch.Tensor, ...]:
        """An agent's layers' (Wᵀ, b) for the members `rows`: taken once an update, so that the steps that use
        them add their gradients into one tensor (not one slice-backward and transpose-copy per step)."""
        taken = [_take(p, rows) for p in self.leaves[6 * agent:6 * agent + 6]]
        return tuple(t.transpose(1, 2).contiguous() if k % 2 == 0 else t for k, t in enumerate(taken))

    @staticmethod
    def _actor(weights: tuple[torch.Tensor, ...], x: torch.Tensor, keep: list | None = None) -> torch.Tensor:
        """An agent's logits on x (members, rows, obs), for its layers' `weights` (_weights): nn.Linear, tanh,
        twice, then nn.Linear, as game._mlp. keep: receives (x, h1, h2), detached (_ChannelProbs reads them)."""
        W1T, b1, W2T, b2, W3T, b3 = weights
        h1 = _Tanh.apply(torch.baddbmm(b1, x, W1T))
        h2 = _Tanh.apply(torch.baddbmm(b2, h1, W2T))
        if keep is not None:
            keep[:] = [x.detach(), h1.detach(), h2.detach()]
        return torch.baddbmm(b3, h2, W3T)

    def _disc(self, x: torch.Tensor, params: list[torch.Tensor]) -> torch.Tensor:
        """The ASP members' discriminators' logits on x (Ma, rows, channel): adversary.Discriminator."""
        layers = len(params) // 2
        for k in range(layers):
            x = torch.baddbmm(params[2 * k + 1], x, params[2 * k].transpose(1, 2))
            if k < layers - 1:
                x = F.leaky_relu(x, self.slope)
        return x.squeeze(-1)

    # ---- random draws, made ahead ------------------------------------------------------------------
    def _draw_chunk(self) -> None:
        """The draws of the next CHUNK updates, member by member with its own generator, in the order of the
        reference update: the episode's seed (game.draw_seed), its choices' Exp(1) (per step, agent and part,
        n × size each: one call makes them in that order), then disc_steps × the indices into U."""
        start, S, _ = self._open_chunk(CHUNK)
        k, n, T = len(self.sp_rows), self.n, self.T
        self.seeds = [[0] * k for _ in range(S)]
        self.exps = torch.empty(S, k, T, n * self.width)
        self.u_idx = torch.zeros(S, self.disc_steps, self.Ma, self.ub, dtype=torch.long)
        for j in range(S):
            for slot, i in enumerate(self.sp_rows):
                gen = self.members[i].gen
                self.seeds[j][slot] = int(torch.randint(SEED_HIGH, (1,), generator=gen))
                self.exps[j, slot].exponential_(generator=gen)
                if i in self.adv_rows:
                    a = self.adv_rows.index(i)
                    for d in range(self.disc_steps):
                        self.u_idx[j, d, a] = torch.randint(self.u_len[a], (self.ub,), generator=gen)
        if self.Ma:
            self._lambda_chunk(start, S)

    # ---- one update -------------------------------------------------------------------------------------
    def _episode(self, j: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The self-play members' episode of update j of the chunk: their L_sp (K_sp,), the ASP members'
        channel outputs (Ma, T·n, size) straight-through from the role's actor on its observations taken as
        given (game.self_play_step), and nothing else."""
        k, n, T = len(self.sp_rows), self.n, self.T
        obs = self.world.reset(self.seeds[j])
        exps = self.exps[j]
        total, entropy = torch.zeros(k, n), torch.zeros(k, n)
        role_acts, role_probs, role_idx, acts = [], [], [], []  # the role's activations, channel probs and choices
        heads: list[list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None] = [None] * len(self.roles)
        weights = [self._weights(self.sp, a) for a in range(len(self.roles))]
        for t in range(T):
            choices, offset = [], 0
            for a, agent in enumerate(self.roles):
                x = obs[a].view(k, n, -1)
                if heads[a] is None or not agent.static:  # a static agent's choices are the same every step
                    heads[a] = self._heads(agent, weights[a], x, acts if a == self.role and self.Ma else None)
                choice = {}
                for p, ((part, size), (logp, probs, h)) in enumerate(zip(agent.parts, heads[a])):
                    q = exps[:, t, offset:offset + n * size].view(k, n, size)
                    offset += n * size
                    index = (probs.detach() / q).argmax(-1)  # = torch.multinomial(probs, 1, generator)
                    choice[part] = straight_through(index, probs).view(k * n, size)
                    entropy = entropy - h
                    if a == self.role and p == self.part:
                        role_idx.append(index)
                if a == self.role and self.Ma:
                    role_acts.append(acts[:])
                    role_probs.append(heads[a][self.part][1].detach())
                choices.append(choice)
            total = total + self.world.step(choices).view(k, n)
            obs = self.world.obs
        loss = -(total.mean(1) + self.entropy * entropy.mean(1)) / T
        channel = None
        if self.Ma:  # the ASP members' rows of every step, step-major: (Ma, T·n, ...)
            def steps(items: list[torch.Tensor]) -> torch.Tensor:
                return torch.stack(items, 1)[self.adv_in_sp].flatten(1, 2)

            x, h1, h2 = (steps([kept[i] for kept in role_acts]) for i in range(3))
            probs = _ChannelProbs.apply(steps(role_probs), x, h1, h2, self._part_start,
                                        *self._weights(self.adv, self.role))
            channel = straight_through(steps(role_idx), probs)
        return loss, channel

    def _heads(self, agent: AgentRole, weights: tuple[torch.Tensor, ...], x: torch.Tensor, keep: list | None = None
               ) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """Per part of the agent's choices on x (self-play members, worlds, obs): log-probabilities,
        probabilities and entropy, as game.choose and game.play compute them."""
        logits, start, out = self._actor(weights, x, keep), 0, []
        for _, size in agent.parts:
            logp = logits[..., start:start + size].log_softmax(-1)
            probs = logp.exp()
            out.append((logp, probs, (probs * logp).sum(-1)))
            start += size
        return out

    @property
    def _part_start(self) -> int:
        """Where the channel part's columns start in the role's logits."""
        return sum(size for _, size in self.roles[self.role].parts[:self.part])

    def _paired_loss(self) -> torch.Tensor:
        """Every member's cross-entropy of each of the role's choices against the base's (M,), 0 without P."""
        logits, start, loss = self._actor(self._weights(slice(None), self.role), self.p_obs), 0, torch.zeros(self.M)
        for p, (_, size) in enumerate(self.roles[self.role].parts):
            logp = logits[..., start:start + size].log_softmax(-1)
            start += size
            nll = -logp.gather(-1, self.p_act[..., p:p + 1]).squeeze(-1)
            loss = loss + (nll * self.p_w).sum(1)
        return loss

    def _adversary(self, channel: torch.Tensor, j: int, vals: dict | None) -> torch.Tensor:
        """disc_steps BCE steps of the ASP members' discriminators on U (real) against the episode's channel
        outputs (fake), then L_u of each through its updated discriminator (Ma,)."""
        fake = channel.detach()
        rows = torch.arange(self.Ma).view(-1, 1)
        for d in range(self.disc_steps):
            real = self.u[rows, self.u_idx[j, d]]
            real_logits, fake_logits = self._disc(real, self.dleaves), self._disc(fake, self.dleaves)
            loss = (F.binary_cross_entropy_with_logits(real_logits, torch.ones_like(real_logits), reduction="none").mean(1)
                    + F.binary_cross_entropy_with_logits(fake_logits, torch.zeros_like(fake_logits),
                                                         reduction="none").mean(1))
            for leaf in self.dleaves:
                leaf.grad = None
            loss.sum().backward()
            _copy_grads(self.dleaves, self.dnet)
            self._step_discriminators()
            if vals is not None:
                vals["disc"] = loss.detach()
                if d == 0:
                    real_logits, fake_logits = real_logits.detach(), fake_logits.detach()
                    vals["disc_acc_real"] = (real_logits > 0).float().mean(1)
                    vals["disc_acc_fake"] = (fake_logits < 0).float().mean(1)
                    vals["d_fake"] = torch.sigmoid(fake_logits).mean(1)
        logits = self._disc(channel, [p.detach() for p in self.dleaves])
        neg = -F.binary_cross_entropy_with_logits(logits, torch.zeros_like(logits), reduction="none").mean(1)
        non_saturating = F.binary_cross_entropy_with_logits(logits, torch.ones_like(logits), reduction="none").mean(1)
        return torch.where(self.neg_bce, neg, non_saturating)

    def train_step(self) -> None:
        j, vals = self._begin_update()
        total = torch.zeros(self.M)
        sp_loss = torch.zeros(self.M)
        if self.sp_rows:
            loss, channel = self._episode(j)
            sp_loss = sp_loss.index_put((self.sp_idx,), loss)
            total = total + self.w_sp * sp_loss
        paired = self._paired_loss() if self.n_p else torch.zeros(self.M)
        total = total + torch.where(self.p_members, self.w_p * paired, torch.zeros(()))
        if self.Ma:
            unpaired = self._adversary(channel, j, vals)
            lam = self.lam_now[j].float()
            total = total.index_add(0, self.adv_idx, lam * unpaired)
        for leaf in self.leaves:
            leaf.grad = None
        if total.requires_grad:
            total.sum().backward()
        _copy_grads(self.leaves, self.net)
        if vals is not None:
            vals["self_play"], vals["paired"] = sp_loss.detach().double(), paired.detach().double()
            if self.Ma:
                vals["unpaired"] = unpaired.detach()
        self._step_model(vals, j, vals is not None)

    # ---- failures and checkpoints ------------------------------------------------------------------
    def _freeze_params(self, rows: list[int]) -> None:
        self.net.freeze(rows)
        if self.dnet is not None:
            self.dnet.freeze([self.adv_rows.index(i) for i in rows if i in self.adv_rows])

    def state_dict(self) -> dict[str, Any]:
        return self._state()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._load_state(state)


class _Tanh(torch.autograd.Function):
    """tanh(x) as 2·σ(2x) − 1 (within 1.2e-7 of torch.tanh for float32; torch.tanh is 6× slower than sigmoid on
    CPU here: 109 against 18 µs on 10 × 64 × 64), with tanh's own backward, 1 − y²."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        y = torch.sigmoid_(x.mul(2.0)).mul_(2.0).sub_(1.0)
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (y,) = ctx.saved_tensors
        return _tanh_backward(grad, y)


class _ChannelProbs(torch.autograd.Function):
    """The ASP members' channel probabilities on the role's observations *taken as given*, as game.self_play_step
    makes them (it runs the role's actor again on the episode's observations, detached): forward, the episode's own
    probabilities of the channel part; backward, the actor's layers run back by hand from the activations the
    episode kept (x, h1, h2: (Ma, T·n, ·)), gradients for the actor's weights only, none for the observations.
    The same gradient as the re-run's, without its forward pass (the channel is the part of the logits at
    `start`)."""

    @staticmethod
    def forward(ctx, probs, x, h1, h2, start, W1T, b1, W2T, b2, W3T, b3):
        ctx.save_for_backward(probs, x, h1, h2, W2T, W3T)
        ctx.start, ctx.b3_shape = start, b3.shape
        return probs.clone()

    @staticmethod
    def backward(ctx, grad):
        probs, x, h1, h2, W2T, W3T = ctx.saved_tensors
        cols = slice(ctx.start, ctx.start + probs.shape[-1])
        g3 = probs * (grad - (grad * probs).sum(-1, keepdim=True))  # softmax's backward: the channel's logits
        gW3T, gb3 = W3T.new_zeros(W3T.shape), W3T.new_zeros(ctx.b3_shape)
        gW3T[..., cols], gb3[..., cols] = torch.bmm(h2.transpose(1, 2), g3), g3.sum(1, keepdim=True)
        g2 = _tanh_backward(torch.bmm(g3, W3T[..., cols].transpose(1, 2)), h2)
        g1 = _tanh_backward(torch.bmm(g2, W2T.transpose(1, 2)), h1)
        return (None, None, None, None, None, torch.bmm(x.transpose(1, 2), g1), g1.sum(1, keepdim=True),
                torch.bmm(h1.transpose(1, 2), g2), g2.sum(1, keepdim=True), gW3T, gb3)


def _rows(rows: list[int]) -> slice | torch.Tensor:
    """Member rows as a slice where they are a contiguous range (a view), else an index tensor (a gather)."""
    first = rows[0] if rows else 0
    if rows == list(range(first, first + len(rows))):
        return slice(first, first + len(rows))
    return torch.tensor(rows, dtype=torch.long)


def _take(t: torch.Tensor, rows: slice | torch.Tensor) -> torch.Tensor:
    return t[rows] if isinstance(rows, slice) else t.index_select(0, rows)


def _copy_grads(leaves: list[torch.Tensor], net: StackedParams) -> None:
    """The leaves' gradients into the stacked gradient buffer (zeros where a leaf got none)."""
    for leaf, g in zip(leaves, net.grad_views):
        if leaf.grad is None:
            g.zero_()
        else:
            g.copy_(leaf.grad.view_as(g))


class PackedSpeakerListenerTrainer(PackedVMASTrainer, card=VMASSpeakerListener):
    pass


class PackedReferenceTrainer(PackedVMASTrainer, card=VMASReference):
    pass


TRAINERS_OF = {t.domain: (t,) for t in (PackedSpeakerListenerTrainer, PackedReferenceTrainer)}


def pack_key(spec: CellSpec) -> tuple:
    """Cells with equal keys can share a pack (the values of its domain's trainer's `shared`)."""
    return TRAINERS_OF[spec.domain][0].pack_key(spec)
