"""The VMAS domains' torch half: the team, episodes through the differentiable world, the base and its
acceptance, P and U, the paired loss, the convention outputs and evaluation. Every function reads its domain's
knobs as `<spec.domain>_<knob>`, so both domains (speaker–listener, reference) share it.

An episode is `episode_len` steps of n worlds from one reset seed. Every choice (each agent's move and word) is
a straight-through sample (forward: the one-hot of a draw from the softmax with the cell's generator;
backward: the softmax's gradient), so the return is differentiable in every agent's weights through the world
and the heard words. Training a team is: play an episode with gradients, loss = −(mean return per step) −
entropy · (mean entropy per step), one Adam step. Evaluation plays every composition on the same reset seed
and the same action generator seed (common random numbers).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.core.contract import SelfPlayOut
from asp_dist.domains.vmas.scenarios import LANDMARKS, SCENARIOS, AgentRole
from asp_dist.domains.vmas.world import WorldOptions, Worlds
from asp_dist.nn import seeded

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

PAIRED_WORLDS = 32  # base episodes run together while P is collected: P(n) is a prefix of P(m) for n < m
MAX_WORLDS = 1024  # worlds at most in one batch of data collection
SEED_HIGH = 2**31 - 1
UNUSED_WORDS = -1.0  # a base's score when its team ignores its words: no bar (>= 0) accepts it
WORLDS_CAP = 16  # batches of worlds kept per process, the least recently used dropped first
_WORLDS: OrderedDict[tuple[int, WorldOptions], Worlds] = OrderedDict()  # reset reseeds them: safe to reuse


def knob(spec: CellSpec, suffix: str) -> Any:
    return getattr(spec, f"{spec.domain}_{suffix}")


def scenario(spec: CellSpec) -> str:
    """The scenario of the spec's domain (its card's `scenario`)."""
    from asp_dist.core.registry import get_domain

    return get_domain(spec.domain).scenario


def roles(spec: CellSpec) -> tuple[AgentRole, ...]:
    return SCENARIOS[scenario(spec)].agents


class Team(nn.Module):
    """One actor per agent, in the scenario's order: observation -> the logits of each of its parts."""

    def __init__(self, agents: tuple[AgentRole, ...], hidden: int):
        super().__init__()
        self.actors = nn.ModuleList([_mlp(a.obs, sum(s for _, s in a.parts), hidden) for a in agents])

    def agent(self, index: int) -> nn.Module:
        return self.actors[index]


def _mlp(inputs: int, outputs: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                         nn.Linear(hidden, outputs))


def options(spec: CellSpec) -> WorldOptions:
    name = scenario(spec)
    reward = getattr(spec, f"{spec.domain}_reward", SCENARIOS[name].rewards[0])  # a knob where there is a choice
    return WorldOptions(scenario=name, goal_per_world=knob(spec, "goal_per_world"), force=knob(spec, "force"),
                        reward=reward)


def worlds(n: int, opts: WorldOptions) -> Worlds:
    key = (n, opts)
    if key not in _WORLDS:
        _WORLDS[key] = Worlds(n, opts)
        while len(_WORLDS) > WORLDS_CAP:
            _WORLDS.popitem(last=False)
    _WORLDS.move_to_end(key)
    return _WORLDS[key]


def role(spec: CellSpec) -> tuple[int, int]:
    """(the new agent's index, its channel part's index): an agent with one part has it as its channel."""
    agents = roles(spec)
    index = [a.name for a in agents].index(knob(spec, "new_agent"))
    parts = [p for p, _ in agents[index].parts]
    return index, 0 if len(parts) == 1 else parts.index(knob(spec, "channel"))


def draw_seed(gen: torch.Generator) -> int:
    return int(torch.randint(SEED_HIGH, (1,), generator=gen))


def choose(logits: torch.Tensor, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(straight-through one-hot, index, log-probabilities) of one sampled choice per row."""
    logp = logits.log_softmax(-1)
    probs = logp.exp()
    index = torch.multinomial(probs.detach(), 1, generator=gen).view(-1)
    return straight_through(index, probs), index, logp


def straight_through(index: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """Forward: the one-hot of `index`; backward: the gradient of `probs`."""
    return F.one_hot(index, probs.shape[-1]).to(probs.dtype) + probs - probs.detach()


@dataclass
class Episode:
    returns: torch.Tensor  # (n,) team return per world (with grad when played with it)
    entropy: torch.Tensor  # (n,) summed over steps, agents and parts
    goal: torch.Tensor  # (n, agents that see a goal)
    words: list[torch.Tensor]  # per agent that speaks, (T, n) word indices said
    role_obs: list[torch.Tensor] = field(default_factory=list)  # per step, (n, obs) of the recorded agent
    role_actions: list[torch.Tensor] = field(default_factory=list)  # per step, (n, parts) its choices' indices


def play(spec: CellSpec, actors: list[nn.Module], n: int, seed: int, gen: torch.Generator,
         record: int | None = None, random_words: bool = False) -> Episode:
    """One episode of n worlds from reset seed `seed`, one actor per agent; gradients flow where the caller
    allows them. record: the agent whose observations and choices to keep. random_words: every word replaced
    by a uniformly random one (the intervention)."""
    world = worlds(n, options(spec))
    obs = world.reset(seed)
    goal = world.goal.clone()
    total, entropy = torch.zeros(n), torch.zeros(n)
    agents = world.roles
    words: list[list[torch.Tensor]] = [[] for a in agents if a.words]
    role_obs, role_actions = [], []
    for _ in range(knob(spec, "episode_len")):
        choices, speaking = [], 0
        for i, (agent, actor) in enumerate(zip(agents, actors)):
            logits = None if random_words and not agent.moves else actor(obs[i])  # a speaker only speaks
            choice, indices, start = {}, [], 0
            for part, size in agent.parts:
                part_logits = torch.zeros(n, size) if part == "say" and random_words else logits[:, start:start + size]
                start += size
                one_hot, index, logp = choose(part_logits, gen)
                choice[part] = one_hot
                indices.append(index)
                entropy = entropy - (logp.exp() * logp).sum(-1)
                if part == "say":
                    words[speaking].append(index)
                    speaking += 1
            if record == i:
                role_obs.append(obs[i])
                role_actions.append(torch.stack(indices, 1))
            choices.append(choice)
        total = total + world.step(choices)
        obs = world.obs
    return Episode(total, entropy, goal, [torch.stack(w) for w in words], role_obs, role_actions)


def team_loss(spec: CellSpec, episode: Episode) -> torch.Tensor:
    return -(episode.returns.mean() + knob(spec, "entropy") * episode.entropy.mean()) / knob(spec, "episode_len")


def word_mi(goal: torch.Tensor, words: torch.Tensor) -> float:
    """Mutual information (nats) between a goal (n,) and the words said about it (T, n), over every step of
    every world."""
    vocabulary = int(words.max()) + 1 if words.numel() else 1
    joint = np.zeros((LANDMARKS, vocabulary))
    np.add.at(joint, (goal.expand_as(words).reshape(-1).numpy(), words.reshape(-1).numpy()), 1.0)
    joint /= joint.sum()
    outer = joint.sum(1, keepdims=True) @ joint.sum(0, keepdims=True)
    seen = joint > 0
    return float((joint[seen] * np.log(joint[seen] / outer[seen])).sum())


def team_mi(episode: Episode) -> float:
    """The mean over the agents that speak of the MI between the goal each sees and its words."""
    return float(np.mean([word_mi(episode.goal[:, i], w) for i, w in enumerate(episode.words)]))


@torch.no_grad()
def word_figures(spec: CellSpec, team: Team, gen: torch.Generator) -> tuple[float, float]:
    """(MI goal → word, return lost when every word is random) of a team, on eval_episodes worlds, the
    intervention on the same reset seed and action draws."""
    n, seed, action_seed = spec.eval_episodes, draw_seed(gen), draw_seed(gen)
    own = play(spec, list(team.actors), n, seed, torch.Generator().manual_seed(action_seed))
    rand = play(spec, list(team.actors), n, seed, torch.Generator().manual_seed(action_seed), random_words=True)
    return team_mi(own), float(own.returns.mean() - rand.returns.mean())


# ---- the contract's functions -------------------------------------------------------------------------------
def new_agents(spec, seed):
    return seeded(seed, lambda: Team(roles(spec), knob(spec, "hidden")))


def train_base(spec, seed, progress=None):
    """The team through the differentiable world for base_train_steps episodes of base_worlds worlds.
    Score: the goal → word mutual information in nats; UNUSED_WORDS (below any bar) when random words cost the
    team less than accept_drop > 0 (agents that ignore the words: no word convention)."""
    team = new_agents(spec, seed)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(team.parameters(), lr=knob(spec, "base_lr"))
    steps = spec.base_train_steps
    for step in range(steps):
        episode = play(spec, list(team.actors), knob(spec, "base_worlds"), draw_seed(gen), gen)
        opt.zero_grad(set_to_none=True)
        team_loss(spec, episode).backward()
        opt.step()
        if progress is not None and (step + 1) % max(1, steps // 20) == 0:
            progress("base", step + 1, steps, {})
    team.eval()
    mi, drop = word_figures(spec, team, gen)
    used = knob(spec, "accept_drop") == 0 or drop >= knob(spec, "accept_drop")
    return team, mi if used else UNUSED_WORDS


@torch.no_grad()
def paired(spec, base, n, gen):
    """n (observation, choices) pairs of the new agent's role: one uniform step of each of n base episodes,
    PAIRED_WORLDS episodes at a time."""
    r = role(spec)
    agent = roles(spec)[r[0]]
    obs_rows, act_rows = [], []
    for _ in range(math.ceil(n / PAIRED_WORLDS)):
        seed, steps = draw_seed(gen), torch.randint(knob(spec, "episode_len"), (PAIRED_WORLDS,), generator=gen)
        episode = play(spec, list(base.actors), PAIRED_WORLDS, seed, gen, record=r[0])
        rows = torch.arange(PAIRED_WORLDS)
        obs_rows.append(torch.stack(episode.role_obs)[steps, rows])
        act_rows.append(torch.stack(episode.role_actions)[steps, rows])
    if not obs_rows:
        return {"obs": torch.zeros(0, agent.obs), "action": torch.zeros(0, len(agent.parts), dtype=torch.long)}
    return {"obs": torch.cat(obs_rows)[:n], "action": torch.cat(act_rows)[:n]}


@torch.no_grad()
def _role_rows(spec: CellSpec, team: Team, size: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The role's observations and channel choices (exact one-hots) on every step of the team's episodes."""
    r = role(spec)
    agent = roles(spec)[r[0]]
    width = agent.parts[r[1]][1]
    T = knob(spec, "episode_len")
    obs_rows, choice_rows, count = [], [], 0
    while count < size:
        n = min(MAX_WORLDS, math.ceil((size - count) / T))
        episode = play(spec, list(team.actors), n, draw_seed(gen), gen, record=r[0])
        obs_rows.append(torch.cat(episode.role_obs))
        choice_rows.append(F.one_hot(torch.cat(episode.role_actions)[:, r[1]], width).float())  # exact one-hots
        count += n * T
    if not obs_rows:
        return torch.zeros(0, agent.obs), torch.zeros(0, width)
    return torch.cat(obs_rows)[:size], torch.cat(choice_rows)[:size]


def unpaired(spec, base, size, gen):
    """The base's choices on the new agent's channel (one-hot words or moves) on every step of base episodes."""
    return {"channel": _role_rows(spec, base, size, gen)[1]}


def self_play_step(spec, agents, state, gen):
    """One episode of batch_size worlds of the new team through the differentiable world. Its channel outputs
    are the role's choices on every step, straight-through from the role's actor on its observations taken as
    given: the adversary's gradient trains what the new agent does with what it sees, not, through the world,
    its partners or its own earlier steps (as in the PettingZoo adapter, whose observations carry none)."""
    r, part = role(spec)
    episode = play(spec, list(agents.actors), spec.batch_size, draw_seed(gen), gen, record=r)
    probs = _part_logits(spec, agents, torch.cat(episode.role_obs).detach())[part].softmax(-1)
    channel = straight_through(torch.cat(episode.role_actions)[:, part], probs)
    return SelfPlayOut(loss=team_loss(spec, episode), outputs={"channel": channel},
                       info={"reward": float(episode.returns.mean().detach()) / knob(spec, "episode_len")})


def _part_logits(spec: CellSpec, agents: Team, obs: torch.Tensor) -> list[torch.Tensor]:
    index = role(spec)[0]
    out, start = agents.agent(index)(obs), 0
    parts = []
    for _, size in roles(spec)[index].parts:
        parts.append(out[:, start:start + size])
        start += size
    return parts


def paired_loss(spec, agents, paired):
    """Cross-entropy of each of the role's choices against the base's."""
    return sum(F.cross_entropy(logits, paired["action"][:, j])
               for j, logits in enumerate(_part_logits(spec, agents, paired["obs"])))


def convention_outputs(spec, agents, n, gen):
    """n straight-through channel choices (with grad) of the new agent on its role's observations in the new
    team's own episodes."""
    obs, _ = _role_rows(spec, agents, n, gen)
    return {"channel": choose(_part_logits(spec, agents, obs)[role(spec)[1]], gen)[0]}


@torch.no_grad()
def evaluate(spec, base, agents, gen):
    """Eq. 1 with one new agent and the other compositions, on one reset seed and one action seed."""
    r, part = role(spec)
    n, seed, action_seed = spec.eval_episodes, draw_seed(gen), draw_seed(gen)

    def episode(actors, **kw) -> Episode:
        return play(spec, actors, n, seed, torch.Generator().manual_seed(action_seed), **kw)

    count = len(roles(spec))
    new_in_role = [agents.agent(i) if i == r else base.agent(i) for i in range(count)]
    base_in_role = [base.agent(i) if i == r else agents.agent(i) for i in range(count)]
    base_team = episode(list(base.actors), record=r)
    mixed = episode(new_in_role)
    random_words = episode(list(base.actors), random_words=True)
    obs = torch.cat(base_team.role_obs)
    greedy = [_part_logits(spec, team, obs)[part].argmax(-1) for team in (base, agents)]
    return {"mixed": float(mixed.returns.mean()), "mixed_swapped": float(episode(base_in_role).returns.mean()),
            "self_play_new": float(episode(list(agents.actors)).returns.mean()),
            "self_play_base": float(base_team.returns.mean()),
            "channel_match": float((greedy[0] == greedy[1]).float().mean()),
            "base_word_mi": team_mi(base_team),
            "base_word_drop": float(base_team.returns.mean() - random_words.returns.mean()),
            "mixed_word_mi": team_mi(mixed)}
