"""The particle world's torch half: the environment, the agents, A2C (with and without a replay buffer),
the base, P and U, the paired loss and evaluation. The card (asp_dist.domains.particles: the world's
description, knobs, metrics, validation) calls the functions at the end, one per Domain method, and
imports this module on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.core.contract import SelfPlayOut, Tensors
from asp_dist.domains.particles import POOL, ParticlesDomain
from asp_dist.hashing import stable_hash
from asp_dist.nn import seeded

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

BOX = 5.0                 # the world is [-BOX, BOX]²
TARGET_BOX = 4.0          # targets are drawn in [-TARGET_BOX, TARGET_BOX]² (see docs/decisions/0007-particle-world.md)
NEAR = 1.4                # within this distance of the target the reward is NEAR_REWARD
NEAR_REWARD = 10.0
REWARD_SCALE = 0.1        # A2C trains on reward/10 so values stay O(10); reported returns are raw
N_ACTIONS = 5
MOVES = torch.tensor([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


def target_for(spec: CellSpec) -> torch.Tensor:
    """The trial's fixed target, from (root_seed, trial) only: every base retry and every new
    pair of the trial lives in the same world."""
    seed = int(stable_hash({"particles_target": [spec.root_seed, spec.trial]})[:12], 16)
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand(2, generator=gen) * 2 - 1) * TARGET_BOX


def spawn(n: int, gen: torch.Generator) -> torch.Tensor:
    return (torch.rand(n, 2, generator=gen) * 2 - 1) * BOX


def env_step(pos: torch.Tensor, actions: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Move every actor, clip to the box, and return (new positions, raw rewards)."""
    pos = (pos + MOVES[actions]).clamp_(-BOX, BOX)
    dist = torch.linalg.vector_norm(pos - target, dim=-1)
    return pos, dist.reciprocal().masked_fill_(dist < NEAR, NEAR_REWARD)


def sample_actions(logits: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """One draw per row from softmax(logits), with the explicit generator."""
    return torch.multinomial(logits.softmax(-1), 1, generator=gen).view(-1)


class ParticleAgents(nn.Module):
    """Speaker (x, y) -> tanh message; listener message -> action logits; critic (x, y, time left) -> value.

    The message is bounded by tanh so that the base's and the new speaker's messages live in
    the same box [-1, 1]^d: the paired MSE has a fixed scale and neither the listener nor the
    discriminator can be fooled (or helped) by a speaker that simply inflates its messages.
    Forward passes call F.linear directly: at batch 8 the cost is per op, not per flop."""

    def __init__(self, message_dim: int, hidden: int):
        super().__init__()
        self.speaker = nn.Sequential(nn.Linear(2, hidden), nn.ReLU(), nn.Linear(hidden, message_dim), nn.Tanh())
        self.listener = nn.Sequential(nn.Linear(message_dim, hidden), nn.ReLU(), nn.Linear(hidden, N_ACTIONS))
        self.critic = nn.Sequential(nn.Linear(3, hidden), nn.ReLU(), nn.Linear(hidden, 1))
        self.message_dim = message_dim

    def speak(self, pos: torch.Tensor) -> torch.Tensor:
        l1, l2 = self.speaker[0], self.speaker[2]
        return torch.tanh(F.linear(torch.relu(F.linear(pos * (1.0 / BOX), l1.weight, l1.bias)), l2.weight, l2.bias))

    def listen(self, message: torch.Tensor) -> torch.Tensor:
        l1, l2 = self.listener[0], self.listener[2]
        return F.linear(torch.relu(F.linear(message, l1.weight, l1.bias)), l2.weight, l2.bias)

    def value(self, features: torch.Tensor) -> torch.Tensor:
        """features: (x/BOX, y/BOX, time left / episode length)."""
        l1, l2 = self.critic[0], self.critic[2]
        return F.linear(torch.relu(F.linear(features, l1.weight, l1.bias)), l2.weight, l2.bias).view(-1)


def critic_features(pos: torch.Tensor, t: torch.Tensor, T: int) -> torch.Tensor:
    return torch.cat([pos * (1.0 / BOX), (T - t).unsqueeze(1) * (1.0 / T)], dim=1)


def a2c_update(spec: CellSpec, agents: ParticleAgents, state: Tensors, target: torch.Tensor,
               gen: torch.Generator) -> SelfPlayOut:
    """Advance the envs in `state` by rollout_len steps and return the A2C loss of that rollout.

    The rollout runs with gradients (speaker -> message -> listener), so the loss needs no second
    forward pass; the critic values every visited state and the bootstrap state in one batch.
    Each env has its own time step (envs start staggered over the episode), so a batch mixes
    episode phases like a sample from a replay buffer would. At batch 8 the cost is the number
    of tensor ops, so the loop is written to keep that number small."""
    T, K = spec.particles_episode_len, spec.particles_rollout_len
    pos, t = state["pos"], state["t"]
    feats, logps, ents, rews, dones, messages = [], [], [], [], [], []
    for _ in range(K):
        msg = agents.speak(pos)
        logp = agents.listen(msg).log_softmax(-1)
        a = torch.multinomial(logp.detach().exp(), 1, generator=gen)
        with torch.no_grad():
            feats.append(critic_features(pos, t, T))
            pos, r = env_step(pos, a.view(-1), target)
            t = t + 1
            done = t >= T
            if bool(done.any()):  # a new episode starts for these envs: re-spawn them
                pos = torch.where(done.unsqueeze(1), spawn(len(pos), gen), pos)
                t = t.masked_fill_(done, 0)
        messages.append(msg)
        logps.append(logp.gather(1, a).view(-1))
        ents.append((logp.exp() * logp).sum(-1))  # negative entropy
        rews.append(r)
        dones.append(done)
    state["pos"], state["t"] = pos, t
    with torch.no_grad():
        feats.append(critic_features(pos, t, T))

    values = agents.value(torch.cat(feats))  # K visited states + the bootstrap state
    B = len(pos)
    with torch.no_grad():
        ret = values[K * B:]
        returns = []
        for k in reversed(range(K)):
            # A finished episode's last step is terminal: time left is part of the state.
            ret = rews[k] * REWARD_SCALE + spec.particles_gamma * ret.masked_fill(dones[k], 0.0)
            returns.append(ret)
        returns = returns[0] if K == 1 else torch.cat(returns[::-1])
    values = values[: K * B]
    logp_taken = logps[0] if K == 1 else torch.cat(logps)
    neg_entropy = ents[0] if K == 1 else torch.cat(ents)
    td = returns - values
    loss = (-logp_taken * td.detach() + spec.particles_value_coef * td.pow(2)
            + spec.particles_entropy * neg_entropy).mean()
    return SelfPlayOut(loss=loss, outputs={"message": messages[0] if K == 1 else torch.cat(messages)})


def replay_a2c_update(spec: CellSpec, agents: ParticleAgents, state: Tensors, target: torch.Tensor,
                      gen: torch.Generator) -> SelfPlayOut:
    """The paper's "batches of size 8 sampled uniformly from the experience replay buffer":
    advance the batch_size envs one step with the current policy, push those transitions into a
    FIFO of the last particles_replay_size, and return the one-step actor-critic loss of a
    uniform batch of it, re-spoken by the current speaker (so the message, and the
    discriminator's fakes, come from the buffer's states). The stored action's log-probability
    is taken under the current policy without importance weights, as a plain replay A2C does."""
    T, B, N = spec.particles_episode_len, spec.batch_size, spec.particles_replay_size
    with torch.no_grad():
        pos, t = state["pos"], state["t"]
        a = sample_actions(agents.listen(agents.speak(pos)), gen)
        feats = critic_features(pos, t, T)
        new_pos, r = env_step(pos, a, target)
        t_next = t + 1
        done = t_next >= T
        next_feats = critic_features(new_pos, t_next.clamp(max=T), T)
        if bool(done.any()):
            new_pos = torch.where(done.unsqueeze(1), spawn(B, gen), new_pos)
            t_next = t_next.masked_fill(done, 0)
        state["pos"], state["t"] = new_pos, t_next
        slots = (state["replay_head"] + torch.arange(B)) % N
        state["replay_pos"][slots], state["replay_feats"][slots], state["replay_next"][slots] = pos, feats, next_feats
        state["replay_action"][slots], state["replay_reward"][slots] = a, r
        state["replay_done"][slots] = done
        state["replay_head"] = (state["replay_head"] + B) % N
        state["replay_count"] = torch.clamp(state["replay_count"] + B, max=N)
        idx = torch.randint(int(state["replay_count"]), (B,), generator=gen)
        bootstrap = agents.value(state["replay_next"][idx]).masked_fill(state["replay_done"][idx], 0.0)
        returns = state["replay_reward"][idx] * REWARD_SCALE + spec.particles_gamma * bootstrap
    msg = agents.speak(state["replay_pos"][idx])
    logp = agents.listen(msg).log_softmax(-1)
    values = agents.value(state["replay_feats"][idx])
    td = returns - values
    loss = (-logp.gather(1, state["replay_action"][idx].view(-1, 1)).view(-1) * td.detach()
            + spec.particles_value_coef * td.pow(2) + spec.particles_entropy * (logp.exp() * logp).sum(-1)).mean()
    return SelfPlayOut(loss=loss, outputs={"message": msg}, info={"reward": float(r.mean())})


@torch.no_grad()
def play(speakers: list[ParticleAgents], listeners: list[ParticleAgents], episodes: int, T: int,
         target: torch.Tensor, gen: torch.Generator) -> list[float]:
    """Mean episode return of each (speaker, listener) team over `episodes` parallel episodes."""
    teams = len(speakers)
    pos = [spawn(episodes, gen) for _ in range(teams)]
    total = [torch.zeros(episodes) for _ in range(teams)]
    for _ in range(T):
        for i in range(teams):
            a = sample_actions(listeners[i].listen(speakers[i].speak(pos[i])), gen)
            pos[i], r = env_step(pos[i], a, target)
            total[i] += r
    return [float(x.mean()) for x in total]


@torch.no_grad()
def sample_steps(agents: ParticleAgents, episodes: int, T: int, target: torch.Tensor,
                 gen: torch.Generator) -> Tensors:
    """Run `episodes` self-play episodes and keep one step of each, uniform over its T steps:
    the state, the message sent there and the action taken."""
    pick = torch.randint(T, (episodes,), generator=gen)
    pos = spawn(episodes, gen)
    kept_pos = torch.zeros(episodes, 2)
    kept_msg = torch.zeros(episodes, agents.message_dim)
    kept_act = torch.zeros(episodes, dtype=torch.long)
    for step in range(T):
        msg = agents.speak(pos)
        a = sample_actions(agents.listen(msg), gen)
        here = pick == step
        kept_pos = torch.where(here[:, None], pos, kept_pos)
        kept_msg = torch.where(here[:, None], msg, kept_msg)
        kept_act = torch.where(here, a, kept_act)
        pos, _ = env_step(pos, a, target)
    return {"state": kept_pos, "message": kept_msg, "action": kept_act}


# ---- base ---------------------------------------------------------------------------------
def train_base(spec, seed, progress=None):
    """A2C self-play with more parallel envs than the new agents; score = mean self-play
    return over eval_episodes episodes."""
    agents = new_agents(spec, seed)
    gen = torch.Generator().manual_seed(seed)
    target = target_for(spec)
    base_spec = spec.replace(batch_size=spec.particles_base_envs)
    opt = torch.optim.Adam(agents.parameters(), lr=spec.particles_base_lr, **ParticlesDomain.optimizer_options)
    state = init_self_play(base_spec, agents, gen)
    steps = spec.base_train_steps
    for step in range(steps):
        loss = a2c_update(base_spec, agents, state, target, gen).loss
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if progress is not None and (step + 1) % max(1, steps // 20) == 0:
            progress("base", step + 1, steps, {})
    score = play([agents], [agents], spec.eval_episodes, spec.particles_episode_len, target, gen)[0]
    return agents.eval(), score


# ---- data ---------------------------------------------------------------------------------
def paired(spec, base, n, gen):
    pool = sample_steps(base, POOL, spec.particles_episode_len, target_for(spec), gen)
    return {k: v[:n] for k, v in pool.items()}


def unpaired(spec, base, size, gen):
    return {"message": sample_steps(base, size, spec.particles_episode_len, target_for(spec), gen)["message"]}


# ---- new agents ---------------------------------------------------------------------------
def new_agents(spec, seed):
    return seeded(seed, lambda: ParticleAgents(spec.particles_message_dim, spec.particles_hidden))


def init_self_play(spec, agents, gen):
    # The target rides along in the state so the hot loop never re-derives it.
    # Envs start staggered over the episode so that every batch mixes episode phases.
    B, T = spec.batch_size, spec.particles_episode_len
    state = {"pos": spawn(B, gen), "t": torch.arange(B) * T // B, "target": target_for(spec)}
    N = spec.particles_replay_size
    if N:
        state.update(replay_pos=torch.zeros(N, 2), replay_feats=torch.zeros(N, 3), replay_next=torch.zeros(N, 3),
                     replay_action=torch.zeros(N, dtype=torch.long), replay_reward=torch.zeros(N),
                     replay_done=torch.zeros(N, dtype=torch.bool), replay_head=torch.tensor(0),
                     replay_count=torch.tensor(0))
    return state


def self_play_step(spec, agents, state, gen):
    update = replay_a2c_update if spec.particles_replay_size else a2c_update
    return update(spec, agents, state, state["target"], gen)


def paired_loss(spec, agents, paired):
    speaker = F.mse_loss(agents.speak(paired["state"]), paired["message"])
    if not spec.particles_paired_listener:
        return speaker
    return speaker + F.cross_entropy(agents.listen(paired["message"]), paired["action"])


def convention_outputs(spec, agents, n, gen):
    """Messages on the agents' own state distribution: one uniform step of each of n episodes."""
    states = sample_steps(agents, n, spec.particles_episode_len, target_for(spec), gen)["state"]
    return {"message": agents.speak(states)}


# ---- evaluation ---------------------------------------------------------------------------
@torch.no_grad()
def evaluate(spec, base, agents, gen):
    T, n, target = spec.particles_episode_len, spec.eval_episodes, target_for(spec)
    base_spk, new_spk, new_sp, base_sp = play([base, agents, agents, base], [agents, base, agents, base],
                                              n, T, target, gen)
    # Convention agreement on states uniform over the box (diagnostics, not the headline).
    states = spawn(n, gen)
    base_msg, new_msg = base.speak(states), agents.speak(states)
    match = agents.listen(base_msg).argmax(-1) == base.listen(base_msg).argmax(-1)
    return {"mixed": (base_spk + new_spk) / 2, "mixed_base_speaker": base_spk, "mixed_new_speaker": new_spk,
            "self_play_new": new_sp, "self_play_base": base_sp,
            "message_mse": float(F.mse_loss(new_msg, base_msg)), "action_match": float(match.float().mean())}
