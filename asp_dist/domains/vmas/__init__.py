"""MPE's speaker–listener on VMAS, with a base team whose words are a convention.

The world is mpe2's `simple_speaker_listener` (a speaker sees which of three landmarks is the goal and says
one of three words; the listener hears it a step later, sees the landmarks and moves, five moves; both get
−distance² of the listener to the goal), run on VMAS's vectorized, differentiable simulator (world.py; where
VMAS's own scenario differs from mpe2's, the option and its default are there). Knobs: vmas_speaker_listener_*.

Every team, base and new, learns through the differentiable world: an episode of `batch_size` worlds (the
base: `_base_worlds`) is played with straight-through samples of every choice (forward the one-hot of the
sampled word or move, gradient the softmax's), and the loss is minus the mean return per step, back-
propagated through the world, the heard words and the listener into the speaker (decision 0060: the
PettingZoo adapter's A2C does not even learn a listener for an oracle speaker's words).

A base is accepted only if its words carry the goal and the listener uses them: the mutual information
between the goal and the speaker's sampled word is at least `_accept_mi` nats (log 3 = 1.10 is a perfect
code), and replacing every word by a uniformly random one costs the team at least `_accept_drop` return per
episode. Both figures are in every row (base_word_mi, base_word_drop).

The new agent is either agent (`_new_agent`): a new listener must understand the base speaker's words (its
channel, the adversary's, is its move), a new speaker must be understood by the base listener (its channel is
its word). Without vmas installed (`pip install 'asp-dist[vmas]'`) the domain is set aside.
"""
from __future__ import annotations

import importlib.util
from typing import TYPE_CHECKING, Any

from asp_dist.core.contract import GameDomain, MetricInfo, PaperFacts, game_attribute, require
from asp_dist.knobs import Knob

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

INSTALL = "pip install 'asp-dist[vmas]'"
ROLES = ("listener_0", "speaker_0")
P = "vmas_speaker_listener"  # the domain's name: its knobs are vmas_speaker_listener_<knob>
POOL = 4096  # paired counts above this are refused (each pair is one base episode)


class VMASSpeakerListener(GameDomain):
    name = P
    channels = ("channel",)
    accept_field = f"{P}_accept_mi"
    paper = PaperFacts(
        metric_label="mixed-team return per 25-step episode (−distance², shared)",
        claim="does ASP help a new listener (or speaker) adopt the base team's words in MPE's speaker–listener?",
        in_paper=False,
    )
    knobs = (
        Knob(f"{P}_new_agent", str, "listener_0", "The agent being replaced: listener_0 (must understand the "
             "base speaker's words; its channel is its move) or speaker_0 (must be understood by the base "
             "listener; its channel is its word).", choices=ROLES, shapes_base=False),
        Knob(f"{P}_goal_per_world", bool, True, "Each world draws its own goal (mpe2); False: one goal for "
             "the whole batch, as VMAS's own scenario."),
        Knob(f"{P}_force", float, 5.0, "Force of a listener's move (mpe2: 5; VMAS's discrete moves: 1)."),
        Knob(f"{P}_reward", str, "dist2", "Team reward per step: dist2 = −distance² (mpe2), dist = "
             "−2·distance (VMAS).", choices=("dist2", "dist")),
        Knob(f"{P}_episode_len", int, 25, "Steps per episode.", bound=10_000),
        Knob(f"{P}_hidden", int, 64, "Hidden units of each agent's two-layer MLP.", bound=16_384),
        Knob(f"{P}_entropy", float, 0.001, "Entropy bonus per step, summed over both agents' choices."),
        Knob(f"{P}_base_worlds", int, 256, "Worlds per episode while the base team trains.", bound=100_000),
        Knob(f"{P}_base_lr", float, 0.003, "Adam learning rate of the base team."),
        Knob(f"{P}_accept_mi", float, 0.9, "Base accepted when the mutual information goal → sampled word is "
             "at least this many nats (log 3 = 1.10: a perfect code) and random words cost at least "
             f"{P}_accept_drop."),
        Knob(f"{P}_accept_drop", float, 3.0, "Base accepted only when replacing the speaker's words by "
             "uniformly random ones lowers the team's return per episode by at least this (the listener uses "
             "the words)."),
    )
    defaults = dict(
        lambda_paired=1.0, lambda_unpaired=0.1, unpaired_size=1024,
        train_steps=1000, batch_size=64, lr=0.003,
        disc_hidden=64, disc_layers=1, disc_lr=0.001,
        base_train_steps=2000, eval_episodes=512, base_steps_growth=1.5, base_max_attempts=5,
    )
    smoke = {"train_steps": 6, "base_train_steps": 4, "batch_size": 4, "eval_episodes": 16, "unpaired_size": 64,
             "disc_hidden": 16, f"{P}_hidden": 16, f"{P}_base_worlds": 8, f"{P}_episode_len": 6,
             f"{P}_accept_mi": 0.0, f"{P}_accept_drop": 0.0}
    metrics = {
        "mixed": MetricInfo(True, "Eq. 1: mean return per episode of the new agent in its role with the base "
                                  "agent in the other"),
        "mixed_swapped": MetricInfo(True, "the other mixed team: the base agent in the new agent's role with "
                                          "the new team's other agent"),
        "self_play_new": MetricInfo(True, "mean return per episode of the new team"),
        "self_play_base": MetricInfo(True, "mean return per episode of the base team"),
        "channel_match": MetricInfo(True, "fraction of the role's observations in base episodes on which the "
                                          "new agent's greedy channel choice equals the base's"),
        "base_word_mi": MetricInfo(True, "mutual information (nats) between the goal and the base speaker's "
                                         "sampled word"),
        "base_word_drop": MetricInfo(True, "base team's return per episode minus its return when every word is "
                                           "replaced by a uniformly random one (the listener's use of words)"),
        "mixed_word_mi": MetricInfo(True, "mutual information (nats) between the goal and the speaker's word "
                                          "in the mixed team"),
    }

    def __init__(self) -> None:
        """Refuses (ImportError, one line: the registry sets the domain aside) where vmas is not installed."""
        if importlib.util.find_spec("vmas") is None:
            raise ImportError(f"vmas is not installed: {INSTALL}")

    def knob(self, spec: CellSpec, suffix: str) -> Any:
        return getattr(spec, f"{P}_{suffix}")

    def validate(self, spec: CellSpec) -> None:
        for knob in ("hidden", "episode_len", "base_worlds"):
            require(self.knob(spec, knob) >= 1, f"{P}_{knob} must be >= 1, got {self.knob(spec, knob)}")
        for knob in ("force", "base_lr"):
            require(self.knob(spec, knob) > 0, f"{P}_{knob} must be > 0, got {self.knob(spec, knob)}")
        require(self.knob(spec, "entropy") >= 0, f"{P}_entropy must be >= 0, got {self.knob(spec, 'entropy')}")
        require(spec.batch_size >= 1, f"batch_size must be >= 1 (worlds per self-play episode), got {spec.batch_size}")
        require(spec.paired <= POOL, f"paired must be <= {POOL} for {self.name}, got {spec.paired}")

    def channel_dims(self, spec: CellSpec) -> dict[str, int]:
        from asp_dist.domains.vmas.world import N_MOVES, WORDS

        return {"channel": N_MOVES if self.knob(spec, "new_agent") == "listener_0" else WORDS}

    def tensor_sizes(self, spec: CellSpec) -> dict[str, int]:
        worlds = max(self.knob(spec, "base_worlds"), spec.batch_size, min(spec.eval_episodes, 4096))
        hidden, steps = self.knob(spec, "hidden"), self.knob(spec, "episode_len")
        return {f"{P}_hidden²": hidden ** 2, f"worlds × {P}_episode_len × {P}_hidden": worlds * steps * hidden,
                "unpaired_size × channel": spec.unpaired_size * 5}


def __getattr__(name: str) -> Any:
    """The game's names (SpeakerListenerTeam, ...), imported on first access."""
    return game_attribute(__name__, name)
