"""The PettingZoo adapter's cost per environment step, beside our particle world's, on one thread.

    python bench/bench_pettingzoo.py                 # about 20 s; --seconds S per figure (default 2)
    python bench/bench_pettingzoo.py --domain mpe_reference

Needs the `pettingzoo` extra (pip install -e '.[pettingzoo]'), and asp-dist installed so that the adapter's
domains are registered. Per environment step (one step of one env copy, all agents acting), in µs:

  env alone        MPE's parallel env stepped by itself with random actions (PettingZoo's own cost)
  batch step       the adapter's EnvBatch: n copies stepped together with given actions (the loop over copies)
  self-play A2C    one update of the new team (batch_size copies × rollout_len steps: acting, stepping, the
                   loss and its backward, one Adam step) divided by the env steps it takes
  base A2C         the same at the base's base_envs copies
  evaluation       play(): episodes of a fixed team, no gradient

and the same rows for the particle world (asp_dist/domains/particles/game.py, whose env is a few torch ops on
all copies at once): its reference A2C update (a2c_update, autograd) at the paper's batch of 8 and rollout 1,
its base's at 256 envs, and its evaluation (play). Each figure is the median of blocks of about --seconds.
Load on a shared machine inflates every figure: the load average is printed with them.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from asp_dist.core.registry import DOMAINS, get_domain  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402


def per_step_us(step, env_steps: int, seconds: float, blocks: int = 3) -> float:
    """Median over `blocks` blocks of µs per env step of `step()` (which takes `env_steps` env steps)."""
    step()  # warm-up
    t0 = time.perf_counter()
    step()
    reps = max(1, int(seconds / blocks / max(time.perf_counter() - t0, 1e-6)))
    out = []
    for _ in range(blocks):
        t0 = time.perf_counter()
        for _ in range(reps):
            step()
        out.append((time.perf_counter() - t0) / (reps * env_steps) * 1e6)
    return statistics.median(out)


def adapter_rows(name: str, seconds: float) -> dict[str, float]:
    from asp_dist.domains.pettingzoo import game
    from asp_dist.domains.pettingzoo.envs import EnvBatch, env_action, make_env

    domain = get_domain(name)
    spec = CellSpec(domain=name, method="osp", paired=0).resolved()
    facts = domain.facts(spec)
    gen = torch.Generator().manual_seed(0)
    rows = {}

    env = make_env(facts.env, facts.kwargs, "env")
    env.reset(seed=0)
    actions = game.random_env_actions(facts, 1, gen)

    def env_alone():
        if not env.agents:
            env.reset(seed=1)
        env.step({a.name: env_action(actions[k][0], a) for k, a in enumerate(facts.agents)})

    rows["env alone"] = per_step_us(env_alone, 1, seconds)

    n = spec.batch_size
    batch = EnvBatch(facts, n)
    batch.reset(range(n), range(n))
    many = game.random_env_actions(facts, n, gen)

    def batch_step():
        _, done = batch.step(many)
        if done.any():
            idx = np.flatnonzero(done)
            batch.reset(idx, idx)

    rows[f"batch step ({n} copies)"] = per_step_us(batch_step, n, seconds)
    batch.close()

    for label, envs in ((f"self-play A2C ({spec.batch_size} copies × {domain.knob(spec, 'rollout_len')} steps)",
                         spec.batch_size),
                        (f"base A2C ({domain.knob(spec, 'base_envs')} copies × {domain.knob(spec, 'rollout_len')} "
                         f"steps)", domain.knob(spec, "base_envs"))):
        agents = game.new_agents(domain, spec, 0)
        opt = torch.optim.Adam(agents.parameters(), lr=1e-3)
        runner = game.Runner(facts, envs)
        runner.start(gen)

        def update():
            loss = game.a2c_rollout(domain, spec, facts, agents, runner, gen).loss
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        rows[label] = per_step_us(update, envs * domain.knob(spec, "rollout_len"), seconds)
        runner.close()

    agents = game.new_agents(domain, spec, 0)
    episodes = 64
    rows[f"evaluation ({episodes} episodes)"] = per_step_us(
        lambda: game.play(facts, list(agents.actors), game.draw_seeds(gen, episodes), gen),
        episodes * facts.episode_len, seconds)
    return rows


def particle_rows(seconds: float) -> dict[str, float]:
    from asp_dist.domains.particles import game

    domain = get_domain("particles")
    spec = CellSpec(domain="particles", method="osp", paired=0).resolved()
    target = game.target_for(spec)
    gen = torch.Generator().manual_seed(0)
    rows = {}
    for label, envs in ((f"self-play A2C ({spec.batch_size} envs × {spec.particles_rollout_len} step)",
                         spec.batch_size),
                        (f"base A2C ({spec.particles_base_envs} envs × {spec.particles_rollout_len} step)",
                         spec.particles_base_envs)):
        s = spec.replace(batch_size=envs)
        agents = domain.new_agents(s, 0)
        opt = torch.optim.Adam(agents.parameters(), lr=1e-3, **domain.optimizer_options)
        state = game.init_self_play(s, agents, gen)

        def update():
            loss = game.a2c_update(s, agents, state, target, gen).loss
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        rows[label] = per_step_us(update, envs * spec.particles_rollout_len, seconds)
    agents = domain.new_agents(spec, 0)
    episodes = 64
    rows[f"evaluation ({episodes} episodes)"] = per_step_us(
        lambda: game.play([agents], [agents], episodes, spec.particles_episode_len, target, gen),
        episodes * spec.particles_episode_len, seconds)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--domain", default="mpe_speaker_listener", help="a PettingZoo adapter domain")
    parser.add_argument("--seconds", type=float, default=2.0, help="time per figure (default 2)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.domain not in DOMAINS:
        from asp_dist.core.registry import set_aside

        why = set_aside().get(args.domain, "not registered: pip install -e '.[pettingzoo]' (entry points)")
        print(f"bench_pettingzoo: domain {args.domain!r}: {why}", file=sys.stderr)
        return 1
    print(f"PettingZoo adapter ({args.domain}) vs particle world, µs per environment step, one thread; "
          f"load average {os.getloadavg()[0]:.2f}")
    for title, rows in ((args.domain, adapter_rows(args.domain, args.seconds)),
                        ("particles", particle_rows(args.seconds))):
        print(f"\n  {title}")
        for label, us in rows.items():
            print(f"    {label:<44} {us:>9.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
