"""A PettingZoo parallel environment as an asp-dist domain, from a short declaration (the card, no torch).

A researcher declares which environment, which agent is the *new* one (the agent being replaced), which part
of its action is the convention channel the adversary watches, how the team's reward is formed and how long
an episode is; the adapter does the rest:

    from asp_dist.domains.pettingzoo import PettingZooDomain, PettingZooGame

    class SpeakerListener(PettingZooDomain):
        name = "mpe_speaker_listener"                       # = the entry point's name; knobs are <name>_<knob>
        declaration = PettingZooGame(
            env="mpe2.simple_speaker_listener_v4",          # module[:factory], factory default parallel_env
            new_agent="listener_0", channel="move",
            parts={"speaker_0": (("say", 3),), "listener_0": (("move", 5),)},
            team_reward="shared", episode_len=25, continuous_kwarg="continuous_actions",
            accept_gain=15.0,
        )

- The base team (one actor per agent and a centralised critic, small MLPs) learns by self-play A2C on many
  copies of the env stepped together, until its mean team return beats a uniformly random team's by
  `<name>_accept_gain`.
- P (paired): n (observation, action) pairs of the new agent's role, one uniform step of each of n base
  episodes; U (unpaired): the base's channel outputs (one-hot of the part, or its slice of a Box action)
  on every step of base episodes, without observations.
- The new team trains by self-play A2C (OSP, ASP), the paired loss (cross-entropy on every part of the
  role's action; mean squared error for a Box) and, for ASP, the adversary on the channel: the new agent's
  sampled channel output, straight-through (forward the one-hot of the sample, gradient the softmax's; for a
  Box the reparameterised sample).
- Evaluation: Eq. 1 of the paper with one new agent: `mixed` is the mean team return of the new agent in its
  role with the base agents in every other role.

Knobs name the environment (`<name>_env`), the new agent and the channel, so one declaration serves every
agent of its env (cells differing only in which agent is new share a base); a second environment is a second
declaration and a second domain (its units and its bar are its own: asp-dist stats compares within a domain).
The torch half is game.py; envs.py finds, checks and steps the environments (imports pettingzoo on first use).
Without pettingzoo or the env's package installed, the domain is set aside with one line saying what to install.
"""

from __future__ import annotations

import importlib
import importlib.util
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any

from asp_dist.core.contract import Domain, MetricInfo, PaperFacts, game_attribute, require
from asp_dist.domains.pettingzoo import envs
from asp_dist.knobs import Knob

if TYPE_CHECKING:
    from asp_dist.spec import CellSpec

POOL = 4096  # paired counts above this are refused (each pair is one base episode)
INSTALL = "pip install 'asp-dist[pettingzoo]'"
TEAM_REWARDS = envs.TEAM_REWARDS


@dataclass(frozen=True)
class PettingZooGame:
    """What a researcher declares: the environment, the new agent and its convention channel, the team reward.

    env              "package.module" or "package.module:factory" of a PettingZoo *parallel* env (factory
                     default `parallel_env`); the `<name>_env` knob's default
    new_agent        the agent being replaced (`<name>_new_agent`'s default)
    channel          the part of the new agent's action the adversary watches (`<name>_channel`'s default)
    parts            each agent's action parts, {agent: ((part, size), ...)}: digits of a Discrete action (the
                     first the least significant), entries of a MultiDiscrete, slices of a Box (envs.py); an
                     agent left out has one part, "action", its whole action
    env_kwargs       fixed keyword arguments of the factory
    episode_len      steps per episode (`<name>_episode_len`); passed as `episode_kwarg` where the env takes one,
                     and the adapter cuts episodes there in any case
    continuous_kwarg the factory's switch to continuous actions, if any (`<name>_continuous`)
    team_reward      sum | mean | shared (every agent gets the same reward: checked on the env)
    accept_gain      the base's bar (`<name>_accept_gain`): its mean team return per episode minus that of a
                     uniformly random team on the same reset seeds (knobs are >= 0, MPE's returns are not)
    reward_scale     A2C trains on reward × this (`<name>_reward_scale`); returns are reported raw
    env_knobs        factory keyword arguments exposed as knobs: ((kwarg, type, default, doc), ...) → <name>_<kwarg>
    metric_label, claim   what `mixed` measures (axis label) and the question the domain asks (asp-dist stats)
    defaults, smoke  the domain's values of common knobs (and of its own), as Domain.defaults and Domain.smoke
    install          what to install when the env's package is missing
    """

    env: str
    new_agent: str
    channel: str
    parts: dict[str, tuple[tuple[str, int], ...]] = field(default_factory=dict)
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    episode_len: int = 25
    episode_kwarg: str | None = "max_cycles"
    continuous_kwarg: str | None = None
    team_reward: str = "sum"
    accept_gain: float = 0.0
    reward_scale: float = 1.0
    env_knobs: tuple[tuple[str, type, Any, str], ...] = ()
    metric_label: str = "mixed-team return per episode"
    claim: str = "does ASP help a new agent adopt the base team's convention in this environment?"
    defaults: dict[str, Any] = field(default_factory=dict)
    smoke: dict[str, Any] = field(default_factory=dict)
    install: str = INSTALL

    def problems(self) -> list[str]:
        """What is wrong with the declaration itself, checked without the environment."""
        out = []
        for what in ("env", "new_agent", "channel"):
            if not isinstance(getattr(self, what), str) or not getattr(self, what).strip():
                out.append(f"{what} must be a non-empty string")
        if self.team_reward not in TEAM_REWARDS:
            out.append(f"team_reward must be one of {', '.join(TEAM_REWARDS)}, got {self.team_reward!r}")
        if not isinstance(self.episode_len, int) or self.episode_len < 1:
            out.append(f"episode_len must be an integer >= 1, got {self.episode_len!r}")
        for agent, parts in self.parts.items():
            names = [p[0] for p in parts]
            if not parts or len(set(names)) != len(names) or any(
                    not isinstance(n, str) or not isinstance(s, int) or isinstance(s, bool) or s < 1 for n, s in parts):
                out.append(f"parts of {agent!r} must be distinct (name, size >= 1) pairs, got {parts!r}")
        for kwarg, kind, default, doc in self.env_knobs:
            if not kwarg.isidentifier() or kind not in (int, float, str, bool) or not doc:
                out.append(f"env knob {kwarg!r} must be (kwarg, int|float|str|bool, default, doc)")
        return out


# The adapter's A2C and network knobs, the same for every declaration: (suffix, type, default, doc, extra).
A2C_KNOBS = (
    ("hidden", int, 64, "Hidden units of every actor's and the critic's two-layer MLP.", dict(bound=16_384)),
    ("gamma", float, 0.95, "A2C discount factor.", {}),
    ("entropy", float, 0.01, "A2C entropy bonus weight (summed over agents and action parts).", {}),
    ("value_coef", float, 0.5, "A2C value-loss weight.", {}),
    ("rollout_len", int, 5, "Environment steps per A2C update (n-step return length).", dict(bound=10_000)),
    ("base_envs", int, 32, "Env copies stepped together while the base team trains.", dict(bound=100_000)),
    ("base_lr", float, 0.003, "Adam learning rate of the base team.", {}),
)
METRICS = {
    "mixed": MetricInfo(True, "Eq. 1: mean team return of the new agent in its role with the base agents in "
                              "every other role"),
    "mixed_swapped": MetricInfo(True, "mean team return of the base agent in the new agent's role with the new "
                                      "team in every other role (the other mixed composition)"),
    "self_play_new": MetricInfo(True, "mean team return of the new team"),
    "self_play_base": MetricInfo(True, "mean team return of the base team"),
    "channel_match": MetricInfo(True, "fraction of the role's observations in base episodes on which the new "
                                      "agent's greedy channel output equals the base's (argmax of the part's "
                                      "logits, or of its slice of the Box mean)"),
}
COMMON_DEFAULTS = dict(
    lambda_paired=1.0, lambda_unpaired=0.1, unpaired_size=1024,
    train_steps=3000, batch_size=8, lr=0.001,
    disc_hidden=64, disc_layers=1, disc_lr=0.001,
    base_train_steps=1500, eval_episodes=200, base_steps_growth=1.5, base_max_attempts=5,
)


class PettingZooDomain(Domain):
    """A domain made from a `PettingZooGame` declaration (class attribute `declaration`). A subclass names
    itself (`name`) and declares; knobs, defaults, smoke spec, metrics and paper facts follow from the
    declaration when the class is made. Every cell trains on asp-dist's reference trainer."""

    declaration: PettingZooGame
    channels = ("channel",)
    metrics = METRICS

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        decl = cls.__dict__.get("declaration")
        if decl is None:  # an intermediate class without a declaration of its own
            return
        problems = decl.problems() if isinstance(decl, PettingZooGame) else ["it is not a PettingZooGame"]
        if problems:
            raise TypeError(f"{cls.__name__}.declaration: {problems[0]}")
        p = cls.name
        knobs = [
            Knob(f"{p}_env", str, decl.env, "PettingZoo parallel env, package.module[:factory] (factory default "
                                             "parallel_env)."),
            Knob(f"{p}_new_agent", str, decl.new_agent, "The agent being replaced: the new agent's role.",
                 shapes_base=False),
            Knob(f"{p}_channel", str, decl.channel, "Part of the new agent's action the adversary watches "
                                                     "(its convention channel).", shapes_base=False),
            Knob(f"{p}_team_reward", str, decl.team_reward, "Team reward per step: sum | mean | shared (every "
                                                            "agent gets the same).", choices=TEAM_REWARDS),
            Knob(f"{p}_episode_len", int, decl.episode_len, "Steps per episode.", bound=100_000),
            Knob(f"{p}_reward_scale", float, decl.reward_scale, "A2C trains on reward × this; returns are "
                                                                "reported raw."),
        ]
        if decl.continuous_kwarg:
            knobs.append(Knob(f"{p}_continuous", bool, False, f"Continuous (Box) actions: the env's "
                                                              f"{decl.continuous_kwarg}=True; a Gaussian policy."))
        knobs += [Knob(f"{p}_{kwarg}", kind, default, doc) for kwarg, kind, default, doc in decl.env_knobs]
        knobs += [Knob(f"{p}_{suffix}", kind, default, doc, **extra) for suffix, kind, default, doc, extra in A2C_KNOBS]
        knobs.append(Knob(f"{p}_accept_gain", float, float(decl.accept_gain),
                          "Base accepted when its mean team return per episode beats a uniformly random team's "
                          "(same reset seeds) by at least this."))
        cls.knobs = tuple(knobs)
        cls.accept_field = f"{p}_accept_gain"
        cls.defaults = {**COMMON_DEFAULTS, **decl.defaults}
        cls.smoke = {"train_steps": 16, "base_train_steps": 8, "batch_size": 4, "eval_episodes": 8,
                     "unpaired_size": 64, "disc_hidden": 16, f"{p}_hidden": 16, f"{p}_base_envs": 8,
                     f"{p}_rollout_len": 2, f"{p}_episode_len": 8, f"{p}_accept_gain": 0.0, **decl.smoke}
        cls.paper = PaperFacts(metric_label=decl.metric_label, claim=decl.claim, in_paper=False)

    def __init__(self) -> None:
        """Refuses (ImportError, one line: the registry sets the domain aside) where pettingzoo or the env's
        package is not installed; looks for them without importing them."""
        decl = self.declaration
        for package in dict.fromkeys(("pettingzoo", envs.factory_path(decl.env)[0].split(".")[0])):
            if importlib.util.find_spec(package) is None:
                raise ImportError(f"{package} is not installed: {decl.install}")

    # ---- the card ------------------------------------------------------------------------------------
    @property
    def game(self) -> ModuleType:
        """The adapter's torch half, whatever module the declaring class lives in."""
        return importlib.import_module("asp_dist.domains.pettingzoo.game")

    @property
    def trainers(self) -> tuple[type, ...]:
        return ()  # the reference trainer

    def env_kwargs(self, spec: CellSpec) -> tuple[tuple[str, Any], ...]:
        decl = self.declaration
        kwargs = dict(decl.env_kwargs)
        if decl.episode_kwarg:
            kwargs[decl.episode_kwarg] = self.knob(spec, "episode_len")
        if decl.continuous_kwarg:
            kwargs[decl.continuous_kwarg] = self.knob(spec, "continuous")
        kwargs.update({kwarg: self.knob(spec, kwarg) for kwarg, *_ in decl.env_knobs})
        return tuple(sorted(kwargs.items()))

    def facts(self, spec: CellSpec) -> envs.EnvFacts:
        """The environment of `spec`, described and checked (cached per process; SpecError when unusable)."""
        parts = tuple(sorted(self.declaration.parts.items()))
        return envs.describe(self.knob(spec, "env"), self.env_kwargs(spec), parts, self.knob(spec, "team_reward"),
                             self.knob(spec, "episode_len"), f"{self.name}_env")

    def role(self, spec: CellSpec) -> tuple[envs.AgentFacts, int, int]:
        """The new agent's facts, and the index and size of its channel part."""
        agent = self.facts(spec).agent(self.knob(spec, "new_agent"))
        index, size = agent.part(self.knob(spec, "channel"))
        return agent, index, size

    def validate(self, spec: CellSpec) -> None:
        p = self.name
        for suffix in ("hidden", "episode_len", "rollout_len", "base_envs"):
            require(self.knob(spec, suffix) >= 1, f"{p}_{suffix} must be >= 1, got {self.knob(spec, suffix)}")
        require(0.0 <= self.knob(spec, "gamma") <= 1.0, f"{p}_gamma must be in [0, 1], got {self.knob(spec, 'gamma')}")
        for suffix in ("base_lr", "reward_scale"):
            require(self.knob(spec, suffix) > 0, f"{p}_{suffix} must be > 0, got {self.knob(spec, suffix)}")
        for suffix in ("entropy", "value_coef"):
            require(self.knob(spec, suffix) >= 0, f"{p}_{suffix} must be >= 0, got {self.knob(spec, suffix)}")
        require(spec.paired <= POOL, f"paired must be <= {POOL} for {p}, got {spec.paired}")
        facts = self.facts(spec)  # the env: importable, buildable, its spaces usable
        agent = self.knob(spec, "new_agent")
        require(agent in facts.names, f"{p}_new_agent {agent!r} is not an agent of {facts.env}; its agents: "
                                      f"{', '.join(facts.names)}")
        channel, parts = self.knob(spec, "channel"), facts.agent(agent).parts
        listed = ", ".join(f"{n} ({s})" for n, s in parts)
        require(channel in [n for n, _ in parts],
                f"{p}_channel {channel!r} is not a part of {agent}'s action in {facts.env}; its parts: {listed}")

    def channel_dims(self, spec: CellSpec) -> dict[str, int]:
        return {"channel": self.role(spec)[2]}

    def tensor_sizes(self, spec: CellSpec) -> dict[str, int]:
        facts = self.facts(spec)
        width = max(self.knob(spec, "hidden"), *(a.obs_dim for a in facts.agents), *(a.head for a in facts.agents))
        critic = sum(a.obs_dim for a in facts.agents) + 1
        rows = self.knob(spec, "rollout_len") * max(self.knob(spec, "base_envs"), spec.batch_size)
        return {f"{self.name}_hidden²": self.knob(spec, "hidden") ** 2,
                f"{self.name}_rollout_len × envs × width": rows * width,
                f"{self.name}_rollout_len × envs × critic input": rows * critic,
                "eval_episodes × width": min(spec.eval_episodes, 256) * width,
                "unpaired_size × width": spec.unpaired_size * width,
                f"envs × {self.name}_episode_len × action width": max(self.knob(spec, "base_envs"), spec.batch_size)
                * self.knob(spec, "episode_len") * max(a.width for a in facts.agents)}

    # ---- the game (game.py), each with this domain first ----------------------------------------------
    def train_base(self, spec, seed, progress=None):
        return self.game.train_base(self, spec, seed, progress)

    def paired(self, spec, base, n, gen):
        return self.game.paired(self, spec, base, n, gen)

    def unpaired(self, spec, base, size, gen):
        return self.game.unpaired(self, spec, base, size, gen)

    def new_agents(self, spec, seed):
        return self.game.new_agents(self, spec, seed)

    def init_self_play(self, spec, agents, gen):
        return self.game.init_self_play(self, spec, agents, gen)

    def self_play_step(self, spec, agents, state, gen):
        return self.game.self_play_step(self, spec, agents, state, gen)

    def paired_loss(self, spec, agents, paired):
        return self.game.paired_loss(self, spec, agents, paired)

    def convention_outputs(self, spec, agents, n, gen):
        return self.game.convention_outputs(self, spec, agents, n, gen)

    def evaluate(self, spec, base, agents, gen):
        return self.game.evaluate(self, spec, base, agents, gen)


# ---- the two declarations asp-dist ships (entry points in pyproject.toml) ----------------------------------
class MPESpeakerListener(PettingZooDomain):
    """MPE's simple_speaker_listener_v4: speaker_0 sees the goal landmark's colour and says one of 3 words;
    listener_0 hears it (a step later), sees the landmarks and moves (5 actions). Both get −distance²."""

    name = "mpe_speaker_listener"
    declaration = PettingZooGame(
        env="mpe2.simple_speaker_listener_v4",
        new_agent="listener_0", channel="move",
        parts={"speaker_0": (("say", 3),), "listener_0": (("move", 5),)},
        team_reward="shared", episode_len=25, continuous_kwarg="continuous_actions",
        accept_gain=15.0,
        metric_label="mixed-team return per 25-step episode (MPE: −distance², shared)",
        claim="does ASP help a new listener (or speaker) adopt the base team's words in MPE's speaker–listener?",
    )


class MPEReference(PettingZooDomain):
    """MPE's simple_reference_v3: two agents, each sees the other's goal and both speak (10 words) and move
    (5 actions) at once: the Discrete(50) action is move + 5 × say. The team reward is the sum of the two."""

    name = "mpe_reference"
    declaration = PettingZooGame(
        env="mpe2.simple_reference_v3",
        new_agent="agent_1", channel="say",
        parts={"agent_0": (("move", 5), ("say", 10)), "agent_1": (("move", 5), ("say", 10))},
        team_reward="sum", episode_len=25, continuous_kwarg="continuous_actions",
        env_knobs=(("local_ratio", float, 0.5, "Weight of an agent's own distance in its reward (the rest: "
                                               "the team's mean distance)."),),
        accept_gain=12.0,
        metric_label="mixed-team return per 25-step episode (MPE: sum of both agents' rewards)",
        claim="does ASP help a new agent adopt its partner's words when both agents speak (MPE simple_reference)?",
    )


def __getattr__(name: str) -> Any:
    """The game's names (TeamAgents, a2c_update, ...), imported on first access."""
    return game_attribute(__name__, name)
