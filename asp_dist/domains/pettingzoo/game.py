"""The PettingZoo adapter's torch half: the team's networks, A2C self-play on many env copies, the base, P and U,
the paired loss, the convention outputs and evaluation. Every function takes the domain (the card: its
declaration and the environment's facts) first, then the contract's arguments.

Agents. One actor per agent (a two-layer MLP of its own observation: logits of every part of a discrete
action, or the mean of a Box action squashed into its bounds with a learned log-std) and a centralised critic
(a two-layer MLP of every agent's observation and the fraction of the episode left). A team acts by sampling.

A2C. Synchronous advantage actor-critic with n-step bootstrapped returns (`<name>_rollout_len` steps per
update) on `batch_size` env copies (the base: `<name>_base_envs`), the team reward shared by all actors, the
loss -log π(a)·A + value_coef·(R - V)² - entropy·H summed over agents and parts. Episodes end at
`<name>_episode_len` (the time left is a critic input, so the cut is a true terminal) or when the env ends
them, and the copy restarts with a reset seed drawn from the generator: a seed reproduces everything, the
environment's own randomness included. The copies of the new team's self-play start staggered over the
episode (each advanced by uniform random actions), so that every batch mixes episode phases.

Self-play state. The contract keeps the state as tensors (it checkpoints): each copy's reset seed, its step
and the env actions of its current episode. The env copies themselves live in this module, found again by the
state they last wrote; a state restored from a checkpoint (or any state they did not write) rebuilds them by
resetting with the seeds and replaying the actions, and checks the observations match.

(About 510 lines, over the project's 500: it is the contract's torch half for any PettingZoo env, one function per
contract method, as a built-in domain's game.py is; the env copies' bookkeeping (Runner) serves all of them.)
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.core.contract import SelfPlayOut, Tensors
from asp_dist.domains.pettingzoo import PettingZooDomain
from asp_dist.domains.pettingzoo.envs import BOX, DISCRETE, AgentFacts, EnvBatch, EnvFacts
from asp_dist.nn import seeded

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

PAIRED_ENVS = 32  # base episodes run together while P is collected: P(n) is a prefix of P(m) for n < m
EVAL_ENVS = 256  # env copies at most stepped together in evaluation and data collection
SEED_HIGH = 2**31 - 1
LIVE_CAP = 16  # self-play env batches kept alive per process (an evicted one is rebuilt from its state)


# ---- networks ---------------------------------------------------------------------------------------------
class Actor(nn.Module):
    """obs -> logits of every part (discrete) or the Box mean in [low, high] (with a learned log-std)."""

    def __init__(self, agent: AgentFacts, hidden: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(agent.obs_dim, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                 nn.Linear(hidden, agent.head))
        self.kind = agent.kind
        self.sizes = tuple(s for _, s in agent.parts)
        if agent.kind == BOX:
            self.log_std = nn.Parameter(torch.full((agent.head,), -1.0))
            self.register_buffer("low", torch.tensor(agent.low, dtype=torch.float32))
            self.register_buffer("span", torch.tensor(agent.high, dtype=torch.float32) - self.low)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs)


class TeamAgents(nn.Module):
    """One actor per agent of the env (in the env's agent order) and the team's centralised critic."""

    def __init__(self, facts: EnvFacts, hidden: int):
        super().__init__()
        self.names = facts.names
        self.actors = nn.ModuleList([Actor(a, hidden) for a in facts.agents])
        critic_in = sum(a.obs_dim for a in facts.agents) + 1
        self.critic = nn.Sequential(nn.Linear(critic_in, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                    nn.Linear(hidden, 1))

    def value(self, features: torch.Tensor) -> torch.Tensor:
        return self.critic(features).view(-1)


@dataclass
class Act:
    """One agent's actions for a batch of observations."""

    env: np.ndarray  # (B, width) the env actions (float64: indices or Box values)
    logp: torch.Tensor  # (B,) log-probability of the taken action, summed over parts
    neg_entropy: torch.Tensor  # (B,) summed over parts
    parts: torch.Tensor  # (B, parts) part indices (discrete kinds) or (B, dim) Box action (clipped)
    channel: torch.Tensor | None  # (B, width of the channel) straight-through output, when asked for


def act(actor: Actor, obs: torch.Tensor, gen: torch.Generator, channel: int | None = None,
        greedy: bool = False) -> Act:
    """Sample (or take the mode of) the actor's actions; `channel`: the part whose straight-through output to return."""
    out = actor(obs)
    if actor.kind == BOX:
        mean = actor.low + actor.span * torch.sigmoid(out)
        std = actor.span * actor.log_std.exp()
        eps = torch.zeros_like(mean) if greedy else torch.randn(mean.shape, generator=gen)
        raw = mean + std * eps
        clipped = torch.minimum(torch.maximum(raw, actor.low), actor.low + actor.span)
        z = (raw.detach() - mean) / std
        logp = (-0.5 * z.pow(2) - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        neg_entropy = -(std.log() + 0.5 * math.log(2 * math.pi * math.e)).sum(-1).expand(len(obs))
        chan = None
        if channel is not None:
            start = sum(actor.sizes[:channel])
            chan = clipped[:, start:start + actor.sizes[channel]]
        action = clipped.detach()
        return Act(action.double().numpy(), logp, neg_entropy, action, chan)
    logps, negs, taken, chan = [], [], [], None
    start = 0
    for j, size in enumerate(actor.sizes):
        logits = out[:, start:start + size]
        start += size
        logp_all = logits.log_softmax(-1)
        probs = logp_all.exp()
        idx = probs.argmax(-1) if greedy else torch.multinomial(probs.detach(), 1, generator=gen).view(-1)
        logps.append(logp_all.gather(1, idx.view(-1, 1)).view(-1))
        negs.append((probs * logp_all).sum(-1))
        taken.append(idx)
        if j == channel:
            chan = F.one_hot(idx, size).to(probs.dtype) + probs - probs.detach()
    parts = torch.stack(taken, 1)
    if actor.kind == DISCRETE:
        strides = torch.tensor([math.prod(actor.sizes[:j]) for j in range(len(actor.sizes))])
        env = (parts * strides).sum(1, keepdim=True)
    else:  # MULTI
        env = parts
    return Act(env.double().numpy(), sum(logps), sum(negs), parts, chan)


def critic_features(obs: list[torch.Tensor], t: np.ndarray, T: int) -> torch.Tensor:
    left = torch.from_numpy((T - t).astype(np.float32) / T).unsqueeze(1)
    return torch.cat([*obs, left], dim=1)


def draw_seeds(gen: torch.Generator, n: int) -> np.ndarray:
    return torch.randint(SEED_HIGH, (n,), generator=gen).numpy()


def random_env_actions(facts: EnvFacts, n: int, gen: torch.Generator) -> list[np.ndarray]:
    """Uniform random env actions of every agent (the staggered start of self-play)."""
    out = []
    for a in facts.agents:
        if a.kind == BOX:
            low, high = torch.tensor(a.low), torch.tensor(a.high)
            out.append((low + (high - low) * torch.rand(n, len(a.low), generator=gen, dtype=torch.float64)).float()
                       .double().numpy())
        else:
            sizes = [s for _, s in a.parts]
            idx = torch.stack([torch.randint(s, (n,), generator=gen) for s in sizes], 1)
            if a.kind == DISCRETE:
                idx = (idx * torch.tensor([math.prod(sizes[:j]) for j in range(len(sizes))])).sum(1, keepdim=True)
            out.append(idx.double().numpy())
    return out


# ---- many env copies with their episode's history ------------------------------------------------------
class Runner:
    """n env copies that play episode after episode, with each copy's reset seed and the env actions of its
    current episode (what rebuilds it from a checkpoint)."""

    def __init__(self, facts: EnvFacts, n: int):
        self.facts, self.n = facts, n
        self.batch = EnvBatch(facts, n)
        self.seeds = np.zeros(n, dtype=np.int64)
        self.hist = [np.zeros((n, facts.episode_len, a.width)) for a in facts.agents]
        self.published: torch.Tensor | None = None  # the state tensor this runner last wrote ("t")

    def start(self, gen: torch.Generator) -> None:
        self.seeds[:] = draw_seeds(gen, self.n)
        self.batch.reset(range(self.n), self.seeds)

    def obs(self) -> list[torch.Tensor]:
        return [torch.tensor(o) for o in self.batch.obs]

    def step(self, actions: list[np.ndarray], gen: torch.Generator) -> tuple[np.ndarray, np.ndarray]:
        rows, t = np.arange(self.n), self.batch.t
        for k, a in enumerate(actions):
            self.hist[k][rows, t] = a
        rewards, done = self.batch.step(actions)
        if done.any():
            idx = np.flatnonzero(done)
            self.seeds[idx] = draw_seeds(gen, len(idx))
            self.batch.reset(idx, self.seeds[idx])
        return rewards, done

    def publish(self, state: Tensors) -> None:
        state["seeds"] = torch.from_numpy(self.seeds.copy())
        state["t"] = torch.from_numpy(self.batch.t.copy())
        for k, o in enumerate(self.batch.obs):
            state[f"obs{k}"] = torch.from_numpy(o.copy())
            state[f"hist{k}"] = torch.from_numpy(self.hist[k].copy())
        self.published = state["t"]

    @classmethod
    def rebuild(cls, facts: EnvFacts, state: Tensors) -> Runner:
        """Env copies in the state `state` describes: reset with its seeds, its episodes' actions replayed."""
        n = len(state["seeds"])
        runner = cls(facts, n)
        runner.seeds[:] = state["seeds"].numpy()
        runner.batch.reset(range(n), runner.seeds)
        t = state["t"].numpy()
        for k in range(len(facts.agents)):
            runner.hist[k][:] = state[f"hist{k}"].numpy()
        for step in range(int(t.max()) if n else 0):
            index = np.flatnonzero(t > step)
            runner.batch.step([h[:, step] for h in runner.hist], index=index)
        for k, o in enumerate(runner.batch.obs):
            if not np.array_equal(o, state[f"obs{k}"].numpy()) or not np.array_equal(runner.batch.t, t):
                raise RuntimeError(f"{facts.env} did not reach the same observations when its episodes were replayed "
                                   f"from their seeds and actions: it is not deterministic given them, so a "
                                   f"checkpoint of its self-play cannot be resumed")
        runner.published = state["t"]
        return runner

    def close(self) -> None:
        self.batch.close()


_LIVE: OrderedDict[int, Runner] = OrderedDict()  # id(state dict) -> the runner that last wrote it


def runner_for(facts: EnvFacts, state: Tensors) -> Runner:
    runner = _LIVE.get(id(state))
    if runner is None or runner.published is not state.get("t") or runner.facts != facts:
        if runner is not None:
            runner.close()
        runner = Runner.rebuild(facts, state)
        _LIVE[id(state)] = runner
        while len(_LIVE) > LIVE_CAP:
            _LIVE.popitem(last=False)[1].close()
    _LIVE.move_to_end(id(state))
    return runner


# ---- A2C ----------------------------------------------------------------------------------------------------
def a2c_rollout(domain: PettingZooDomain, spec: CellSpec, facts: EnvFacts, agents: TeamAgents, runner: Runner,
                gen: torch.Generator, channel: tuple[int, int] | None = None) -> SelfPlayOut:
    """Advance the runner `rollout_len` steps with the team's sampled actions; the A2C loss of that rollout and
    (channel = (agent index, part index)) that agent's straight-through channel outputs."""
    T, K = domain.knob(spec, "episode_len"), domain.knob(spec, "rollout_len")
    gamma, scale = domain.knob(spec, "gamma"), domain.knob(spec, "reward_scale")
    feats, logps, negs, rews, dones, chans = [], [], [], [], [], []
    returns_raw = []
    for _ in range(K):
        obs = runner.obs()
        acts = [act(actor, obs[i], gen, channel[1] if channel is not None and channel[0] == i else None)
                for i, actor in enumerate(agents.actors)]
        feats.append(critic_features(obs, runner.batch.t, T))
        rewards, done = runner.step([a.env for a in acts], gen)
        logps.append(sum(a.logp for a in acts))
        negs.append(sum(a.neg_entropy for a in acts))
        rews.append(torch.from_numpy(rewards).float())
        returns_raw.append(rewards)
        dones.append(torch.from_numpy(done))
        if channel is not None:
            chans.append(acts[channel[0]].channel)
    feats.append(critic_features(runner.obs(), runner.batch.t, T))
    values = agents.value(torch.cat(feats))
    B = runner.n
    with torch.no_grad():
        ret = values[K * B:]
        out = []
        for k in reversed(range(K)):
            ret = rews[k] * scale + gamma * ret.masked_fill(dones[k], 0.0)
            out.append(ret)
        returns = torch.cat(out[::-1])
    td = returns - values[: K * B]
    loss = (-torch.cat(logps) * td.detach() + domain.knob(spec, "value_coef") * td.pow(2)
            + domain.knob(spec, "entropy") * torch.cat(negs)).mean()
    outputs = {"channel": torch.cat(chans)} if channel is not None else {}
    return SelfPlayOut(loss=loss, outputs=outputs, info={"reward": float(np.mean(returns_raw))})


def stagger(runner: Runner, gen: torch.Generator) -> None:
    """Copy i advanced by i·T/n uniform random steps, so that the copies' episodes are out of phase."""
    T, n = runner.facts.episode_len, runner.n
    target = np.arange(n) * T // n
    for step in range(int(target.max()) if n else 0):
        actions = random_env_actions(runner.facts, n, gen)
        index = np.flatnonzero(target > step)
        rows, t = index, runner.batch.t[index]
        for k, a in enumerate(actions):
            runner.hist[k][rows, t] = a[index]
        _, done = runner.batch.step(actions, index=index)
        if done.any():
            ended = index[done]
            runner.seeds[ended] = draw_seeds(gen, len(ended))
            runner.batch.reset(ended, runner.seeds[ended])


# ---- episodes of fixed teams (data and evaluation) --------------------------------------------------------
@torch.no_grad()
def play(facts: EnvFacts, actors: list[Actor | None], seeds: np.ndarray, gen: torch.Generator,
         on_step=None) -> np.ndarray:
    """One episode per seed, played by `actors` (one per agent, in the env's order; None: uniformly random
    actions), in chunks of EVAL_ENVS copies; the team return of each. on_step(obs, acts, active) sees every step
    (active: the copies still playing)."""
    returns = np.zeros(len(seeds))
    for lo in range(0, len(seeds), EVAL_ENVS):
        chunk = seeds[lo:lo + EVAL_ENVS]
        batch = EnvBatch(facts, len(chunk))
        try:
            batch.reset(range(len(chunk)), chunk)
            active = np.ones(len(chunk), dtype=bool)
            for _ in range(facts.episode_len):
                obs = [torch.tensor(o) for o in batch.obs]
                acts = [act(actor, obs[i], gen) if actor is not None else None for i, actor in enumerate(actors)]
                if on_step is not None:
                    on_step(obs, acts, active.copy())
                if any(a is None for a in acts):
                    uniform = random_env_actions(facts, len(chunk), gen)
                    env_actions = [a.env if a is not None else u for a, u in zip(acts, uniform)]
                else:
                    env_actions = [a.env for a in acts]
                index = np.flatnonzero(active)
                rewards, done = batch.step(env_actions, index=index)
                returns[lo + index] += rewards
                active[index[done]] = False
                if not active.any():
                    break
        finally:
            batch.close()
    return returns


def role_of(domain: PettingZooDomain, spec: CellSpec) -> tuple[EnvFacts, int, int]:
    """(facts, the new agent's index, its channel part's index)."""
    facts = domain.facts(spec)
    agent = facts.agent(domain.knob(spec, "new_agent"))
    return facts, facts.index(agent.name), agent.part(domain.knob(spec, "channel"))[0]


def channel_of(agent: AgentFacts, part: int, a: Act) -> torch.Tensor:
    """The channel output of taken actions, without gradient: one-hot of the part (discrete) or its Box slice."""
    if agent.kind == BOX:
        start = agent.part_offset(part)
        return a.parts[:, start:start + agent.parts[part][1]]
    return F.one_hot(a.parts[:, part], agent.parts[part][1]).float()


# ---- the contract's functions -------------------------------------------------------------------------------
def new_agents(domain, spec, seed):
    facts = domain.facts(spec)
    return seeded(seed, lambda: TeamAgents(facts, domain.knob(spec, "hidden")))


def train_base(domain, spec, seed, progress=None):
    """Self-play A2C on base_envs copies. Score: the base team's mean return over eval_episodes episodes minus a
    uniformly random team's on the same reset seeds, floored at 0 (the bar, a knob, is >= 0; MPE's returns are
    negative): how much the base has learnt, in the env's return units."""
    facts = domain.facts(spec)
    agents = new_agents(domain, spec, seed)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(agents.parameters(), lr=domain.knob(spec, "base_lr"))
    runner = Runner(facts, domain.knob(spec, "base_envs"))
    try:
        runner.start(gen)
        stagger(runner, gen)
        steps = spec.base_train_steps
        for step in range(steps):
            loss = a2c_rollout(domain, spec, facts, agents, runner, gen).loss
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if progress is not None and (step + 1) % max(1, steps // 20) == 0:
                progress("base", step + 1, steps, {})
    finally:
        runner.close()
    agents.eval()
    seeds = draw_seeds(gen, spec.eval_episodes)
    random_team = play(facts, [None] * len(facts.agents), seeds, gen).mean()
    gain = play(facts, list(agents.actors), seeds, gen).mean() - random_team
    return agents, max(0.0, float(gain))


def paired(domain, spec, base, n, gen):
    """n (observation, action) pairs of the new agent's role: one uniform step (reservoir-sampled, so uniform
    over episodes that end early too) of each of n base episodes, run PAIRED_ENVS at a time."""
    facts, r, _ = role_of(domain, spec)
    agent = facts.agents[r]
    obs_rows, act_rows = [], []
    for _ in range(math.ceil(n / PAIRED_ENVS)):
        kept: dict[str, torch.Tensor] = {}
        seen = np.zeros(PAIRED_ENVS)

        def keep(obs, acts, active):
            seen[active] += 1
            u = torch.rand(PAIRED_ENVS, generator=gen).numpy()
            take = torch.from_numpy(active & (u * seen < 1.0))  # replace with probability 1/seen
            for key, value in (("obs", obs[r]), ("action", acts[r].parts)):
                kept[key] = torch.where(take.view(-1, 1), value, kept[key]) if key in kept else value.clone()

        play(facts, list(base.actors), draw_seeds(gen, PAIRED_ENVS), gen, keep)
        obs_rows.append(kept["obs"])
        act_rows.append(kept["action"])
    if not obs_rows:
        width = agent.head if agent.kind == BOX else len(agent.parts)
        return {"obs": torch.zeros(0, agent.obs_dim),
                "action": torch.zeros(0, width) if agent.kind == BOX else torch.zeros(0, width, dtype=torch.long)}
    return {"obs": torch.cat(obs_rows)[:n], "action": torch.cat(act_rows)[:n]}


def _role_steps(facts: EnvFacts, actors: list[Actor], r: int, part: int | None, size: int,
                gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The role's observations (and its channel outputs, for `part`) on every step of episodes of `actors`, in
    order, until `size` are collected."""
    obs_rows, chan_rows, count = [], [], 0
    agent = facts.agents[r]

    def collect(obs, acts, active):
        obs_rows.append(obs[r][torch.from_numpy(active)])
        if part is not None:
            chan_rows.append(channel_of(agent, part, acts[r])[torch.from_numpy(active)])

    while count < size:
        episodes = min(EVAL_ENVS, math.ceil((size - count) / facts.episode_len))
        play(facts, actors, draw_seeds(gen, episodes), gen, collect)
        count = sum(len(o) for o in obs_rows)
    obs = torch.cat(obs_rows)[:size] if obs_rows else torch.zeros(0, agent.obs_dim)
    chan = torch.cat(chan_rows)[:size] if chan_rows else None
    return obs, chan


def unpaired(domain, spec, base, size, gen):
    """The base's channel outputs on every step of base episodes (one-hot of the part, or its Box slice)."""
    facts, r, part = role_of(domain, spec)
    _, chan = _role_steps(facts, list(base.actors), r, part, size, gen)
    if chan is None:
        chan = torch.zeros(0, facts.agents[r].parts[part][1])
    return {"channel": chan}


def init_self_play(domain, spec, agents, gen):
    facts = domain.facts(spec)
    runner = Runner(facts, spec.batch_size)
    runner.start(gen)
    stagger(runner, gen)
    state: Tensors = {}
    runner.publish(state)
    _LIVE[id(state)] = runner
    while len(_LIVE) > LIVE_CAP:
        _LIVE.popitem(last=False)[1].close()
    return state


def self_play_step(domain, spec, agents, state, gen):
    facts, r, part = role_of(domain, spec)
    runner = runner_for(facts, state)
    out = a2c_rollout(domain, spec, facts, agents, runner, gen, channel=(r, part))
    runner.publish(state)
    return out


def paired_loss(domain, spec, agents, paired):
    """Cross-entropy of every part of the role's action against the base's (mean squared error for a Box)."""
    _, r, _ = role_of(domain, spec)
    actor = agents.actors[r]
    out = actor(paired["obs"])
    if actor.kind == BOX:
        return F.mse_loss(actor.low + actor.span * torch.sigmoid(out), paired["action"])
    loss, start = 0.0, 0
    for j, size in enumerate(actor.sizes):
        loss = loss + F.cross_entropy(out[:, start:start + size], paired["action"][:, j])
        start += size
    return loss


def convention_outputs(domain, spec, agents, n, gen):
    """n channel outputs (straight-through, with grad) of the new agent on the role's observations in the new
    team's own episodes."""
    facts, r, part = role_of(domain, spec)
    obs, _ = _role_steps(facts, list(agents.actors), r, None, n, gen)
    return {"channel": act(agents.actors[r], obs, gen, channel=part).channel}


@torch.no_grad()
def evaluate(domain, spec, base, agents, gen):
    """Eq. 1 with one new agent, and the other compositions, with common random numbers: the same reset seeds and
    the same generator seed for the actions, so that two compositions of the same actors play the same episodes."""
    facts, r, part = role_of(domain, spec)
    seeds = draw_seeds(gen, spec.eval_episodes)
    action_seed = int(draw_seeds(gen, 1)[0])

    def same() -> torch.Generator:
        return torch.Generator().manual_seed(action_seed)

    new_in_role = [agents.actors[i] if i == r else base.actors[i] for i in range(len(facts.agents))]
    base_in_role = [base.actors[i] if i == r else agents.actors[i] for i in range(len(facts.agents))]
    role_obs = []

    def watch(obs, acts, active):
        role_obs.append(obs[r][torch.from_numpy(active)])

    base_sp = play(facts, list(base.actors), seeds, same(), watch).mean()
    mixed = play(facts, new_in_role, seeds, same()).mean()
    swapped = play(facts, base_in_role, seeds, same()).mean()
    new_sp = play(facts, list(agents.actors), seeds, same()).mean()
    obs = torch.cat(role_obs)
    agent = facts.agents[r]
    start, size = agent.part_offset(part), agent.parts[part][1]
    greedy = []
    for actor in (base.actors[r], agents.actors[r]):
        out = actor(obs)
        if actor.kind == BOX:
            out = actor.low + actor.span * torch.sigmoid(out)
        greedy.append(out[:, start:start + size].argmax(-1))
    return {"mixed": float(mixed), "mixed_swapped": float(swapped), "self_play_new": float(new_sp),
            "self_play_base": float(base_sp), "channel_match": float((greedy[0] == greedy[1]).float().mean())}
