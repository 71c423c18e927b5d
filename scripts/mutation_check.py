"""The suite still catches what matters: break the code in one way at a time and run the tests meant to catch
it. Each mutation is a one-place text change in a source file (applied, then always restored); a mutation
"is caught" when the named tests fail. Prints a Markdown table (the one in docs/decisions/0029-mutation-check.md).

    python scripts/mutation_check.py            # every mutation (a few minutes on two cores)
    python scripts/mutation_check.py --only 3   # one of them
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    what: str  # the behaviour broken, in words
    file: str
    old: str | tuple[str, ...]  # exact text, found once (or several such texts)
    new: str | tuple[str, ...]
    tests: tuple[str, ...]  # pytest node ids or -k selections ("file::test" or "file -k expr")

    def edits(self) -> list[tuple[str, str]]:
        olds = (self.old,) if isinstance(self.old, str) else self.old
        news = (self.new,) if isinstance(self.new, str) else self.new
        return list(zip(olds, news))


MUTATIONS = (
    Mutation("a finished cell's file is overwritten (resume writes a cell twice)", "asp_dist/fsutil.py",
             ("    if final.exists():\n        return False\n", "            os.link(tmp, final)  # atomic"),
             ("", "            os.replace(tmp, final)  # atomic"), ("tests/test_store.py",)),
    Mutation("a damaged cell file is not set aside (its cell stays pending for ever)", "asp_dist/results/store.py",
             "    damaged = damaged_cells(sweep_dir, grid)\n", "    damaged = {}\n",
             ("tests/test_store.py -k damaged",)),
    Mutation("a packed particle member's speaker gradient is 1 % off", "asp_dist/domains/particles/packed.py",
             "        # Speaker backward.\n        dh = _threshold_backward(_lin_back(_tanh_backward(dm, m),",
             "        # Speaker backward.\n        dh = _threshold_backward(_lin_back(_tanh_backward(dm * 1.01, m),",
             ("tests/test_packed_particles.py -k equals_autograd",)),
    Mutation("--sql accepts any statement (the read-only guard)", "asp_dist/results/query.py",
             "    if kind != duckdb.StatementType.SELECT:\n", "    if False:\n", ("tests/test_query_readonly.py",)),
    Mutation("an S3 lease never lapses (a silent holder blocks for ever)", "asp_dist/sweep/lease.py",
             'if rec.get("released") or self.age_s > float(rec.get("ttl_s", ttl_s)):',
             'if rec.get("released"):', ("tests/test_s3.py -k silent_lease",)),
    Mutation("the embedded Ray listens on every interface", "asp_dist/sweep/ray_host.py",
             "                stack.enter_context(loopback_only())\n", "",
             ("tests/test_sweep.py::test_sweep_listens_on_loopback_only",)),
    Mutation("a SIGTERM while Ray starts runs Ray's handler", "asp_dist/sweep/ray_host.py",
             "                with _signals_held(sigterm):\n", "                with nullcontext():\n",
             ("tests/test_sweep_lifecycle.py -k whatever_handler",)),
    Mutation("λ1 < 0 is accepted for PC and OSP", "asp_dist/spec.py",
             "        self.refuse_negatives()\n        if self.lambda_schedule_frac is not None",
             "        if self.lambda_schedule_frac is not None", ("tests/test_bad_inputs.py -k neg-lambda",)),
    Mutation("P and U no longer depend on the paired count (common random numbers broken)", "asp_dist/spec.py",
             'material = {"base": self.base_fields(), "paired": spec.paired}',
             'material = {"base": self.base_fields()}', ("tests/test_golden_rows.py",)),
    Mutation("the reader counts a file holding another cell's row", "asp_dist/results/store.py",
             "                    if row[\"cell_id\"] != path.stem:", "                    if False:",
             ("tests/test_store.py",)),
    Mutation("a full disk is a crash retried, not one line", "asp_dist/errors.py",
             "    return isinstance(err, OSError) and (", "    return False and (",
             ("tests/test_sweep_lifecycle.py -k full_disk",)),
    Mutation("a restored cell starts over instead of continuing from its checkpoint", "asp_dist/sweep/trial.py",
             "    restore = _restored_state()\n    if restore is not None:\n",
             "    restore = None\n    if restore is not None:\n",
             ("tests/test_sweep.py::test_a_damaged_sweep_extended_then_killed_resumes_to_every_cell_once",)),
    Mutation("Tune's S3 sync skips a file that changed (the bucket keeps a stale experiment state)",
             "asp_dist/sweep/tune_storage.py", "            if self._written.get(path) == digest:",
             "            if path in self._written:", ("tests/test_tune_storage.py",)),
    Mutation("the optimizer shortcut stays after torch._dynamo loads (a plugin's torch.compile would trace the "
             "optimizer)", "asp_dist/training/torch_runtime.py",
             '        if "torch._dynamo" not in sys.modules:\n            return fn(*args, **kwargs)',
             "        if True:\n            return fn(*args, **kwargs)", ("tests/test_torch_runtime.py",)),
    Mutation("a training process imports torch._dynamo again (optimizer steps not covered)",
             "asp_dist/training/torch_runtime.py", "    for cls, step in grad_mode_steps():",
             "    for cls, step in ():", ("tests/test_torch_runtime.py",)),
    Mutation("the embedded Ray prestarts idle workers that no cell can use", "asp_dist/sweep/ray_host.py",
             'SYSTEM_CONFIG = {"prestart_worker_first_driver": False}',
             'SYSTEM_CONFIG = {"prestart_worker_first_driver": True}',
             ("tests/test_sweep.py::test_sweep_listens_on_loopback_only",)),
    Mutation("trainables keep Tune's runtime env on the embedded Ray (a setup_worker.py process per worker)",
             "asp_dist/sweep/tune.py", "nullcontext() if address else worker_start.trainables_without_runtime_env()",
             "nullcontext()", ("tests/test_sweep.py::test_ray_workers_start_lean",)),
    Mutation("the embedded Ray starts the autoscaler monitor and the log monitor again", "asp_dist/sweep/ray_host.py",
             '        kwargs.setdefault("include_log_monitor", False)\n        kwargs.setdefault("no_monitor", True)\n',
             "", ("tests/test_sweep.py::test_ray_workers_start_lean",)),
    Mutation("trainable workers lose Tune's variables (not set before the embedded Ray starts)",
             "asp_dist/sweep/worker_start.py",
             ("        os.environ[key] = wanted[key]", "    _INHERITED.update({k: os.environ[k] for k in wanted})"),
             ("        pass", "    _INHERITED.update(wanted)"),
             ("tests/test_sweep.py::test_ray_workers_start_lean",)),
    Mutation("a trainable imports IPython to clear a shell it does not have", "asp_dist/sweep/worker_start.py",
             '        if "IPython" in sys.modules:\n            original()', "        original()",
             ("tests/test_worker_start.py",)),
    Mutation("a killed driver's torn W&B record stops a resumed cell's W&B run", "asp_dist/tracking/wandb.py",
             "        if pos + 7 + length > len(data):  # the torn tail of a killed writer",
             "        if False:", ("tests/test_tracking.py -k cut_short",)),
    Mutation("a trainable called outside Ray starts a local Ray to look for a tracker hub", "asp_dist/sweep/trial.py",
             "        if not ray.is_initialized():", "        if False:",
             ("tests/test_pack_sweep.py -k test_pack_trainable_writes_run_packs",)),
    Mutation("resampled Wilcoxon tests take the method scipy picks for the whole stack",
             "asp_dist/analysis/rank_tests.py",
             "    groups = [(~zero, False)] if n > 50 else", "    groups = [(~zero, False)] if True else",
             ("tests/test_power.py -k scipys_for_that_row_alone",)),
    Mutation("the VAE base's hand-derived update drops the reparameterisation's ½ in ∂z/∂log σ²",
             "asp_dist/domains/vae/base_update.py",
             "torch.add(g_z.mul_(eps).mul_(std).mul_(0.5),", "torch.add(g_z.mul_(eps).mul_(std),",
             ("tests/test_vae.py -k hand_derived_base_update_is",)),
    Mutation("the VAE cell's hand-derived update leaves the paired rows out of the decoder's gradient",
             "asp_dist/domains/vae/hand_derived.py",
             "        if n_p:\n            s = pixels[n:]\n", "        if False:\n            s = pixels[n:]\n",
             ("tests/test_vae.py -k fast_updates",)),
)


def pytest_args(selection: str) -> list[str]:
    node, _, expr = selection.partition(" -k ")
    return [node] + (["-k", expr] if expr else [])


def run(mutation: Mutation) -> tuple[bool, float, str]:
    path = ROOT / mutation.file
    text = mutated = path.read_text()
    for old, new in mutation.edits():
        if mutated.count(old) != 1:
            return False, 0.0, f"mutation text found {mutated.count(old)} times in {mutation.file}"
        mutated = mutated.replace(old, new)
    path.write_text(mutated)
    try:
        start = time.monotonic()
        failed = []
        for selection in mutation.tests:
            proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", "-n", "0",
                                   *pytest_args(selection)], cwd=ROOT, capture_output=True, text=True)
            if proc.returncode == 5:
                return False, time.monotonic() - start, f"no test selected by {selection!r}"
            if proc.returncode == 1:  # tests ran and failed (2+: collection errors, usage: not a catch)
                lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("FAILED")]
                failed.append(lines[0].split(" - ")[0].removeprefix("FAILED ") if lines else selection)
        return bool(failed), time.monotonic() - start, "; ".join(failed) or "nothing failed"
    finally:
        path.write_text(text)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", type=int, nargs="*", help="mutation numbers (1-based)")
    args = parser.parse_args()
    chosen = [(i, m) for i, m in enumerate(MUTATIONS, 1) if not args.only or i in args.only]
    print("| # | broken | caught by | s |\n|---|---|---|---|")
    missed = 0
    for i, mutation in chosen:
        caught, seconds, detail = run(mutation)
        missed += not caught
        print(f"| {i} | {mutation.what} | {'`' + detail + '`' if caught else '**NOT CAUGHT** ' + detail} | "
              f"{seconds:.0f} |", flush=True)
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
