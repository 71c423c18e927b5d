"""The signaling game's torch half: the speaker and listener tables, the base convention, self-play,
the paired loss and evaluation. The card (asp_dist.domains.signaling: knobs, metrics, validation)
calls these functions, one per Domain method, and imports this module on first use.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.core.contract import SelfPlayOut
from asp_dist.nn import seeded

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

POOL = 4096  # paired states are the first n of a fixed pool, so P(n) is a prefix of P(n+1)


def class_sizes(states: int, tokens: int, skew: float) -> list[int]:
    """States per class for p_k ∝ exp(-skew·k), by largest remainder, at least one state each."""
    weights = [math.exp(-skew * k) for k in range(tokens)]
    total = sum(weights)
    spare = states - tokens
    raw = [spare * w / total for w in weights]
    sizes = [1 + int(r) for r in raw]
    order = sorted(range(tokens), key=lambda k: (-(raw[k] - int(raw[k])), k))
    for k in order[: states - sum(sizes)]:
        sizes[k] += 1
    return sizes


def state_classes(spec: CellSpec) -> torch.Tensor:
    sizes = class_sizes(spec.signaling_states, spec.signaling_tokens, spec.signaling_skew)
    return torch.repeat_interleave(torch.arange(len(sizes)), torch.tensor(sizes))


class SignalingAgents(nn.Module):
    """Speaker: state -> token logits (a table); listener: token -> class logits (a table)."""

    def __init__(self, states: int, tokens: int):
        super().__init__()
        self.speaker = nn.Parameter(torch.randn(states, tokens) * 0.1)
        self.listener = nn.Parameter(torch.randn(tokens, tokens) * 0.1)

    def speak_hard(self, states: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        """Gumbel-softmax straight-through: one-hot tokens forward, soft gradients backward."""
        logits = self.speaker[states]
        u = torch.rand(logits.shape, generator=gen).clamp_(1e-9, 1 - 1e-9)
        soft = F.softmax(logits - torch.log(-torch.log(u)), dim=-1)
        hard = F.one_hot(soft.argmax(-1), soft.shape[-1]).to(soft.dtype)
        return hard + soft - soft.detach()

    def greedy_tokens(self) -> torch.Tensor:
        return self.speaker.argmax(-1)

    def greedy_actions(self) -> torch.Tensor:
        return self.listener.argmax(-1)


def train_base(spec, seed, progress=None):
    """The base is a convention drawn at random: a permutation of tokens over classes."""
    gen = torch.Generator().manual_seed(seed)
    perm = torch.randperm(spec.signaling_tokens, generator=gen)
    agents = SignalingAgents(spec.signaling_states, spec.signaling_tokens)
    with torch.no_grad():
        classes = state_classes(spec)
        agents.speaker.copy_(F.one_hot(perm[classes], spec.signaling_tokens).float() * 10)
        agents.listener.copy_(F.one_hot(torch.argsort(perm), spec.signaling_tokens).float() * 10)
    return agents, accuracy(agents.greedy_tokens(), agents.greedy_actions(), spec)


def paired(spec, base, n, gen):
    states = torch.randint(spec.signaling_states, (max(n, POOL),), generator=gen)[:n]
    tokens = base.greedy_tokens()[states]
    return {"state": states, "token": tokens, "action": base.greedy_actions()[tokens]}


def unpaired(spec, base, size, gen):
    states = torch.randint(spec.signaling_states, (size,), generator=gen)
    return {"token": F.one_hot(base.greedy_tokens()[states], spec.signaling_tokens).float()}


def new_agents(spec, seed):
    return seeded(seed, lambda: SignalingAgents(spec.signaling_states, spec.signaling_tokens))


def self_play_step(spec, agents, state, gen):
    states = torch.randint(spec.signaling_states, (spec.batch_size,), generator=gen)
    tokens = agents.speak_hard(states, gen)
    probs = F.softmax(tokens @ agents.listener, dim=-1)
    reward = probs.gather(1, state_classes(spec)[states][:, None]).squeeze(1)
    return SelfPlayOut(loss=-reward.mean(), outputs={"token": tokens}, info={"reward": float(reward.detach().mean())})


def paired_loss(spec, agents, paired):
    return (F.cross_entropy(agents.speaker[paired["state"]], paired["token"])
            + F.cross_entropy(agents.listener[paired["token"]], paired["action"]))


def convention_outputs(spec, agents, n, gen):
    states = torch.randint(spec.signaling_states, (n,), generator=gen)
    return {"token": agents.speak_hard(states, gen)}


def evaluate(spec, base, agents, gen):
    acc = lambda s, l: accuracy(s.greedy_tokens(), l.greedy_actions(), spec)  # noqa: E731
    a, b = acc(base, agents), acc(agents, base)
    match = float((agents.greedy_tokens() == base.greedy_tokens()).float().mean())
    return {"mixed": (a + b) / 2, "mixed_base_speaker": a, "mixed_new_speaker": b,
            "self_play_new": acc(agents, agents), "self_play_base": acc(base, base), "convention_match": match}


def accuracy(tokens: torch.Tensor, actions: torch.Tensor, spec: CellSpec) -> float:
    return float((actions[tokens] == state_classes(spec)).float().mean())
