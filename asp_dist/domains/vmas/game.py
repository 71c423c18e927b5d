"""The VMAS speaker–listener's torch half: the team, episodes through the differentiable world, the base
and its acceptance, P and U, the paired loss, the convention outputs and evaluation.

An episode is `episode_len` steps of n worlds from one reset seed. Every choice is a straight-through
sample (forward: the one-hot of a draw from the softmax with the cell's generator; backward: the softmax's
gradient), so the return is differentiable in both agents' weights through the world, the heard word and the
listener. Training a team is: play an episode with gradients, loss = −(mean return per step) − entropy ·
(mean entropy per step), one Adam step. Evaluation plays every composition on the same reset seed and the
same action generator seed (common random numbers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.core.contract import SelfPlayOut
from asp_dist.domains.vmas.world import LISTENER_OBS, N_MOVES, SPEAKER_OBS, WORDS, Worlds, WorldOptions
from asp_dist.nn import seeded

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

PAIRED_WORLDS = 32  # base episodes run together while P is collected: P(n) is a prefix of P(m) for n < m
MAX_WORLDS = 1024  # worlds at most in one batch of data collection
SEED_HIGH = 2**31 - 1
SPEAKER, LISTENER = 0, 1
_WORLDS: dict[tuple[int, WorldOptions], Worlds] = {}  # built once per (n, options) per process: reset reseeds them


class SpeakerListenerTeam(nn.Module):
    """speaker: goal colour -> word logits; listener: (velocity, landmarks, heard word) -> move logits."""

    def __init__(self, hidden: int):
        super().__init__()
        self.speaker = _mlp(SPEAKER_OBS, WORDS, hidden)
        self.listener = _mlp(LISTENER_OBS, N_MOVES, hidden)

    def agent(self, index: int) -> nn.Module:
        return self.speaker if index == SPEAKER else self.listener


def _mlp(inputs: int, outputs: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                         nn.Linear(hidden, outputs))


def knob(spec: CellSpec, suffix: str):
    return getattr(spec, f"vmas_speaker_listener_{suffix}")


def options(spec: CellSpec) -> WorldOptions:
    return WorldOptions(goal_per_world=knob(spec, "goal_per_world"), force=knob(spec, "force"),
                        reward=knob(spec, "reward"), episode_len=knob(spec, "episode_len"))


def worlds(n: int, opts: WorldOptions) -> Worlds:
    key = (n, opts)
    if key not in _WORLDS:
        _WORLDS[key] = Worlds(n, opts)
    return _WORLDS[key]


def role(spec: CellSpec) -> int:
    return LISTENER if knob(spec, "new_agent") == "listener_0" else SPEAKER


def draw_seed(gen: torch.Generator) -> int:
    return int(torch.randint(SEED_HIGH, (1,), generator=gen))


def choose(logits: torch.Tensor, gen: torch.Generator, greedy: bool = False) -> tuple[torch.Tensor, torch.Tensor,
                                                                                          torch.Tensor]:
    """(straight-through one-hot, index, log-probabilities) of one choice per row."""
    logp = logits.log_softmax(-1)
    probs = logp.exp()
    index = probs.argmax(-1) if greedy else torch.multinomial(probs.detach(), 1, generator=gen).view(-1)
    return F.one_hot(index, probs.shape[-1]).to(probs.dtype) + probs - probs.detach(), index, logp


@dataclass
class Episode:
    returns: torch.Tensor  # (n,) team return per world (with grad when played with it)
    entropy: torch.Tensor  # (n,) summed over steps and both agents
    goal: torch.Tensor  # (n,)
    words: torch.Tensor  # (T, n) word indices said
    role_obs: list[torch.Tensor]  # per step, (n, obs) of the recorded role (record=...)
    role_choice: list[torch.Tensor]  # per step, (n, channel) straight-through one-hots of the recorded role


def play(spec: CellSpec, speaker: nn.Module, listener: nn.Module, n: int, seed: int, gen: torch.Generator,
         record: int | None = None, random_words: bool = False, greedy: bool = False) -> Episode:
    """One episode of n worlds from reset seed `seed`; gradients flow where the caller allows them.
    random_words: the speaker's words replaced by uniformly random ones (the intervention)."""
    world = worlds(n, options(spec))
    obs = world.reset(seed)
    goal = world.goal.clone()
    total, entropy = torch.zeros(n), torch.zeros(n)
    words, role_obs, role_choice = [], [], []
    for _ in range(knob(spec, "episode_len")):
        word_logits = torch.zeros(n, WORDS) if random_words else speaker(obs[SPEAKER])
        word, word_index, word_logp = choose(word_logits, gen, greedy and not random_words)
        move, _, move_logp = choose(listener(obs[LISTENER]), gen, greedy)
        if record is not None:
            role_obs.append(obs[record])
            role_choice.append(word if record == SPEAKER else move)
        words.append(word_index)
        entropy = entropy - (word_logp.exp() * word_logp).sum(-1) - (move_logp.exp() * move_logp).sum(-1)
        total = total + world.step(word, move)
        obs = world.obs
    return Episode(total, entropy, goal, torch.stack(words), role_obs, role_choice)


def team_loss(spec: CellSpec, episode: Episode) -> torch.Tensor:
    T = knob(spec, "episode_len")
    return -(episode.returns.mean() + knob(spec, "entropy") * episode.entropy.mean()) / T


def word_mi(goal: torch.Tensor, words: torch.Tensor) -> float:
    """Mutual information (nats) between the goal and the word said, over every step of every world."""
    joint = np.zeros((WORDS, WORDS))
    np.add.at(joint, (goal.expand_as(words).reshape(-1).numpy(), words.reshape(-1).numpy()), 1.0)
    joint /= joint.sum()
    outer = joint.sum(1, keepdims=True) @ joint.sum(0, keepdims=True)
    seen = joint > 0
    return float((joint[seen] * np.log(joint[seen] / outer[seen])).sum())


@torch.no_grad()
def word_figures(spec: CellSpec, team: SpeakerListenerTeam, gen: torch.Generator) -> tuple[float, float]:
    """(MI goal → word, return lost when every word is random) of a team, on eval_episodes worlds, the
    intervention on the same reset seed and action draws."""
    n, seed, action_seed = spec.eval_episodes, draw_seed(gen), draw_seed(gen)
    own = play(spec, team.speaker, team.listener, n, seed, torch.Generator().manual_seed(action_seed))
    rand = play(spec, team.speaker, team.listener, n, seed, torch.Generator().manual_seed(action_seed),
                random_words=True)
    return word_mi(own.goal, own.words), float(own.returns.mean() - rand.returns.mean())


# ---- the contract's functions -------------------------------------------------------------------------------
def new_agents(spec, seed):
    return seeded(seed, lambda: SpeakerListenerTeam(knob(spec, "hidden")))


def train_base(spec, seed, progress=None):
    """The team through the differentiable world for base_train_steps episodes of base_worlds worlds.
    Score: the goal → word mutual information in nats, 0 when random words cost the team less than
    vmas_speaker_listener_accept_drop (a listener that ignores the words: no word convention)."""
    team = new_agents(spec, seed)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(team.parameters(), lr=knob(spec, "base_lr"))
    steps = spec.base_train_steps
    for step in range(steps):
        episode = play(spec, team.speaker, team.listener, knob(spec, "base_worlds"), draw_seed(gen), gen)
        opt.zero_grad(set_to_none=True)
        team_loss(spec, episode).backward()
        opt.step()
        if progress is not None and (step + 1) % max(1, steps // 20) == 0:
            progress("base", step + 1, steps, {})
    team.eval()
    mi, drop = word_figures(spec, team, gen)
    return team, mi if drop >= knob(spec, "accept_drop") else 0.0


@torch.no_grad()
def paired(spec, base, n, gen):
    """n (observation, choice) pairs of the new agent's role: one uniform step of each of n base episodes,
    PAIRED_WORLDS episodes at a time."""
    r = role(spec)
    T = knob(spec, "episode_len")
    obs_rows, act_rows = [], []
    for _ in range(math.ceil(n / PAIRED_WORLDS)):
        seed, steps = draw_seed(gen), torch.randint(T, (PAIRED_WORLDS,), generator=gen)
        episode = play(spec, base.speaker, base.listener, PAIRED_WORLDS, seed, gen, record=r)
        rows = torch.arange(PAIRED_WORLDS)
        obs_rows.append(torch.stack(episode.role_obs)[steps, rows])
        act_rows.append(torch.stack(episode.role_choice)[steps, rows].argmax(-1))
    width = SPEAKER_OBS if r == SPEAKER else LISTENER_OBS
    if not obs_rows:
        return {"obs": torch.zeros(0, width), "action": torch.zeros(0, dtype=torch.long)}
    return {"obs": torch.cat(obs_rows)[:n], "action": torch.cat(act_rows)[:n]}


@torch.no_grad()
def _role_rows(spec: CellSpec, team: SpeakerListenerTeam, size: int, gen: torch.Generator, r: int):
    """The role's observations and choices (one-hot) on every step of the team's episodes, `size` rows."""
    T = knob(spec, "episode_len")
    obs_rows, choice_rows, count = [], [], 0
    while count < size:
        n = min(MAX_WORLDS, math.ceil((size - count) / T))
        episode = play(spec, team.speaker, team.listener, n, draw_seed(gen), gen, record=r)
        obs_rows.append(torch.cat(episode.role_obs))
        choice_rows.append(F.one_hot(torch.cat(episode.role_choice).argmax(-1), WORDS if r == SPEAKER else N_MOVES)
                           .float())  # exact one-hots (straight-through ones differ by rounding)
        count += n * T
    width = SPEAKER_OBS if r == SPEAKER else LISTENER_OBS
    dim = WORDS if r == SPEAKER else N_MOVES
    if not obs_rows:
        return torch.zeros(0, width), torch.zeros(0, dim)
    return torch.cat(obs_rows)[:size], torch.cat(choice_rows)[:size]


def unpaired(spec, base, size, gen):
    """The base's choices on the new agent's channel (one-hot words or moves) on every step of base episodes."""
    return {"channel": _role_rows(spec, base, size, gen, role(spec))[1]}


def self_play_step(spec, agents, state, gen):
    """One episode of batch_size worlds of the new team through the differentiable world; its channel
    outputs are the role's straight-through choices on every step."""
    r = role(spec)
    episode = play(spec, agents.speaker, agents.listener, spec.batch_size, draw_seed(gen), gen, record=r)
    return SelfPlayOut(loss=team_loss(spec, episode), outputs={"channel": torch.cat(episode.role_choice)},
                       info={"reward": float(episode.returns.mean().detach()) / knob(spec, "episode_len")})


def paired_loss(spec, agents, paired):
    return F.cross_entropy(agents.agent(role(spec))(paired["obs"]), paired["action"])


def convention_outputs(spec, agents, n, gen):
    """n straight-through channel choices (with grad) of the new agent on its role's observations in the new
    team's own episodes."""
    r = role(spec)
    obs, _ = _role_rows(spec, agents, n, gen, r)
    return {"channel": choose(agents.agent(r)(obs), gen)[0]}


@torch.no_grad()
def evaluate(spec, base, agents, gen):
    """Eq. 1 with one new agent and the other compositions, on one reset seed and one action seed."""
    r = role(spec)
    n, seed, action_seed = spec.eval_episodes, draw_seed(gen), draw_seed(gen)

    def mean_return(speaker, listener, **kw) -> Episode:
        return play(spec, speaker, listener, n, seed, torch.Generator().manual_seed(action_seed), **kw)

    new_in_role = (agents.speaker, base.listener) if r == SPEAKER else (base.speaker, agents.listener)
    base_in_role = (base.speaker, agents.listener) if r == SPEAKER else (agents.speaker, base.listener)
    base_team = mean_return(base.speaker, base.listener, record=r)
    mixed = mean_return(*new_in_role)
    random_words = mean_return(base.speaker, base.listener, random_words=True)
    obs = torch.cat(base_team.role_obs)
    greedy = [team.agent(r)(obs).argmax(-1) for team in (base, agents)]
    return {"mixed": float(mixed.returns.mean()), "mixed_swapped": float(mean_return(*base_in_role).returns.mean()),
            "self_play_new": float(mean_return(agents.speaker, agents.listener).returns.mean()),
            "self_play_base": float(base_team.returns.mean()),
            "channel_match": float((greedy[0] == greedy[1]).float().mean()),
            "base_word_mi": word_mi(base_team.goal, base_team.words),
            "base_word_drop": float(base_team.returns.mean() - random_words.returns.mean()),
            "mixed_word_mi": word_mi(mixed.goal, mixed.words)}
