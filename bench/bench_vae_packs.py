"""Same-shape VAE packs against each member alone: the most favourable packing for PackedVAETrainer.

    OMP_NUM_THREADS=1 python bench/bench_vae_packs.py            # about 4 minutes idle
    OMP_NUM_THREADS=1 python bench/bench_vae_packs.py --profile  # where a pack's time goes (10 PC members)

bench_packing.py packs the paper grid's cells in grid order (mixed methods and paired counts, so P
is padded to the pack's largest and PC members ride along in the self-play rows). Here every pack is
K cells of ONE method and paired count that differ only in the trial (the cells `--pack method`
would group if the VAE's pack_key held the paired count): no padding, no ride-along. Paper-size VAE
(d = 32, hidden 512, batch 64), untrained bases (an update costs the same whatever the base taught),
P, U and the trainers built as bench_packing.py builds them.
CPU time per member-update after 3 warm-up updates, the better of two alternating blocks of
--updates updates per path. Prints one line per (method, paired, K); load averages before and after.
"""

from __future__ import annotations

import argparse
import os
import time

import torch
from bench_packing import build_pack, cell_data, single_trainer  # the same setup as the grid-order benchmark

from asp_dist.spec import CellSpec
from asp_dist.domains.vae.packed import PackedVAETrainer


def warm_trainers(method: str, paired: int, k: int) -> tuple[list, PackedVAETrainer]:
    """k cells of one method and paired count (trials 0..k-1): each on run_cell's trainer, and as one
    pack; both after 3 warm-up updates."""
    specs = [CellSpec(domain="vae", method=method, paired=paired, trial=t).resolved() for t in range(k)]
    data = cell_data(specs)
    alone = [single_trainer(s, d) for s, d in zip(specs, data)]
    pack = build_pack(PackedVAETrainer, specs, data)
    for _ in range(3):
        pack.train_step()
        for t in alone:
            t.train_step()
    return alone, pack


def cpu_ms_per_member_update(method: str, paired: int, k: int, updates: int) -> tuple[float, float]:
    """(alone, packed): CPU ms per member-update of k cells of one method and paired count."""
    alone, pack = warm_trainers(method, paired, k)
    best_alone = best_pack = float("inf")
    for _ in range(2):
        start = time.process_time()
        for _ in range(updates):
            pack.train_step()
        best_pack = min(best_pack, (time.process_time() - start) / (updates * k) * 1e3)
        start = time.process_time()
        for t in alone:
            for _ in range(updates):
                t.train_step()
        best_alone = min(best_alone, (time.process_time() - start) / (updates * k) * 1e3)
    return best_alone, best_pack


def profile_pc_pack(k: int = 10, updates: int = 10) -> None:
    """torch profiler tables (self CPU time per op) of k PC cells at 32 paired: as one pack, then alone."""
    from torch.profiler import ProfilerActivity, profile

    alone, pack = warm_trainers("pc", 32, k)
    for title, run in (("pack", lambda: [pack.train_step() for _ in range(updates)]),
                       ("alone", lambda: [t.train_step() for t in alone for _ in range(updates)])):
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            run()
        print(f"{title}: {k} PC cells x {updates} updates")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=10))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--updates", type=int, default=30)
    ap.add_argument("--K", type=int, nargs="+", default=[4, 10])
    ap.add_argument("--profile", action="store_true", help="profile a pack of 10 PC cells against them alone")
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.profile:
        profile_pc_pack()
        return
    print(f"torch {torch.__version__} ({torch.backends.cpu.get_cpu_capability()}), 1 thread; "
          f"load average {os.getloadavg()[0]:.2f} at start")
    for method, paired in (("pc", 32), ("osp", 32), ("asp", 32), ("osp", 8)):
        for k in args.K:
            alone, packed = cpu_ms_per_member_update(method, paired, k, args.updates)
            print(f"{method} paired={paired} K={k}: alone {alone:.2f} ms, packed {packed:.2f} ms per member-update "
                  f"-> {alone / packed:.2f}x", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
