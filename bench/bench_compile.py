"""The particle pack's update as it is (eager), under torch.compile and as a JAX program,
member-updates per second at K = 1, 9, 21, 63 in one run on one machine (one core each).

    OMP_NUM_THREADS=1 python bench/bench_compile.py --json compile.json           # all (about 5 min idle)
    OMP_NUM_THREADS=1 python bench/bench_compile.py --check                       # correctness checks only
    OMP_NUM_THREADS=1 python bench/bench_compile.py --K 1 9 --updates 20          # a quick try

Packs (--members): "grid" (default) is a sweep's pack: the paper grid's cells in the order trial, paired,
method (pc, osp, asp), the first K (9: trial 0's paired 0-2 x 3 methods; 21: one trial; 63: three trials);
K = 1 is a lone sweep cell, the costliest: ASP with 6 paired (run_cell trains it as a pack of one).
"asp": the first K ASP cells (paired 0-6 of trial 0, then trial 1, ...), the most work per member. The
base of a trial is an untrained agent pair; P and U are sampled from it as run_cell samples them
(bench/bench_packing.py's cells and data).

Variants (--variants), each from the same initial weights and data:

- eager: asp_dist.domains.particles.packed.PackedParticleTrainer.train_step, as sweeps run it.
- compile: torch.compile (inductor's CPU code generation; one graph, fullgraph=True; static shapes) of the
  largest pure piece of train_step (functional_core, CompiledCorePack below): the forward pass (rollout,
  paired rows, critic), the hand-derived backward, the discriminator steps with their Adam step
  (elementwise, torch's formula) and L_u's gradient, given the update's draws and episode phases as
  tensors. The draws (made ahead per 128 updates with the members' generators), the model's fused Adam
  step with its finite check and the records stay eager, as in train_step; the table's "in graph" is the
  share of the wall time spent inside the compiled piece. torch.compile(train_step) as it is does not
  work (torch 2.13): dynamo breaks the graph at the generator calls of _draw_chunk ("a stateful RNG
  operation") and at bool(isfinite(...)) (Tensor.item), and inductor then fails on torch._fused_adam_ over
  the stacked buffers ("mutating a non-functional tensor with a functional tensor"); a probe in a fresh
  process records what happens (--no-whole-step skips it). --check compares the compiled piece with eager.
- compile-cpp: the same with inductor's C++ wrapper (cpp_wrapper: no Python between the kernels).
- jax: bench/jax_particle_pack.py, the same arithmetic per update (layer sizes, batch rows, loss terms,
  discriminator steps, Adam) through jax.vjp; jax.vmap over members, jax.lax.scan over updates, one
  jax.jit; draws from JAX keys inside the program. Skipped with one line when jax is missing (pip install
  jax; it is not a project dependency). --check compares one update with the torch pack's from the same
  state and the torch pack's own draws.

Time per member-update = wall (and CPU) time of --updates updates / (updates x K), median over --blocks
blocks; variants alternate within each round of blocks, so a load that changes hits them all. Keep
--updates a multiple of 128: the torch variants make their draws every 128 updates (a block of fewer may
hold none). Warm-up first: eager WARMUP updates; compile its first call (the compile time: dynamo, AOT
autograd, inductor, the C++ compiler) then WARMUP updates; jax its jit compile (lower + compile, timed
apart) then one block. The process's first compile also pays inductor's start-up (imports, toolchain
checks), as a sweep worker would once: that is K = 1's "compile", and "compile-cpp" compiles each graph
after "compile" has. Inductor's cache (FX graph and AOT autograd caches) lives in TORCHINDUCTOR_CACHE_DIR,
by default here a fresh temporary directory, so that the first compile in the run is cold; afterwards a
fresh process compiles the same graphs against that cache (the warm-cache compile time, --no-warm-cache
skips it). Set TORCHINDUCTOR_CACHE_DIR to reuse a cache. JAX's persistent compilation cache is not
enabled: each process jit-compiles. One thread everywhere: torch.set_num_threads(1),
TORCHINDUCTOR_COMPILE_THREADS=1, XLA_FLAGS single-threaded Eigen (set before jax is imported); the CPU
time / wall ratio is printed per variant (it shows whether anything ran on a second core). Load on a shared machine inflates every figure:
the load averages are printed and stored.

--check (instead of the timing): two mixed packs of 9 at the paper's shapes (check_packs), 3 updates;
jax: each update from the torch pack's state with its draws; compile: compiled and eager packs side by
side. Loss terms, the model's gradient, discriminator weights and positions must agree to TOL relative to
each tensor's largest magnitude, the model's weights after Adam to 0.1 lr; exit status 1 if not.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

# One thread each, set before torch and jax are imported; a fresh inductor cache unless one is given.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("TORCHINDUCTOR_COMPILE_THREADS", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")
if "xla_cpu_multi_thread_eigen" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = " ".join(
        [os.environ.get("XLA_FLAGS", ""), "--xla_cpu_multi_thread_eigen=false"]).strip()
FRESH_CACHE = "TORCHINDUCTOR_CACHE_DIR" not in os.environ
if FRESH_CACHE:
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="bench_compile_inductor_")

import numpy as np
import torch
import torch.nn.functional as F
from _common import machine_info, timed
from bench_packing import build_pack, cell_data, grid_cells

from asp_dist.domains.particles.game import BOX, REWARD_SCALE, env_step
from asp_dist.domains.particles.packed import PackedParticleTrainer
from asp_dist.training.stacked import BETAS, EPS

try:
    import jax
    import jax_particle_pack as jp
except ImportError:
    jax = jp = None

KS = (1, 9, 21, 63)
VARIANTS = ("eager", "compile", "compile-cpp", "jax")
METHODS = ("pc", "osp", "asp")
WARMUP = 20
# Multiples of the packed trainer's CHUNK (128 updates of draws made ahead), so that every block holds the
# same number of refills; 1024 updates of a pack of 21 are ~2 s of eager work on an idle core.
UPDATES, BLOCKS = 1024, 3
TOL = 1e-5  # --check: largest difference / the tensor's largest magnitude

_tanh_backward = torch.ops.aten.tanh_backward
_threshold_backward = torch.ops.aten.threshold_backward
_leaky_relu_backward = torch.ops.aten.leaky_relu_backward


# ---- packs ----------------------------------------------------------------------------------------

def pack_specs(k: int, members: str):
    """The cells of a pack of k (see the docstring): a sweep's pack of the paper grid, or ASP cells only."""
    if k == 1:
        return [grid_cells("particles", 7, "asp")[-1]]  # a lone cell: ASP, 6 paired
    return grid_cells("particles", k, "asp" if members == "asp" else None)


def describe(specs) -> str:
    trials = sorted({s.trial for s in specs})
    mix = "/".join(str(sum(s.method == m for s in specs)) for m in METHODS)
    paired = sorted({s.paired for s in specs})
    return f"pc/osp/asp {mix}, paired {paired[0]}{f'-{paired[-1]}' if len(paired) > 1 else ''}, " \
           f"trial{'s' if len(trials) > 1 else ''} {trials[0]}{f'-{trials[-1]}' if len(trials) > 1 else ''}"


# ---- torch.compile: train_step's middle as one pure function ---------------------------------------

def functional_core(pack: PackedParticleTrainer):
    """train_step's forward pass, backward pass and discriminator steps for `pack` as a pure function of
    tensors (the same ops in the same order as train_step with record on, except where noted), for
    torch.compile: what depends on the update (its draws, its episode phases) comes in as tensors, so one
    graph serves every update. It writes the model's gradient into net.grad and the discriminators' new
    weights and moments into dnet's buffers, and returns the new positions and the update's diagnostics."""
    M, B, Kr, n, D, Ma, ds, ub = pack.M, pack.B, pack.Kr, pack.n, pack.D, pack.Ma, pack.disc_steps, pack.ub
    N = B * Kr
    assert pack.any_self_play, "a pack without self-play (PC only) is not benchmarked"
    layout = [(g.storage_offset(), g.shape) for g in pack.net.grad_views]  # weights (M, out, in), biases (M, out)
    sp_rows, p_rows = [slice(0, B), slice(B + n, B + n + N - B)], slice(B, B + n)
    rows, put_rows = pack._rows, pack._put_rows
    if Ma:
        dlayout = [(g.storage_offset(), g.shape) for g in pack.dnet.grad_views]
        layers, slope = len(dlayout) // 2, pack.slope
        dlr = torch.zeros_like(pack.dnet.param)  # per-element learning rate (StackedParams groups by lr)
        for r, lr in enumerate(pack.dnet.lrs):
            for start, size in pack.dnet.member_ranges[r]:
                dlr[start:start + size] = lr

    def blocks(flat, lay):
        return [flat[o:o + s.numel()].view(s) for o, s in lay]

    def adam(p, g, m, v, step, lr):  # torch's fused Adam, elementwise
        m = m + (1 - BETAS[0]) * (g - m)
        v = BETAS[1] * v + (1 - BETAS[1]) * g * g
        return p - (lr / (1 - BETAS[0] ** step)) * m / (v.sqrt() / (1 - BETAS[1] ** step).sqrt() + EPS), m, v

    def lin_back(dy, x, w, input_grad=True):  # y = x·Wᵀ + b: (dW, db, dx)
        return torch.bmm(dy.transpose(1, 2), x), dy.sum(1), torch.bmm(dy, w) if input_grad else None

    def disc_forward(W, x):
        inputs = [x]
        for i in range(layers):
            x = torch.baddbmm(W[2 * i + 1].unsqueeze(1), x, W[2 * i].transpose(1, 2))
            if i < layers - 1:
                x = F.leaky_relu(x, slope)
                inputs.append(x)
        return x.view(x.shape[0], -1), inputs

    def disc_backward(W, dlogits, inputs, input_grad):
        dy, grads = dlogits.unsqueeze(2), [None] * len(W)
        for i in reversed(range(layers)):
            grads[2 * i], grads[2 * i + 1], dy = lin_back(dy, inputs[i], W[2 * i], i > 0 or input_grad)
            if i > 0:
                dy = _leaky_relu_backward(dy, inputs[i], slope, True)
        return grads, dy

    def core(param, grad, dparam, dexp_avg, dexp_avg_sq, dsteps, pos, E, respawn, real_idx, lam_coef, tfeat, done):
        sw1, sb1, sw2, sb2, lw1, lb1, lw2, lb2, cw1, cb1, cw2, cb2 = blocks(param, layout)
        sb1, sb2, lb1, lb2, cb1, cb2 = (b.unsqueeze(1) for b in (sb1, sb2, lb1, lb2, cb1, cb2))
        vals = {}
        # 1. forward: the rollout (PackedParticleTrainer._rollout), paired rows after step 0's
        spk_x, spk_h, spk_m, lis_in, lis_h, lis_logp, acts, feats, rews = ([] for _ in range(9))
        for k in range(Kr):
            x = pos * (1.0 / BOX)
            xs = torch.cat([x, pack.paired_x], 1) if k == 0 and n else x
            h = torch.baddbmm(sb1, xs, sw1.transpose(1, 2)).relu()
            m = torch.baddbmm(sb2, h, sw2.transpose(1, 2)).tanh()
            li = torch.cat([m[:, :B], pack.paired_msg], 1) if k == 0 and n else m
            hl = torch.baddbmm(lb1, li, lw1.transpose(1, 2)).relu()
            logp = torch.baddbmm(lb2, hl, lw2.transpose(1, 2)).log_softmax(-1)
            a = (logp[:, :B].exp() / E[k]).argmax(-1)
            feats.append(torch.cat([x, tfeat[k]], 2))
            pos, r = env_step(pos, a, pack.target)
            pos = torch.where(done[k], respawn[k], pos)  # eager: only at phases where an episode ends
            for store, value in ((spk_x, xs), (spk_h, h), (spk_m, m), (lis_in, li), (lis_h, hl), (lis_logp, logp)):
                store.append(value)
            acts.append(a)
            rews.append(r)
        feats.append(torch.cat([pos * (1.0 / BOX), tfeat[Kr]], 2))
        feats = torch.cat(feats, 1)
        hc = torch.baddbmm(cb1, feats, cw1.transpose(1, 2)).relu()
        values = torch.baddbmm(cb2, hc, cw2.transpose(1, 2)).view(M, -1)
        ret, returns = values[:, Kr * B:], []
        for k in reversed(range(Kr)):
            ret = rews[k] * REWARD_SCALE + pack.gamma * ret.masked_fill(done[k].view(1, B), 0.0)
            returns.append(ret)
        x, h, m, li, hl, logp = (torch.cat(t, 1) for t in (spk_x, spk_h, spk_m, lis_in, lis_h, lis_logp))
        probs = logp.exp()

        # d(loss)/d(logits) of the listener, d(loss)/d(message) of the speaker
        dz = torch.empty_like(logp)
        sp_logp, sp_probs = rows(logp, sp_rows), rows(probs, sp_rows)
        td = torch.cat(returns[::-1], 1) - values[:, :Kr * B]
        onehot = (torch.cat(acts, 1).unsqueeze(2) == pack.action_ids).float()
        plogp = sp_probs * sp_logp
        dz_sp = ((sp_probs - onehot) * td.unsqueeze(2)
                 + pack.ent3 * (plogp - sp_probs * plogp.sum(2, keepdim=True))) * pack.sp_scale
        put_rows(dz, sp_rows, dz_sp)
        dv = td * pack.dv_scale
        vals["self_play"] = (-(sp_logp * onehot).sum(2) * td + pack.vc2 * td * td + pack.ent2 * plogp.sum(2)).mean(1)
        if n:
            dz[:, p_rows] = (probs[:, p_rows] - pack.paired_onehot) * pack.pw
        g_lw2, g_lb2, dhl = lin_back(dz, hl, lw2)
        g_lw1, g_lb1, dm = lin_back(_threshold_backward(dhl, hl, 0.0), li, lw1)
        if n:
            diff = m[:, p_rows] - pack.paired_msg
            dm[:, p_rows] = diff * pack.pmw
            mse = ((diff * diff).sum(2) * pack.row_mask).sum(1, keepdim=True).mul_(pack.inv_nD)
            loglik = ((logp[:, p_rows] * pack.paired_onehot).sum(2) * pack.row_mask).sum(1, keepdim=True)
            vals["paired"] = (mse - loglik.mul_(pack.inv_n)).view(-1)
        else:
            vals["paired"] = torch.zeros(M)

        # 2. ASP: disc_steps discriminator steps, then λ1·dL_u/d(fake) through the updated discriminator
        if Ma:
            fake = rows(m, sp_rows)
            fake = fake if pack.all_adv else fake.index_select(0, pack.adv_idx)
            dp, d_avg, d_sq, dstep = dparam, dexp_avg, dexp_avg_sq, dsteps
            for k in range(ds):
                W = blocks(dp, dlayout)
                real = pack.U.index_select(0, real_idx[k]).view(Ma, ub, D)
                logits, inputs = disc_forward(W, torch.cat([real, fake], 1))
                dgrads, _ = disc_backward(W, (torch.sigmoid(logits) - pack.disc_labels) * pack.disc_scale, inputs,
                                          input_grad=False)
                vals["disc"] = F.binary_cross_entropy_with_logits(logits, pack.disc_labels, reduction="none") \
                    .mul(pack.disc_scale).sum(1)
                if k == 0:
                    real_l, fake_l = logits[:, :ub], logits[:, ub:]
                    vals["disc_acc_real"] = (real_l > 0).float().mean(1)
                    vals["disc_acc_fake"] = (fake_l < 0).float().mean(1)
                    vals["d_fake"] = torch.sigmoid(fake_l).mean(1)
                dstep = dstep + 1
                dp, d_avg, d_sq = adam(dp, torch.cat([g.reshape(-1) for g in dgrads]), d_avg, d_sq, dstep, dlr)
            W = blocks(dp, dlayout)
            logits, inputs = disc_forward(W, fake)
            sig = torch.sigmoid(logits)
            dlogits = (sig - pack.ns_float) * lam_coef if pack.any_ns else sig * lam_coef
            vals["unpaired"] = torch.where(pack.ns.view(-1), F.softplus(-logits).mean(1), -F.softplus(logits).mean(1))
            _, d_adv = disc_backward(W, dlogits, inputs, input_grad=True)
            if not pack.all_adv:
                d_adv = torch.zeros(M, N, D).index_copy(0, pack.adv_idx, d_adv)
            for span, part in zip(sp_rows, (d_adv[:, :B], d_adv[:, B:])):
                if span.stop > span.start:
                    dm[:, span] += part
            for buf, new in ((dparam, dp), (dexp_avg, d_avg), (dexp_avg_sq, d_sq), (dsteps, dstep)):
                buf.copy_(new)

        # speaker and critic backward; the gradient in the stacked buffer's layout
        g_sw2, g_sb2, dh = lin_back(_tanh_backward(dm, m), h, sw2)
        g_sw1, g_sb1, _ = lin_back(_threshold_backward(dh, h, 0.0), x, sw1, input_grad=False)
        hc, dv3 = hc[:, :Kr * B], dv.unsqueeze(2)
        g_cw2, g_cb2 = torch.bmm(dv3.transpose(1, 2), hc), dv.sum(1, keepdim=True)
        g_cw1, g_cb1, _ = lin_back(_threshold_backward(dv3 * cw2, hc, 0.0), feats[:, :Kr * B], cw1, input_grad=False)
        grad.copy_(torch.cat([g.reshape(-1) for g in (g_sw1, g_sb1, g_sw2, g_sb2, g_lw1, g_lb1, g_lw2, g_lb2,
                                                       g_cw1, g_cb1, g_cw2, g_cb2)]))
        return pos, vals

    return core


class CompiledCorePack(PackedParticleTrainer):
    """PackedParticleTrainer whose train_step runs functional_core under torch.compile between the eager
    draws and the eager model step. Frozen discriminators are not handled (nothing diverges here)."""

    def __init__(self, specs, paired, unpaired, agents):
        super().__init__(specs, paired, unpaired, agents)
        T, Kr = self.T, self.Kr
        # by (step·Kr) mod T, the critic's time column and the episode ends of an update's rollout steps
        # (and bootstrap state): tensors, so that one graph serves every update
        self.phase_tfeat = [torch.stack([self.tfeat[(p + k) % T] for k in range(Kr + 1)]) for p in range(T)]
        self.phase_done = [torch.stack([self.done[(p + k) % T] for k in range(Kr)]).view(Kr, 1, self.B, 1)
                           for p in range(T)]
        self.core = None  # compiled_pack sets it
        self.core_s = 0.0  # wall time inside the compiled piece
        d = self.dnet
        self.dbufs = (d.param, d.exp_avg, d.exp_avg_sq, d.steps) if d is not None else (None,) * 4

    @torch.no_grad()
    def train_step(self) -> None:
        if self.step >= self.train_steps:
            raise RuntimeError(f"the pack has finished its {self.train_steps} updates")
        if self.step >= self.chunk_end:
            self._draw_chunk()
        j, Kr, ds = self.step - self.chunk_start, self.Kr, self.disc_steps
        phase = (self.step * Kr) % self.T
        real, lam = (self.real_flat[j * ds:(j + 1) * ds], self.lam_coef[j]) if self.Ma else (None, None)
        t0 = time.perf_counter()
        self.pos, vals = self.core(self.net.param, self.net.grad, *self.dbufs, self.pos,
                                   self.E[j * Kr:(j + 1) * Kr], self.respawn[j * Kr:(j + 1) * Kr], real, lam,
                                   self.phase_tfeat[phase], self.phase_done[phase])
        self.core_s += time.perf_counter() - t0
        record = self.recording()
        self._step_model(vals if record else None, j, record)


def dynamo_counts() -> dict:
    from torch._dynamo.utils import counters
    return {"graph_breaks": sum(counters["graph_break"].values()),
            "unique_graphs": counters["stats"].get("unique_graphs", 0),
            "recompiles": sum(counters["recompiles"].values()) if "recompiles" in counters else None}


def compiled_pack(specs, data, variant: str) -> CompiledCorePack:
    """A CompiledCorePack of `specs`, its core compiled lazily (at the first train_step) by torch.compile:
    inductor, one graph (fullgraph), static shapes; "compile-cpp" with inductor's C++ wrapper."""
    pack = build_pack(CompiledCorePack, specs, data)
    options = {"options": {"cpp_wrapper": True}} if variant == "compile-cpp" else {}
    pack.core = torch.compile(functional_core(pack), fullgraph=True, dynamic=False, **options)
    return pack


# ---- the measurement of one K ------------------------------------------------------------------------

class JaxRun:
    """The JAX variant: the pack's state from a torch pack, `updates` updates per call of one compiled scan."""

    def __init__(self, pack, updates: int):
        self.cfg, self.c, self.a, self.s = jp.from_torch(pack)
        self.key = jax.random.key(0)
        t0 = time.perf_counter()
        self.compiled = jp.run.lower(self.cfg, self.c, self.a, self.s, self.key, updates).compile()
        self.compile_s = time.perf_counter() - t0

    def block(self) -> None:
        self.s, self.key, losses = self.compiled(self.c, self.a, self.s, self.key)
        jax.block_until_ready((self.s, losses))


def measure(k: int, members: str, variants: list[str], updates: int, blocks: int) -> dict:
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    specs = pack_specs(k, members)
    if WARMUP + 1 + blocks * updates > specs[0].train_steps:
        raise SystemExit(f"{WARMUP} warm-up + {blocks} x {updates} updates exceed the cells' train_steps "
                         f"({specs[0].train_steps}); lower --updates or --blocks")
    data = cell_data(specs)
    out = {"k": k, "cells": describe(specs), "cell_ids": [s.cell_id for s in specs], "load_start": os.getloadavg(),
           "variants": {}}
    steps, compiled = {}, {}
    for v in variants:
        if v == "jax" and jp is None:  # said once at the start
            continue
        r = out["variants"][v] = {}
        if v == "eager":
            pack = build_pack(PackedParticleTrainer, specs, data)
            steps[v] = pack.train_step
            timed(pack.train_step, WARMUP)
        elif v.startswith("compile"):
            before = dynamo_counts()
            pack = compiled_pack(specs, data, v)
            r["compile_s"] = timed(pack.train_step, 1)[0]  # the first call: trace, compile, run once
            timed(pack.train_step, WARMUP)
            after = dynamo_counts()
            r["dynamo"] = {key: (after[key] - before[key]) if after[key] is not None else None for key in after}
            steps[v], compiled[v] = pack.train_step, pack
            pack.core_s = 0.0
        elif v == "jax":
            pack = build_pack(PackedParticleTrainer, specs, data)
            run = JaxRun(pack, updates)
            r["compile_s"] = run.compile_s
            run.block()  # warm-up: one block
            steps[v] = run.block
    times = {v: [] for v in steps}
    names = list(steps)
    for b in range(blocks):
        for v in names if b % 2 == 0 else names[::-1]:
            n = 1 if v == "jax" else updates  # a JAX call is a whole block
            wall, cpu = timed(steps[v], n)
            times[v].append((wall / (updates * k) * 1e3, cpu / (updates * k) * 1e3))
    for v, ts in times.items():
        r = out["variants"][v]
        r.update(ms=statistics.median(t[0] for t in ts), cpu_ms=statistics.median(t[1] for t in ts), blocks=ts)
        r["per_s"] = 1e3 / r["ms"]
        r["cpu_per_wall"] = r["cpu_ms"] / r["ms"]
        if v in compiled:  # the share of the wall time inside the compiled piece
            r["in_graph"] = compiled[v].core_s / (sum(t[0] for t in ts) * updates * k / 1e3)
    if "eager" in times:
        for r in out["variants"].values():
            r["vs_eager"] = out["variants"]["eager"]["ms"] / r["ms"]
            r["vs_eager_cpu"] = out["variants"]["eager"]["cpu_ms"] / r["cpu_ms"]
    out.update(total_s=time.perf_counter() - t0, load_end=os.getloadavg())
    return out


# ---- fresh processes: a warm-cache compile, torch.compile(train_step) as it is ---------------------------

def child(args: list[str]) -> dict:
    proc = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, check=False)
    if proc.returncode:
        return {"error": (proc.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def warm_compile(ks: list[int], members: str, variants: list[str]) -> dict:
    """In a fresh process (run against the parent's inductor cache): each K's compile variants' first call."""
    torch.set_num_threads(1)
    out = {}
    for k in ks:
        specs = pack_specs(k, members)
        data = cell_data(specs)
        for v in variants:
            pack = compiled_pack(specs, data, v)
            out[f"{v} {k}"] = timed(pack.train_step, 1)[0]
    return out


def whole_step(k: int, members: str) -> dict:
    """torch.compile(PackedParticleTrainer.train_step) as it is, three calls: how they end, dynamo's graphs
    and graph breaks (reasons, first lines)."""
    from torch._dynamo.utils import counters

    torch.set_num_threads(1)
    specs = pack_specs(k, members)
    pack = build_pack(PackedParticleTrainer, specs, cell_data(specs))
    step = torch.compile(pack.train_step)
    out: dict = {"k": k}
    t0 = time.perf_counter()
    try:
        for _ in range(3):
            step()
        out["outcome"] = "ran"
    except Exception as exc:  # noqa: BLE001 - the probe records whatever stops torch.compile
        found = re.findall(r"mutating [^.]*\.|While executing %\S+", str(exc))
        out["outcome"] = f"{type(exc).__name__}: " + " / ".join(found or [str(exc).strip()[:200]])
    out["seconds"] = time.perf_counter() - t0
    reasons: dict[str, int] = {}
    for reason, count in counters["graph_break"].items():
        text = " ".join(x.strip() for x in reason.splitlines() if x.strip()).split(" Hint:")[0][:200]
        reasons[text] = reasons.get(text, 0) + count
    out.update(graphs=counters["stats"].get("unique_graphs", 0), graph_breaks=sum(reasons.values()),
               break_reasons=reasons)
    return out


# ---- --check ---------------------------------------------------------------------------------------------

def _rel(x, y) -> float:
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return float(np.abs(x - y).max() / max(np.abs(y).max(), 1e-12)) if y.size else 0.0


def check_packs() -> dict[str, list]:
    """Two mixed packs of 9 (trial 0, paired 0-2, pc/osp/asp) at the paper's shapes, λ1 constant (its warm-up
    starts at 0, which would zero L_u's gradient): as sweeps run, and with every loop longer than one (rollouts
    of 3 steps over 4-step episodes, so episodes end and re-spawn; 2 discriminator steps; 2 hidden layers; one
    non-saturating ASP member)."""
    base = [s.replace(lambda_unpaired_schedule="constant") for s in grid_cells("particles", 9)]
    loops = [s.replace(particles_rollout_len=3, particles_episode_len=4, disc_steps=2, disc_layers=2,
                       unpaired_batch=6, unpaired_size=300) for s in base]
    loops[5] = loops[5].replace(adversary_loss="non_saturating")
    return {"paper shapes": base, "longer loops": loops}


def recorded(pack) -> list:
    """Make `pack` record every update and keep each update's diagnostics (train_step's vals) in a list."""
    got, record = [], pack._record
    pack.recording = lambda: True

    def keep(vals, j):
        got.append({k: v.clone() for k, v in vals.items()})
        record(vals, j)

    pack._record = keep
    return got


def _keep_worst(worst: dict[str, float], diffs: dict[str, float]) -> None:
    for key, d in diffs.items():
        worst[key] = max(worst.get(key, 0.0), d)


def _verdict(label: str, worst: dict[str, float]) -> tuple[bool, str]:
    """Whether every difference is within tolerance (weights after Adam: 0.1 lr, the rest TOL), and its line."""
    good = all(d <= (0.1 if key == "weights (/lr)" else TOL) for key, d in worst.items())
    return good, f"{label}: {'ok' if good else 'FAILED'}: " + ", ".join(f"{key} {d:.1e}" for key, d in worst.items())


def check(variants: list[str], updates: int = 3) -> tuple[bool, list[str]]:
    """jax: one update from the torch pack's state and its own draws, `updates` times: the loss terms, the
    model's gradient, the discriminators' and the model's weights after the update and the positions against
    the torch pack's. compile: the compiled pack and the eager pack side by side from the same start: each
    update's loss terms and gradient. Differences are relative to the tensor's largest magnitude; weights after
    an Adam step are compared in units of the learning rate (a first Adam step is ±lr wherever |g| ≫ eps, so
    rounding in a gradient element near 0 moves its weight by a fraction of lr)."""
    torch.set_num_threads(1)
    ok, lines = True, []
    for name, specs in check_packs().items():
        data = cell_data(specs)
        lr = min(s.lr for s in specs)
        if "jax" in variants and jp is not None:
            pack = build_pack(PackedParticleTrainer, specs, data)
            vals = recorded(pack)
            worst: dict[str, float] = {}
            for u in range(updates):
                cfg, c, a, s = jp.from_torch(pack)
                pack.train_step()
                s, got = jp.update_jit(cfg, c, a, s, jp.draws_from_torch(pack, u - pack.chunk_start), True)
                diffs = {term: _rel(got[term], vals[-1][term]) for term in ("self_play", "paired", "disc", "unpaired")
                         if term in got}
                diffs["gradient"] = max(_rel(x, y) for x, y in zip(got["grads"], jp._split(pack.net.grad,
                                                                                             pack.net.grad_views)))
                diffs["discriminator weights"] = max(_rel(x, y) for x, y in zip(
                    s.dparams, jp._split(pack.dnet.param, pack.dnet.grad_views)))
                diffs["positions"] = _rel(s.pos, pack.pos)
                diffs["weights (/lr)"] = max(float(np.abs(np.asarray(x) - np.asarray(y)).max()) / lr for x, y in zip(
                    s.params, jp._split(pack.net.param, pack.net.grad_views)))
                _keep_worst(worst, diffs)
            good, line = _verdict(f"jax vs eager, {name}, {updates} updates", worst)
            ok &= good
            lines.append(line)
        for v in (v for v in variants if v.startswith("compile")):
            eager, comp = build_pack(PackedParticleTrainer, specs, data), compiled_pack(specs, data, v)
            ev, cv = recorded(eager), recorded(comp)
            worst = {}
            for _ in range(updates):
                eager.train_step()
                comp.train_step()
                diffs = {term: _rel(cv[-1][term], ev[-1][term]) for term in ev[-1]}
                diffs["gradient"] = _rel(comp.net.grad, eager.net.grad)
                diffs["discriminator weights"] = _rel(comp.dnet.param, eager.dnet.param)
                diffs["positions"] = _rel(comp.pos, eager.pos)
                diffs["weights (/lr)"] = float((comp.net.param - eager.net.param).abs().max()) / lr
                _keep_worst(worst, diffs)
            good, line = _verdict(f"{v} vs eager, {name}, {updates} updates", worst)
            ok &= good
            lines.append(line)
    return ok, lines


# ---- the run ---------------------------------------------------------------------------------------------

def loads(x) -> str:
    return " / ".join(f"{v:.2f}" for v in x)


def table(r: dict, warm: dict) -> list[str]:
    lines = [("| variant | member-updates/s | ms per member-update (wall / CPU) | vs eager (wall / CPU) "
              "| CPU / wall | in graph | compile s (cold / warm cache) |"), "|---|---:|---:|---:|---:|---:|---:|"]
    for v, x in r["variants"].items():
        ratio = f"{x['vs_eager']:.2f}x / {x['vs_eager_cpu']:.2f}x" if "vs_eager" in x else "-"
        comp = "-"
        if "compile_s" in x:
            w = warm.get(f"{v} {r['k']}")
            comp = f"{x['compile_s']:.1f}" + (f" / {w:.1f}" if isinstance(w, float) else "")
        share = f"{x['in_graph']:.0%}" if "in_graph" in x else "-"
        lines.append(f"| {v} | {x['per_s']:,.0f} | {x['ms']:.4f} / {x['cpu_ms']:.4f} | {ratio} "
                     f"| {x['cpu_per_wall']:.2f} | {share} | {comp} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--K", nargs="+", type=int, default=list(KS), dest="ks", help="pack sizes")
    ap.add_argument("--members", choices=("grid", "asp"), default="grid", help="which cells make a pack")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--updates", type=int, default=UPDATES, help="updates per timing block")
    ap.add_argument("--blocks", type=int, default=BLOCKS, help="timing blocks per variant; the median is reported")
    ap.add_argument("--check", action="store_true", help="only the correctness checks (exit 1 if one fails)")
    ap.add_argument("--no-warm-cache", action="store_true", help="skip the warm-cache compile (a fresh process)")
    ap.add_argument("--no-whole-step", action="store_true", help="skip the torch.compile(train_step) probe")
    ap.add_argument("--json", metavar="OUT", help="write every figure to this JSON file")
    ap.add_argument("--warm-compile", nargs="+", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--whole-step", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    compiles = [v for v in args.variants if v.startswith("compile")]
    if args.warm_compile:
        print(json.dumps(warm_compile(args.warm_compile, args.members, compiles)))
        return 0
    if args.whole_step:
        print(json.dumps(whole_step(args.whole_step, args.members)))
        return 0

    torch._dynamo.config.recompile_limit = 64  # one graph per pack shape, all in this process
    t0 = time.perf_counter()
    report: dict = {"machine": machine_info(), "jax": jax.__version__ if jax else None,
                    "date_start": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                    "load_start": os.getloadavg(), "command": " ".join(
                        ["OMP_NUM_THREADS=1 python bench/bench_compile.py", *(argv if argv is not None else sys.argv[1:])]),
                    "members": args.members, "variants": args.variants, "updates": args.updates,
                    "blocks": args.blocks, "warmup": WARMUP, "xla_flags": os.environ["XLA_FLAGS"],
                    "inductor_cache": {"dir": os.environ["TORCHINDUCTOR_CACHE_DIR"], "fresh": FRESH_CACHE}}
    m = report["machine"]
    print(f"# {m['host']}: {m['cpu_model']}, {m['cores']} cores, {m['memory']}; torch {m['torch']} "
          f"({m['torch_cpu_capability']}), jax {report['jax'] or '-'}; one thread; load average "
          f"{loads(report['load_start'])} at start", flush=True)
    if jp is None and "jax" in args.variants:
        print("# jax: not installed (pip install jax): the jax variant is skipped")
    if args.check:
        good, lines = check(args.variants)
        for line in lines:
            print(f"# check: {line}", flush=True)
        report["check"] = {"ok": good, "lines": lines}
    else:
        print(f"# inductor cache {report['inductor_cache']['dir']} ({'fresh' if FRESH_CACHE else 'given'}); "
              f"{args.blocks} blocks x {args.updates} updates per variant, after warm-up", flush=True)
        report["results"] = []
        for k in args.ks:
            r = measure(k, args.members, args.variants, args.updates, args.blocks)
            report["results"].append(r)
            print(f"# K = {k} done in {r['total_s']:.0f} s: " + ", ".join(
                f"{v} {x['per_s']:,.0f}/s" for v, x in r["variants"].items()), flush=True)
        report["warm_compile"] = {} if args.no_warm_cache or not compiles else child(
            ["--warm-compile", *map(str, args.ks), "--members", args.members, "--variants", *compiles])
        if report["warm_compile"]:
            print("\n# warm-cache compile (fresh process, same inductor cache): "
                  + ", ".join(f"{key}: {v:.1f} s" if isinstance(v, float) else f"{key}: {v}"
                              for key, v in report["warm_compile"].items()), flush=True)
        if not args.no_whole_step and compiles:
            w = report["whole_step"] = child(["--whole-step", str(min(args.ks)), "--members", args.members])
            if "error" in w:
                print(f"# torch.compile(train_step) probe failed to run: {w['error']}")
            else:
                print(f"# torch.compile(train_step) as it is, K = {w['k']}: {w['outcome']} ({w['seconds']:.0f} s); "
                      f"dynamo {w['graphs']} graphs, {w['graph_breaks']} graph breaks:", flush=True)
                for reason, count in w["break_reasons"].items():
                    print(f"#   {count} x {reason}")
        for r in report["results"]:
            print(f"\n## K = {r['k']} ({r['cells']}): load {loads(r['load_start'][:1])}-{loads(r['load_end'][:1])}")
            print("\n".join(table(r, report["warm_compile"])))
        print()
    report.update(date_end=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                  load_end=os.getloadavg(), elapsed_s=time.perf_counter() - t0)
    print(f"# load average {loads(report['load_end'])} at end; {report['elapsed_s']:.0f} s in all", flush=True)
    if FRESH_CACHE:  # this run's own cache
        shutil.rmtree(os.environ["TORCHINDUCTOR_CACHE_DIR"], ignore_errors=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)
            f.write("\n")
    return 0 if report.get("check", {}).get("ok", True) else 1


if __name__ == "__main__":
    sys.exit(main())
