"""The particle pack's update as a JAX program: the third variant of bench/bench_compile.py.

One update does, per member, what asp_dist/domains/particles/packed.py's train_step does (the same
layer sizes, batch rows, loss terms and discriminator steps; here through jax.vjp instead of
hand-derived gradients):

  1. the self-play rollout of particles_rollout_len steps of batch_size envs (speaker -> message ->
     listener -> sampled action -> env step, re-spawn at episode end), the paired rows riding along
     with step 0's, the critic on every visited state and the bootstrap state; L_sp (A2C) and L_p
     (speaker MSE + listener cross-entropy on the member's own paired rows, padded rows masked);
  2. ASP members: disc_steps BCE steps of the discriminator (U real, the rollout's messages fake),
     each with its Adam step, then L_u through the updated discriminator;
  3. the gradient of w_sp·L_sp + λ0·L_p + λ1·L_u (λ1 on the member's schedule), zeroed for a member whose
     gradient is not finite (the torch pack freezes it), one Adam step (torch's arithmetic, per-member
     learning rate). The loss terms come out of every update (the torch pack records about 1 in 10).

Members are one function under jax.vmap (the discriminator part over the ASP members only, as the
torch pack), updates a jax.lax.scan, the whole run one jax.jit. Random draws come from a JAX key per
update (per-member keys; a different stream from torch's generators); `update` also takes the torch
pack's own draws, which is how bench_compile.py --check compares one update with the torch pack's.
Everything starts from a torch pack (`from_torch`): same weights, data, positions and constants.

jax must be imported after XLA_FLAGS is set (bench_compile.py sets one thread before importing this).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from asp_dist.domains.particles.game import BOX, MOVES, N_ACTIONS, NEAR, NEAR_REWARD, REWARD_SCALE
from asp_dist.training.stacked import BETAS, EPS

SCHEDULES = ("constant", "warmup", "anneal")  # λ1 schedules, by code
MOVES_J = jnp.asarray(MOVES.numpy())  # the five moves (stay, ±x, ±y)


@dataclass(frozen=True)
class Config:
    """What fixes shapes and control flow (jit's static argument): the pack's shared fields."""

    M: int           # members
    B: int           # envs per member (batch_size)
    T: int           # episode length
    Kr: int          # rollout steps per update
    D: int           # message dimension
    n: int           # paired rows (the pack's largest paired set; others padded, masked)
    Ma: int          # ASP members
    adv_rows: tuple  # their places in the pack
    ds: int          # discriminator steps per update
    ub: int          # unpaired rows per discriminator step
    slope: float     # the discriminator's LeakyReLU slope

    @property
    def all_adv(self) -> bool:
        return self.Ma == self.M


class Members(NamedTuple):
    """Per-member constants, leading dimension M (vmapped)."""

    paired_x: jax.Array       # (n, 2), already / BOX
    paired_msg: jax.Array     # (n, D)
    paired_onehot: jax.Array  # (n, 5)
    row_mask: jax.Array       # (n,) 1 for the member's own rows
    inv_n: jax.Array          # 1 / max(n_i, 1)
    inv_nD: jax.Array         # 1 / (max(n_i, 1) · D)
    target: jax.Array         # (2,)
    gamma: jax.Array
    ent: jax.Array
    vc: jax.Array
    w_sp: jax.Array           # loss weights: self-play, paired (λ0)
    w_p: jax.Array
    lr: jax.Array


class Adversaries(NamedTuple):
    """Per-ASP-member constants, leading dimension Ma."""

    U: jax.Array          # (u_max, D), padded
    u_size: jax.Array     # rows of U that are the member's
    lr: jax.Array
    ns: jax.Array         # non-saturating L_u (else the paper's negative BCE)
    lam: jax.Array        # λ1 (before its schedule)
    schedule: jax.Array   # index into SCHEDULES
    span: jax.Array       # max(1, lambda_schedule_frac · train_steps)


class State(NamedTuple):
    params: tuple   # speaker w1 b1 w2 b2, listener w1 b1 w2 b2, critic w1 b1 w2 b2: (M, out, in) and (M, out)
    m: tuple        # Adam moments
    v: tuple
    t: jax.Array    # Adam step count (float32, shared: every member steps together)
    dparams: tuple  # discriminators, (Ma, ...) per layer weight and bias
    dm: tuple
    dv: tuple
    dt: jax.Array
    pos: jax.Array  # (M, B, 2)
    step: jax.Array  # update count (int32): the episode clock and λ1's schedule


class Draws(NamedTuple):
    """One update's random draws: Exp(1) per action (sampling is argmax(p / E), torch.multinomial's one-sample
    path), re-spawn positions, indices into U."""

    E: jax.Array         # (M, Kr, B, 5)
    respawn: jax.Array   # (M, Kr, B, 2), positions
    real_idx: jax.Array  # (Ma, ds, ub)


# ---- one member's pieces --------------------------------------------------------------------------

def _linear(x, w, b):
    return x @ w.T + b


def _disc(dp, x, slope):
    """An MLP of LeakyReLU layers with one output: logits (rows,)."""
    layers = len(dp) // 2
    for i in range(layers):
        x = _linear(x, dp[2 * i], dp[2 * i + 1])
        if i < layers - 1:
            x = jax.nn.leaky_relu(x, slope)
    return x[:, 0]


def _adam(p, g, m, v, t, lr):
    """torch's (fused) Adam step, amsgrad off, no weight decay."""
    m = m + (1 - BETAS[0]) * (g - m)
    v = BETAS[1] * v + (1 - BETAS[1]) * g * g
    bc1, bc2 = 1 - BETAS[0] ** t, 1 - BETAS[1] ** t
    return p - (lr / bc1) * m / (jnp.sqrt(v) / jnp.sqrt(bc2) + EPS), m, v


def _tree_adam(ps, gs, ms, vs, t, lr):
    """Adam on every tensor; lr a scalar, or one per member (leading dimension) broadcast over each tensor."""
    out = [_adam(p, g, m, v, t, lr.reshape((-1,) + (1,) * (p.ndim - 1)) if lr.ndim else lr)
           for p, g, m, v in zip(ps, gs, ms, vs)]
    return tuple(o[0] for o in out), tuple(o[1] for o in out), tuple(o[2] for o in out)


def member_forward(cfg: Config, p, c: Members, pos, E, respawn, step):
    """The rollout and the paired forward pass of one member: ((L_sp, L_p, rollout messages (Kr·B, D)),
    positions after the rollout). Differentiable in p; actions and positions are not."""
    sw1, sb1, sw2, sb2, lw1, lb1, lw2, lb2, cw1, cb1, cw2, cb2 = p
    B, T, Kr, n = cfg.B, cfg.T, cfg.Kr, cfg.n
    t0 = jnp.arange(B) * T // B  # envs start staggered over the episode (init_self_play)

    def clock(k):  # each env's time step at rollout step k of this update
        return (t0 + (step * Kr + k) % T) % T

    def time_left(t):
        return ((T - t).astype(jnp.float32) * (1.0 / T))[:, None]

    feats, logp_taken, neg_ent, rews, dones, msgs = [], [], [], [], [], []
    l_p = jnp.zeros(())
    for k in range(Kr):
        x = pos * (1.0 / BOX)
        xs = jnp.concatenate([x, c.paired_x]) if k == 0 and n else x
        h = jax.nn.relu(_linear(xs, sw1, sb1))
        m = jnp.tanh(_linear(h, sw2, sb2))
        li = jnp.concatenate([m[:B], c.paired_msg]) if k == 0 and n else m
        logp = jax.nn.log_softmax(_linear(jax.nn.relu(_linear(li, lw1, lb1)), lw2, lb2))
        if k == 0 and n:  # the paired loss: MSE of the speaker, cross-entropy of the listener on the data's messages
            mse = (jnp.sum((m[B:] - c.paired_msg) ** 2, 1) * c.row_mask).sum() * c.inv_nD
            loglik = (jnp.sum(logp[B:] * c.paired_onehot, 1) * c.row_mask).sum() * c.inv_n
            l_p = mse - loglik
        m, logp = m[:B], logp[:B]
        a = jnp.argmax(jnp.exp(lax.stop_gradient(logp)) / E[k], -1)
        t = clock(k)
        feats.append(jnp.concatenate([x, time_left(t)], 1))
        pos = jnp.clip(pos + MOVES_J[a], -BOX, BOX)  # env_step
        dist = jnp.sqrt(jnp.sum((pos - c.target) ** 2, 1))
        rews.append(jnp.where(dist < NEAR, NEAR_REWARD, 1.0 / dist))
        done = t + 1 >= T
        pos = jnp.where(done[:, None], respawn[k], pos)
        dones.append(done)
        msgs.append(m)
        logp_taken.append(jnp.take_along_axis(logp, a[:, None], 1)[:, 0])
        neg_ent.append(jnp.sum(jnp.exp(logp) * logp, 1))
    feats.append(jnp.concatenate([pos * (1.0 / BOX), time_left(clock(Kr))], 1))
    values = _linear(jax.nn.relu(_linear(jnp.concatenate(feats), cw1, cb1)), cw2, cb2)[:, 0]
    ret = lax.stop_gradient(values[Kr * B:])
    returns = []
    for k in reversed(range(Kr)):  # n-step returns; a finished episode's last step is terminal
        ret = rews[k] * REWARD_SCALE + c.gamma * jnp.where(dones[k], 0.0, ret)
        returns.append(ret)
    td = jnp.concatenate(returns[::-1]) - values[:Kr * B]
    l_sp = jnp.mean(-jnp.concatenate(logp_taken) * lax.stop_gradient(td) + c.vc * td * td
                    + c.ent * jnp.concatenate(neg_ent))
    return (l_sp, l_p, jnp.concatenate(msgs)), pos


def member_adversarial(cfg: Config, dp, dm, dv, dt, a: Adversaries, real_idx, fake, lam):
    """disc_steps BCE steps of one ASP member's discriminator on U (real) vs `fake`, then λ1·dL_u/d(fake)
    through the updated discriminator. Returns the discriminator's state, its last BCE, L_u and that gradient."""
    ub = cfg.ub
    bce = jnp.zeros(())
    for k in range(cfg.ds):
        x = jnp.concatenate([a.U[real_idx[k]], fake])  # one batch: real rows, then fake rows

        def disc_loss(dp, x=x):
            logits = _disc(dp, x, cfg.slope)
            return jnp.mean(jax.nn.softplus(-logits[:ub])) + jnp.mean(jax.nn.softplus(logits[ub:]))

        bce, g = jax.value_and_grad(disc_loss)(dp)
        dp, dm, dv = _tree_adam(dp, g, dm, dv, dt + k + 1, a.lr)

    def l_u(fake):
        logits = _disc(dp, fake, cfg.slope)
        return jnp.where(a.ns, jnp.mean(jax.nn.softplus(-logits)), -jnp.mean(jax.nn.softplus(logits)))

    lu, d_fake = jax.value_and_grad(l_u)(fake)
    return dp, dm, dv, bce, lu, lam * d_fake


def lambda_now(a: Adversaries, step):
    """λ1 of update `step` on each ASP member's schedule (methods.lambda_factor)."""
    ramp = jnp.minimum(step.astype(jnp.float32) / a.span, 1.0)
    return a.lam * jnp.where(a.schedule == 0, 1.0, jnp.where(a.schedule == 1, ramp, 1.0 - ramp))


# ---- one update of the pack, a scan of them -----------------------------------------------------------

def update(cfg: Config, c: Members, a: Adversaries | None, s: State, d: Draws, debug: bool = False):
    """One update of every member. Returns (state, losses) (with the gradients in `losses` when debug)."""
    fwd = jax.vmap(partial(member_forward, cfg), in_axes=(0, 0, 0, 0, 0, None))
    (l_sp, l_p, fake), backward, pos = jax.vjp(lambda p: fwd(p, c, s.pos, d.E, d.respawn, s.step), s.params,
                                               has_aux=True)
    losses = {"self_play": l_sp, "paired": l_p}
    d_fake = jnp.zeros_like(fake)
    dparams, dm, dv, dt = s.dparams, s.dm, s.dv, s.dt
    if cfg.Ma:
        rows = np.array(cfg.adv_rows)
        fake_a = lax.stop_gradient(fake if cfg.all_adv else fake[rows])
        adv = jax.vmap(partial(member_adversarial, cfg), in_axes=(0, 0, 0, None, 0, 0, 0, 0))
        dparams, dm, dv, bce, lu, d_adv = adv(dparams, dm, dv, dt, a, d.real_idx, fake_a, lambda_now(a, s.step))
        dt = dt + cfg.ds
        d_fake = d_adv if cfg.all_adv else d_fake.at[rows].set(d_adv)
        losses.update(disc=bce, unpaired=lu)
    (grads,) = backward((c.w_sp, c.w_p, d_fake))
    # a member whose gradient is not finite gets none this update (the torch pack freezes it for good)
    finite = jnp.isfinite(sum(g.reshape(cfg.M, -1).sum(1) for g in grads))
    grads = tuple(jnp.where(finite.reshape((-1,) + (1,) * (g.ndim - 1)), g, 0.0) for g in grads)
    t = s.t + 1
    params, m, v = _tree_adam(s.params, grads, s.m, s.v, t, c.lr)
    if debug:
        losses["grads"] = grads
    return State(params, m, v, t, dparams, dm, dv, dt, pos, s.step + 1), losses


def draw(cfg: Config, a: Adversaries | None, key) -> Draws:
    """One update's draws, from one key per member."""
    def member(key):
        k1, k2 = jax.random.split(key)
        E = jax.random.exponential(k1, (cfg.Kr, cfg.B, N_ACTIONS))
        respawn = (jax.random.uniform(k2, (cfg.Kr, cfg.B, 2)) * 2 - 1) * BOX
        return E, respawn

    k_members, k_real = jax.random.split(key)
    E, respawn = jax.vmap(member)(jax.random.split(k_members, cfg.M))
    real_idx = jnp.zeros((0, cfg.ds, cfg.ub), jnp.int32)
    if cfg.Ma:
        real_idx = jax.vmap(lambda k, high: jax.random.randint(k, (cfg.ds, cfg.ub), 0, high))(
            jax.random.split(k_real, cfg.Ma), a.u_size)
    return Draws(E, respawn, real_idx)


@partial(jax.jit, static_argnums=(0, 5))
def run(cfg: Config, c: Members, a: Adversaries | None, s: State, key, updates: int):
    """`updates` updates of the pack (a scan); returns the state, the next key and each update's losses."""
    def body(carry, _):
        s, key = carry
        key, sub = jax.random.split(key)
        s, losses = update(cfg, c, a, s, draw(cfg, a, sub))
        return (s, key), losses

    (s, key), losses = lax.scan(body, (s, key), None, length=updates)
    return s, key, losses


update_jit = jax.jit(update, static_argnums=(0, 5))


# ---- from a torch pack ------------------------------------------------------------------------------


def _split(flat, grad_views) -> tuple:
    """A StackedParams buffer (param, exp_avg, exp_avg_sq, grad) as its per-tensor blocks, shaped as the
    gradient views: weights (M, out, in), biases (M, out)."""
    return tuple(jnp.asarray(flat[g.storage_offset():g.storage_offset() + g.numel()].view(g.shape).numpy())
                 for g in grad_views)


def from_torch(pack) -> tuple[Config, Members, Adversaries | None, State]:
    """The configuration, constants and state of a torch PackedParticleTrainer (its current weights, Adam
    moments, positions and update count)."""
    mem = pack.members
    f32 = (lambda xs: jnp.asarray(np.asarray(xs, np.float32)))
    cfg = Config(M=pack.M, B=pack.B, T=pack.T, Kr=pack.Kr, D=pack.D, n=pack.n, Ma=pack.Ma,
                 adv_rows=tuple(pack.adv_rows), ds=pack.disc_steps, ub=pack.ub,
                 slope=float(pack.slope) if pack.Ma else 0.01)
    c = Members(paired_x=jnp.asarray(pack.paired_x.numpy()), paired_msg=jnp.asarray(pack.paired_msg.numpy()),
                paired_onehot=jnp.asarray(pack.paired_onehot.numpy()), row_mask=jnp.asarray(pack.row_mask.numpy()),
                inv_n=jnp.asarray(pack.inv_n.view(-1).numpy()), inv_nD=jnp.asarray(pack.inv_nD.view(-1).numpy()),
                target=jnp.asarray(pack.target.view(-1, 2).numpy()), gamma=jnp.asarray(pack.gamma.view(-1).numpy()),
                ent=jnp.asarray(pack.ent2.view(-1).numpy()), vc=jnp.asarray(pack.vc2.view(-1).numpy()),
                w_sp=f32([m.weights.self_play for m in mem]), w_p=f32([m.weights.paired for m in mem]),
                lr=f32([m.spec.lr for m in mem]))
    net, gv = pack.net, pack.net.grad_views
    params, m, v = (_split(b, gv) for b in (net.param, net.exp_avg, net.exp_avg_sq))
    a, dparams, dm, dv, dt = None, (), (), (), jnp.zeros(())
    if pack.Ma:
        specs = [mem[i].spec for i in pack.adv_rows]
        a = Adversaries(U=jnp.asarray(pack.U.view(pack.Ma, -1, pack.D).numpy()),
                        u_size=jnp.asarray(pack.u_sizes, jnp.int32), lr=f32([s.disc_lr for s in specs]),
                        ns=jnp.asarray([s.adversary_loss == "non_saturating" for s in specs]),
                        lam=f32([mem[i].weights.unpaired for i in pack.adv_rows]),
                        schedule=jnp.asarray([SCHEDULES.index(s.lambda_unpaired_schedule) for s in specs], jnp.int32),
                        span=f32([max(1.0, s.lambda_schedule_frac * s.train_steps) for s in specs]))
        dnet = pack.dnet
        dparams, dm, dv = (_split(b, dnet.grad_views) for b in (dnet.param, dnet.exp_avg, dnet.exp_avg_sq))
        dt = jnp.asarray(float(dnet.steps), jnp.float32)
    s = State(params, m, v, jnp.asarray(float(net.steps), jnp.float32), dparams, dm, dv, dt,
              jnp.asarray(pack.pos.numpy()), jnp.asarray(pack.step, jnp.int32))
    return cfg, c, a, s


def draws_from_torch(pack, j: int) -> Draws:
    """The torch pack's own draws for update j of its current chunk (made ahead by _draw_chunk)."""
    Kr, ds = pack.Kr, pack.disc_steps
    E = pack.E[j * Kr:(j + 1) * Kr].transpose(0, 1)
    respawn = pack.respawn[j * Kr:(j + 1) * Kr].transpose(0, 1)
    real = pack.real_idx[j * ds:(j + 1) * ds].transpose(0, 1) if pack.Ma else np.zeros((0, ds, pack.ub))
    return Draws(jnp.asarray(E.numpy()), jnp.asarray(respawn.numpy()), jnp.asarray(np.asarray(real), jnp.int32))
