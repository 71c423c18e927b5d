"""The lever game's torch half: the game itself, the CommNet, deep Q-learning, P and U, and evaluation.
The card (asp_dist.domains.levers: the game's description, knobs, metrics, validation) calls the
functions from "base" on, one per Domain method, and imports this module on first use.
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.core.contract import ProgressFn, SelfPlayOut, Tensors
from asp_dist.domains.levers import AGENTS, POOL
from asp_dist.nn import seeded

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

FIGURE_GAMES = 50  # games whose last-block vectors go into the PCA figure
FIGURE_SEED = 20240601  # fixed, so every cell's figure shows the same games


# ---- the game ------------------------------------------------------------------------------------
def draw_games(num_ids: int, n: int, gen: torch.Generator) -> torch.Tensor:
    """n games of AGENTS distinct IDs each, (n, AGENTS) long; seat order is random."""
    return torch.rand(n, num_ids, generator=gen).argsort(dim=1)[:, :AGENTS]


def all_games(num_ids: int) -> torch.Tensor:
    """Every ordered triple of distinct IDs (720 for 10 IDs): exhaustive, exact evaluation."""
    return torch.tensor(list(itertools.permutations(range(num_ids), AGENTS)), dtype=torch.long)


def team_reward(ids: torch.Tensor, levers: torch.Tensor) -> torch.Tensor:
    """Fraction of levers i pulled by the agent with the i-th smallest ID, per game: (n,)."""
    rank = ids.argsort(dim=1).argsort(dim=1)
    return (levers == rank).float().mean(dim=1)


# ---- the network ---------------------------------------------------------------------------------
class CommNet(nn.Module):
    def __init__(self, num_ids: int, hidden: int, levers: int = AGENTS):
        super().__init__()
        self.embed = nn.Embedding(num_ids, hidden)
        self.f1 = nn.Linear(hidden, hidden)
        self.f2 = nn.Linear(2 * hidden, hidden)  # acts on [h1, c1]
        self.q = nn.Linear(hidden, levers)

    def block1(self, ids: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.f1(self.embed(ids)))

    def block2(self, h1: torch.Tensor, c1: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.f2(torch.cat([h1, c1], dim=-1)))

    def forward(self, ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Self-play team of this network: (h1, h2, q), each (games, AGENTS, ·)."""
        h1 = self.block1(ids)
        h2 = self.block2(h1, communicate(h1))
        return h1, h2, self.q(h2)


def communicate(h: torch.Tensor) -> torch.Tensor:
    """Each seat hears the mean of the other seats' vectors (CommNet's c)."""
    return (h.sum(dim=1, keepdim=True) - h) / (h.shape[1] - 1)


def team_forward(nets: list[CommNet], seat_net: torch.Tensor, ids: torch.Tensor):
    """A team whose seat s of game g is played by nets[seat_net[g, s]]: (h1, h2, q)."""
    def pick(per_net: list[torch.Tensor]) -> torch.Tensor:
        stacked = torch.stack(per_net)  # (nets, games, seats, ·)
        index = seat_net[None, :, :, None].expand(1, -1, -1, stacked.shape[-1])
        return stacked.gather(0, index).squeeze(0)

    h1 = pick([net.block1(ids) for net in nets])
    c1 = communicate(h1)
    h2 = pick([net.block2(h1, c1) for net in nets])
    q = pick([net.q(h2) for net in nets])
    return h1, h2, q


def seat_arrangements(new_agents: int) -> torch.Tensor:
    """Every way to seat `new_agents` new agents (1) among base agents (0): (arrangements, AGENTS)."""
    rows = [[1 if s in seats else 0 for s in range(AGENTS)]
            for seats in itertools.combinations(range(AGENTS), new_agents)]
    return torch.tensor(rows, dtype=torch.long)


# ---- deep Q-learning -----------------------------------------------------------------------------
def epsilon(spec: CellSpec, step: int, total: int) -> float:
    """Linear decay from eps_start to eps_end over the first eps_decay_frac of training."""
    span = max(1.0, spec.levers_eps_decay_frac * total)
    frac = min(1.0, step / span)
    return spec.levers_eps_start + frac * (spec.levers_eps_end - spec.levers_eps_start)


def init_replay(spec: CellSpec) -> Tensors:
    size = spec.levers_replay_size
    return {"ids": torch.zeros(size, AGENTS, dtype=torch.long), "levers": torch.zeros(size, AGENTS, dtype=torch.long),
            "reward": torch.zeros(size), "filled": torch.zeros((), dtype=torch.long),
            "pos": torch.zeros((), dtype=torch.long), "step": torch.zeros((), dtype=torch.long)}


def dqn_step(spec: CellSpec, net: CommNet, state: Tensors, gen: torch.Generator, total_steps: int) -> SelfPlayOut:
    """One deep-Q update: play batch_size fresh ε-greedy games and regress the team's chosen
    Q-value on the reward, over the fresh games plus batch_size games replayed from the buffer.
    One forward pass serves acting (detached) and learning, which halves the per-update cost."""
    batch, size = spec.batch_size, spec.levers_replay_size
    eps = epsilon(spec, int(state["step"]), total_steps)
    fresh = draw_games(spec.levers_num_ids, batch, gen)
    filled = int(state["filled"])
    replayed = torch.randint(filled, (batch,), generator=gen) if filled > 0 else None
    ids = fresh if replayed is None else torch.cat([fresh, state["ids"][replayed]])
    h1, h2, q = net(ids)

    greedy = q[:batch].detach().argmax(dim=-1)
    random_levers = torch.randint(AGENTS, greedy.shape, generator=gen)
    explore = torch.rand(greedy.shape, generator=gen) < eps
    levers = torch.where(explore, random_levers, greedy)
    reward = team_reward(fresh, levers)
    all_levers, all_reward = levers, reward
    if replayed is not None:
        all_levers = torch.cat([levers, state["levers"][replayed]])
        all_reward = torch.cat([reward, state["reward"][replayed]])
    chosen = q.gather(2, all_levers.unsqueeze(-1)).squeeze(-1)  # (games, AGENTS)
    loss = F.mse_loss(chosen.mean(dim=1), all_reward)

    slots = (state["pos"] + torch.arange(batch)) % size
    state["ids"][slots], state["levers"][slots], state["reward"][slots] = fresh, levers, reward
    state["pos"].copy_((state["pos"] + batch) % size)
    state["filled"].copy_(torch.clamp(state["filled"] + batch, max=size))
    state["step"].add_(1)
    hidden = h1.shape[-1]
    return SelfPlayOut(loss=loss, outputs={"f1": h1.reshape(-1, hidden), "f2": h2.reshape(-1, hidden)},
                       info={"reward": float(reward.mean()), "epsilon": eps})


def greedy_reward(nets: list[CommNet], seat_net: torch.Tensor, ids: torch.Tensor) -> float:
    """Mean greedy team reward of games `ids` under each seat arrangement in `seat_net` (A, AGENTS)."""
    games = ids.repeat(len(seat_net), 1)
    seats = seat_net.repeat_interleave(len(ids), dim=0)
    levers = team_forward(nets, seats, games)[2].argmax(dim=-1)
    return float(team_reward(games, levers).mean())


# ---- base -------------------------------------------------------------------------------------
def train_base(spec: CellSpec, seed: int, progress: ProgressFn | None = None) -> tuple[nn.Module, float]:
    net = new_agents(spec, seed)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(net.parameters(), lr=spec.levers_base_lr)
    state = init_replay(spec)
    total = spec.base_train_steps
    for step in range(total):
        loss = dqn_step(spec, net, state, gen, total).loss
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if progress is not None and (step + 1) % max(1, total // 20) == 0:
            progress("base", step + 1, total, {})
    net.eval()
    with torch.no_grad():
        score = self_play_reward(spec, net, torch.Generator().manual_seed(seed))
    return net, score


def eval_games(spec: CellSpec, gen: torch.Generator) -> torch.Tensor:
    games = all_games(spec.levers_num_ids)
    if spec.eval_episodes >= len(games):
        return games
    return games[torch.randperm(len(games), generator=gen)[: spec.eval_episodes]]


def self_play_reward(spec: CellSpec, net: CommNet, gen: torch.Generator) -> float:
    return greedy_reward([net], torch.zeros(1, AGENTS, dtype=torch.long), eval_games(spec, gen))


# ---- data -------------------------------------------------------------------------------------
@torch.no_grad()
def paired(spec: CellSpec, base: nn.Module, n: int, gen: torch.Generator) -> Tensors:
    ids = draw_games(spec.levers_num_ids, max(n, POOL), gen)[:n]
    h1, h2, q = base(ids)
    return {"ids": ids, "f1": h1, "f2": h2, "levers": q.argmax(dim=-1)}


@torch.no_grad()
def unpaired(spec: CellSpec, base: nn.Module, size: int, gen: torch.Generator) -> Tensors:
    games = -(-size // AGENTS)
    h1, h2, _ = base(draw_games(spec.levers_num_ids, games, gen))
    hidden = spec.levers_hidden
    return {"f1": h1.reshape(-1, hidden)[:size].clone(), "f2": h2.reshape(-1, hidden)[:size].clone()}


# ---- new agents -------------------------------------------------------------------------------
def new_agents(spec: CellSpec, seed: int) -> nn.Module:
    return seeded(seed, lambda: CommNet(spec.levers_num_ids, spec.levers_hidden))


def init_self_play(spec: CellSpec, agents: nn.Module, gen: torch.Generator) -> Tensors:
    return init_replay(spec)


def self_play_step(spec: CellSpec, agents: nn.Module, state: Tensors, gen: torch.Generator) -> SelfPlayOut:
    return dqn_step(spec, agents, state, gen, spec.train_steps)


def paired_loss(spec: CellSpec, agents: nn.Module, paired: Tensors) -> torch.Tensor:
    """MSE on both f-block outputs for the paired games' IDs, cross-entropy (Q as logits) on the levers."""
    h1, h2, q = agents(paired["ids"])
    return (F.mse_loss(h1, paired["f1"]) + F.mse_loss(h2, paired["f2"])
            + F.cross_entropy(q.reshape(-1, q.shape[-1]), paired["levers"].reshape(-1)))


def convention_outputs(spec: CellSpec, agents: nn.Module, n: int, gen: torch.Generator) -> Tensors:
    h1, h2, _ = agents(draw_games(spec.levers_num_ids, -(-n // AGENTS), gen))
    hidden = spec.levers_hidden
    return {"f1": h1.reshape(-1, hidden)[:n], "f2": h2.reshape(-1, hidden)[:n]}


# ---- evaluation -------------------------------------------------------------------------------
@torch.no_grad()
def evaluate(spec: CellSpec, base: nn.Module, agents: nn.Module, gen: torch.Generator) -> dict[str, float]:
    ids = eval_games(spec, gen)
    nets = [base, agents]  # seat value 0 = base, 1 = new
    r1 = greedy_reward(nets, seat_arrangements(1), ids)
    r2 = greedy_reward(nets, seat_arrangements(2), ids)
    sp_new = greedy_reward(nets, torch.ones(1, AGENTS, dtype=torch.long), ids)
    sp_base = greedy_reward(nets, torch.zeros(1, AGENTS, dtype=torch.long), ids)
    match = float((agents(ids)[2].argmax(-1) == base(ids)[2].argmax(-1)).float().mean())
    mixed_reward = (r1 + r2) / 2
    return {"mixed": 1.0 - mixed_reward, "mixed_reward": mixed_reward,
            "reward_1new_2base": r1, "reward_2new_1base": r2,
            "self_play_new": 1.0 - sp_new, "self_play_base": 1.0 - sp_base, "lever_match": match}


@torch.no_grad()
def figure_data(spec: CellSpec, base: nn.Module, agents: nn.Module):
    """Last f-block vectors (h2) of a fixed set of games, for the PCA figure coloured by agent ID."""
    ids = draw_games(spec.levers_num_ids, FIGURE_GAMES, torch.Generator().manual_seed(FIGURE_SEED))
    hidden = spec.levers_hidden

    def vectors(net: nn.Module) -> list[list[float]]:
        return [[round(x, 4) for x in row] for row in net(ids)[1].reshape(-1, hidden).tolist()]

    return {"kind": "comm", "base": vectors(base), "new": vectors(agents), "ids": ids.reshape(-1).tolist()}
