"""The PettingZoo side of the adapter, without torch: find an environment, describe it, step many copies.

`describe` imports the environment's module (pettingzoo and the env's package, only here and only when a
spec of a PettingZoo domain is resolved or trained), builds one copy, and reads what the adapter needs from
it: the agents, each agent's observation width, its action space and how the declared action *parts* lie in
it. Everything that is wrong with an environment, for the adapter, is a SpecError of one line: an env that
cannot be imported or built, an agent or part the env does not have, a space the adapter cannot use.

`EnvBatch` steps n copies of one environment together (a list of copies: PettingZoo has no vector API of its
own); an episode ends when any agent terminates or is truncated, or when the env drops its agents, or at the
declared episode length, and the batch's caller resets it with a seed it draws (from its torch.Generator, so a
seed reproduces everything). Copies are pooled per (env, keyword arguments) and reused: building one costs
about as much as a few steps.

Action parts. An agent's action is one of:
  Discrete(n)       parts (name, size) are the digits of a mixed-radix number, the first the least
                    significant: action = i0 + s0·i1 + s0·s1·i2 ... (MPE's simple_reference: move 5 × say 10)
  MultiDiscrete(v)  parts are its entries, in order (sizes = v)
  Box((d,), lo, hi) parts are consecutive slices (sizes add up to d), bounds finite
An agent without declared parts has one part, "action", the whole action.
"""

from __future__ import annotations

import functools
import importlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from asp_dist.errors import SpecError

DEFAULT_FACTORY = "parallel_env"
DISCRETE, MULTI, BOX = "discrete", "multidiscrete", "box"
TEAM_REWARDS = ("sum", "mean", "shared")


@dataclass(frozen=True)
class AgentFacts:
    """What the adapter knows of one agent: its observation width (Box flattened, Discrete one-hot), its action
    space's kind, its parts (name, size) and, for a Box, the bounds of every dimension."""

    name: str
    obs_kind: str  # "box" | "discrete"
    obs_dim: int
    kind: str  # DISCRETE | MULTI | BOX
    parts: tuple[tuple[str, int], ...]
    low: tuple[float, ...] = ()
    high: tuple[float, ...] = ()

    @property
    def width(self) -> int:
        """Columns of this agent's env action in a (B, width) matrix: 1 (Discrete), one per entry
        (MultiDiscrete), one per dimension (Box)."""
        return 1 if self.kind == DISCRETE else len(self.parts) if self.kind == MULTI else sum(s for _, s in self.parts)

    @property
    def head(self) -> int:
        """Outputs of the actor's head: a logit per value of every part (discrete kinds), a mean per dimension (Box)."""
        return sum(s for _, s in self.parts)

    def part(self, name: str) -> tuple[int, int]:
        """(index, size) of the part `name`."""
        names = [n for n, _ in self.parts]
        return names.index(name), self.parts[names.index(name)][1]

    def part_offset(self, index: int) -> int:
        return sum(s for _, s in self.parts[:index])


@dataclass(frozen=True)
class EnvFacts:
    env: str  # "module:factory"
    kwargs: tuple[tuple[str, Any], ...]
    agents: tuple[AgentFacts, ...]
    team_reward: str
    episode_len: int

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.agents)

    def index(self, agent: str) -> int:
        return self.names.index(agent)

    def agent(self, name: str) -> AgentFacts:
        return self.agents[self.index(name)]

    @property
    def key(self) -> tuple:
        return (self.env, self.kwargs)


def factory_path(env: str) -> tuple[str, str]:
    """("module", "factory") of "module" or "module:factory"."""
    module, _, attr = env.partition(":")
    return module.strip(), (attr.strip() or DEFAULT_FACTORY)


def load_factory(env: str, knob: str) -> Any:
    """The env factory named by `env` ("package.module[:factory]"); SpecError naming the knob if there is none."""
    module_name, attr = factory_path(env)
    if not module_name or not all(part.isidentifier() for part in module_name.split(".")) or not attr.isidentifier():
        raise SpecError(f"{knob} must be 'package.module' or 'package.module:factory' (a PettingZoo parallel env), "
                        f"got {env!r}")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise SpecError(f"{knob}: no environment {module_name!r} ({type(err).__name__}: {err}); "
                        f"is its package installed (pip install 'asp-dist[pettingzoo]')?") from None
    except Exception as err:  # a module that fails while importing
        raise SpecError(f"{knob}: importing {module_name!r} failed: {type(err).__name__}: {_first_line(err)}") from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise SpecError(f"{knob}: {module_name!r} has no environment factory {attr!r} (a PettingZoo parallel env, "
                        f"e.g. {module_name}:{DEFAULT_FACTORY})")
    return factory


def make_env(env: str, kwargs: tuple[tuple[str, Any], ...], knob: str) -> Any:
    """One copy of the environment; SpecError when it cannot be built or is not a PettingZoo parallel env."""
    factory = load_factory(env, knob)
    module_name, attr = factory_path(env)
    try:
        made = factory(**dict(kwargs))
    except Exception as err:
        args = ", ".join(f"{k}={v!r}" for k, v in kwargs)
        raise SpecError(f"{knob}: {module_name}.{attr}({args}) failed: {type(err).__name__}: "
                        f"{_first_line(err)}") from None
    from pettingzoo import AECEnv, ParallelEnv

    if not isinstance(made, ParallelEnv):
        kind = "an AEC env (use its parallel_env)" if isinstance(made, AECEnv) else f"a {type(made).__name__}"
        _close(made)
        raise SpecError(f"{knob}: {module_name}.{attr} made {kind}, not a PettingZoo parallel environment")
    return made


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else ""


def _space_facts(space: Any, name: str, declared: tuple[tuple[str, int], ...] | None, env: str) -> dict[str, Any]:
    """kind, parts, low, high of an agent's action space; SpecError for a space the adapter cannot use."""
    from gymnasium import spaces

    what = f"{env}: agent {name!r}"
    if isinstance(space, spaces.Discrete):
        n = int(space.n)
        if int(space.start) != 0:
            raise SpecError(f"{what} has action space {space} starting at {space.start}; the adapter takes Discrete "
                            f"spaces that start at 0")
        parts = declared or (("action", n),)
        if math.prod(s for _, s in parts) != n:
            raise SpecError(f"{what}: its action parts {_parts(parts)} multiply to {math.prod(s for _, s in parts)}, "
                            f"but its action space is {space}")
        return dict(kind=DISCRETE, parts=parts)
    if isinstance(space, spaces.MultiDiscrete) and len(space.nvec.shape) == 1:
        nvec = tuple(int(v) for v in space.nvec)
        if np.any(np.asarray(space.start) != 0):
            raise SpecError(f"{what} has action space {space} with a non-zero start; the adapter takes MultiDiscrete "
                            f"spaces that start at 0")
        parts = declared or tuple((f"action{i}", v) for i, v in enumerate(nvec))
        if tuple(s for _, s in parts) != nvec:
            raise SpecError(f"{what}: its action parts {_parts(parts)} do not match its action space {space} "
                            f"(one part per entry, sizes {list(nvec)})")
        return dict(kind=MULTI, parts=parts)
    if isinstance(space, spaces.Box) and len(space.shape) == 1:
        low, high = np.asarray(space.low, dtype=np.float64), np.asarray(space.high, dtype=np.float64)
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise SpecError(f"{what} has action space {space}, unbounded; the adapter takes Box actions with "
                            f"finite bounds (it squashes its Gaussian policy's mean into them)")
        dim = int(space.shape[0])
        parts = declared or (("action", dim),)
        if sum(s for _, s in parts) != dim:
            raise SpecError(f"{what}: its action parts {_parts(parts)} add up to {sum(s for _, s in parts)}, "
                            f"but its action space is {space}")
        return dict(kind=BOX, parts=parts, low=tuple(low.tolist()), high=tuple(high.tolist()))
    raise SpecError(f"{what} has action space {space}, which the adapter cannot use: it takes Discrete, "
                    f"MultiDiscrete (1-d) or a bounded 1-d Box")


def _parts(parts: tuple[tuple[str, int], ...]) -> str:
    return "(" + ", ".join(f"{n}: {s}" for n, s in parts) + ")"


def _obs_facts(space: Any, name: str, env: str) -> tuple[str, int]:
    from gymnasium import spaces

    if isinstance(space, spaces.Box):
        return "box", int(np.prod(space.shape, dtype=np.int64))
    if isinstance(space, spaces.Discrete) and int(space.start) == 0:
        return "discrete", int(space.n)
    raise SpecError(f"{env}: agent {name!r} has observation space {space}, which the adapter cannot use: it takes "
                    f"Box (flattened) or Discrete (one-hot) observations")


@functools.lru_cache(maxsize=64)
def describe(env: str, kwargs: tuple[tuple[str, Any], ...], parts: tuple[tuple[str, tuple[tuple[str, int], ...]], ...],
             team_reward: str, episode_len: int, knob: str) -> EnvFacts:
    """The facts of an environment, checked (SpecError on anything the adapter cannot use). `parts`: the
    declared (agent, ((part, size), ...)) pairs; `knob`: the knob naming the env, for messages."""
    made = make_env(env, kwargs, knob)
    module, attr = factory_path(env)
    label = f"{module}:{attr}"
    try:
        agents = tuple(made.possible_agents)
        unknown = sorted(set(dict(parts)) - set(agents))
        if unknown:
            raise SpecError(f"{label} has no agent {' or '.join(map(repr, unknown))}, for which the declaration "
                            f"gives action parts; its agents: {', '.join(agents)}")
        declared = dict(parts)
        facts = []
        for name in agents:
            obs_kind, obs_dim = _obs_facts(made.observation_space(name), name, label)
            facts.append(AgentFacts(name, obs_kind, obs_dim, **_space_facts(made.action_space(name), name,
                                                                            declared.get(name), label)))
        out = EnvFacts(label, kwargs, tuple(facts), team_reward, episode_len)
        try:
            _check_episodes(made, out)
        except SpecError:
            raise
        except Exception as err:  # the env's own reset or step failed
            raise SpecError(f"{label}: a first episode failed: {type(err).__name__}: {_first_line(err)}") from None
    finally:
        _close(made)
    return out


def _check_episodes(env: Any, facts: EnvFacts) -> None:
    """Reset gives every agent an observation; under team_reward = shared every agent gets the same reward
    (checked on a short rollout of random actions from a fixed seed: validation only, it draws no seed of a cell)."""
    obs, _ = env.reset(seed=0)
    missing = [a for a in facts.names if a not in obs]
    if missing:
        raise SpecError(f"{facts.env}: reset gives no observation to {', '.join(missing)}; the adapter needs every "
                        f"agent from the first step")
    if facts.team_reward != "shared":
        return
    rng = np.random.default_rng(0)
    for _ in range(min(facts.episode_len, 10)):
        actions = {a.name: _random_action(a, rng) for a in facts.agents if a.name in env.agents}
        if not actions:
            break
        _, rewards, terminated, truncated, _ = env.step(actions)
        values = [float(rewards.get(a, 0.0)) for a in facts.names]
        if max(values) - min(values) > 1e-6 * max(1.0, max(abs(v) for v in values)):
            raise SpecError(f"{facts.env}: team reward 'shared' but its agents' rewards differ "
                            f"({', '.join(f'{a} {v:.4g}' for a, v in zip(facts.names, values))}); use sum or mean")
        if any(terminated.values()) or any(truncated.values()):
            break


def _random_action(agent: AgentFacts, rng: np.random.Generator) -> Any:
    if agent.kind == DISCRETE:
        return int(rng.integers(math.prod(s for _, s in agent.parts)))
    if agent.kind == MULTI:
        return np.array([rng.integers(s) for _, s in agent.parts], dtype=np.int64)
    return rng.uniform(agent.low, agent.high).astype(np.float32)


def _close(env: Any) -> None:
    try:
        env.close()
    except Exception:  # closing is a courtesy (rendering); an env that fails at it has nothing to release
        pass


# ---- stepping many copies -------------------------------------------------------------------------------
_FREE: dict[tuple, list[Any]] = {}  # env copies not in use, per EnvFacts.key
_FREE_CAP = 1024  # copies kept per key once released


def acquire(facts: EnvFacts, n: int) -> list[Any]:
    free = _FREE.setdefault(facts.key, [])
    taken = [free.pop() for _ in range(min(n, len(free)))]
    return taken + [make_env(facts.env, facts.kwargs, "env") for _ in range(n - len(taken))]


def release(facts: EnvFacts, envs: list[Any]) -> None:
    free = _FREE.setdefault(facts.key, [])
    free.extend(envs[: max(0, _FREE_CAP - len(free))])


def flat_obs(value: Any, agent: AgentFacts) -> np.ndarray:
    if agent.obs_kind == "discrete":
        out = np.zeros(agent.obs_dim, dtype=np.float32)
        out[int(value)] = 1.0
        return out
    return np.asarray(value, dtype=np.float32).reshape(-1)


def env_action(row: np.ndarray, agent: AgentFacts) -> Any:
    """One env's action from its row of the agent's (B, width) action matrix."""
    if agent.kind == DISCRETE:
        return int(row[0])
    if agent.kind == MULTI:
        return row.astype(np.int64)
    return row.astype(np.float32)


class EnvBatch:
    """n copies of one environment stepped together. `obs[i]` is agent i's (n, obs_dim) float32 observations;
    `t` each copy's step within its episode. After `step`, the copies whose episode ended (`done`) keep their
    last observations until `reset` starts them again."""

    def __init__(self, facts: EnvFacts, n: int):
        self.facts, self.n = facts, n
        self.envs = acquire(facts, n)
        self.obs = [np.zeros((n, a.obs_dim), dtype=np.float32) for a in facts.agents]
        self.t = np.zeros(n, dtype=np.int64)
        self.closed = False

    def reset(self, index: list[int] | np.ndarray, seeds: list[int] | np.ndarray) -> None:
        for i, seed in zip(index, seeds):
            obs, _ = self.envs[i].reset(seed=int(seed))
            self._write(i, obs)
            self.t[i] = 0

    def _write(self, i: int, obs: dict[str, Any]) -> None:
        for k, agent in enumerate(self.facts.agents):
            value = obs.get(agent.name)
            if value is not None:
                self.obs[k][i] = flat_obs(value, agent)

    def step(self, actions: list[np.ndarray], index: list[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Step every copy (or those in `index`) with its row of each agent's (n, width) action matrix; the team
        reward and whether each copy's episode ended (for the copies stepped)."""
        facts = self.facts
        index = range(self.n) if index is None else index
        rewards = np.zeros(len(index), dtype=np.float64)
        done = np.zeros(len(index), dtype=bool)
        agents = facts.agents
        for j, i in enumerate(index):
            env = self.envs[i]
            live = env.agents
            act = {a.name: env_action(actions[k][i], a) for k, a in enumerate(agents) if a.name in live}
            obs, rew, terminated, truncated, _ = env.step(act)
            self._write(i, obs)
            values = [float(rew.get(a.name, 0.0)) for a in agents]
            # shared: every agent gets the team's reward (checked by describe), so the mean is that reward
            rewards[j] = sum(values) if facts.team_reward == "sum" else sum(values) / len(values)
            self.t[i] += 1
            done[j] = (self.t[i] >= facts.episode_len or not env.agents or any(terminated.values())
                       or any(truncated.values()))
        return rewards, done

    def close(self) -> None:
        if not self.closed:
            release(self.facts, self.envs)
            self.envs, self.closed = [], True

    def __del__(self) -> None:  # a batch dropped without close() gives its copies back
        try:
            self.close()
        except Exception:
            pass
