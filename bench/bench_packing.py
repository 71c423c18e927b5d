"""The packing figures in one run on one machine: packed training against today's single-cell path
for every domain with a packed trainer, the VAE update against the machine's matmul rate, and
peak memory per worker.

    OMP_NUM_THREADS=1 python bench/bench_packing.py --json packing.json --markdown  # all (about 4.5 min idle)
    OMP_NUM_THREADS=1 python bench/bench_packing.py --by-method ...                # + one-method packs (+2 min)
    OMP_NUM_THREADS=1 python bench/bench_packing.py --domains levers --K 8 21 --no-vae
    OMP_NUM_THREADS=1 python bench/bench_packing.py --vae-only                     # the VAE part only

Packed domains (--domains, default every registered domain with a packed trainer, asp_dist.training.engines;
a newly registered one is benchmarked without edits here). Cells are the domain's paper grid
(the space ``paper-<domain>``, or GRID_SPACE below) in the order trial, paired, method
(pc, osp, asp): a pack of K holds the first K, so K = 21 is one trial's cells (7 paired counts x
3 methods) and every K has the grid's mix of methods. For each K, in a fresh process (its peak
RSS is its own, ru_maxrss):

- packed: one pack of the K cells on the domain's packed trainer, members in the trainer's
  member_order, as the cell pipeline builds it;
- single: the same K cells one at a time on the trainer run_cell picks
  (asp_dist.training.engines.lone_trainer), i.e. today's sweep path, whatever that trainer is.
  K = 1 is one trial's cells, each alone: on the single path and as 1-member packs (the packed
  trainer's own overhead).

Time per member-update = wall (and CPU) time of --updates updates / (updates x K), median over
--blocks blocks, after 20 warm-up updates; packed and single blocks alternate, so a load that
changes during the run hits both. On a shared machine the CPU-time ratio is the steadier one.
Peak RSS is read after the packed phase (before any single trainer exists): "pack of K" is a
worker holding that pack and its data. The K = 1 process first measures a worker of today's
sweep: one ASP cell (the largest: its U, and the discriminators) and nothing else. Neither
includes a cell's evaluation. A lever pack raises glibc's mmap/trim thresholds for its process
(stacked.retain_freed_memory; bench/bench_packed_allocator.py measures that setting), so the
single path runs under it too (bench_packed_levers.py found its timings the same either way).
--by-method adds, per method, a pack of one trial's worth of that method's cells (K = 21: its cells
of 3 trials) against the same cells alone. The base of each trial is
an untrained agent pair (an update costs the same whatever the base taught); P and U are sampled
from it as run_cell samples them. Updates run from the start of training, so about 1 in 10
records its losses (a curve window), against about 1 in 5 over a whole cell.

VAE part (skip with --no-vae): in a fresh process, the update of a VAE cell per method (pc, osp,
asp) at paper settings (d = 32, paired 32, batch 64) on the trainer run_cell picks, methods
alternating per block, and the base update (batch 128, the domain's own train_base between its
first and last progress report). Each as GFLOP per CPU second (bench/bench_vae.py's operation
counts) against the machine's matmul rate on one thread (128x784 @ 784x512 per CPU second,
median of three measurements: before and after the cells' updates, after the base's). Peak RSS after an ASP
cell's trainer has run (MNIST loaded, before the other trainers and the base exist). Where run_cell's
trainer is a fast one, the reference update (training.trainer.Trainer) is timed beside it. Stacked
VAEs: the self-play update of K = 1, 4, 8, 21 VAEs through batched matmuls (stacked_vae_cpu_ms),
the prototype that preceded the VAE's packed trainer (docs/decisions/0022-packed-vae-trainer-out-of-sweeps.md); that
trainer itself is benchmarked with the other packed domains.

Load on a shared machine inflates every figure: the load averages are printed and stored.
bench/bench_vae.py (whole VAE cells, other latent sizes) and bench/bench_packed_allocator.py stay
separate. Before this script: bench/bench_packed.py (particles) and bench/bench_packed_levers.py.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
import os
import statistics
import subprocess
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from _common import machine_info, peak_rss_mib, timed  # noqa: E402

from asp_dist.core.registry import DOMAINS, get_domain  # noqa: E402
from asp_dist.spec import CellSpec  # noqa: E402
from asp_dist.sweep.packing import DEFAULT_PACK_SIZE  # noqa: E402
from asp_dist.sweep.spaces import expand  # noqa: E402
from asp_dist.training.engines import lone_trainer, pack_key  # noqa: E402
from asp_dist.training.engines import pack_trainer as packed_trainer_of  # noqa: E402
from asp_dist.training.engines import supports as packable  # noqa: E402
from asp_dist.training.methods import method_weights  # noqa: E402
from asp_dist.training.trainer import Trainer  # noqa: E402

METHODS = ("pc", "osp", "asp")
PACKED = sorted(d for d in DOMAINS if any(t.packs for t in get_domain(d).trainers))  # domains with a packed trainer
# Per-domain table: the grid whose cells are packed (default "paper-<domain>") and the updates per
# timing block (default DEFAULT_UPDATES; about 2-3 s of single-path work per block at K = 21).
GRID_SPACE: dict[str, str] = {}
# Multiples of the packed trainers' CHUNK (updates whose random draws are made ahead: 128 particles,
# 32 levers and VAE), so that every block holds the same number of refills.
UPDATES: dict[str, int] = {"particles": 256, "levers": 64}
DEFAULT_UPDATES = 64
VAE_UPDATES = 100
WARMUP = 20
VAE_SETTINGS = dict(vae_latent_dim=32, paired=32, batch_size=64)  # the paper's VAE cell
# the packing targets: packed >= 4x per member-update at K = 21 (one trial's pack); VAE cells >= 80 % of the matmul rate
TARGET_SPEEDUP, TARGET_MATMUL = 4.0, 0.80


# ---- cells, data, trainers (also used by bench/bench_packed_allocator.py) ---------------------------

@functools.lru_cache(maxsize=None)
def _grid(domain: str) -> tuple[CellSpec, ...]:
    """The packable cells of the domain's grid that share the first one's pack_key (every cell of the
    particle and lever grids; the VAE grid's latent size 32, its other latent sizes being other packs)."""
    cells = [s for s in expand(GRID_SPACE.get(domain, f"paper-{domain}")) if s.domain == domain and packable(s)]
    cells = sorted(cells, key=lambda s: (s.trial, s.paired, METHODS.index(s.method)))
    return tuple(s for s in cells if pack_key(s) == pack_key(cells[0]))


def grid_cells(domain: str, k: int, method: str | None = None) -> list[CellSpec]:
    """The first k packable cells of the domain's grid (of one method if given), in the order trial, paired, method."""
    cells = [s for s in _grid(domain) if method in (None, s.method)]
    if len(cells) < k:
        raise SystemExit(f"{domain}: the grid has {len(cells)} packable cells{f' of {method}' if method else ''}, "
                         f"fewer than K = {k}")
    return cells[:k]


def trial_size(domain: str) -> int:
    """Cells of one trial of the domain's grid (21 for the paper's particle and lever grids)."""
    first = _grid(domain)[0].trial
    return sum(s.trial == first for s in _grid(domain))


def packed_trainer(domain: str) -> type:
    """The domain's packed trainer class (the one that packs its grid's cells)."""
    trainer = packed_trainer_of(_grid(domain)[0])
    if trainer is None:
        raise SystemExit(f"{domain}: no packed trainer")
    return trainer


def cell_data(specs: list[CellSpec]) -> list[tuple[dict, dict]]:
    """P and U per cell, as run_cell samples them (shared by the methods of one trial and paired count).
    The base of a trial is an untrained agent pair."""
    bases, cache, out = {}, {}, []
    for s in specs:
        domain = get_domain(s.domain)
        if (s.domain, s.trial) not in bases:
            bases[s.domain, s.trial] = domain.new_agents(s, 10_000 + s.trial)
        base = bases[s.domain, s.trial]
        key = (s.domain, s.trial, s.paired)
        if key not in cache:
            gen = torch.Generator().manual_seed(s.seed_for("data"))
            cache[key] = (domain.paired(s, base, s.paired, gen) if s.paired else {}, gen.get_state(), {})
        p, after_p, u_cache = cache[key]
        u = {}
        if method_weights(s).needs_adversary:  # U keyed as run_pack keys it (|U|, the domain's unpaired_fields)
            u_key = (s.unpaired_size, *(getattr(s, f) for f in domain.unpaired_fields))
            if u_key not in u_cache:
                u_cache[u_key] = domain.unpaired(s, base, s.unpaired_size, torch.Generator().set_state(after_p))
            u = u_cache[u_key]
        out.append((p, u))
    return out


def fresh_agents(spec: CellSpec):
    return get_domain(spec.domain).new_agents(spec, spec.seed_for("init"))


def single_trainer(spec: CellSpec, data: tuple[dict, dict]):
    """The cell's trainer as run_cell builds it (today's single-cell path, whichever trainer that is)."""
    return lone_trainer(spec).build([spec], [data[0]], [data[1]], [fresh_agents(spec)])


def build_pack(trainer_class: type, specs: list[CellSpec], data: list[tuple[dict, dict]]):
    """One pack of `specs`, members in the trainer's order (as the cell pipeline builds it)."""
    order = trainer_class.member_order(specs)
    return trainer_class.build([specs[i] for i in order], [data[i][0] for i in order], [data[i][1] for i in order],
                         [fresh_agents(specs[i]) for i in order])


# ---- the measurements, each in its own process -------------------------------------------------------

def ms_per(times: list[tuple[float, float]], n: int) -> tuple[float, float]:
    return sum(t[0] for t in times) / n * 1e3, sum(t[1] for t in times) / n * 1e3


def one_packed(domain: str, k: int, method: str | None, updates: int, blocks: int) -> dict:
    """K = 1: one trial's cells each alone (single path and 1-member packs); K > 1: the first K cells
    as one pack and, interleaved, the same cells alone."""
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    trainer_class, per_trial = packed_trainer(domain), trial_size(domain)
    out: dict = {"domain": domain, "k": k, "method": method, "load_start": os.getloadavg(),
                 "packed_trainer": trainer_class.__name__}
    if k == 1:  # a worker of today's sweep: one ASP cell (the largest), nothing else in the process
        asp = grid_cells(domain, per_trial, "asp")[-1]
        trainer = single_trainer(asp, cell_data([asp])[0])
        timed(trainer.train_step, WARMUP)
        out.update(rss_single_mib=peak_rss_mib(), rss_single_cell=asp.cell_id)
        del trainer
    specs = grid_cells(domain, per_trial if k == 1 else k, method)
    steps = min(s.train_steps for s in specs)
    if WARMUP + blocks * updates > steps:  # a pack refuses to train past its cells' end
        raise SystemExit(f"{domain}: {WARMUP} warm-up + {blocks} blocks x {updates} updates exceeds the cells' "
                         f"train_steps ({steps}); lower --updates or --blocks")
    data = cell_data(specs)
    out["rss_data_mib"] = peak_rss_mib()
    packs = [build_pack(trainer_class, [s], [d]) for s, d in zip(specs, data)] if k == 1 else \
        [build_pack(trainer_class, specs, data)]
    for p in packs:
        timed(p.train_step, WARMUP)
    out.update(rss_packed_mib=peak_rss_mib(), mix={m: sum(s.method == m for s in specs) for m in METHODS})
    singles = [single_trainer(s, d) for s, d in zip(specs, data)]
    for t in singles:
        timed(t.train_step, WARMUP)
    out["single_trainer"] = sorted({type(t).__name__ for t in singles})
    out["setup_s"] = time.perf_counter() - t0
    per = updates * len(specs)
    packed, alone = [], []  # (wall, CPU) ms per member-update, per block
    for _ in range(blocks):
        packed.append(ms_per([timed(p.train_step, updates) for p in packs], per))
        alone.append(ms_per([timed(t.train_step, updates) for t in singles], per))
    for name, blocks_ in (("packed", packed), ("single", alone)):
        out[f"{name}_ms"] = statistics.median(b[0] for b in blocks_)
        out[f"{name}_cpu_ms"] = statistics.median(b[1] for b in blocks_)
        out[f"{name}_blocks"] = blocks_
    out["speedup"] = out["single_ms"] / out["packed_ms"]
    out["speedup_cpu"] = out["single_cpu_ms"] / out["packed_cpu_ms"]
    out.update(total_s=time.perf_counter() - t0, load_end=os.getloadavg())
    return out


STACKED_VAE_K = (1, 4, 8, 21)


def stacked_vae_cpu_ms(k: int, updates: int, blocks: int, d: int = 32, hidden: int = 512, batch: int = 64) -> float:
    """CPU ms per member-update of K VAEs stacked on a leading dimension: the self-play update
    (BCE + KL of a batch of 64) through batched matmuls (baddbmm), autograd, one fused Adam step
    for all. The prototype of a packed VAE trainer: what batching the VAE's matmuls would gain."""
    from asp_dist.data.mnist import PIXELS

    gen = torch.Generator().manual_seed(0)
    shapes = [(PIXELS, hidden), (1, hidden), (hidden, 2 * d), (1, 2 * d), (d, hidden), (1, hidden), (hidden, PIXELS), (1, PIXELS)]
    params = [(torch.randn((k, *s), generator=gen) * 0.03).requires_grad_() for s in shapes]
    opt = torch.optim.Adam(params, lr=1e-3, fused=True)
    x, eps = torch.rand(k, batch, PIXELS, generator=gen), torch.randn(k, batch, d, generator=gen)

    def update() -> None:
        w1, b1, w2, b2, w3, b3, w4, b4 = params
        mu, logvar = torch.baddbmm(b2, torch.relu(torch.baddbmm(b1, x, w1)), w2).chunk(2, -1)
        z = mu + torch.exp(0.5 * logvar) * eps
        logits = torch.baddbmm(b4, torch.relu(torch.baddbmm(b3, z, w3)), w4)
        recon = torch.nn.functional.binary_cross_entropy_with_logits(logits, x, reduction="sum") / batch
        kl = (-0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(-1)).sum() / batch
        opt.zero_grad(set_to_none=True)
        (recon + kl).backward()
        opt.step()

    timed(update, 5)
    return statistics.median(timed(update, updates)[1] for _ in range(blocks)) / (updates * k) * 1e3


def one_vae(updates: int, blocks: int) -> dict:
    from bench_vae import base_update_flops, base_update_time, matmul_rate, update_flops

    from asp_dist.data.mnist import load_mnist

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    out: dict = {"load_start": os.getloadavg(), "settings": dict(VAE_SETTINGS)}
    load_mnist()
    out["mnist_load_s"] = time.perf_counter() - t0
    rates = [matmul_rate()]
    domain = get_domain("vae")
    spec0 = CellSpec(domain="vae", **VAE_SETTINGS).resolved()
    base = domain.new_agents(spec0, 10_000)
    trainers = {}
    for method in ("asp", "pc", "osp"):  # ASP first: the peak RSS after it is an ASP cell's worker
        spec = spec0.replace(method=method).resolved()
        weights, gen = method_weights(spec), torch.Generator().manual_seed(spec.seed_for("data"))
        paired = domain.paired(spec, base, spec.paired, gen) if spec.paired else {}
        unpaired = domain.unpaired(spec, base, spec.unpaired_size, gen) if weights.needs_adversary else {}
        trainer = lone_trainer(spec).build([spec], [paired], [unpaired], [fresh_agents(spec)])
        timed(trainer.train_step, 10)
        if method == "asp":
            out["rss_asp_cell_mib"] = peak_rss_mib()
        trainers[method] = (spec, trainer)
        if type(trainer) is not Trainer:  # the reference update beside the fast one: what the fast path gains
            trainers[f"{method} (reference)"] = (spec, Trainer(spec, domain, fresh_agents(spec), paired, unpaired, weights))
            timed(trainers[f"{method} (reference)"][1].train_step, 10)
    out["trainer"] = sorted({type(t).__name__ for _, t in trainers.values()})
    names = list(trainers)
    times: dict[str, list[tuple[float, float]]] = {m: [] for m in names}
    for b in range(blocks):
        for m in names if b % 2 == 0 else names[::-1]:
            wall, cpu = timed(trainers[m][1].train_step, updates)
            times[m].append((wall / updates, cpu / updates))
    out["stacked_cpu_ms"] = {k: stacked_vae_cpu_ms(k, max(2, updates // 4), blocks) for k in STACKED_VAE_K}
    rates.append(matmul_rate())
    base_wall, base_cpu = base_update_time(spec0, max(updates, 2))
    rates.append(matmul_rate())
    rate = statistics.median(r[1] for r in rates)
    out.update(matmul_gflops_cpu=[r[1] for r in rates], matmul_gflops_wall=[r[0] for r in rates],
               matmul_gflops=rate, matmul_64_gflops=matmul_rate(64)[1], matmul_32_gflops=matmul_rate(32)[1])
    rows = {}
    for m in names:
        spec = trainers[m][0]
        wall, cpu = statistics.median(t[0] for t in times[m]), statistics.median(t[1] for t in times[m])
        rows[m] = {"gflop": update_flops(spec) / 1e9, "ms": wall * 1e3, "cpu_ms": cpu * 1e3, "blocks": times[m]}
    rows["base"] = {"gflop": base_update_flops(spec0) / 1e9, "ms": base_wall * 1e3, "cpu_ms": base_cpu * 1e3,
                    "batch": spec0.vae_base_batch}
    for r in rows.values():
        r["gflops_cpu"] = r["gflop"] / r["cpu_ms"] * 1e3
        r["of_matmul"] = r["gflops_cpu"] / rate
    out.update(rows=rows, rss_end_mib=peak_rss_mib(), total_s=time.perf_counter() - t0, load_end=os.getloadavg())
    return out


# ---- the run: one process per measurement, a table as they come, JSON and markdown at the end ---------

def child(args: list[str]) -> dict | None:
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    if proc.returncode:
        sys.stderr.write(f"{' '.join(args)} failed:\n{proc.stderr}")
        return None
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["process_s"] = time.perf_counter() - t  # the whole process: start-up, set-up, timing
    return out


def loads(x) -> str:
    return " / ".join(f"{v:.2f}" for v in x)


def mix(r: dict) -> str:
    return "/".join(str(r["mix"][m]) for m in METHODS)


def rss_text(r: dict) -> str:
    text = f"{r['rss_packed_mib']:.0f} MiB (data {r['rss_data_mib']:.0f})"
    if "rss_single_mib" in r:
        text = f"one ASP cell alone {r['rss_single_mib']:.0f} MiB; " + text
    return text


def target_row(rows: list[dict]) -> dict | None:
    """The figure the packing speed-up target (TARGET_SPEEDUP) is read at: all methods, K = the sweep's default
    pack size (one trial), else the largest K > 1 measured."""
    mixed = [r for r in rows if r["method"] is None and r["k"] > 1]
    exact = [r for r in mixed if r["k"] == DEFAULT_PACK_SIZE]
    return (exact or sorted(mixed, key=lambda r: r["k"]))[-1] if mixed else None


def markdown(report: dict) -> str:
    m = report["machine"]
    lines = [f"Machine: {m['cpu_model']}, {m['cores']} cores, {m['memory']}; torch {m['torch']} "
             f"({m['torch_cpu_capability']}), one thread. {report['date_start']} to {report['date_end']}, "
             f"load average (1 / 5 / 15 min) {loads(report['load_start'])} before, {loads(report['load_end'])} after.",
             f"`{report['command']}`", ""]
    for domain, rows in report["packed"].items():
        lines += [f"**{domain}**, ms per member-update (CPU; wall in brackets), median of {report['blocks']} blocks "
                  f"of {report['updates'][domain]} updates:", "",
                  "| K (pc/osp/asp) | single-cell | packed | speed-up | peak RSS (worker) |",
                  "|---|---:|---:|---:|---:|"]
        for r in rows:
            what = f"{r['k']} ({mix(r)})" + (" each alone" if r["k"] == 1 else "") + (
                f", {r['method']} only" if r["method"] else "")
            rss = f"{r['rss_packed_mib']:.0f} MiB"
            if "rss_single_mib" in r:
                rss = f"{r['rss_single_mib']:.0f} MiB one ASP cell; {rss}"
            lines.append(f"| {what} | {r['single_cpu_ms']:.3f} ({r['single_ms']:.3f}) | {r['packed_cpu_ms']:.3f} "
                         f"({r['packed_ms']:.3f}) | {r['speedup_cpu']:.1f}× ({r['speedup']:.1f}×) | {rss} |")
        trainers = sorted({t for r in rows for t in r["single_trainer"]})
        lines += ["", f"Single-cell path: {', '.join(trainers)}; packed: {rows[0]['packed_trainer']}.", ""]
    v = report.get("vae")
    if v:
        lines += [f"**VAE** (d = 32, paired 32, batch 64; base batch 128), matmul 128×784 @ 784×512 on one thread: "
                  f"{v['matmul_gflops']:.1f} GFLOP per CPU s (median of "
                  f"{', '.join(f'{x:.1f}' for x in v['matmul_gflops_cpu'])}; 64 rows {v['matmul_64_gflops']:.1f}, "
                  f"32 rows {v['matmul_32_gflops']:.1f}):", "",
                  "| update | GFLOP | ms CPU (wall) | GFLOP per CPU s | of matmul |", "|---|---:|---:|---:|---:|"]
        for name, r in v["rows"].items():
            lines.append(f"| {name} | {r['gflop']:.3f} | {r['cpu_ms']:.2f} ({r['ms']:.2f}) | {r['gflops_cpu']:.1f} "
                         f"| {r['of_matmul']:.0%} |")
        stacked = v["stacked_cpu_ms"]
        lines += ["", "Stacked VAEs (the self-play update of K VAEs through batched matmuls, one fused Adam; "
                  "what a packed VAE trainer would gain), CPU ms per member-update: "
                  + ", ".join(f"K = {k}: {ms:.2f}" for k, ms in stacked.items()), ""]
    lines += ["Packing targets and worker memory:", ""] + [f"- {t}" for t in report["summary"]]
    return "\n".join(lines)


def summary(report: dict) -> list[str]:
    """The packing targets (TARGET_SPEEDUP, TARGET_MATMUL), met or not, and the peak RSS of a worker: one ASP cell
    alone, one pack."""
    out = []
    for domain, rows in report["packed"].items():
        r = target_row(rows)
        if r:
            ok = r["speedup_cpu"] >= TARGET_SPEEDUP
            out.append(f"{domain} K = {r['k']}: {r['speedup_cpu']:.1f}× per member-update (CPU; wall "
                       f"{r['speedup']:.1f}×), target ≥ {TARGET_SPEEDUP:.0f}×: {'met' if ok else 'NOT met'}")
        alone = next((x for x in rows if "rss_single_mib" in x), None)
        if alone and r:
            out.append(f"{domain} worker peak RSS: one ASP cell alone {alone['rss_single_mib']:.0f} MiB, "
                       f"a pack of {r['k']} {r['rss_packed_mib']:.0f} MiB (training, no evaluation)")
    v = report.get("vae")
    if v:
        low = min(METHODS, key=lambda n: v["rows"][n]["of_matmul"])
        ok = v["rows"][low]["of_matmul"] >= TARGET_MATMUL
        out.append(f"VAE cells: lowest {low} {v['rows'][low]['of_matmul']:.0%} of the matmul rate (base update "
                   f"{v['rows']['base']['of_matmul']:.0%}), target ≥ {TARGET_MATMUL:.0%}: {'met' if ok else 'NOT met'}")
        out.append(f"vae worker peak RSS: one ASP cell {v['rss_asp_cell_mib']:.0f} MiB (MNIST loaded; training, "
                   "no evaluation)")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--domains", nargs="*", default=list(PACKED), choices=list(PACKED),
                    help="packed domains to benchmark (default: all with a packed trainer; none with a bare --domains)")
    ap.add_argument("--K", nargs="+", type=int, default=[1, 8, 21, 64], dest="ks", help="pack sizes")
    ap.add_argument("--updates", type=int, help=f"updates per timing block (default per domain: {UPDATES}, "
                    f"else {DEFAULT_UPDATES}; VAE {VAE_UPDATES})")
    ap.add_argument("--blocks", type=int, default=5, help="timing blocks; the median is reported")
    ap.add_argument("--by-method", action="store_true",
                    help="also packs of one method, K = one trial's cells (21: one method's cells of 3 trials)")
    ap.add_argument("--no-vae", action="store_true", help="skip the VAE part")
    ap.add_argument("--vae-only", action="store_true", help="only the VAE part")
    ap.add_argument("--json", metavar="OUT", help="write every figure to this JSON file")
    ap.add_argument("--markdown", action="store_true", help="print tables ready for docs/performance.md at the end")
    ap.add_argument("--one-packed", nargs=3, metavar=("DOMAIN", "K", "METHOD"), help=argparse.SUPPRESS)
    ap.add_argument("--one-vae", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one_packed:
        domain, k, method = args.one_packed
        print(json.dumps(one_packed(domain, int(k), None if method == "-" else method, args.updates, args.blocks)))
        return 0
    if args.one_vae:
        print(json.dumps(one_vae(args.updates, args.blocks)))
        return 0

    domains = [] if args.vae_only else args.domains
    vae = not args.no_vae
    updates = {d: args.updates or UPDATES.get(d, DEFAULT_UPDATES) for d in domains}
    t0 = time.perf_counter()
    report: dict = {"machine": machine_info(), "date_start": datetime.datetime.now(datetime.timezone.utc).isoformat(
        timespec="seconds"), "load_start": os.getloadavg(), "command": " ".join(
        ["OMP_NUM_THREADS=1 python bench/bench_packing.py", *(argv if argv is not None else sys.argv[1:])]),
        "ks": args.ks, "blocks": args.blocks, "updates": updates, "packed": {}, "vae": None}
    m = report["machine"]
    print(f"# {m['host']}: {m['cpu_model']}, {m['cores']} cores; torch {m['torch']} ({m['torch_cpu_capability']}), "
          f"1 thread; load average {loads(report['load_start'])} at start", flush=True)
    failed = False
    for domain in domains:
        ks = sorted(set(args.ks))
        runs = [(k, None) for k in ks]
        if args.by_method:
            runs += [(trial_size(domain), meth) for meth in METHODS]
        print(f"\n## {domain}: ms per member-update, {args.blocks} blocks x {updates[domain]} updates "
              f"(packed trainer {packed_trainer(domain).__name__})")
        print("| K | cells (pc/osp/asp) | single path (wall / CPU) | packed (wall / CPU) "
              "| speed-up (wall / CPU) | peak RSS | load | s |")
        print("|---|---|---|---|---|---|---|---|", flush=True)
        rows = []
        for k, method in runs:
            r = child(["--one-packed", domain, str(k), method or "-", "--updates", str(updates[domain]),
                       "--blocks", str(args.blocks)])
            if r is None:
                failed = True
                continue
            rows.append(r)
            cells = mix(r) + (" (each alone)" if k == 1 else "") + (f" ({method} only)" if method else "")
            print(f"| {k} | {cells} | {r['single_ms']:.3f} / {r['single_cpu_ms']:.3f} | {r['packed_ms']:.3f} / "
                  f"{r['packed_cpu_ms']:.3f} | {r['speedup']:.1f}x / {r['speedup_cpu']:.1f}x | {rss_text(r)} "
                  f"| {r['load_start'][0]:.1f}-{r['load_end'][0]:.1f} | {r['process_s']:.0f} |", flush=True)
        if rows:
            print(f"single path: {', '.join(sorted({t for r in rows for t in r['single_trainer']}))}")
        report["packed"][domain] = rows
    if vae:
        n = args.updates or VAE_UPDATES
        print(f"\n## VAE: d 32, paired 32, batch 64, {args.blocks} blocks x {n} updates; base update batch 128",
              flush=True)
        v = child(["--one-vae", "--updates", str(n), "--blocks", str(args.blocks)])
        if v is None:
            failed = True
        else:
            report["vae"] = v
            print(f"matmul 128x784 @ 784x512, 1 thread: {v['matmul_gflops']:.1f} GFLOP per CPU s (median of "
                  f"{', '.join(f'{x:.1f}' for x in v['matmul_gflops_cpu'])}; 64 rows {v['matmul_64_gflops']:.1f}, "
                  f"32 rows {v['matmul_32_gflops']:.1f}); MNIST load {v['mnist_load_s']:.1f} s; "
                  f"trainer {', '.join(v['trainer'])}")
            print("| update | GFLOP | ms wall / CPU | GFLOP per CPU s | of matmul |")
            print("|---|---|---|---|---|")
            for name, r in v["rows"].items():
                print(f"| {name} | {r['gflop']:.3f} | {r['ms']:.2f} / {r['cpu_ms']:.2f} | {r['gflops_cpu']:.1f} "
                      f"| {r['of_matmul']:.0%} |")
            print("stacked VAEs, CPU ms per member-update: "
                  + ", ".join(f"K = {k}: {ms:.2f}" for k, ms in v["stacked_cpu_ms"].items()))
            print(f"peak RSS: {v['rss_asp_cell_mib']:.0f} MiB after an ASP cell's updates, {v['rss_end_mib']:.0f} MiB "
                  f"at the end (3 cells' trainers, a base, its test-set evaluation); load "
                  f"{v['load_start'][0]:.1f}-{v['load_end'][0]:.1f}; {v['process_s']:.0f} s")
    report.update(date_end=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                  load_end=os.getloadavg(), elapsed_s=time.perf_counter() - t0)
    report["summary"] = summary(report)
    print()
    for line in report["summary"]:
        print(f"# {line}")
    print(f"# load average {loads(report['load_end'])} at end; {report['elapsed_s']:.0f} s in all", flush=True)
    if args.markdown:
        print("\n" + markdown(report))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)
            f.write("\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
