"""Particle and lever packs against the matmul rate of their own shapes (bench/vae_roofline.py for the VAE), and
the paper grid's floor for them restated from it.

    OMP_NUM_THREADS=1 python bench/pack_roofline.py --json docs/bench-results/pack-roofline-<date>.json   # ~3 min
    OMP_NUM_THREADS=1 python bench/pack_roofline.py --updates 128 --blocks 1                              # a try

For each domain and packing of the paper grid (tune_spaces/paper-<domain>.toml) -- one trial's 21 cells, as
`--pack trial` builds a unit, and 63 cells of one method, as `--pack method --pack-size 63` does -- one pack is
built as the cell pipeline builds it (bench/bench_packing.py; an untrained base stands in for the trial's: the
shapes and the work are the same), and one of its updates (train_step: every member's update) is measured as
bench/_roofline.roofline measures the VAE's: each batched matrix product captured with its operands' layout and
timed alone, the update timed over whole chunks of pre-drawn random numbers (multiples of 128 updates), and one
fused Adam step over the pack's stacked parameters timed alone.

The floor restated: the grid's work for the domain at the rate of its own shapes is, per pack, train_steps x the
update's matmuls alone, summed over the grid's packs and shared by the workers -- what the grid would take if an
update did nothing but its products. paper_grid_floor.py's particle and lever figures instead counted
6 x parameters x rows at the machine's peak matmul rate, which no product of a few thousand weights reaches.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from _common import machine_info  # noqa: E402
from _roofline import finish, roofline  # noqa: E402
from bench_packing import build_pack, cell_data, grid_cells, packed_trainer  # noqa: E402

from asp_dist.sweep.spaces import expand  # noqa: E402
from asp_dist.training.float_mode import denormals_flushed  # noqa: E402

DOMAINS = ("particles", "levers")
PACKINGS = {"trial (21)": (21, None), **{f"method (63, {m.upper()})": (63, m) for m in ("pc", "osp", "asp")}}
WORKERS = 2  # the paper grid's: a laptop's two workers


def pack_update(domain: str, k: int, method: str | None):
    """The pack's train_step and its parameters (the stacked buffers Adam steps), after a few updates."""
    specs = grid_cells(domain, k, method)
    pack = build_pack(packed_trainer(domain), specs, cell_data(specs))
    params = [pack.net.param] + ([pack.dnet.param] if getattr(pack, "dnet", None) is not None else [])
    for _ in range(5):
        pack.train_step()
    return specs, pack.train_step, params


def grid_floor(domain: str, rows: dict[str, dict]) -> dict:
    """The domain's paper grid at its shapes' rate, in minutes over WORKERS workers: as one trial's packs of 21,
    and as each method's cells in packs of 63 (a last, smaller pack counted pro rata: its products scale with
    its members); and the grid's updates as measured here (packs of a trial)."""
    grid = [s for s in expand(f"paper-{domain}") if s.domain == domain]
    steps = grid[0].resolved().train_steps
    trials = len({s.trial for s in grid})
    by_trial = trials * steps * rows["trial (21)"]["matmuls_alone_ms"] / 1e3
    by_method = sum(sum(s.method == m for s in grid) / 63 * steps * rows[f"method (63, {m.upper()})"]
                    ["matmuls_alone_ms"] / 1e3 for m in ("pc", "osp", "asp"))
    return {"cells": len(grid), "train_steps": steps,
            "floor_min_pack_trial": by_trial / 60 / WORKERS, "floor_min_pack_method_63": by_method / 60 / WORKERS,
            "update_min_pack_trial": trials * steps * rows["trial (21)"]["update_ms"] / 1e3 / 60 / WORKERS}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--updates", type=int, default=512, help="updates per timed block (a multiple of 128)")
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    result: dict = {"machine": machine_info(), "load_before": load_before, "domains": {}}
    with denormals_flushed():  # as training runs (asp_dist.training.float_mode)
        for domain in DOMAINS:
            rows = {}
            for name, (k, method) in PACKINGS.items():
                specs, step, params = pack_update(domain, k, method)
                # every timed update must be one of the cells' train_steps (levers: 1,000), warm-ups included
                room = (specs[0].resolved().train_steps - 16) * 5 // (6 * args.blocks + 1)
                updates = min(args.updates, max(128, room // 128 * 128))
                row = roofline(f"{domain} {name}", step, params, updates, args.blocks)
                row.update(k=k, member_update_us=row["update_ms"] / k * 1e3,
                           member_matmuls_us=row["matmuls_alone_ms"] / k * 1e3)
                rows[name] = row
            floor = grid_floor(domain, rows)
            print(f"{domain}: paper grid {floor['cells']} cells x {floor['train_steps']} updates over {WORKERS} "
                  f"workers: the products alone {floor['floor_min_pack_trial']:.2f} min as packs of a trial "
                  f"({floor['floor_min_pack_method_63']:.2f} min as packs of 63 of a method); the updates as "
                  f"measured {floor['update_min_pack_trial']:.1f} min", flush=True)
            result["domains"][domain] = {"rows": rows, "grid": floor}
    finish(result, load_before, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
