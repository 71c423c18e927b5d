"""MPE's communication worlds on VMAS, with base teams whose words are a convention.

Two domains, one per mpe2 world (scenarios.py says who moves, who speaks and what each sees; world.py is the
VMAS scenario, with the option and its default wherever VMAS's own scenario differs from mpe2's):

- `vmas_speaker_listener`: mpe2's `simple_speaker_listener` (a speaker sees which of three landmarks is the goal
  and says one of three words; the listener hears it a step later and moves; −distance² of the listener to the
  goal). The new agent is the listener (it must understand the base speaker's words; its channel is its move)
  or the speaker (it must be understood by the base listener; its channel is its word).
- `vmas_reference`: mpe2's `simple_reference` (two agents, each sees where its partner must go, says one of ten
  words and moves; −distance of each partner to its goal, summed). The new agent's channel is its word or move.

Every team, base and new, learns through the differentiable world: an episode of `batch_size` worlds (the
base: `_base_worlds`) is played with straight-through samples of every choice (forward the one-hot of the
sampled word or move, gradient the softmax's), and the loss is minus the mean return per step, back-
propagated through the world and the heard words into every agent (decision 0060: the PettingZoo adapter's
A2C does not even learn a listener for an oracle speaker's words).

A base is accepted only if its words carry the goal and its team uses them: the mutual information between the
goal an agent sees and the words it says (the mean over the agents that speak) is at least `_accept_mi` nats
(log 3 = 1.10 is a perfect code), and replacing every word by a uniformly random one costs the team at least
`_accept_drop` return per episode. Both figures are in every row (base_word_mi, base_word_drop). Knobs:
<domain>_<knob>. Without vmas installed (`pip install 'asp-dist[vmas]'`) both domains are set aside.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType
from typing import TYPE_CHECKING, Any

from asp_dist.core.contract import GameDomain, MetricInfo, PaperFacts, game_attribute, require
from asp_dist.domains.vmas.scenarios import SCENARIOS
from asp_dist.knobs import Knob

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

INSTALL = "pip install 'asp-dist[vmas]'"
POOL = 4096  # paired counts above this are refused (each pair is one base episode)
METRICS = {
    "mixed": MetricInfo(True, "Eq. 1: mean return per episode of the new agent in its role with the base agents "
                              "in the others"),
    "mixed_swapped": MetricInfo(True, "the other mixed team: the base agent in the new agent's role with the new "
                                      "team's other agents"),
    "self_play_new": MetricInfo(True, "mean return per episode of the new team"),
    "self_play_base": MetricInfo(True, "mean return per episode of the base team"),
    "channel_match": MetricInfo(True, "fraction of the role's observations in base episodes on which the new "
                                      "agent's greedy channel choice equals the base's"),
    "base_word_mi": MetricInfo(True, "mutual information (nats) between the goal an agent sees and its sampled "
                                     "words, mean over the base's agents that speak"),
    "base_word_drop": MetricInfo(True, "base team's return per episode minus its return when every word is "
                                       "replaced by a uniformly random one (the team's use of its words)"),
    "mixed_word_mi": MetricInfo(True, "the same mutual information in the mixed team"),
}


class VMASDomain(GameDomain):
    """A VMAS communication world as a domain: a subclass names itself, its scenario (scenarios.SCENARIOS), its
    default new agent and channel, and what its metric measures; knobs follow when the class is made."""

    scenario: str
    new_agent: str
    channel: str = ""  # the default channel where the new agent both moves and speaks
    channels = ("channel",)
    metrics = METRICS

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        p, world = cls.name, SCENARIOS[cls.scenario]
        names = tuple(a.name for a in world.agents)
        parts = tuple(dict.fromkeys(part for a in world.agents for part, _ in a.parts))
        knobs = [Knob(f"{p}_new_agent", str, cls.new_agent, "The agent being replaced: the new agent's role.",
                      choices=names, shapes_base=False)]
        if any(len(a.parts) > 1 for a in world.agents):
            knobs.append(Knob(f"{p}_channel", str, cls.channel, "Part of the new agent's choices the adversary "
                              "watches (its convention channel).", choices=parts, shapes_base=False))
        knobs += [
            Knob(f"{p}_goal_per_world", bool, True, "Each world draws its own goals (mpe2); False: one draw for "
                 "the whole batch, as VMAS's own scenarios."),
            Knob(f"{p}_force", float, 5.0, "Force of a move (mpe2: 5; VMAS's discrete moves: 1)."),
        ]
        if len(world.rewards) > 1:
            knobs.append(Knob(f"{p}_reward", str, world.rewards[0], "Team reward per step: dist2 = −distance² "
                              "(mpe2), dist = −2·distance (VMAS).", choices=world.rewards))
        knobs += [
            Knob(f"{p}_episode_len", int, 25, "Steps per episode.", bound=10_000),
            Knob(f"{p}_hidden", int, 64, "Hidden units of each agent's two-layer MLP.", bound=16_384),
            Knob(f"{p}_entropy", float, 0.001, "Entropy bonus per step, summed over every agent's choices."),
            Knob(f"{p}_base_worlds", int, 256, "Worlds per episode while the base team trains.", bound=100_000),
            Knob(f"{p}_base_lr", float, 0.003, "Adam learning rate of the base team."),
            Knob(f"{p}_accept_mi", float, 0.9, "Base accepted when the mutual information goal → sampled word "
                 f"is at least this many nats (log 3 = 1.10: a perfect code) and random words cost at least "
                 f"{p}_accept_drop."),
            Knob(f"{p}_accept_drop", float, 3.0, "Base accepted only when replacing its words by uniformly random "
                 "ones lowers the team's return per episode by at least this (the team uses the words); 0: no "
                 "such check."),
        ]
        cls.knobs = tuple(knobs)
        # P holds the new agent's observations and choices; U its channel's choices
        cls.paired_fields = (f"{p}_new_agent",)
        cls.unpaired_fields = tuple(k.name for k in knobs if k.name in (f"{p}_new_agent", f"{p}_channel"))
        cls.accept_field = f"{p}_accept_mi"
        cls.defaults = dict(
            lambda_paired=1.0, lambda_unpaired=0.1, unpaired_size=1024,
            train_steps=1000, batch_size=64, lr=0.003,
            disc_hidden=64, disc_layers=1, disc_lr=0.001,
            base_train_steps=2000, eval_episodes=512, base_steps_growth=1.5, base_max_attempts=5,
        )
        cls.smoke = {"train_steps": 6, "base_train_steps": 4, "batch_size": 4, "eval_episodes": 16,
                     "unpaired_size": 64, "disc_hidden": 16, f"{p}_hidden": 16, f"{p}_base_worlds": 8,
                     f"{p}_episode_len": 6, f"{p}_accept_mi": 0.0, f"{p}_accept_drop": 0.0}

    def __init__(self) -> None:
        """Refuses (ImportError, one line: the registry sets the domain aside) where vmas is not installed."""
        if importlib.util.find_spec("vmas") is None:
            raise ImportError(f"vmas is not installed: {INSTALL}")

    @property
    def game(self) -> ModuleType:
        """The torch half, shared by every VMAS domain."""
        return importlib.import_module("asp_dist.domains.vmas.game")

    @property
    def trainers(self) -> tuple[type, ...]:
        """Its packed trainer (trainers.py), for `--pack` sweeps; a lone cell trains on the reference."""
        return importlib.import_module("asp_dist.domains.vmas.trainers").TRAINERS_OF[self.name]

    def channel_part(self, spec: CellSpec) -> tuple[str, int]:
        """The new agent's channel part and its size."""
        agent = next(a for a in SCENARIOS[self.scenario].agents if a.name == self.knob(spec, "new_agent"))
        if len(agent.parts) == 1:
            return agent.parts[0]
        channel = self.knob(spec, "channel")
        require(channel in dict(agent.parts), f"{self.name}_channel {channel!r} is not a part of {agent.name}'s "
                                              f"choices; its parts: {', '.join(p for p, _ in agent.parts)}")
        return channel, dict(agent.parts)[channel]

    def validate(self, spec: CellSpec) -> None:
        p = self.name
        for knob in ("hidden", "episode_len", "base_worlds"):
            require(self.knob(spec, knob) >= 1, f"{p}_{knob} must be >= 1, got {self.knob(spec, knob)}")
        for knob in ("force", "base_lr"):
            require(self.knob(spec, knob) > 0, f"{p}_{knob} must be > 0, got {self.knob(spec, knob)}")
        require(self.knob(spec, "entropy") >= 0, f"{p}_entropy must be >= 0, got {self.knob(spec, 'entropy')}")
        require(spec.batch_size >= 1, f"batch_size must be >= 1 (worlds per self-play episode), got {spec.batch_size}")
        require(spec.paired <= POOL, f"paired must be <= {POOL} for {p}, got {spec.paired}")
        self.channel_part(spec)

    def channel_dims(self, spec: CellSpec) -> dict[str, int]:
        return {"channel": self.channel_part(spec)[1]}

    def tensor_sizes(self, spec: CellSpec) -> dict[str, int]:
        p = self.name
        worlds = max(self.knob(spec, "base_worlds"), spec.batch_size, spec.eval_episodes)  # evaluation: one batch
        hidden, steps = self.knob(spec, "hidden"), self.knob(spec, "episode_len")
        return {f"{p}_hidden²": hidden ** 2, f"worlds × {p}_episode_len × {p}_hidden": worlds * steps * hidden,
                "unpaired_size × channel": spec.unpaired_size * self.channel_part(spec)[1]}


class VMASSpeakerListener(VMASDomain):
    name = "vmas_speaker_listener"
    scenario = "speaker_listener"
    new_agent = "listener_0"
    paper = PaperFacts(
        metric_label="mixed-team return per episode (−distance², shared)",
        claim="does ASP help a new listener (or speaker) adopt the base team's words in MPE's speaker–listener?",
        in_paper=False,
    )


class VMASReference(VMASDomain):
    name = "vmas_reference"
    scenario = "reference"
    new_agent, channel = "agent_1", "say"
    paper = PaperFacts(
        metric_label="mixed-team return per episode (−distance of each agent's partner, summed)",
        claim="does ASP help a new agent adopt its partner's words when both agents speak (MPE simple_reference)?",
        in_paper=False,
    )


def __getattr__(name: str) -> Any:
    """The game's names (Team, play, ...), imported on first access."""
    return game_attribute(__name__, name)
