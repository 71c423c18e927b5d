"""MPE's speaker–listener on VMAS's vectorized, differentiable simulator: the scenario and a batch of worlds.

VMAS 1.5.2's own `simple_speaker_listener` differs from mpe2's `simple_speaker_listener_v4` (measured,
docs/decisions/0060-words-through-a-differentiable-world.md); this scenario matches mpe2 by default, each
difference an option:

  goal per world       VMAS draws one goal for the whole batch; here every world draws its own (goal_per_world)
  reward               mpe2: −distance² (reward = "dist2"); VMAS: −2·distance ("dist", its sum over two agents)
  listener force       mpe2 multiplies a move by 5 (force); VMAS's discrete moves by 1
  actions              mpe2: listener 5 moves (stay, −x, +x, −y, +y), speaker 3 words; VMAS: 9 moves, and 27
                       speaker actions. Here the agents choose among mpe2's sets and the batch feeds VMAS the
                       continuous action they mean (a force, a one-hot word), so gradients can pass through.
  episode              25 steps, then every world resets (VMAS's episodes never end unless told)

Kept from VMAS, not mpe2: the integrator. VMAS updates the velocity first and moves with the new one
(semi-implicit Euler); mpe2 moves with the old velocity. From one state and one action both reach the same
velocity, and VMAS's position is mpe2's plus dt·(new velocity − old) (tests/test_vmas_domain.py).

Resets draw from the batch's own torch.Generator (VMAS's scenarios use the global RNG; this one does not), so
a seed reproduces every world.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

COLOURS = torch.tensor([[0.65, 0.15, 0.15], [0.15, 0.65, 0.15], [0.15, 0.15, 0.65]])  # mpe2's landmark colours
MOVES = torch.tensor([[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])  # mpe2's discrete moves
WORDS, N_MOVES, LANDMARKS = 3, 5, 3
SPEAKER_OBS, LISTENER_OBS = 3, 2 + 2 * LANDMARKS + WORDS  # colour | velocity, landmarks relative, heard word
REWARDS = ("dist2", "dist")


@dataclass(frozen=True)
class WorldOptions:
    """Where this world may differ from mpe2's (defaults: as mpe2)."""

    goal_per_world: bool = True
    force: float = 5.0
    reward: str = "dist2"
    episode_len: int = 25


def scenario_class():
    """The VMAS scenario (imports vmas: only when a world is built)."""
    from vmas.simulator.core import Agent, Landmark, Sphere, World
    from vmas.simulator.scenario import BaseScenario

    class SpeakerListener(BaseScenario):
        def make_world(self, batch_dim: int, device: torch.device, **kwargs):
            self.options: WorldOptions = kwargs.pop("options")
            self.rng: torch.Generator = kwargs.pop("rng")
            world = World(batch_dim=batch_dim, device=device, dim_c=WORDS, dt=0.1, drag=0.25)
            world.add_agent(Agent(name="speaker_0", collide=False, movable=False, silent=False, shape=Sphere(0.075)))
            world.add_agent(Agent(name="listener_0", collide=False, movable=True, silent=True, shape=Sphere(0.075),
                                  u_range=self.options.force))
            for i in range(LANDMARKS):
                world.add_landmark(Landmark(name=f"landmark {i}", collide=False, shape=Sphere(0.04)))
            self.goal = torch.zeros(batch_dim, dtype=torch.long)
            return world

        def reset_world_at(self, env_index: int | None = None):
            n = self.world.batch_dim if env_index is None else 1
            draw = n if self.options.goal_per_world else 1
            goal = torch.randint(0, LANDMARKS, (draw,), generator=self.rng).expand(n)
            if env_index is None:
                self.goal = goal.clone()
            else:
                self.goal[env_index] = goal[0]
            for entity in self.world.agents + self.world.landmarks:
                entity.set_pos(torch.rand(n, 2, generator=self.rng) * 2 - 1, batch_index=env_index)
                if entity.movable:
                    entity.set_vel(torch.zeros(n, 2), batch_index=env_index)

        def reward(self, agent):
            if agent is self.world.agents[0]:  # one team reward per step, computed once
                goals = torch.stack([lm.state.pos for lm in self.world.landmarks], 1)
                delta = self.world.agents[1].state.pos - goals[torch.arange(self.world.batch_dim), self.goal]
                square = delta.pow(2).sum(-1)
                self.team_reward = -square if self.options.reward == "dist2" else -2 * square.sqrt()
            return self.team_reward

        def observation(self, agent):
            if agent is self.world.agents[0]:
                return COLOURS[self.goal]
            relative = [lm.state.pos - agent.state.pos for lm in self.world.landmarks]
            return torch.cat([agent.state.vel, *relative, self.world.agents[0].state.c], -1)

    return SpeakerListener


class Worlds:
    """n speaker–listener worlds stepped as one batch; every episode starts all of them from a seed.
    `step` takes each agent's one-hot choice (straight-through tensors keep their gradient: the world is
    differentiable) and returns the team reward per world."""

    def __init__(self, n: int, options: WorldOptions):
        import vmas

        self.n, self.options = n, options
        self.rng = torch.Generator()
        self.env = vmas.make_env(scenario_class()(), num_envs=n, continuous_actions=True, grad_enabled=True,
                                 options=options, rng=self.rng)
        self.obs: list[torch.Tensor] = []
        self.t = 0

    def reset(self, seed: int) -> list[torch.Tensor]:
        self.rng.manual_seed(seed)
        self.obs = self.env.reset()
        self.t = 0
        return self.obs

    @property
    def goal(self) -> torch.Tensor:
        return self.env.scenario.goal

    def step(self, word: torch.Tensor, move: torch.Tensor) -> torch.Tensor:
        """word (n, 3) and move (n, 5) one-hot (or straight-through) choices -> team reward (n,).

        Steps VMAS's World directly, as its Environment.step does for this scenario, without the Environment's
        per-step checks and its swap of the global RNG states (`local_seed`, which nothing here draws from):
        about a third of an episode's CPU (bench/bench_vmas.py). `reference_step` is the Environment's path;
        tests/test_vmas_domain.py holds the two equal."""
        world, scenario = self.env.world, self.env.scenario
        speaker, listener = world.agents
        speaker.action.u = torch.zeros(self.n, 2)  # the speaker does not move
        speaker.action.c = word
        listener.action.u = move @ (MOVES * self.options.force)
        for agent in world.agents:
            scenario.env_process_action(agent)  # the action's force (its dynamics)
        world.step()
        reward = scenario.reward(speaker)
        self.obs = [scenario.observation(speaker), scenario.observation(listener)]
        self.t += 1
        return reward

    def reference_step(self, word: torch.Tensor, move: torch.Tensor) -> torch.Tensor:
        """The same step through VMAS's Environment.step."""
        speaker = torch.cat([torch.zeros(self.n, 2), word], -1)
        self.obs, rewards, _, _ = self.env.step([speaker, move @ (MOVES * self.options.force)])
        self.t += 1
        return rewards[0]
