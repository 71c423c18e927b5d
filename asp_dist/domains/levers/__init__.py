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

from typing import TYPE_CHECKING, Any

from asp_dist.core.contract import GameDomain, MetricInfo, PaperFacts, game_attribute, require
from asp_dist.knobs import Knob

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

AGENTS = 3  # agents per game, and levers (paper: 3)
POOL = 1024  # paired games are the first n of a fixed pool, so P(n) is a prefix of P(n+1)


# ---- the domain ----------------------------------------------------------------------------------
class LeversDomain(GameDomain):
    name = "levers"
    channels = ("f1", "f2")
    accept_field = "levers_accept_reward"
    paper = PaperFacts(
        metric_label="mixed-team error, 1 − reward (fraction of levers)",
        claim="ASP better than OSP (p < 0.05) and PC (p < 0.01) over 4–8 paired (Friedman)",
        test_paired=(4, 8),
        threshold=(1 - 0.683, "error of the best policy without communication (1 - 0.683)"),
    )
    knobs = (  # name, type, default, doc; choices, neutral value, base-shaping, bound
        Knob('levers_hidden', int, 32, 'Hidden size of the CommNet f-blocks.', bound=16_384),
        Knob('levers_num_ids', int, 10, 'Agent IDs are drawn from 0..num_ids-1 (paper: 10).', bound=100),
        Knob('levers_eps_start', float, 1.0, 'ε-greedy exploration at the start of training.'),
        Knob('levers_eps_end', float, 0.05, 'ε-greedy exploration at the end of the schedule.'),
        Knob('levers_eps_decay_frac', float, 0.5, 'Fraction of training over which ε decays linearly.'),
        Knob('levers_replay_size', int, 4096, 'Replay buffer capacity (games).', bound=10_000_000),
        Knob('levers_base_lr', float, 0.003, 'Adam learning rate of the base network.'),
        Knob('levers_accept_reward', float, 0.95, 'Base accepted at mean reward >= this (paper: 0.95).'),
    )
    legacy_identity = True  # knobs recorded as CellSpec fields before domains were plugins
    # A cell in about a second (asp-dist check-domain, the registry-wide tests)
    smoke = dict(levers_hidden=8, base_train_steps=30, train_steps=20, batch_size=16, levers_replay_size=64,
                 unpaired_size=60, disc_hidden=8, eval_episodes=120, levers_accept_reward=0.0)
    defaults = dict(
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


def __getattr__(name: str) -> Any:
    """The game's names (CommNet, dqn_step, draw_games, epsilon, ...), imported on first access."""
    return game_attribute(__name__, name)
