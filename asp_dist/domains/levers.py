"""The CommNet lever game (the paper's third domain), trained by ε-greedy deep Q-learning.

Game: three agents receive three distinct IDs from 0..num_ids-1 and each pulls one of three
levers at once. The team reward is the fraction of levers i pulled by the agent holding the
i-th smallest ID, which equals the fraction of agents that pull the lever of their own rank
(IDs 8, 3, 5 pulling 0, 1, 1 score 1/3: only ID 5, rank 1, is right).

Network (CommNet, Sukhbaatar, Szlam & Fergus 2016), weights shared by the agents of one network:

    h0 = embed(id)                      ID embedding
    h1 = tanh(W1 h0)                    f-block layer 1          -> channel "f1"
    c1 = mean of the OTHER agents' h1   communication
    h2 = tanh(W2 h1 + C2 c1)            f-block layer 2          -> channel "f2"
    q  = Wq h2                          Q-value of each lever

A team is a per-seat choice of network. `team_forward` runs every block of every network on
every seat and selects each seat's own result, so mixed teams stay one vectorised pass; the
communication mixes whatever the seated agents emitted. A team of one network takes exactly
the same arithmetic as its self-play forward (selection copies values), which the tests check.

Training: the game has one step, so the Q target is the reward itself. The team's value is
the mean of the agents' chosen Q-values (the reward is exactly a mean of per-agent terms), and
it is regressed on the team reward over games drawn from a replay buffer that lives in the
self-play state tensors, so it checkpoints with the cell.
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from asp_dist.domains.contract import Domain, MetricInfo, PaperFacts, ProgressFn, SelfPlayOut, Tensors, require
from asp_dist.nn import seeded

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

AGENTS = 3  # agents per game, and levers (paper: 3)
POOL = 1024  # paired games are the first n of a fixed pool, so P(n) is a prefix of P(n+1)
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


# ---- the domain ----------------------------------------------------------------------------------
class LeversDomain(Domain):
    name = "levers"
    channels = ("f1", "f2")
    accept_field = "levers_accept_reward"
    paper = PaperFacts(
        metric_label="mixed-team error, 1 − reward (fraction of levers)",
        claim="ASP better than OSP (p < 0.05) and PC (p < 0.01) over 4–8 paired (Friedman)",
        test_paired=(4, 8),
        threshold=(1 - 0.683, "error of the best policy without communication (1 - 0.683)"),
    )
    defaults = dict(
        levers_hidden=32, levers_num_ids=10,
        levers_eps_start=1.0, levers_eps_end=0.05, levers_eps_decay_frac=0.5,
        levers_replay_size=4096, levers_base_lr=3e-3, levers_accept_reward=0.95,
        lambda_paired=1.0, lambda_unpaired=0.1, unpaired_size=4096,
        train_steps=1000, batch_size=128, lr=3e-3,
        disc_hidden=32, disc_layers=1, disc_lr=1e-3,
        base_train_steps=1000, eval_episodes=720,
    )
    metrics = {
        "mixed": MetricInfo(False, "Eq. 1 error: 1 - mean reward of the 1-new+2-base and 2-new+1-base teams"),
        "mixed_reward": MetricInfo(True, "Eq. 1 reward: 1 - mixed"),
        "reward_1new_2base": MetricInfo(True, "reward of 1 new + 2 base agents, averaged over the 3 seatings"),
        "reward_2new_1base": MetricInfo(True, "reward of 2 new + 1 base agents, averaged over the 3 seatings"),
        "self_play_new": MetricInfo(False, "error (1 - reward) of a team of three new agents"),
        "self_play_base": MetricInfo(False, "error (1 - reward) of a team of three base agents"),
        "lever_match": MetricInfo(True, "fraction of (game, seat) where the new team pulls the base team's lever"),
    }

    def validate(self, spec: CellSpec) -> None:
        require(spec.levers_num_ids >= AGENTS, f"levers_num_ids must be >= {AGENTS}, got {spec.levers_num_ids}")
        require(spec.levers_hidden >= 1, "levers_hidden must be >= 1")
        require(spec.levers_replay_size >= spec.batch_size,
                f"levers_replay_size ({spec.levers_replay_size}) must be >= batch_size ({spec.batch_size})")
        for name in ("levers_eps_start", "levers_eps_end", "levers_eps_decay_frac"):
            require(0.0 <= getattr(spec, name) <= 1.0, f"{name} must be in [0, 1], got {getattr(spec, name)}")
        require(spec.levers_base_lr > 0, "levers_base_lr must be > 0")

    # [the paper's values in brackets] evaluation lists every game, num_ids³ of them (970200 at 100), in Python;
    # the CommNet's weights are hidden × 2·hidden; the replay buffer holds 7 numbers per game.
    upper_bounds = {"levers_num_ids": 100, "levers_hidden": 16_384, "levers_replay_size": 10_000_000}  # [10, 32, 4096]

    def tensor_sizes(self, spec: CellSpec) -> dict[str, int]:
        h, ids = spec.levers_hidden, spec.levers_num_ids
        games = {"batch_size": 2 * spec.batch_size, "paired": max(spec.paired, POOL),
                 "unpaired_size": -(-spec.unpaired_size // AGENTS),
                 "unpaired_batch": -(-spec.unpaired_batch // AGENTS),
                 # the mixed teams: 3 seatings of the eval games, both networks run on every seat
                 "eval_episodes": 6 * min(spec.eval_episodes, ids * (ids - 1) * (ids - 2))}
        width = max(ids, 2 * h)  # drawing games (rand over the IDs) or [h1, c1]
        return {"levers_hidden × 2·levers_hidden": 2 * h * h,
                **{f"{knob} games × {AGENTS} seats × width {width}": n * AGENTS * width for knob, n in games.items()}}

    def channel_dims(self, spec: CellSpec) -> dict[str, int]:
        return {"f1": spec.levers_hidden, "f2": spec.levers_hidden}

    def _net(self, spec: CellSpec, seed: int) -> CommNet:
        return seeded(seed, lambda: CommNet(spec.levers_num_ids, spec.levers_hidden))

    # ---- base -------------------------------------------------------------------------------------
    def train_base(self, spec: CellSpec, seed: int, progress: ProgressFn | None = None) -> tuple[nn.Module, float]:
        net = self._net(spec, seed)
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
            score = self._self_play_reward(spec, net, torch.Generator().manual_seed(seed))
        return net, score

    def _eval_games(self, spec: CellSpec, gen: torch.Generator) -> torch.Tensor:
        games = all_games(spec.levers_num_ids)
        if spec.eval_episodes >= len(games):
            return games
        return games[torch.randperm(len(games), generator=gen)[: spec.eval_episodes]]

    def _self_play_reward(self, spec: CellSpec, net: CommNet, gen: torch.Generator) -> float:
        return greedy_reward([net], torch.zeros(1, AGENTS, dtype=torch.long), self._eval_games(spec, gen))

    # ---- data -------------------------------------------------------------------------------------
    @torch.no_grad()
    def paired(self, spec: CellSpec, base: nn.Module, n: int, gen: torch.Generator) -> Tensors:
        ids = draw_games(spec.levers_num_ids, max(n, POOL), gen)[:n]
        h1, h2, q = base(ids)
        return {"ids": ids, "f1": h1, "f2": h2, "levers": q.argmax(dim=-1)}

    @torch.no_grad()
    def unpaired(self, spec: CellSpec, base: nn.Module, size: int, gen: torch.Generator) -> Tensors:
        games = -(-size // AGENTS)
        h1, h2, _ = base(draw_games(spec.levers_num_ids, games, gen))
        hidden = spec.levers_hidden
        return {"f1": h1.reshape(-1, hidden)[:size].clone(), "f2": h2.reshape(-1, hidden)[:size].clone()}

    # ---- new agents -------------------------------------------------------------------------------
    def new_agents(self, spec: CellSpec, seed: int) -> nn.Module:
        return self._net(spec, seed)

    def init_self_play(self, spec: CellSpec, agents: nn.Module, gen: torch.Generator) -> Tensors:
        return init_replay(spec)

    def self_play_step(self, spec: CellSpec, agents: nn.Module, state: Tensors, gen: torch.Generator) -> SelfPlayOut:
        return dqn_step(spec, agents, state, gen, spec.train_steps)

    def paired_loss(self, spec: CellSpec, agents: nn.Module, paired: Tensors) -> torch.Tensor:
        """MSE on both f-block outputs for the paired games' IDs, cross-entropy (Q as logits) on the levers."""
        h1, h2, q = agents(paired["ids"])
        return (F.mse_loss(h1, paired["f1"]) + F.mse_loss(h2, paired["f2"])
                + F.cross_entropy(q.reshape(-1, q.shape[-1]), paired["levers"].reshape(-1)))

    def convention_outputs(self, spec: CellSpec, agents: nn.Module, n: int, gen: torch.Generator) -> Tensors:
        h1, h2, _ = agents(draw_games(spec.levers_num_ids, -(-n // AGENTS), gen))
        hidden = spec.levers_hidden
        return {"f1": h1.reshape(-1, hidden)[:n], "f2": h2.reshape(-1, hidden)[:n]}

    # ---- evaluation -------------------------------------------------------------------------------
    @torch.no_grad()
    def evaluate(self, spec: CellSpec, base: nn.Module, agents: nn.Module, gen: torch.Generator) -> dict[str, float]:
        ids = self._eval_games(spec, gen)
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
    def figure_data(self, spec: CellSpec, base: nn.Module, agents: nn.Module):
        """Last f-block vectors (h2) of a fixed set of games, for the PCA figure coloured by agent ID."""
        ids = draw_games(spec.levers_num_ids, FIGURE_GAMES, torch.Generator().manual_seed(FIGURE_SEED))
        hidden = spec.levers_hidden

        def vectors(net: nn.Module) -> list[list[float]]:
            return [[round(x, 4) for x in row] for row in net(ids)[1].reshape(-1, hidden).tolist()]

        return {"kind": "comm", "base": vectors(base), "new": vectors(agents), "ids": ids.reshape(-1).tolist()}
