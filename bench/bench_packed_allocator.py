"""Does a packed trainer gain from glibc's retained freed memory (stacked.retain_freed_memory)?

    OMP_NUM_THREADS=1 python bench/bench_packed_allocator.py                        # particles K = 21, 64
    OMP_NUM_THREADS=1 python bench/bench_packed_allocator.py --domain levers --ks 21

Each measurement is a fresh process (the setting is process-wide and glibc's thresholds adapt to
what a process freed before, so only a new process starts from the defaults): it builds one pack
of the first K cells of the paper grid at paper settings (bench_packing.py's cells, data and pack;
bench_packed.py's and bench_packed_levers.py's before), calls retain_freed_memory() or keeps glibc's defaults
(a trainer's own call is then a no-op), runs 20 warm-up updates and times --updates updates.
The two settings alternate, --rounds times per K, the first of each pair swapped every round, so
that a load that changes during the run hits both. Reported per member-update: CPU time (the
steadier figure on a shared machine), system CPU time, and minor page faults per update (the
mechanism itself, independent of load); medians over the rounds, with min-max for CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")


def one(domain: str, k: int, retain: bool, updates: int) -> dict:
    import torch
    from bench_packing import build_pack, cell_data, grid_cells, packed_trainer

    from asp_dist.training import stacked

    torch.set_num_threads(1)
    if retain:
        stacked.retain_freed_memory()
    else:
        stacked._MALLOC_DONE = True  # the trainer's own call (levers) is then a no-op: glibc's defaults
    specs = grid_cells(domain, k)
    pack = build_pack(packed_trainer(domain), specs, cell_data(specs))
    for _ in range(20):
        pack.train_step()
    r0, c0 = resource.getrusage(resource.RUSAGE_SELF), time.process_time()
    for _ in range(updates):
        pack.train_step()
    cpu, r1 = time.process_time() - c0, resource.getrusage(resource.RUSAGE_SELF)
    per = updates * k
    return {"domain": domain, "k": k, "retain": retain, "cpu_ms": cpu / per * 1e3,
            "sys_ms": (r1.ru_stime - r0.ru_stime) / per * 1e3, "faults": (r1.ru_minflt - r0.ru_minflt) / updates,
            "rss_mib": r1.ru_maxrss / 1024, "load": os.getloadavg()[0]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    from bench_packing import PACKED

    ap.add_argument("--domain", choices=list(PACKED), default="particles")
    ap.add_argument("--ks", default="21,64", help="pack sizes")
    ap.add_argument("--rounds", type=int, default=6, help="processes per setting and K")
    ap.add_argument("--updates", type=int, default=300, help="timed updates per process")
    ap.add_argument("--one", nargs=3, help=argparse.SUPPRESS)  # domain k retain
    args = ap.parse_args(argv)
    if args.one:
        domain, k, retain = args.one
        print(json.dumps(one(domain, int(k), retain == "1", args.updates)))
        return 0

    print(f"# {args.domain}, {args.rounds} rounds x {args.updates} updates, load average "
          f"{os.getloadavg()[0]:.2f} at start")
    print("| K | allocator | CPU ms per member-update, median (min-max) | system CPU ms | page faults per update "
          "| peak RSS | load |")
    print("|---|---|---|---|---|---|---|")
    for k in (int(x) for x in args.ks.split(",")):
        runs: dict[bool, list[dict]] = {False: [], True: []}
        for r in range(args.rounds):
            for retain in ((False, True) if r % 2 == 0 else (True, False)):
                proc = subprocess.run([sys.executable, __file__, "--one", args.domain, str(k), str(int(retain)),
                                       "--updates", str(args.updates)], capture_output=True, text=True, check=False)
                if proc.returncode:
                    sys.stderr.write(proc.stderr)
                    return proc.returncode
                runs[retain].append(json.loads(proc.stdout.strip().splitlines()[-1]))
        for retain, rs in runs.items():
            cpu = [x["cpu_ms"] for x in rs]
            print(f"| {k} | {'retain_freed_memory' if retain else 'glibc defaults'} | {statistics.median(cpu):.4f} "
                  f"({min(cpu):.4f}-{max(cpu):.4f}) | {statistics.median(x['sys_ms'] for x in rs):.4f} "
                  f"| {statistics.median(x['faults'] for x in rs):.1f} "
                  f"({min(x['faults'] for x in rs):.1f}-{max(x['faults'] for x in rs):.1f}) "
                  f"| {max(x['rss_mib'] for x in rs):.0f} MiB | {min(x['load'] for x in rs):.1f}-"
                  f"{max(x['load'] for x in rs):.1f} |", flush=True)
    print(f"# load average {os.getloadavg()[0]:.2f} at end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
