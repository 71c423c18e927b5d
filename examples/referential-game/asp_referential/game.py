"""The referential game's torch half: objects, the speaker and listener networks, the base code,
self-play, the paired loss, the convention outputs and evaluation. The card (asp_referential:
knobs, metrics, validation) calls these functions, one per Domain method, and imports this module
the first time a cell needs it.

Objects are the V^A tuples of A attributes with V values, numbered in mixed radix (object i has
attribute a = (i // V^a) % V) and shown to the networks as A concatenated one-hots (width A·V).
A message is L symbols of a vocabulary of K, a (L, K) one-hot, flattened to width L·K for the
listener and the adversary. Symbols are sampled with Gumbel-softmax straight-through: the forward
pass is the hard one-hot of argmax(logits + Gumbel noise), the backward pass the gradient of the
softmax at temperature referential_tau, so the listener's cross-entropy trains the speaker end to
end. Every random choice (Gumbel noise, objects, distractors, the target's slot) is drawn from the
torch.Generator passed in.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.core.contract import SelfPlayOut
from asp_dist.nn import seeded
from asp_referential import POOL

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

BASE_SCORE_GAMES = 4096  # games of the base's acceptance score (drawn from the base's own seed)


# ---- objects and games ----------------------------------------------------------------------------
def n_objects(spec: CellSpec) -> int:
    return spec.referential_values ** spec.referential_attributes


def object_features(spec: CellSpec, objects: torch.Tensor) -> torch.Tensor:
    """(..., A·V) concatenated one-hots of the objects' attribute values."""
    A, V = spec.referential_attributes, spec.referential_values
    radix = V ** torch.arange(A)
    values = (objects[..., None] // radix) % V  # (..., A)
    return F.one_hot(values, V).flatten(-2).float()


def sample_objects(spec: CellSpec, n: int, gen: torch.Generator) -> torch.Tensor:
    return torch.randint(n_objects(spec), (n,), generator=gen)


def sample_games(spec: CellSpec, n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """n games: (targets (n,), candidates (n, C) object ids, slot (n,) of the target among them).

    The C-1 distractors are distinct and uniform among the objects other than the target (the
    smallest C-1 of uniform keys, the target's key set to 2), and the target sits in a uniform slot."""
    N, C = n_objects(spec), spec.referential_candidates
    targets = sample_objects(spec, n, gen)
    keys = torch.rand((n, N), generator=gen)
    keys[torch.arange(n), targets] = 2.0
    distractors = keys.topk(C - 1, dim=1, largest=False).indices  # (n, C-1)
    slot = torch.randint(C, (n,), generator=gen)
    candidates = torch.empty((n, C), dtype=torch.long)
    others = torch.ones((n, C), dtype=torch.bool)
    others[torch.arange(n), slot] = False
    candidates[others] = distractors.flatten()
    candidates[torch.arange(n), slot] = targets
    return targets, candidates, slot


# ---- the agents -----------------------------------------------------------------------------------
class ReferentialAgents(nn.Module):
    """Speaker: object features -> L×K symbol logits (an MLP with one hidden layer). Listener: the
    flattened message -> an embedding (an MLP), scored by dot product against each candidate's
    embedding (a linear map of its features); it picks the candidate with the highest score."""

    def __init__(self, spec: CellSpec):
        super().__init__()
        A, V, L, K, H = (spec.referential_attributes, spec.referential_values, spec.referential_msg_len,
                         spec.referential_vocab, spec.referential_hidden)
        self.L, self.K, self.tau = L, K, spec.referential_tau
        self.speaker = nn.Sequential(nn.Linear(A * V, H), nn.ReLU(), nn.Linear(H, L * K))
        self.listener_msg = nn.Sequential(nn.Linear(L * K, H), nn.ReLU(), nn.Linear(H, H))
        self.listener_obj = nn.Linear(A * V, H)

    def logits(self, features: torch.Tensor) -> torch.Tensor:
        return self.speaker(features).view(*features.shape[:-1], self.L, self.K)

    def speak(self, features: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        """Gumbel-softmax straight-through: (n, L·K) hard one-hot symbols forward, soft gradients back."""
        logits = self.logits(features)
        u = torch.rand(logits.shape, generator=gen).clamp_(1e-9, 1 - 1e-9)
        soft = F.softmax((logits - torch.log(-torch.log(u))) / self.tau, dim=-1)
        hard = F.one_hot(soft.argmax(-1), self.K).to(soft.dtype)
        return (hard + soft - soft.detach()).flatten(-2)

    def greedy_symbols(self, features: torch.Tensor) -> torch.Tensor:
        """(n, L) the argmax symbols: the speaker's code, as evaluated."""
        return self.logits(features).argmax(-1)

    def one_hot(self, symbols: torch.Tensor) -> torch.Tensor:
        return F.one_hot(symbols, self.K).float().flatten(-2)

    def scores(self, message: torch.Tensor, candidate_features: torch.Tensor) -> torch.Tensor:
        """(n, C) the listener's logits over the candidates given (n, L·K) messages."""
        query = self.listener_msg(message)  # (n, H)
        keys = self.listener_obj(candidate_features)  # (n, C, H)
        return (keys @ query[:, :, None]).squeeze(-1)


# ---- the base convention --------------------------------------------------------------------------
def game_loss(spec: CellSpec, agents: ReferentialAgents, gen: torch.Generator, batch: int):
    """One batch of self-play games: the listener's cross-entropy on the target's slot (through the
    straight-through message into the speaker), the messages, and the batch's accuracy."""
    targets, candidates, slot = sample_games(spec, batch, gen)
    message = agents.speak(object_features(spec, targets), gen)
    scores = agents.scores(message, object_features(spec, candidates))
    loss = F.cross_entropy(scores, slot)
    return loss, message, float((scores.detach().argmax(-1) == slot).float().mean())


def train_base(spec, seed, progress=None):
    """The base pair in self-play from `seed`; its score is the greedy accuracy of the pair on
    BASE_SCORE_GAMES fresh games (compared with referential_accept_accuracy)."""
    gen = torch.Generator().manual_seed(seed)
    agents = seeded(seed, lambda: ReferentialAgents(spec))
    opt = torch.optim.Adam(agents.parameters(), lr=spec.referential_base_lr)
    steps = spec.base_train_steps
    for step in range(steps):
        loss, _, acc = game_loss(spec, agents, gen, spec.referential_base_batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if progress is not None and (step + 1) % max(1, steps // 20) == 0:
            progress("base", step + 1, steps, {"accuracy": acc})
    agents.eval()
    with torch.no_grad():
        score = accuracy(spec, agents, agents, *sample_games(spec, BASE_SCORE_GAMES, gen))
    return agents, score


def paired(spec, base, n, gen):
    """P: the first n of a pool of POOL games: the target object, the base speaker's greedy message
    (L symbols), the game's candidates and the base listener's choice on that message."""
    targets, candidates, _ = sample_games(spec, max(n, POOL), gen)
    targets, candidates = targets[:n], candidates[:n]
    with torch.no_grad():
        symbols = base.greedy_symbols(object_features(spec, targets))
        choice = base.scores(base.one_hot(symbols), object_features(spec, candidates)).argmax(-1)
    return {"object": targets, "message": symbols, "candidates": candidates, "choice": choice}


def unpaired(spec, base, size, gen):
    """U: the base speaker's greedy messages on `size` uniform objects, one-hot flattened (size, L·K)."""
    with torch.no_grad():
        symbols = base.greedy_symbols(object_features(spec, sample_objects(spec, size, gen)))
    return {"message": base.one_hot(symbols)}


# ---- the new agents -------------------------------------------------------------------------------
def new_agents(spec, seed):
    return seeded(seed, lambda: ReferentialAgents(spec))


def self_play_step(spec, agents, state, gen):
    loss, message, acc = game_loss(spec, agents, gen, spec.batch_size)
    return SelfPlayOut(loss=loss, outputs={"message": message}, info={"accuracy": acc})


def paired_loss(spec, agents, paired):
    """Speaker: cross-entropy of each symbol against the base's; listener: cross-entropy of its
    scores on the base's message against the base listener's choice."""
    logits = agents.logits(object_features(spec, paired["object"]))  # (n, L, K)
    speaker = F.cross_entropy(logits.flatten(0, 1), paired["message"].flatten())
    scores = agents.scores(agents.one_hot(paired["message"]), object_features(spec, paired["candidates"]))
    return speaker + F.cross_entropy(scores, paired["choice"])


def convention_outputs(spec, agents, n, gen):
    return {"message": agents.speak(object_features(spec, sample_objects(spec, n, gen)), gen)}


# ---- evaluation -----------------------------------------------------------------------------------
def accuracy(spec, speaker, listener, targets, candidates, slot) -> float:
    """Greedy accuracy of `speaker`'s messages read by `listener` on the given games."""
    message = speaker.one_hot(speaker.greedy_symbols(object_features(spec, targets)))
    picks = listener.scores(message, object_features(spec, candidates)).argmax(-1)
    return float((picks == slot).float().mean())


def evaluate(spec, base, agents, gen):
    """Every composition on the same eval_episodes games (common random numbers), and the fraction
    of all V^A objects on which the new speaker's greedy message equals the base's."""
    games = sample_games(spec, spec.eval_episodes, gen)
    a, b = accuracy(spec, base, agents, *games), accuracy(spec, agents, base, *games)
    everything = object_features(spec, torch.arange(n_objects(spec)))
    match = (agents.greedy_symbols(everything) == base.greedy_symbols(everything)).all(-1)
    return {"mixed": (a + b) / 2, "mixed_base_speaker": a, "mixed_new_speaker": b,
            "self_play_new": accuracy(spec, agents, agents, *games),
            "self_play_base": accuracy(spec, base, base, *games),
            "message_match": float(match.float().mean())}
