"""Is the one cell pipeline as fast as the paths it replaced? Per member-update training time of the same
cells in this tree and in an older revision, measured in one run on one machine.

    OMP_NUM_THREADS=1 python bench/bench_engines.py --rev 30b7675 --rounds 3 --json engines.json

Cases (each a fresh process, one thread, through the public entry points both trees have: run_cell for a
lone cell, run_pack for a pack): a particle, a lever and a VAE cell of the paper's settings alone (ASP,
the costliest method), and one trial's 21 particle and 21 lever cells as one pack. Time per member-update
= the row's train-phase CPU (and wall) time / train_steps (a pack's rows carry their share of the pack's
time). Bases are trained in the process first, with a tiny budget and no bar: only the train phase is
timed. Rounds alternate which tree goes first, so a load that drifts hits both; the figure per case is the
median over rounds. The older revision is checked out once with `git worktree` under /tmp and imported by
putting it first on PYTHONPATH (the installed entry points name modules, so they resolve there too).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# case -> (space of the cells, how many of the first trial's cells, train_steps, method filter, paired filter)
CASES = {
    "particles-cell": ("paper-particles", 1, 3000, "asp", 4),
    "levers-cell": ("paper-levers", 1, 1000, "asp", 4),
    "vae-cell": ("paper-vae", 1, 150, "asp", 32),
    "particles-pack21": ("paper-particles", 21, 1000, None, None),
    "levers-pack21": ("paper-levers", 21, 400, None, None),
}
BASE = dict(base_train_steps=20, base_max_attempts=1, eval_episodes=16)
NO_BAR = {"particles": {"particles_accept_return": 0.0}, "levers": {"levers_accept_reward": 0.0}, "vae": {}}


def child(case: str) -> dict:
    """Runs in the tree under test: the case's cells, their train-phase time per member-update."""
    import torch

    from asp_dist.sweep.spaces import expand
    from asp_dist.training.cell import run_cell
    try:
        from asp_dist.training.engines import run_pack  # the one pipeline
    except ImportError:
        from asp_dist.training.packed import run_pack  # before it

    torch.set_num_threads(1)
    space, k, steps, method, paired = CASES[case]
    cells = [s for s in expand(space) if method in (None, s.method) and paired in (None, s.paired)]
    first = min(s.trial for s in cells)
    domain = cells[0].domain
    if domain == "vae":  # the paper's VAE cell: latent size 32
        cells = [s for s in cells if s.vae_latent_dim in (None, 32)]
    specs = [s.replace(train_steps=steps, **BASE, **NO_BAR[domain]).resolved()
             for s in cells if s.trial == first][:k]
    if k == 1:
        rows = [run_cell(specs[0])]
    else:
        results = run_pack(specs)
        assert all(r.row is not None for r in results), [r.error for r in results]
        rows = [r.row for r in results]
    import asp_dist

    return {"case": case, "members": len(rows), "train_steps": steps, "package": asp_dist.__file__,
            "cpu_ms": 1e3 * sum(r["time_train_cpu_s"] for r in rows) / (steps * len(rows)),
            "wall_ms": 1e3 * sum(r["time_train_wall_s"] for r in rows) / (steps * len(rows))}


def worktree(rev: str) -> Path:
    path = Path(f"/tmp/asp-bench-rev-{rev}")
    if not path.exists():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), rev], check=True,
                       capture_output=True)
    return path


def measure(tree: Path, case: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", case], env=env, cwd=tree,
                         capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{case} in {tree}: {out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", help="the older revision to compare with (default: this tree only)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--json", help="write every measurement and the medians here")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child)))
        return 0
    trees = {"now": ROOT}
    if args.rev:
        trees = {"rev": worktree(args.rev), "now": ROOT}
    load = [os.getloadavg()[0]]
    runs: list[dict] = []
    for r in range(args.rounds):
        order = list(trees) if r % 2 == 0 else list(trees)[::-1]
        for case in args.cases:
            for name in order:
                runs.append(dict(measure(trees[name], case), tree=name, round=r))
        load.append(os.getloadavg()[0])
    print(f"load average (1 min) during the run: {min(load):.2f}-{max(load):.2f}")
    header = "| case | " + " | ".join(f"{t} CPU ms" for t in trees) + (" | now / rev |" if args.rev else " |")
    print(header + "\n|" + "---|" * (header.count("|") - 1))
    medians = {}
    for case in args.cases:
        med = {t: statistics.median(x["cpu_ms"] for x in runs if x["case"] == case and x["tree"] == t) for t in trees}
        medians[case] = med
        ratio = f" | {med['now'] / med['rev']:.3f} |" if args.rev else " |"
        print(f"| {case} | " + " | ".join(f"{med[t]:.4f}" for t in trees) + ratio)
    if args.json:
        Path(args.json).write_text(json.dumps({"rev": args.rev, "load": load, "runs": runs, "medians": medians},
                                              indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
