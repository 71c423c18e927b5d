"""Our particle speaker-listener world next to MPE's simple_speaker_listener_v4 (the Farama Foundation's mpe2
package, through PettingZoo's parallel API), compared where the two coincide.

    pip install -e ".[pettingzoo]"     # pettingzoo and mpe2 at the versions pinned in pyproject.toml
    python scripts/compare_mpe.py      # --episodes 10 --steps 40 --seed 0; --trace: every step of episode 0

What coincides: one moving agent on a plane (our actor, MPE's listener_0), one target (MPE's goal landmark),
five discrete moves (stay, +-x, +-y), and a per-step reward that is a function of the agent's distance to the
target, shared by speaker and listener. The script puts MPE's world in our world's state (listener at our
actor's position and at rest, the goal landmark on our target), plays the same moves in both, and prints the
largest absolute difference per quantity. What differs in kind (messages, what each agent observes, physics,
episode length, landmark count, reward shaping) is listed as such, with MPE's side read from its objects,
and not forced into a number.

Exit status 0 whenever it runs to the end, whatever the differences; non-zero only on a crash.
docs/mpe-comparison.md records its output and explains every difference.
"""

from __future__ import annotations

import argparse
import datetime
import inspect
import platform
from importlib.metadata import version

import numpy as np
import torch

try:
    from mpe2 import simple_speaker_listener_v4 as mpe_ssl
except ImportError as exc:  # the only way this script stops early: it has nothing to compare against
    raise SystemExit(f"compare_mpe: {exc}; install the extra first: pip install -e '.[pettingzoo]'") from exc

from asp_dist.domains.particles import ParticlesDomain
from asp_dist.domains.particles.game import BOX, MOVES, N_ACTIONS, NEAR, NEAR_REWARD, TARGET_BOX, env_step, spawn
from asp_dist.machine import cpu_model

OURS = {knob.name: knob.default for knob in ParticlesDomain.knobs}  # our defaults (episode length, message width)
SPEAKER, LISTENER = "speaker_0", "listener_0"
# Our move index -> MPE's discrete listener action that pushes the same way.
# Ours (game.MOVES): 0 stay, 1 +x, 2 -x, 3 +y, 4 -y.  MPE: 0 no_action, 1 -x, 2 +x, 3 -y, 4 +y.
# The "move direction" row below measures that this table is right.
OURS_TO_MPE = np.array([0, 2, 1, 4, 3])


class MaxDiff:
    """The largest absolute difference seen per quantity, with where it was seen."""

    def __init__(self) -> None:
        self.rows: dict[str, list] = {}

    def add(self, name: str, ours, theirs, where: str, note: str = "") -> None:
        diff = float(np.max(np.abs(np.asarray(ours, dtype=np.float64) - np.asarray(theirs, dtype=np.float64))))
        row = self.rows.setdefault(name, [0.0, "", note, 0])
        row[3] += 1
        if diff > row[0] or not row[1]:
            row[0], row[1] = diff, where

    def print(self, title: str) -> None:
        print(f"\n{title}")
        print(f"  {'quantity':<58} {'max |diff|':>11}  {'at':<12} {'n':>5}  note")
        for name, (diff, where, note, n) in self.rows.items():
            where = where if diff else "-"
            print(f"  {name:<58} {diff:>11.3g}  {where:<12} {n:>5}  {note}".rstrip())


def our_reward_from_distance(d: float) -> float:
    return NEAR_REWARD if d < NEAR else 1.0 / d


def put_mpe_in_our_state(env, pos: np.ndarray, target: np.ndarray) -> int:
    """Listener at our actor's position and at rest; MPE's goal landmark (drawn by its reset) on our target.
    The two other landmarks stay where MPE's reset put them: nothing in our world corresponds to them.
    Returns the goal landmark's index."""
    world = env.unwrapped.world
    listener = world.agents[1]
    listener.state.p_pos = np.asarray(pos, dtype=np.float64).copy()
    listener.state.p_vel = np.zeros(world.dim_p)
    goal = world.agents[0].goal_b
    goal.state.p_pos = np.asarray(target, dtype=np.float64).copy()
    return next(i for i, landmark in enumerate(world.landmarks) if landmark is goal)


def header() -> None:
    print("Particle world (asp-dist) vs MPE simple_speaker_listener_v4 (mpe2, PettingZoo parallel API)")
    print(f"  date {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC · {cpu_model()} · "
          f"Python {platform.python_version()} · numpy {np.__version__} · torch {torch.__version__} · "
          f"pettingzoo {version('pettingzoo')} · mpe2 {version('mpe2')} · gymnasium {version('gymnasium')}")


def facts(steps: int) -> None:
    """Side by side: what each world is. MPE's column is read from a fresh environment, not typed in."""
    env = mpe_ssl.parallel_env()
    env.reset(seed=0)
    world = env.unwrapped.world
    speaker, listener = world.agents
    default_cycles = inspect.signature(mpe_ssl.raw_env).parameters["max_cycles"].default
    cont = mpe_ssl.parallel_env(continuous_actions=True)
    cont.reset(seed=0)
    # MPE's episode length, measured: step the default environment until it truncates.
    n = 0
    while env.agents:
        env.step({agent: 0 for agent in env.agents})
        n += 1
    width = OURS["particles_message_dim"]
    speaker_obs, listener_obs = cont.observation_space(SPEAKER).shape[0], cont.observation_space(LISTENER).shape[0]
    rows = [
        ("episode length (steps)", f"{OURS['particles_episode_len']}, then the actor re-spawns",
         f"{n} (max_cycles default {default_cycles}), then truncation; this script runs max_cycles={steps}"),
        ("landmarks / targets", "1 target, fixed for a whole trial, in [-4, 4]^2",
         f"{len(world.landmarks)} landmarks, one of them the goal, all re-drawn in [-1, 1]^2 at every reset"),
        ("start of the moving agent", "uniform in [-5, 5]^2, at rest (no velocity)",
         "uniform in [-1, 1]^2, velocity 0"),
        ("speaker observes", "actor's (x, y): 2 numbers", f"goal landmark's colour: {speaker_obs} numbers"),
        ("listener observes", f"the message only: {width} numbers",
         f"own velocity, all landmarks relative to itself, the message: {listener_obs} numbers"),
        ("message (speaker action)", f"continuous, {width}-d, tanh in [-1, 1], heard the same step",
         (f"dim_c={world.dim_c}: {env.action_space(SPEAKER)} one-hot or {cont.action_space(SPEAKER)}, "
          "heard the next step")),
        ("listener action", f"Discrete({N_ACTIONS}): stay, +x, -x, +y, -y, one unit",
         f"{env.action_space(LISTENER)}: no_action, -x, +x, -y, +y (a force) or {cont.action_space(LISTENER)}"),
        ("reward per step (shared)", f"{NEAR_REWARD:g} if distance < {NEAR} else 1/distance",
         "-(distance^2), the same value for both agents"),
        ("dynamics", "position += move, clipped to [-5, 5]^2",
         (f"force -> velocity -> position: dt={world.dt}, damping={world.damping}, mass={listener.mass}, "
          f"accel={listener.accel} (None: 5.0), max_speed={listener.max_speed}, no walls")),
        ("collisions", "none", f"collide={listener.collide} (agents), {world.landmarks[0].collide} (landmarks)"),
        ("speaker moves", "no (it has no body)", f"movable={speaker.movable}"),
    ]
    print("\nThe two worlds (not compared: they differ in kind)")
    print(f"  {'':<28} {'ours':<56} MPE")
    for name, ours, theirs in rows:
        print(f"  {name:<28} {ours:<56} {theirs}")


def impulse_response() -> None:
    """Physics: from rest at (-4, 0), push +x for 8 steps, then stay for 6, in both worlds."""
    env = mpe_ssl.parallel_env(max_cycles=14)
    env.reset(seed=0)
    world = env.unwrapped.world
    start, target = np.array([-4.0, 0.0]), np.array([3.0, 3.0])
    put_mpe_in_our_state(env, start, target)
    pos, target_t = torch.tensor(start[None], dtype=torch.float32), torch.tensor(target, dtype=torch.float32)
    print("\nPhysics: one agent from rest at (-4, 0), +x for 8 steps, then stay for 6 (not compared: "
          "ours moves one unit per step, MPE integrates a force)")
    print(f"  {'step':>4} {'action':>6} {'ours dx':>8} {'MPE dx':>8} {'MPE vx':>8}")
    for t in range(14):
        a = 1 if t < 8 else 0
        old_ours, old_mpe = float(pos[0, 0]), float(world.agents[1].state.p_pos[0])
        pos, _ = env_step(pos, torch.tensor([a]), target_t)
        env.step({SPEAKER: 0, LISTENER: int(OURS_TO_MPE[a])})
        p, v = world.agents[1].state.p_pos, world.agents[1].state.p_vel
        print(f"  {t + 1:>4} {'+x' if a else 'stay':>6} {float(pos[0, 0]) - old_ours:>8.4f} {p[0] - old_mpe:>8.4f} "
              f"{v[0]:>8.4f}")
    print("  MPE: position moves by the velocity of the step before, so a push shows one step later; the speed "
          "tends to accel*dt/damping = 2.0 (0.2 per step) and decays by 0.75 per step once released.")


def run(episodes: int, steps: int, seed: int, trace: bool) -> None:
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    free = MaxDiff()      # both worlds stepped on their own from the same start
    same = MaxDiff()      # MPE's observation and reward functions evaluated on our world's states
    inner = MaxDiff()     # checks within MPE that the comparison relies on
    probe = mpe_ssl.parallel_env(max_cycles=steps)  # a second MPE world, written into at every state of ours
    probe.reset(seed=seed)
    clips = 0             # steps at which the box edge stopped our actor (MPE has no walls)
    rewards = {"ours": [], "MPE": []}  # per-step rewards on the same states, for their ranges
    for ep in range(episodes):
        target_t = (torch.rand(2, generator=gen) * 2 - 1) * TARGET_BOX  # as target_for draws it, seeded here
        pos_t = spawn(1, gen)                                            # our start, as in training
        target, start = target_t.double().numpy(), pos_t[0].double().numpy()
        disc = mpe_ssl.parallel_env(max_cycles=steps)
        cont = mpe_ssl.parallel_env(max_cycles=steps, continuous_actions=True)
        disc.reset(seed=seed + ep)
        cont.reset(seed=seed + ep)
        goal = put_mpe_in_our_state(disc, start, target)
        put_mpe_in_our_state(cont, start, target)
        lis_d, lis_c = disc.unwrapped.world.agents[1], cont.unwrapped.world.agents[1]
        world = disc.unwrapped.world
        accel = lis_d.accel if lis_d.accel is not None else 5.0  # simple_env's default sensitivity
        ret_ours = ret_mpe = 0.0
        if trace and ep == 0:
            print(f"\nEpisode 0, step by step (target {target.round(3)}, MPE goal landmark {goal})")
            print(f"  {'t':>3} {'a':>2} {'ours x':>8} {'ours y':>8} {'MPE x':>8} {'MPE y':>8} "
                  f"{'ours r':>8} {'MPE r':>9}")
        for t in range(1, steps + 1):
            where = f"ep {ep} t {t}"
            a = int(rng.integers(N_ACTIONS))
            word = int(rng.integers(world.dim_c))                 # discrete speaker: one of 3 symbols
            message = rng.random(world.dim_c).astype(np.float32)  # continuous speaker: Box(0, 1, (3,))
            vel_before = lis_d.state.p_vel.copy()
            clipped = bool((torch.abs(pos_t + MOVES[a]) > BOX).any())
            pos_t, r_t = env_step(pos_t, torch.tensor([a]), target_t)
            one_hot = np.zeros(5, dtype=np.float32)
            one_hot[OURS_TO_MPE[a]] = 1.0
            obs, rew, _, trunc, _ = disc.step({SPEAKER: word, LISTENER: int(OURS_TO_MPE[a])})
            obs_c, _, _, _, _ = cont.step({SPEAKER: message, LISTENER: one_hot})
            pos, r = pos_t[0].double().numpy(), float(r_t[0])
            ret_ours += r
            ret_mpe += rew[LISTENER]

            # Free run: both worlds from the same start under the same moves.
            # MPE's listener observation: [own velocity (2), offsets of the 3 landmarks (6), the message (3)].
            free.add("listener position (x, y)", pos, lis_d.state.p_pos, where, "physics differ")
            free.add("distance to target", np.linalg.norm(pos - target),
                     np.linalg.norm(lis_d.state.p_pos - target), where)
            free.add("reward, ours vs MPE (raw)", r, rew[LISTENER], where, "different definitions")
            free.add("listener obs: goal relative position vs target - ours", target - pos,
                     obs[LISTENER][2 + 2 * goal: 4 + 2 * goal], where, "our listener does not observe it")
            if t == steps:
                free.add("episode return, ours vs MPE", ret_ours, ret_mpe, where)
            clips += clipped

            # The same state: our state written into MPE, MPE's own functions evaluated on it.
            g = put_mpe_in_our_state(probe, pos, target)
            lw = probe.unwrapped.world
            p_obs = probe.unwrapped.observe(LISTENER)
            p_rew = float(probe.unwrapped.scenario.reward(lw.agents[1], lw))
            d_mpe = float(np.sqrt(-p_rew))
            rewards["ours"].append(r)
            rewards["MPE"].append(p_rew)
            same.add("listener obs: goal relative position vs target - ours", target - pos,
                     p_obs[2 + 2 * g: 4 + 2 * g], where, "MPE observations are float32")
            same.add("distance: sqrt(-MPE reward) vs ours", np.linalg.norm(pos - target), d_mpe, where)
            same.add("reward: ours recomputed from MPE's distance vs ours", r, our_reward_from_distance(d_mpe), where,
                     "same distance, different shaping")
            same.add("reward, ours vs MPE (raw)", r, p_rew, where, "10 or 1/d vs -d^2")
            same.add("speaker reward vs listener reward", float(probe.unwrapped.scenario.reward(lw.agents[0], lw)),
                     p_rew, where, "shared in both worlds")

            # Within MPE: what the comparison takes for granted.
            push = (lis_d.state.p_vel - (1 - world.damping) * vel_before) * lis_d.mass / (world.dt * accel)
            inner.add("move direction: force recovered from MPE velocity vs ours", MOVES[a].numpy(), push, where,
                      "checks OURS_TO_MPE")
            inner.add("speaker reward vs listener reward (from step)", rew[SPEAKER], rew[LISTENER], where)
            inner.add("continuous one-hot listener vs discrete: position", lis_c.state.p_pos, lis_d.state.p_pos, where)
            inner.add("listener obs after step t: comm vs discrete word of t", obs[LISTENER][-world.dim_c:],
                      np.eye(world.dim_c)[word], where, "heard at step t+1")
            inner.add("listener obs after step t: comm vs continuous message of t", obs_c[LISTENER][-world.dim_c:],
                      message, where, "heard at step t+1")
            inner.add("truncation flag vs last step (0: only at the last)", trunc[LISTENER], t == steps, where)
            if trace and ep == 0:
                print(f"  {t:>3} {a:>2} {pos[0]:>8.3f} {pos[1]:>8.3f} {lis_d.state.p_pos[0]:>8.3f} "
                      f"{lis_d.state.p_pos[1]:>8.3f} {r:>8.3f} {rew[LISTENER]:>9.3f}")
        disc.close()
        cont.close()
    probe.close()
    n = f"{episodes} episodes x {steps} steps, seed {seed}"
    free.print(f"Free run: the same start and the same moves, each world stepped by itself ({n})")
    print(f"  our actor was stopped by the box edge at {clips} of {episodes * steps} steps (MPE has no walls)")
    same.print("The same state: each state our world visited written into MPE, MPE's observation and reward "
               "functions evaluated on it")
    for name, values in rewards.items():
        print(f"  {name} per-step reward on these states (random moves, not a trained pair): "
              f"min {min(values):.4g}, mean {np.mean(values):.4g}, max {max(values):.4g}")
    inner.print("Within MPE: what the comparison relies on")


def not_compared() -> None:
    print("\nNot compared, because the worlds differ in kind:")
    for line in (
        (f"messages: ours {OURS['particles_message_dim']}-d continuous (tanh) vs MPE 3-d (one-hot of Discrete(3), "
         "or Box(0, 1)); no map from one to the other preserves meaning"),
        "speaker observations: ours the actor's (x, y), MPE the goal landmark's colour; no shared content",
        ("listener observations: ours the message only; MPE's velocity and landmark offsets have no counterpart "
         "our listener sees (the goal offset is compared above against our state, which our listener never sees)"),
        "velocity: our world has none (a move is a displacement), so MPE's velocity has nothing to match",
        "the two non-goal landmarks: our world has one target; MPE's others stay where its reset put them",
        "trained agents: our speaker and listener cannot act in MPE (wrong observation and message widths)",
    ):
        print(f"  - {line}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--steps", type=int, default=OURS["particles_episode_len"], help="steps per episode")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trace", action="store_true", help="print every step of episode 0")
    args = parser.parse_args()
    header()
    facts(args.steps)
    impulse_response()
    run(args.episodes, args.steps, args.seed, args.trace)
    not_compared()


if __name__ == "__main__":
    main()
