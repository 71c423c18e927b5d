"""MPE's communication worlds on VMAS's vectorized, differentiable simulator: the scenarios and a batch of worlds.

Two of mpe2's worlds, each as a VMAS scenario:

  speaker_listener  a speaker sees which of three landmarks is the goal and says one of 3 words; the listener
                    hears it a step later, sees the landmarks relative to itself and moves; both get
                    −distance² of the listener to the goal (mpe2 `simple_speaker_listener_v4`)
  reference         two agents, each sees which landmark its partner must reach, says one of 10 words and
                    moves; each agent's reward is −distance of its partner to that landmark, the team's their
                    sum (mpe2 `simple_reference_v3`, whose local_ratio does not change the sum)

VMAS's own scenarios differ from mpe2's (measured, docs/decisions/0060-words-through-a-differentiable-world.md);
these match mpe2 by default, each difference an option:

  goal per world       VMAS draws the goals once for the whole batch; here every world draws its own (goal_per_world)
  reward               speaker_listener: mpe2 −distance² (reward = "dist2"), VMAS −2·distance ("dist")
  force                mpe2 multiplies a move by 5 (force); VMAS's discrete moves by 1
  actions              mpe2: 5 moves (stay, −x, +x, −y, +y) and the words; VMAS: 9 moves, and a product with the
                       words. Here agents choose among mpe2's sets and the batch hands VMAS the continuous action
                       they mean (a force, a one-hot word), so gradients can pass through.
  episode              25 steps, then every world resets (VMAS's episodes never end unless told)

Kept from VMAS, not mpe2: the integrator. VMAS updates the velocity first and moves with the new one
(semi-implicit Euler); mpe2 moves with the old velocity. From one state and one action both reach the same
velocity, and VMAS's position is mpe2's plus dt·(new velocity − old) (tests/test_vmas_domain.py).

Resets draw from the batch's own torch.Generator (VMAS's scenarios use the global RNG; these do not), so a
seed reproduces every world.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from asp_dist.domains.vmas.scenarios import LANDMARKS, SCENARIOS, AgentRole

MOVES = torch.tensor([[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])  # mpe2's discrete moves


@dataclass(frozen=True)
class WorldOptions:
    """Where a world may differ from mpe2's (defaults: as mpe2)."""

    scenario: str = "speaker_listener"
    goal_per_world: bool = True
    force: float = 5.0
    reward: str = "dist2"


def scenario_class():
    """The VMAS scenario of every world here (imports vmas: only when a world is built)."""
    from vmas.simulator.core import Agent, Landmark, Sphere, World
    from vmas.simulator.scenario import BaseScenario

    class MPEScenario(BaseScenario):
        """goal[:, i]: the landmark agent i sees as its goal (speaker_listener: the speaker's, for the listener;
        reference: agent i's, for its partner)."""

        def make_world(self, batch_dim: int, device: torch.device, **kwargs):
            self.options: WorldOptions = kwargs.pop("options")
            self.rng: torch.Generator = kwargs.pop("rng")
            self.spec = SCENARIOS[self.options.scenario]
            words = max(a.words for a in self.spec.agents)
            world = World(batch_dim=batch_dim, device=device, dim_c=words, dt=0.1, drag=0.25)
            for role in self.spec.agents:
                world.add_agent(Agent(name=role.name, collide=False, movable=role.moves, silent=not role.words,
                                      shape=Sphere(0.075), u_range=self.options.force))
            for i in range(LANDMARKS):
                world.add_landmark(Landmark(name=f"landmark {i}", collide=False, shape=Sphere(0.04)))
            self.colours = torch.tensor(self.spec.colours)
            self.goal = torch.zeros(batch_dim, self.seers, dtype=torch.long)
            self.seeds = [0]  # one seed per block of worlds (Worlds.reset)
            return world

        @property
        def seers(self) -> int:
            """Agents that see a goal: the speaker; in reference, both."""
            return sum(a.words > 0 for a in self.spec.agents)

        def reset_world_at(self, env_index: int | None = None):
            """Every world afresh: the batch is len(self.seeds) equal blocks, block b drawn from self.rng seeded
            with self.seeds[b], in the order a lone batch of that block's size draws them (the goals, then each
            agent's and landmark's position), so a block's worlds are those of a lone batch reset from its seed."""
            if env_index is not None:
                raise NotImplementedError("the worlds reset all together, from seeds (Worlds.reset)")
            n = self.world.batch_dim // len(self.seeds)
            draw = n if self.options.goal_per_world else 1
            goals, positions = [], []
            for seed in self.seeds:
                self.rng.manual_seed(seed)
                goals.append(torch.randint(0, LANDMARKS, (draw, self.seers), generator=self.rng).expand(n, self.seers))
                positions.append([torch.rand(n, 2, generator=self.rng) * 2 - 1
                                  for _ in self.world.agents + self.world.landmarks])
            self.goal = torch.cat(goals)
            for k, entity in enumerate(self.world.agents + self.world.landmarks):
                entity.set_pos(torch.cat([block[k] for block in positions]), batch_index=None)
                if entity.movable:
                    entity.set_vel(torch.zeros(self.world.batch_dim, 2), batch_index=None)

        def goal_position(self, seer: int) -> torch.Tensor:
            landmarks = torch.stack([lm.state.pos for lm in self.world.landmarks], 1)
            return landmarks[torch.arange(self.world.batch_dim), self.goal[:, seer]]

        def reward(self, agent):
            if agent is self.world.agents[0]:  # one team reward per step, computed once
                if self.options.scenario == "speaker_listener":
                    square = (self.world.agents[1].state.pos - self.goal_position(0)).pow(2).sum(-1)
                    self.team_reward = -square if self.options.reward == "dist2" else -2 * square.sqrt()
                else:  # reference: each agent's partner against the goal the agent sees
                    self.team_reward = -sum((self.world.agents[1 - i].state.pos - self.goal_position(i)).norm(dim=-1)
                                            for i in range(2))
            return self.team_reward

        def observation(self, agent):
            index = self.world.agents.index(agent)
            if not agent.movable:  # the speaker: the goal's colour
                return self.colours[self.goal[:, 0]]
            relative = [lm.state.pos - agent.state.pos for lm in self.world.landmarks]
            heard = [other.state.c for other in self.world.agents if other is not agent and not other.silent]
            seen = [self.colours[self.goal[:, index]]] if not agent.silent else []
            return torch.cat([agent.state.vel, *relative, *seen, *heard], -1)

    return MPEScenario


class Worlds:
    """n worlds of one scenario stepped as one batch; every episode starts all of them from a seed, or, for a
    packed trainer, each of `blocks` equal blocks of them from its own seed (a block is then, world for world,
    a lone batch of n / blocks worlds reset from that seed). `step` takes each agent's choices as one-hots
    (straight-through tensors keep their gradient: the world is differentiable) and returns the team reward
    per world."""

    def __init__(self, n: int, options: WorldOptions):
        import vmas

        self.n, self.options = n, options
        self.roles = SCENARIOS[options.scenario].agents
        self.rng = torch.Generator()
        self.env = vmas.make_env(scenario_class()(), num_envs=n, continuous_actions=True, grad_enabled=True,
                                 options=options, rng=self.rng)
        self.obs: list[torch.Tensor] = []
        self.t = 0

    def reset(self, seed: int | Sequence[int]) -> list[torch.Tensor]:
        """Every world from `seed`, or block b of the batch from seed[b]; the agents' observations.

        Resets VMAS's World directly, as its Environment.reset does (`reference_reset`, tested equal), without
        the Environment's swap of the global RNG states."""
        seeds = [seed] if isinstance(seed, int) else list(seed)
        if not seeds or self.n % len(seeds):
            raise ValueError(f"{self.n} worlds do not split into {len(seeds)} equal blocks")
        scenario = self.env.scenario
        scenario.seeds = seeds
        scenario.env_reset_world_at(None)
        self.obs = [scenario.observation(agent) for agent in self.env.world.agents]
        self.t = 0
        return self.obs

    def reference_reset(self, seed: int) -> list[torch.Tensor]:
        """The same reset through VMAS's Environment.reset."""
        self.env.scenario.seeds = [seed]
        self.obs = self.env.reset()
        self.t = 0
        return self.obs

    @property
    def goal(self) -> torch.Tensor:
        """(n, agents that see a goal) landmark indices."""
        return self.env.scenario.goal

    def _move(self, role: AgentRole, choice: dict[str, torch.Tensor]) -> torch.Tensor:
        return choice["move"] @ (MOVES * self.options.force) if role.moves else torch.zeros(self.n, 2)

    def step(self, choices: list[dict[str, torch.Tensor]]) -> torch.Tensor:
        """Each agent's {part: (n, size) one-hot} -> team reward (n,).

        Steps VMAS's World directly, as its Environment.step does for these scenarios, without the Environment's
        per-step checks and its swap of the global RNG states (`local_seed`, which nothing here draws from):
        about a third of an episode's CPU (bench/bench_vmas.py). `reference_step` is the Environment's path;
        tests/test_vmas_domain.py holds the two equal."""
        world, scenario = self.env.world, self.env.scenario
        for agent, role, choice in zip(world.agents, self.roles, choices):
            agent.action.u = self._move(role, choice)
            if role.words:
                agent.action.c = choice["say"]
            scenario.env_process_action(agent)  # the action's force (its dynamics)
        world.step()
        reward = scenario.reward(world.agents[0])
        self.obs = [scenario.observation(agent) for agent in world.agents]
        self.t += 1
        return reward

    def reference_step(self, choices: list[dict[str, torch.Tensor]]) -> torch.Tensor:
        """The same step through VMAS's Environment.step."""
        actions = [torch.cat([self._move(role, choice), *([choice["say"]] if role.words else [])], -1)
                   for role, choice in zip(self.roles, choices)]
        self.obs, rewards, _, _ = self.env.step(actions)
        self.t += 1
        return rewards[0]
