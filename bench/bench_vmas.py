"""MPE's speaker–listener on VMAS (vmas_speaker_listener) against mpe2 through the PettingZoo adapter
(mpe_speaker_listener), on one thread, in CPU seconds (time.process_time).

    python bench/bench_vmas.py                       # env steps only, about 1 minute
    python bench/bench_vmas.py --cells               # and one default cell of each domain (several minutes)
    python bench/bench_vmas.py --cells --json docs/bench-results/vmas-<date>.json
    python bench/bench_vmas.py --profile             # where one VMAS self-play episode's CPU goes, and nothing else

Needs the `pettingzoo` and `vmas` extras. Rows:

  env steps        world-steps per CPU-second with random actions, no learning: mpe2's copies through the
                   adapter's EnvBatch (a Python loop over copies) and VMAS's worlds as one batch, at n worlds
  training steps   world-steps per CPU-second of each domain's own learner at its defaults: the adapter's A2C
                   update (8 copies × 5 steps, autograd) and one VMAS episode through the differentiable world
                   (64 worlds × 25 steps, forward and backward)
  cells (--cells)  one PC, OSP and ASP cell of each domain at its defaults, on a base trained once (its CPU
                   seconds apart): CPU seconds per cell and world-steps per cell; then the VMAS trial's 30 cells
                   (2 roles × 3 methods × paired 0-8) in the two packs of `sweep vmas-words --pack trial`: CPU
                   seconds per packed cell (data, its share of the pack's training, evaluation; no curves, as the
                   lone cells)

Figures are CPU seconds of this process, so load from other processes inflates them less than wall time, but
a busy machine still slows caches and turbo: the load average is printed and stored with them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    cpu_per_call,
    machine_info,
    mpe2_random_steps_per_cpu_s,
    vmas_random_steps_per_cpu_s,
)

from asp_dist.core.registry import get_domain  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402

MPE, VMAS = "mpe_speaker_listener", "vmas_speaker_listener"


def env_steps(n: int) -> dict[str, float]:
    """World-steps per CPU-second with random actions: mpe2 copies (EnvBatch) and VMAS worlds, n each."""
    return {"n": n, "mpe2_steps_per_cpu_s": mpe2_random_steps_per_cpu_s(n),
            "vmas_steps_per_cpu_s": vmas_random_steps_per_cpu_s(n)}


def learner_steps() -> dict[str, float]:
    """World-steps per CPU-second of one update of each domain's learner at its defaults."""
    from asp_dist.domains.pettingzoo import game as pz
    from asp_dist.domains.vmas import game as vm

    mpe_spec = CellSpec(domain=MPE, method="osp").resolved()
    domain, agents = get_domain(MPE), pz.new_agents(get_domain(MPE), mpe_spec, 0)
    gen = torch.Generator().manual_seed(0)
    state = domain.init_self_play(mpe_spec, agents, gen)
    opt = torch.optim.Adam(agents.parameters(), lr=1e-3)

    def a2c():
        loss = domain.self_play_step(mpe_spec, agents, state, gen).loss
        opt.zero_grad()
        loss.backward()
        opt.step()

    vm_spec = CellSpec(domain=VMAS, method="osp").resolved()
    team = vm.new_agents(vm_spec, 0)
    vm_opt = torch.optim.Adam(team.parameters(), lr=1e-3)

    def episode():
        loss = vm.self_play_step(vm_spec, team, {}, gen).loss
        vm_opt.zero_grad()
        loss.backward()
        vm_opt.step()

    mpe_steps = mpe_spec.batch_size * mpe_spec.mpe_speaker_listener_rollout_len
    vm_steps = vm_spec.batch_size * vm_spec.vmas_speaker_listener_episode_len
    return {"mpe2_a2c_steps_per_cpu_s": mpe_steps / cpu_per_call(a2c),
            "vmas_episode_steps_per_cpu_s": vm_steps / cpu_per_call(episode),
            "mpe2_world_steps_per_update": mpe_steps, "vmas_world_steps_per_update": vm_steps}


def cells(trial: int) -> list[dict]:
    """One PC, OSP and ASP cell (paired 2) of each domain at its defaults, on one base per domain; then the VMAS
    trial's cells in the packs `asp-dist sweep vmas-words --pack trial` makes (per role: PC, OSP, ASP × paired 0, 1,
    2, 4, 8), on the same base."""
    from asp_dist.training.cell import run_cell
    from asp_dist.training.bases import train_accepted_base
    from asp_dist.training.engines import run_pack

    out = []
    for name in (MPE, VMAS):
        spec = CellSpec(domain=name, method="asp", paired=2, trial=trial).resolved()
        start = time.process_time()
        base = train_accepted_base(spec)
        base_cpu = time.process_time() - start
        for method in ("pc", "osp", "asp"):
            cell = spec.replace(method=method).resolved()
            start = time.process_time()
            row = run_cell(cell, base=base)
            cpu = time.process_time() - start
            if name == MPE:
                world_steps = cell.train_steps * cell.batch_size * cell.mpe_speaker_listener_rollout_len
            else:
                world_steps = cell.train_steps * cell.batch_size * cell.vmas_speaker_listener_episode_len
            out.append({"domain": name, "method": method, "cpu_s": cpu, "base_cpu_s": base_cpu,
                        "train_world_steps": world_steps if method != "pc" else 0,
                        "mixed": row["eval_mixed"], "base_score": row["base_score"]})
            print(f"  {name:24s} {method:4s} cell {cpu:7.1f} CPU-s  (base {base_cpu:6.1f} CPU-s, "
                  f"{world_steps if method != 'pc' else 0:,} self-play world-steps, mixed {row['eval_mixed']:.2f})",
                  flush=True)
    for role in ("listener_0", "speaker_0"):  # the packs of one trial of the word study, as a sweep makes them
        pack = [spec.replace(method=m, paired=k, vmas_speaker_listener_new_agent=role).resolved()
                for m in ("pc", "osp", "asp") for k in (0, 1, 2, 4, 8)]
        start = time.process_time()
        results = run_pack(pack, bases={spec.base_key: base})  # data, training and evaluation of every member
        cpu = time.process_time() - start
        assert all(r.error is None for r in results), [r.error for r in results if r.error]
        out.append({"domain": VMAS, "method": f"pack of {len(pack)}, new {role}", "cpu_s": cpu / len(pack),
                    "pack_cpu_s": cpu, "base_cpu_s": base_cpu, "members": len(pack),
                    "train_cpu_s_per_member": results[0].row["time_train_cpu_s"],
                    "mixed_by_method": {m: float(np.median([r.row["eval_mixed"] for r in results if r.spec.method == m]))
                                        for m in ("pc", "osp", "asp")}})
        print(f"  {VMAS:24s} trial pack, new {role}: {cpu:7.1f} CPU-s for {len(pack)} cells, "
              f"{cpu / len(pack):5.2f} CPU-s a cell", flush=True)
    return out


def profile_episode(episodes: int = 40) -> dict[str, float]:
    """CPU milliseconds of one VMAS self-play episode at the domain's defaults (OSP, 64 worlds x 25 steps,
    forward through the world, backward, Adam step), split by cProfile into the backward pass, VMAS's World.step,
    the agents' networks and the rest."""
    import cProfile
    import pstats

    from asp_dist.domains.vmas import game as vm

    spec = CellSpec(domain=VMAS, method="osp").resolved()
    team = vm.new_agents(spec, 0)
    opt = torch.optim.Adam(team.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(0)

    def episode():
        loss = vm.self_play_step(spec, team, {}, gen).loss
        opt.zero_grad()
        loss.backward()
        opt.step()

    for _ in range(5):
        episode()
    profiler, start = cProfile.Profile(), time.process_time()
    profiler.enable()
    for _ in range(episodes):
        episode()
    profiler.disable()
    total = (time.process_time() - start) / episodes * 1e3
    stats = pstats.Stats(profiler).stats  # (file, line, name) -> (calls, primitive calls, tottime, cumtime, callers)

    def cumulative(match) -> float:
        return sum(v[3] for k, v in stats.items() if match(k)) / episodes * 1e3

    parts = {"backward": cumulative(lambda k: k[0] == "~" and "run_backward" in k[2]),  # the C++ engine only
             "vmas_world_step": cumulative(lambda k: k[0].endswith("vmas/simulator/core.py") and k[2] == "step"),
             "networks_forward": cumulative(lambda k: k[0].endswith("torch/nn/modules/module.py")
                                            and k[2] == "_call_impl"),
             "sampling": cumulative(lambda k: "multinomial" in k[2])}
    return {"cpu_ms_per_episode_profiled": total, **{f"{k}_ms": v for k, v in parts.items()}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", action="store_true", help="also time one default cell of each method and domain")
    parser.add_argument("--trial", type=int, default=900, help="trial of the timed cells (a calibration id < 1000)")
    parser.add_argument("--json", type=Path, help="write the figures here")
    parser.add_argument("--profile", action="store_true", help="only: where one VMAS episode's CPU goes (cProfile)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.profile:
        parts = profile_episode()
        print(f"load average {os.getloadavg()[0]:.2f}; one VMAS self-play episode, CPU ms (under cProfile):")
        for k, v in parts.items():
            print(f"  {k:32s} {v:7.1f}")
        return 0
    result = {"machine": machine_info(), "load_before": os.getloadavg()[0], "env_steps": [], "learner": {}}
    print(f"load average {result['load_before']:.2f}; world-steps per CPU-second, one thread")
    for n in (1, 64, 1024):
        row = env_steps(n)
        result["env_steps"].append(row)
        print(f"  random actions, {n:5d} worlds: mpe2 {row['mpe2_steps_per_cpu_s']:10,.0f}   "
              f"vmas {row['vmas_steps_per_cpu_s']:10,.0f}   ({row['vmas_steps_per_cpu_s'] / row['mpe2_steps_per_cpu_s']:.1f}×)")
    result["learner"] = learner_steps()
    lr = result["learner"]
    print(f"  training: mpe2 A2C update {lr['mpe2_a2c_steps_per_cpu_s']:,.0f}   vmas episode through the world "
          f"{lr['vmas_episode_steps_per_cpu_s']:,.0f}")
    if args.cells:
        result["cells"] = cells(args.trial)
        by = {(r["domain"], r["method"]): r["cpu_s"] for r in result["cells"]}
        packed = [r["cpu_s"] for r in result["cells"] if r["method"].startswith("pack")]
        per_cell = sum(packed) / len(packed)
        result["packed_cell_ratios"] = {"vs_mpe2_osp": by[(MPE, "osp")] / per_cell,
                                        "vs_vmas_lone_osp": by[(VMAS, "osp")] / per_cell}
        print(f"  a VMAS cell in a trial pack: {per_cell:.2f} CPU-s; the mpe2 OSP cell "
              f"{result['packed_cell_ratios']['vs_mpe2_osp']:.1f} × that, the lone VMAS OSP cell "
              f"{result['packed_cell_ratios']['vs_vmas_lone_osp']:.1f} ×")
    result["load_after"] = os.getloadavg()[0]
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
