"""The agents and landmarks of the VMAS domains' scenarios, without torch (the cards read them): which agents
move, which speak and how many words, what each sees. The worlds themselves: world.py."""

from __future__ import annotations

from dataclasses import dataclass

N_MOVES, LANDMARKS = 5, 3  # mpe2's moves: stay, −x, +x, −y, +y


@dataclass(frozen=True)
class AgentRole:
    """One agent of a scenario: whether it moves (mpe2's 5 moves), how many words it says (0: silent), the width
    of its observation, and whether that observation stays the same for a whole episode (a packed trainer then
    runs its network once an episode, not once a step)."""

    name: str
    moves: bool
    words: int
    obs: int
    static: bool = False

    @property
    def parts(self) -> tuple[tuple[str, int], ...]:
        """Its choices each step, in order: ("move", 5) and/or ("say", words)."""
        return ((("move", N_MOVES),) if self.moves else ()) + ((("say", self.words),) if self.words else ())


@dataclass(frozen=True)
class Scenario:
    agents: tuple[AgentRole, ...]
    colours: tuple[tuple[float, float, float], ...]  # the landmarks', mpe2's values
    rewards: tuple[str, ...]  # the reward options, mpe2's first


SCENARIOS = {
    "speaker_listener": Scenario(
        agents=(AgentRole("speaker_0", moves=False, words=3, obs=3, static=True),  # sees its goal's colour only
                AgentRole("listener_0", moves=True, words=0, obs=2 + 2 * LANDMARKS + 3)),
        colours=((0.65, 0.15, 0.15), (0.15, 0.65, 0.15), (0.15, 0.15, 0.65)), rewards=("dist2", "dist")),
    "reference": Scenario(
        agents=(AgentRole("agent_0", moves=True, words=10, obs=2 + 2 * LANDMARKS + 3 + 10),
                AgentRole("agent_1", moves=True, words=10, obs=2 + 2 * LANDMARKS + 3 + 10)),
        colours=((0.75, 0.25, 0.25), (0.25, 0.75, 0.25), (0.25, 0.25, 0.75)), rewards=("dist",)),
}
