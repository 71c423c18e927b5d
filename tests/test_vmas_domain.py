"""The VMAS domains (speaker–listener, reference): their worlds against mpe2's, learning through the
differentiable world, the word figures a base is accepted on, and the domains set aside without the extra. (The contract and one cell of each
method: tests/test_domain_registry.py, parametrised over every registered domain.)"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F

pytest.importorskip("vmas")

from asp_dist.core.registry import get_domain  # noqa: E402
from asp_dist.domains.vmas import game  # noqa: E402
from asp_dist.domains.vmas.scenarios import SCENARIOS  # noqa: E402
from asp_dist.domains.vmas.world import MOVES, Worlds, WorldOptions  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402

NAME = "vmas_speaker_listener"


REF = "vmas_reference"


def smoke(domain: str = NAME, **knobs) -> CellSpec:
    return CellSpec(domain=domain, method="osp", **{**get_domain(domain).smoke, **knobs}).resolved()


def one_hots(word: int, move: int, words: int = 3) -> list[dict[str, torch.Tensor]]:
    """A speaker's word and a listener's move, as Worlds.step takes them."""
    return [{"say": F.one_hot(torch.tensor([word]), words).float()},
            {"move": F.one_hot(torch.tensor([move]), 5).float()}]


def vmas_at_mpe2_state(raw, seed: int, options: WorldOptions) -> Worlds:
    """One VMAS world with every agent and landmark where mpe2's world `raw` has it (agents at rest, as after
    reset)."""
    world = Worlds(1, options)
    world.reset(seed)
    for vmas_entity, mpe_entity in zip(world.env.world.agents + world.env.world.landmarks,
                                       raw.agents + raw.landmarks):
        vmas_entity.set_pos(torch.tensor(mpe_entity.state.p_pos, dtype=torch.float32).view(1, 2), batch_index=None)
    return world


def assert_moved_as_in_mpe2(state, mpe_state, obs: torch.Tensor, mpe_obs) -> torch.Tensor:
    """A moving agent after the same step in both: the same velocity, its position apart by dt × velocity, its
    observation's velocity and landmarks (relative to it, so apart by the same) as mpe2's. Its velocity."""
    vel = torch.tensor(mpe_state.p_vel, dtype=torch.float32)
    assert torch.allclose(state.vel[0], vel, atol=1e-5)
    assert torch.allclose(state.pos[0], torch.tensor(mpe_state.p_pos, dtype=torch.float32) + 0.1 * vel, atol=1e-5)
    assert torch.allclose(obs[:2], vel, atol=1e-5)
    assert torch.allclose(obs[2:8], torch.tensor(mpe_obs[2:8]) - 0.1 * vel.repeat(3), atol=1e-5)
    return vel


def test_the_world_steps_as_mpe2s_from_the_same_state():
    """From mpe2's reset state, with the same moves and words, every step gives the same velocity, heard word
    and goal colour, and VMAS's position is mpe2's plus dt × velocity (its integrator moves with the new
    velocity, mpe2's with the old: from rest the two differ by exactly that). The reward is −distance² of
    each one's own position."""
    pytest.importorskip("mpe2")
    from mpe2 import simple_speaker_listener_v4

    mpe = simple_speaker_listener_v4.parallel_env(max_cycles=25)
    rng = np.random.default_rng(0)
    for seed in range(3):
        mpe.reset(seed=seed)
        raw = mpe.unwrapped.world
        goal = [i for i, lm in enumerate(raw.landmarks) if lm is raw.agents[0].goal_b][0]
        world = vmas_at_mpe2_state(raw, seed, WorldOptions())
        vm = world.env.world
        world.env.scenario.goal[:] = goal  # (1, 1): the speaker's
        for _ in range(25):
            move, word = int(rng.integers(5)), int(rng.integers(3))
            obs, rew, *_ = mpe.step({"speaker_0": word, "listener_0": move})
            reward = world.step(one_hots(word, move))
            listener, mpe_listener = vm.agents[1].state, raw.agents[1].state
            assert_moved_as_in_mpe2(listener, mpe_listener, world.obs[1][0], obs["listener_0"])
            assert torch.equal(world.obs[1][0, -3:], torch.tensor(obs["listener_0"][-3:]))  # the heard word
            assert torch.allclose(world.obs[0][0], torch.tensor(obs["speaker_0"]))  # the goal's colour
            goal_pos = vm.landmarks[goal].state.pos[0]
            assert math.isclose(float(reward[0]), -float((listener.pos[0] - goal_pos).pow(2).sum()), rel_tol=1e-5)
            assert math.isclose(rew["listener_0"], -float(np.sum((mpe_listener.p_pos - raw.landmarks[goal].state.p_pos)
                                                                 ** 2)), rel_tol=1e-9)


def test_the_reference_world_steps_as_mpe2s_from_the_same_state():
    """mpe2's simple_reference (both agents move and speak, Discrete(50) = move + 5 × word): the same velocities,
    heard words and goal colours, positions apart by dt × velocity, and the team reward (the sum of both agents')
    −distance of each partner to the goal its agent sees, at each one's own positions."""
    pytest.importorskip("mpe2")
    from mpe2 import simple_reference_v3

    mpe = simple_reference_v3.parallel_env(max_cycles=25)
    rng = np.random.default_rng(1)
    for seed in range(2):
        mpe.reset(seed=seed)
        raw = mpe.unwrapped.world
        goals = [[j for j, lm in enumerate(raw.landmarks) if lm is agent.goal_b][0] for agent in raw.agents]
        world = vmas_at_mpe2_state(raw, seed, WorldOptions(scenario="reference"))
        vm = world.env.world
        world.env.scenario.goal[0] = torch.tensor(goals)
        for _ in range(25):
            moves, words = rng.integers(5, size=2), rng.integers(10, size=2)
            obs, rew, *_ = mpe.step({f"agent_{i}": int(moves[i] + 5 * words[i]) for i in range(2)})
            reward = world.step([{"move": F.one_hot(torch.tensor([int(moves[i])]), 5).float(),
                                  "say": F.one_hot(torch.tensor([int(words[i])]), 10).float()} for i in range(2)])
            for i in range(2):
                assert_moved_as_in_mpe2(vm.agents[i].state, raw.agents[i].state, world.obs[i][0], obs[f"agent_{i}"])
                assert torch.allclose(world.obs[i][0, 8:], torch.tensor(obs[f"agent_{i}"][8:]))  # colour, word
            mine = -sum(float((vm.agents[1 - i].state.pos[0] - vm.landmarks[goals[i]].state.pos[0]).norm())
                        for i in range(2))
            assert math.isclose(float(reward[0]), mine, rel_tol=1e-5)
            theirs = -sum(float(np.linalg.norm(raw.agents[1 - i].state.p_pos - raw.landmarks[goals[i]].state.p_pos))
                          for i in range(2))
            assert math.isclose(rew["agent_0"] + rew["agent_1"], theirs, rel_tol=1e-9)


@pytest.mark.parametrize("channel, width", [("say", 10), ("move", 5)])
def test_a_reference_agent_has_either_part_as_its_channel(channel, width):
    spec = smoke(REF, vmas_reference_channel=channel)
    domain = get_domain(REF)
    base, _ = domain.train_base(spec, seed=1)
    assert domain.unpaired(spec, base, 30, torch.Generator().manual_seed(0))["channel"].shape == (30, width)
    p = domain.paired(spec, base, 4, torch.Generator().manual_seed(0))
    assert p["obs"].shape == (4, 21) and p["action"].shape == (4, 2)  # both of its choices
    metrics = domain.evaluate(spec, base, domain.new_agents(spec, 2), torch.Generator().manual_seed(1))
    assert set(metrics) == set(domain.metrics) and all(math.isfinite(v) for v in metrics.values())


@pytest.mark.parametrize("grad", [False, True])
def test_the_direct_step_is_vmass_environment_step(grad):
    """Worlds.step (VMAS's World stepped directly) gives what Environment.step gives: observations, rewards and
    gradients, over a whole episode of straight-through choices."""
    team = game.new_agents(smoke(), 0)
    out = []
    for step in ("step", "reference_step"):
        world, gen = Worlds(8, WorldOptions()), torch.Generator().manual_seed(1)
        obs, total = world.reset(4), 0.0
        with torch.set_grad_enabled(grad):
            for _ in range(25):
                word = game.choose(team.agent(0)(obs[0]), gen)[0]
                move = game.choose(team.agent(1)(obs[1]), gen)[0]
                total = total + getattr(world, step)([{"say": word}, {"move": move}])
                obs = world.obs
        grads = torch.autograd.grad(total.sum(), list(team.parameters())) if grad else []
        out.append((total.detach(), [o.detach() for o in obs], grads))
    (a, obs_a, grad_a), (b, obs_b, grad_b) = out
    assert torch.equal(a, b) and all(torch.equal(x, y) for x, y in zip(obs_a, obs_b))
    assert all(torch.allclose(x, y, rtol=1e-6, atol=1e-9) for x, y in zip(grad_a, grad_b))


def test_options_where_vmas_differs_from_mpe2():
    one_goal = Worlds(64, WorldOptions(goal_per_world=False))
    one_goal.reset(3)
    assert one_goal.goal.unique().numel() == 1  # VMAS's own scenario: one goal for the batch
    per_world = Worlds(64, WorldOptions())
    per_world.reset(3)
    assert per_world.goal.unique().numel() == 3
    for force in (5.0, 1.0):  # mpe2's listener is 5 times VMAS's
        w = Worlds(2, WorldOptions(force=force))
        w.reset(0)
        w.step([{"say": torch.zeros(2, 3)}, {"move": F.one_hot(torch.tensor([2, 4]), 5).float()}])
        assert torch.allclose(w.env.world.agents[1].state.vel, MOVES[[2, 4]] * force * 0.1)
    dist = Worlds(4, WorldOptions(reward="dist"))
    dist.reset(1)
    reward = dist.step([{"say": torch.zeros(4, 3)}, {"move": torch.zeros(4, 5)}])
    goals = torch.stack([lm.state.pos for lm in dist.env.world.landmarks], 1)[torch.arange(4), dist.goal[:, 0]]
    assert torch.allclose(reward, -2 * (dist.env.world.agents[1].state.pos - goals).norm(dim=-1))


def test_an_episode_starts_every_world_afresh_from_its_seed():
    spec = smoke()
    team = game.new_agents(spec, 0)
    a = game.play(spec, list(team.actors), 8, 5, torch.Generator().manual_seed(1))
    b = game.play(spec, list(team.actors), 8, 5, torch.Generator().manual_seed(1))
    assert torch.equal(a.returns, b.returns) and torch.equal(a.words[0], b.words[0])
    world = game.worlds(8, game.options(spec))
    world.reset(5)
    assert torch.equal(world.obs[1][:, -3:], torch.zeros(8, 3))  # no word heard from the last episode
    assert torch.equal(world.obs[1][:, :2], torch.zeros(8, 2))  # at rest


@pytest.mark.parametrize("scenario", sorted(SCENARIOS))
@pytest.mark.parametrize("goal_per_world", [True, False])
def test_a_reset_is_vmass_and_each_block_of_a_packed_batch_is_its_own_lone_batch(scenario, goal_per_world):
    """Worlds.reset (VMAS's World reset directly) gives what Environment.reset gives; a batch reset block by block
    from one seed each (a packed trainer's) holds, block for block, the worlds of lone batches from those seeds."""
    options = WorldOptions(scenario=scenario, goal_per_world=goal_per_world)
    direct, through_env, packed = Worlds(8, options), Worlds(8, options), Worlds(24, options)
    lone = direct.reset(5)
    assert all(torch.equal(a, b) for a, b in zip(lone, through_env.reference_reset(5)))
    assert torch.equal(direct.goal, through_env.goal)
    blocks = packed.reset([7, 5, 9])
    assert all(torch.equal(a[8:16], b) for a, b in zip(blocks, lone)) and torch.equal(packed.goal[8:16], direct.goal)
    with pytest.raises(ValueError, match="equal blocks"):
        packed.reset([1, 2, 3, 4, 5])


@pytest.mark.parametrize("domain", [NAME, REF])
def test_an_agent_declared_static_sees_the_same_all_episode(domain):
    """AgentRole.static (a packed trainer runs such an agent's network once an episode): its observations over an
    episode are equal step for step; a moving agent's are not."""
    spec = smoke(domain, **{f"{domain}_episode_len": 8})
    team = game.new_agents(spec, 0)
    for index, agent in enumerate(game.roles(spec)):
        seen = game.play(spec, list(team.actors), 16, 3, torch.Generator().manual_seed(0), record=index).role_obs
        assert all(torch.equal(o, seen[0]) for o in seen) == agent.static, agent.name


def test_the_return_reaches_the_speaker_through_the_world():
    """The speaker's weights get a gradient from the team's return alone: through its straight-through word,
    the heard word in the listener's observation and the listener's move, whose force moves the listener."""
    spec = smoke(vmas_speaker_listener_entropy=0.0)
    team = game.new_agents(spec, 1)
    episode = game.play(spec, list(team.actors), 16, 2, torch.Generator().manual_seed(0))
    game.team_loss(spec, episode).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in team.agent(0).parameters())
    with torch.no_grad():
        silent = game.play(spec, list(team.actors), 16, 2, torch.Generator().manual_seed(0))
    assert torch.equal(silent.returns, episode.returns.detach())  # the gradient changes nothing forward


@pytest.mark.parametrize("domain, role", [(NAME, "listener_0"), (NAME, "speaker_0"), (REF, "agent_1")])
def test_the_adversarys_outputs_train_the_new_agent_alone(domain, role):
    """Self-play's channel outputs carry gradient into the new agent's actor only: not, through the world and
    the heard words, into its partner (nor into its own earlier steps), as in the PettingZoo adapter."""
    spec = smoke(domain, **{f"{domain}_new_agent": role})
    agents = get_domain(domain).new_agents(spec, 1)
    outputs = get_domain(domain).self_play_step(spec, agents, {}, torch.Generator().manual_seed(0)).outputs
    (outputs["channel"] * torch.randn(outputs["channel"].shape, generator=torch.Generator().manual_seed(1))).sum().backward()
    index = game.role(spec)[0]
    for i, actor in enumerate(agents.actors):
        grads = [p.grad for p in actor.parameters()]
        if i == index:
            assert all(g is not None and g.abs().sum() > 0 for g in grads)
        else:
            assert all(g is None or g.abs().sum() == 0 for g in grads)


def test_word_figures_read_a_code_and_its_use():
    goal = torch.tensor([0, 1, 2, 0, 1, 2])
    assert math.isclose(game.word_mi(goal, goal.expand(4, 6)), math.log(3), rel_tol=1e-9)  # a perfect code
    assert game.word_mi(goal, torch.zeros(4, 6, dtype=torch.long)) == 0.0  # one word for every goal
    assert math.isclose(game.word_mi(goal, torch.tensor([[0, 0, 1, 0, 0, 1]])), math.log(3) - 2 / 3 * math.log(2),
                        rel_tol=1e-9)  # two goals share a word


@pytest.mark.parametrize("drop, bar, score", [(2.0, 3.0, game.UNUSED_WORDS), (2.0, 1.0, 0.8), (-0.5, 0.0, 0.8)])
def test_a_base_scores_its_words_mi_only_when_the_listener_uses_them(monkeypatch, drop, bar, score):
    monkeypatch.setattr(game, "word_figures", lambda spec, team, gen: (0.8, drop))
    assert get_domain(NAME).train_base(smoke(vmas_speaker_listener_accept_drop=bar), seed=3)[1] == score


def test_rows_carry_the_bases_word_figures():
    spec = smoke()
    domain = get_domain(NAME)
    base, _ = domain.train_base(spec, seed=1)
    agents = domain.new_agents(spec, 2)
    metrics = domain.evaluate(spec, base, agents, torch.Generator().manual_seed(4))
    mi, drop = game.word_figures(spec, base, torch.Generator().manual_seed(4))
    assert metrics["base_word_mi"] == mi and metrics["base_word_drop"] == pytest.approx(drop)
    assert set(metrics) == set(domain.metrics)


@pytest.mark.parametrize("role, width", [("listener_0", 5), ("speaker_0", 3)])
def test_the_channel_is_the_new_agents_choice(role, width):
    spec = smoke(vmas_speaker_listener_new_agent=role)
    domain = get_domain(NAME)
    base, _ = domain.train_base(spec, seed=1)
    u = domain.unpaired(spec, base, 40, torch.Generator().manual_seed(0))["channel"]
    assert u.shape == (40, width) and ((u == 0) | (u == 1)).all() and torch.equal(u.sum(-1), torch.ones(40))
    p = domain.paired(spec, base, 5, torch.Generator().manual_seed(0))
    assert p["obs"].shape == (5, 3 if role == "speaker_0" else 11) and p["action"].max() < width


MISSING = """
import sys
sys.modules["vmas"] = None  # as if the extra were not installed
from asp_dist.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_without_the_extra_the_domain_is_set_aside_with_one_line():
    check = subprocess.run([sys.executable, "-c", MISSING, "check-domain", NAME], capture_output=True, text=True,
                           timeout=120)
    assert check.returncode == 2, check.stderr
    assert check.stderr.count("\n") == 1 and "pip install 'asp-dist[vmas]'" in check.stderr


@pytest.mark.parametrize("knobs, message", [
    ({"new_agent": "critic"}, "vmas_speaker_listener_new_agent must be one of"),
    ({"reward": "distance"}, "vmas_speaker_listener_reward must be one of"),
    ({"force": 0.0}, "vmas_speaker_listener_force must be > 0"),
    ({"episode_len": 0}, "vmas_speaker_listener_episode_len must be >= 1"),
    ({"base_worlds": 0}, "vmas_speaker_listener_base_worlds must be >= 1"),
])
def test_bad_input_is_one_line_at_resolution(knobs, message):
    from asp_dist.errors import SpecError

    with pytest.raises(SpecError, match=message) as err:
        CellSpec(domain=NAME, method="asp", paired=2, **{f"{NAME}_{k}": v for k, v in knobs.items()}).resolved()
    assert "\n" not in str(err.value)
