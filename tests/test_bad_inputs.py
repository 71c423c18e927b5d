"""Every bad input to every subcommand ends the same way: exit code 2, exactly one line on stderr
(`asp-dist: error: ...`), no traceback, and nothing written — every file under the test's root (a
results tree with a small finished sweep and broken ones, scratch files, space files, fake MNIST
copies) is byte-identical before and after. All of it is refused before Ray, a training cell or the
stats job could start: those are replaced by stand-ins that fail the test if validation let a case
through. A reader that closes the pipe early (`asp-dist fields | head -1`) ends the command quietly."""

from __future__ import annotations

import json
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from budgets import tiny_spec
from harness import fingerprint

import asp_dist.training.cell as cell_module
from asp_dist import cli
from asp_dist.cli import main
from asp_dist.commands import cell as cell_command
from asp_dist.commands import stats as stats_command
from asp_dist.data import mnist
from asp_dist.results import store
from asp_dist.spec import FIELD_NAMES, field_type
from asp_dist.sweep.ledger import new_manifest

run_cell = cell_module.run_cell  # the real one, for building the sweep; the tests see a stand-in

FLOAT_KNOBS = [n for n in FIELD_NAMES if field_type(n) is float]
INT_KNOBS = [n for n in FIELD_NAMES if field_type(n) is int and n not in cell_command.CELL_FLAGS]


# ---- the world every case runs in: built once ------------------------------------------------------------

@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bad-inputs")
    results = root / "results"
    sweep = results / "tiny"
    specs = [tiny_spec("signaling", method=m, paired=2, trial=0).resolved() for m in ("pc", "osp", "asp")]
    store.write_manifest(sweep, new_manifest("tiny", "tiny-space", specs))
    for spec in specs:  # as asp_dist.sweep.tune.train_cell leaves a finished cell: curve, then row
        curve: list[dict[str, float]] = []
        row = run_cell(spec, curve=curve)
        store.write_curve(sweep, row, curve)
        store.write_row(sweep, row, "tiny")

    good = json.loads((sweep / store.MANIFEST).read_text())
    broken = {
        "trunc": (sweep / store.MANIFEST).read_text()[:200],
        "notjson": "this is not json",
        "listjson": "[1, 2, 3]",
        "nospecs": json.dumps({k: v for k, v in good.items() if k != "specs"}),
        "nospace": json.dumps({k: v for k, v in good.items() if k != "space"}),
        "misaligned": json.dumps({**good, "specs": good["specs"][:1]}),
        "specnotdict": json.dumps({**good, "specs": [1, 2, 3]}),
        "badspec": json.dumps({**good, "specs": [dict(s, domain="chess") for s in good["specs"]]}),
        "stale": json.dumps({**good, "cells": ["a", "b", "c"]}),
    }
    for name, text in broken.items():
        (results / name).mkdir()
        (results / name / store.MANIFEST).write_text(text)
    vae = tiny_spec("vae", method="asp", paired=1).resolved()
    store.write_manifest(results / "vaesweep", new_manifest("vaesweep", "vae-space", [vae]))
    (results / "plain").mkdir()
    (results / "plain" / "precious.txt").write_text("mine")
    (results / "afile").write_text("a file where a sweep would be")

    scratch = root / "scratch"
    scratch.mkdir()
    (scratch / "existing.csv").write_text("precious,csv\n")
    (scratch / "existing.parquet").write_bytes(b"precious, and not parquet")
    (scratch / "afile").write_text("blocks a directory")

    spaces = root / "spaces"
    spaces.mkdir()
    for name, text in SPACE_FILES.items():
        (spaces / f"{name}.toml").write_text(text)
    (spaces / "self-include.toml").write_text(f"include = ['{spaces / 'self-include.toml'}']")

    data = root / "mnist"
    (data / "garbage-dir").mkdir(parents=True)
    (data / "empty-dir").mkdir()
    (data / "garbage.bin").write_bytes(b"\x00\x01 not mnist" * 10)
    (data / "garbage.npz").write_bytes(b"PK\x03\x04 not a zip at all")
    for stem in mnist.IDX_NAMES.values():
        (data / "garbage-dir" / stem).write_bytes(np.arange(100, dtype=np.uint8).tobytes())
    return {"root": root, "results": results, "sweep": sweep, "scratch": scratch, "spaces": spaces, "mnist": data}


SPACE_FILES = {
    "bool-paired": "[[grid]]\naxes = { domain = ['signaling'], paired = [true] }",
    "bool-fixed": "[fixed]\ntrain_steps = true\n[[grid]]\naxes = { domain = ['signaling'], paired = [1] }",
    "bool-float": "[[grid]]\naxes = { domain = ['signaling'], lr = [true] }",
    "nan-lr": "[[grid]]\naxes = { domain = ['signaling'], lr = [nan] }",
    "inf-skew": "[[grid]]\naxes = { domain = ['signaling'], signaling_skew = [inf] }",
    "neg-inf-gamma": "[[grid]]\naxes = { domain = ['particles'], particles_gamma = [-inf] }",
    "zero-steps": "[[grid]]\naxes = { domain = ['signaling'], train_steps = [0] }",
    "chess": "[[grid]]\naxes = { domain = ['chess'] }",
    "xsp": "[[grid]]\naxes = { method = ['xsp'] }",
    "neg-paired": "[[grid]]\naxes = { paired = [-3] }",
    "str-paired": "[[grid]]\naxes = { paired = ['two'] }",
    "one-token": "[[grid]]\naxes = { signaling_tokens = [1] }",
    "bad-range": "[[grid]]\naxes = { trial = { first = 3, last = 1 } }",
    "empty-axis": "[[grid]]\naxes = { trial = [] }",
    "unknown-field": "[[grid]]\naxes = { learning_rate = [0.1] }",
    "unknown-key": "colour = 'red'\n[[grid]]\naxes = { paired = [1] }",
    "no-grid": "description = 'nothing'",
    "bad-toml": "[[grid]\naxes = {",
    "axis-and-fixed": "[[grid]]\nfixed = { paired = 1 }\naxes = { paired = [2] }",
    "choice": "[[grid]]\naxes = { adversary_loss = ['wasserstein'] }",
    "list-domain": "[[grid]]\naxes = { domain = [['signaling']] }",
    "bool-flag-int": "[[grid]]\naxes = { record_figure_data = [2] }",
    "vae": "[[grid]]\nfixed = { vae_train_images = 300 }\naxes = { domain = ['vae'], method = ['asp'], paired = [1] }",
    "huge-paired": "[[grid]]\naxes = { domain = ['signaling'], paired = [1000000000] }",
    "huge-trials": "[[grid]]\naxes = { domain = ['signaling'], trial = { first = 0, last = 9999999 } }",  # 10^7 cells
    "huge-product": "[[grid]]\naxes = { method = ['pc', 'osp', 'asp'], trial = { first = 0, last = 499999 } }",
    "huge-tensor": "[[grid]]\naxes = { domain = ['vae'], unpaired_size = [1000000] }",
}


@pytest.fixture(autouse=True)
def nothing_may_run(monkeypatch):
    """Stand-ins for everything that does work: reaching one means validation let a bad input through."""

    def refuse(*args, **kwargs):
        raise AssertionError("validation let this case through: work would start")

    fake_tune = types.ModuleType("asp_dist.sweep.tune")
    fake_tune.run_plan = fake_tune.run_sweep = fake_tune.resume_sweep = refuse
    monkeypatch.setitem(sys.modules, "asp_dist.sweep.tune", fake_tune)  # never Ray
    monkeypatch.setattr(cell_module, "run_cell", refuse)
    monkeypatch.setattr(stats_command, "run_stats_job", refuse)
    mnist.clear_cache()
    yield
    mnist.clear_cache()


# ---- the cases ----------------------------------------------------------------------------------------------
# (argv with {results} {sweep} {scratch} {spaces} {mnist} {root} filled in, a piece of the expected line,
#  and environment variables to set)
CELL = ["cell", "--domain", "signaling", "--method", "asp", "--paired", "1", "--quiet"]
VAE_CELL = ["cell", "--domain", "vae", "--method", "asp", "--paired", "1", "--quiet", "--set", "vae_train_images=300"]
R = ["--results", "{results}"]

CASES: list[tuple[str, list[str], str, dict[str, str]]] = []


def case(case_id: str, argv: list[str], needle: str, env: dict[str, str] | None = None) -> None:
    CASES.append((case_id, argv, needle, env or {}))


# cell: every float knob refuses NaN and ±inf; no int knob takes a bool; flags and --out
for knob in FLOAT_KNOBS:
    for bad in ("nan", "inf", "-inf"):
        case(f"cell-{knob}={bad}", [*CELL, "--set", f"{knob}={bad}"], f"{knob} must be")
for knob in INT_KNOBS[:12]:
    case(f"cell-{knob}=true", [*CELL, "--set", f"{knob}=true"], f"{knob} must be of type int")
for flag, value in (("paired", "3"), ("paired", "true"), ("domain", "vae"), ("method", "pc"), ("trial", "1")):
    case(f"cell-set-{flag}={value}", [*CELL, "--set", f"{flag}={value}"], f"{flag} is a flag of `asp-dist cell`")
case("cell-threads-0", [*CELL, "--threads", "0"], "--threads must be >= 1")
case("cell-threads-neg", [*CELL, "--threads", "-2"], "--threads must be >= 1")
case("cell-threads-text", [*CELL, "--threads", "two"], "invalid int value")
case("cell-threads-huge", [*CELL, "--threads", "100000000000"], "--threads must be <= 1024")
case("cell-out-empty", [*CELL, "--out", ""], "--out is empty")
case("cell-domain", ["cell", "--domain", "chess", "--method", "asp", "--paired", "1"], "unknown domain 'chess'")
case("cell-method", ["cell", "--domain", "signaling", "--method", "xsp", "--paired", "1"], "unknown method 'xsp'")
case("cell-paired-neg", ["cell", "--domain", "signaling", "--method", "asp", "--paired", "-1"], "paired must be")
case("cell-trial-neg", [*CELL, "--trial", "-1"], "trial must be an integer >= 0")
case("cell-paired-missing", ["cell", "--domain", "signaling", "--method", "asp"], "required: --paired")
case("cell-set-no-equals", [*CELL, "--set", "lr"], "--set expects KEY=VALUE")
case("cell-set-unknown", [*CELL, "--set", "learning_rate=0.1"], "unknown cell field 'learning_rate'")
case("cell-set-empty-key", [*CELL, "--set", "=1"], "unknown cell field ''")
case("cell-steps-0", [*CELL, "--set", "train_steps=0"], "train_steps must be >= 1")
case("cell-steps-frac", [*CELL, "--set", "train_steps=1.5"], "train_steps must be of type int")
case("cell-steps-empty", [*CELL, "--set", "train_steps="], "train_steps must be of type int")
case("cell-steps-huge", [*CELL, "--set", "train_steps=99999999999999999999999"], "train_steps must be an integer")
case("cell-seed-neg", [*CELL, "--set", "root_seed=-1"], "root_seed must be an integer >= 0")
case("cell-bool", [*CELL, "--set", "record_figure_data=maybe"], "record_figure_data must be of type bool")
case("cell-bool-2", [*CELL, "--set", "record_figure_data=2"], "record_figure_data must be of type bool")
case("cell-choice", [*CELL, "--set", "adversary_loss=wasserstein"], "adversary_loss must be one of")
case("cell-tokens", [*CELL, "--set", "signaling_tokens=1"], "signaling_tokens must be >= 2")
case("cell-frac", [*CELL, "--set", "lambda_schedule_frac=0"], "lambda_schedule_frac must be in")
case("cell-lr-0", [*CELL, "--set", "lr=0"], "lr must be > 0")
case("cell-lr-text", [*CELL, "--set", "lr=fast"], "lr must be of type float")
# sizes no machine can run (bounds in asp_dist/spec.py and the domains), negative numbers whatever the method
case("cell-paired-huge", ["cell", "--domain", "signaling", "--method", "asp", "--paired", "1000000000"],
     "paired must be <= 100000, got 1000000000")
case("cell-states-huge", [*CELL, "--set", "signaling_states=1000000000000"],
     "signaling_states must be <= 1000000, got 1000000000000")
case("cell-states-times-tokens", [*CELL, "--set", "signaling_states=1000000", "--set", "signaling_tokens=10000"],
     "out of memory for this cell: one tensor of signaling_states × signaling_tokens = 10000000000 numbers, above "
     "the budget of 268435456")
case("cell-levers-ids", ["cell", "--domain", "levers", "--method", "asp", "--paired", "1", "--set",
                         "levers_num_ids=1000"], "levers_num_ids must be <= 100, got 1000")
case("cell-growth-overflow", [*CELL, "--set", "base_train_steps=10", "--set", "base_steps_growth=1e300"],
     "base_train_steps · base_steps_growth^(base_max_attempts - 1) (the last base attempt's updates) must be <= "
     "1000000000")
for method in ("pc", "osp", "asp"):
    case(f"cell-{method}-neg-lambda", ["cell", "--domain", "signaling", "--method", method, "--paired", "1", "--set",
                                       "lambda_unpaired=-1"], "lambda_unpaired must be >= 0, got -1.0")
case("cell-out-suffix", [*CELL, "--out", "{scratch}/row.txt"], "must name a .parquet file")
case("cell-out-exists", [*CELL, "--out", "{scratch}/existing.parquet"], "never overwritten")
case("cell-out-no-dir", [*CELL, "--out", "{root}/no/such/row.parquet"], "does not exist")
case("cell-out-in-sweep", [*CELL, "--out", "{sweep}/cells/domain=signaling/method=asp/new.parquet"], "inside the sweep")
case("cell-out-sweep-top", [*CELL, "--out", "{sweep}/row.parquet"], "inside the sweep")
case("cell-mnist-missing", VAE_CELL, "does not exist", {"ASP_DIST_MNIST": "{mnist}/no-such-copy"})
case("cell-mnist-file", VAE_CELL, "neither a directory", {"ASP_DIST_MNIST": "{mnist}/garbage.bin"})
case("cell-mnist-npz", VAE_CELL, "could not be read", {"ASP_DIST_MNIST": "{mnist}/garbage.npz"})
case("cell-mnist-dir", VAE_CELL, "not an IDX file", {"ASP_DIST_MNIST": "{mnist}/garbage-dir"})
case("cell-mnist-empty-dir", VAE_CELL, "no train-images-idx3-ubyte", {"ASP_DIST_MNIST": "{mnist}/empty-dir"})

# theory
T = ["theory", "-S", "8", "-A", "2"]
case("theory-probs-text", [*T, "--probs", "a,b"], "--probs 'a,b'")
case("theory-probs-empty", [*T, "--probs", ""], "--probs ''")
case("theory-probs-nan", [*T, "--probs", "0.5,nan"], "must be finite")
case("theory-probs-inf", [*T, "--probs", "inf,1"], "must be finite")
case("theory-probs-neg", [*T, "--probs=-1,2"], ">= 0")
case("theory-probs-zero", [*T, "--probs", "0,0"], "not all zero")
case("theory-probs-count", [*T, "--probs", "0.2,0.3,0.5"], "3 probabilities for 2 actions")
case("theory-skew-nan", [*T, "--skew", "nan"], "--skew must be a finite number")
case("theory-skew-inf", [*T, "--skew", "inf"], "--skew must be a finite number")
case("theory-skew-overflow", ["theory", "-S", "8", "-A", "5", "--skew=-1e6"], "too large")
case("theory-both", [*T, "--skew", "1", "--probs", "1,1"], "either --probs or --skew")
case("theory-S-0", ["theory", "-S", "0", "-A", "2"], "must be >= 1")
case("theory-A-0", ["theory", "-S", "4", "-A", "0"], "must be >= 1")
case("theory-S-neg", ["theory", "-S", "-3", "-A", "2"], "must be >= 1")
case("theory-S-text", ["theory", "-S", "x", "-A", "2"], "invalid int value")
case("theory-A-float", ["theory", "-S", "4", "-A", "2.5"], "invalid int value")
case("theory-S-0-named", ["theory", "--states", "0", "-A", "2"], "--states must be >= 1, got 0")

# fields
case("fields-domain", ["fields", "--domain", "chess"], "unknown domain 'chess'")
case("fields-domain-empty", ["fields", "--domain", ""], "unknown domain ''")
case("fields-extra", ["fields", "extra"], "unrecognized arguments")
case("fields-flag", ["fields", "--bogus"], "unrecognized arguments")

# sweep: flags, space files, names, results dirs, an existing sweep's grid, the data
S = ["sweep", "smoke", *R]
case("sweep-workers-0", [*S, "--workers", "0"], "--workers must be >= 1")
case("sweep-workers-neg", [*S, "--workers", "-1"], "--workers must be >= 1")
case("sweep-failures-neg", [*S, "--max-failures", "-1"], "--max-failures must be >= 0")
case("sweep-ckpt-0", [*S, "--checkpoint-every", "0"], "--checkpoint-every must be > 0")
case("sweep-ckpt-nan", [*S, "--checkpoint-every", "nan"], "--checkpoint-every must be > 0")
case("sweep-ckpt-inf", [*S, "--checkpoint-every", "inf"], "--checkpoint-every must be > 0")
case("sweep-workers-text", [*S, "--workers", "two"], "invalid int value: 'two'")
case("sweep-workers-huge", [*S, "--workers", "1000000"], "--workers must be <= 10000, got 1000000")
case("sweep-failures-huge", [*S, "--max-failures", "1000000"], "--max-failures must be <= 100")
case("sweep-ckpt-huge", [*S, "--checkpoint-every", "1e300"], "--checkpoint-every must be <= 86400 seconds")
case("sweep-connect-huge", [*S, "--connect-timeout", "1e300"], "--connect-timeout must be <= 86400 seconds")
case("sweep-connect-0", [*S, "--connect-timeout", "0"], "--connect-timeout must be > 0 seconds")
case("sweep-pack-size-0", [*S, "--pack", "trial", "--pack-size", "0"], "--pack-size must be >= 1, got 0")
case("sweep-pack-nothing-packs", [*S, "--pack", "trial"],  # smoke: the signaling game alone
     "--pack trial: none of the 18 cells of smoke can be packed (signaling has no packed trainer)")
for flag in ("--logger-dir", "--mlflow-uri", "--wandb-project", "--logger", "--ray-temp-dir"):
    case(f"sweep-empty{flag}", [*S, flag, ""], f"{flag} is empty")  # was: the default, silently
case("sweep-empty-results", ["sweep", "smoke", "--results", ""], "--results is empty")  # was: the current directory
case("sweep-blank-results", ["sweep", "smoke", "--results", "  "], "--results is empty")
case("sweep-ray-temp-file", [*S, "--name", "new", "--ray-temp-dir", "{scratch}/afile"], "is not a directory")
case("sweep-ray-temp-too-long", [*S, "--name", "new", "--ray-temp-dir", "/tmp/" + "x" * 60],
     "too long for Ray's socket paths")
case("sweep-address-empty", [*S, "--name", "new", "--address", ""], "--address is empty")
case("sweep-unknown-space", ["sweep", "no-such-space", *R], "unknown space 'no-such-space'")
case("sweep-missing-file", ["sweep", "{spaces}/missing.toml", *R], "does not exist")
for name, needle in {"bool-paired": "paired must be of type int, got True",
                     "bool-fixed": "train_steps must be of type int, got True",
                     "bool-float": "lr must be of type float, got True",
                     "nan-lr": "lr must be a finite number", "inf-skew": "signaling_skew must be a finite number",
                     "neg-inf-gamma": "particles_gamma must be a finite number",
                     "zero-steps": "train_steps must be >= 1", "chess": "unknown domain 'chess'",
                     "xsp": "unknown method 'xsp'", "neg-paired": "paired must be an integer >= 0",
                     "str-paired": "paired must be of type int", "one-token": "signaling_tokens must be >= 2",
                     "bad-range": "last < first", "empty-axis": "must be a non-empty list",
                     "unknown-field": "unknown cell field 'learning_rate'", "unknown-key": "unknown key(s) colour",
                     "no-grid": "needs at least one [[grid]]", "bad-toml": "invalid TOML",
                     "self-include": "includes itself", "axis-and-fixed": "both an axis and fixed",
                     "choice": "adversary_loss must be one of", "list-domain": "domain must be of type str",
                     "bool-flag-int": "record_figure_data must be of type bool",
                     "huge-paired": "paired must be <= 100000, got 1000000000",
                     "huge-trials": "axis trial has 10000000 values, more than the 1000000 cells a space may hold",
                     "huge-product": "axes method (3) × trial (500000) give 1500000 cells, more than the 1000000",
                     "huge-tensor": "out of memory for this cell: one tensor of unpaired_size × width 784"}.items():
    case(f"sweep-space-{name}", ["sweep", f"{{spaces}}/{name}.toml", *R], needle)
case("sweep-name-path", [*S, "--name", "../escape"], "invalid sweep name")
case("sweep-name-empty", [*S, "--name", ""], "invalid sweep name")
case("sweep-other-grid", [*S, "--name", "tiny"], "was started with another grid")
case("sweep-not-a-sweep", [*S, "--name", "plain"], "is not a sweep")
case("sweep-name-is-file", [*S, "--name", "afile"], "is not a directory")
case("sweep-trunc-manifest", [*S, "--name", "trunc"], "is not valid JSON")
case("sweep-nospace-manifest", [*S, "--name", "nospace"], "'space' is missing")
case("sweep-results-under-file", ["sweep", "smoke", "--results", "{scratch}/afile/results"], "is not writable")
case("sweep-vae-mnist", ["sweep", "{spaces}/vae.toml", "--name", "v", *R], "not an IDX file",
     {"ASP_DIST_MNIST": "{mnist}/garbage-dir"})

# resume
for flags, needle in ((["--workers", "0"], "--workers must be >= 1"), (["--workers", "-3"], "--workers must be >= 1"),
                      (["--max-failures", "-1"], "--max-failures must be >= 0"),
                      (["--checkpoint-every", "-5"], "--checkpoint-every must be > 0"),
                      (["--checkpoint-every", "nan"], "--checkpoint-every must be > 0"),
                      (["--ray-temp-dir", "{scratch}/existing.csv"], "is not a directory"),
                      (["--address", " "], "--address is empty"),
                      (["--max-failures", "many"], "invalid int value"),
                      (["--connect-timeout", "inf"], "--connect-timeout must be > 0 seconds and finite"),
                      (["--logger-dir", ""], "--logger-dir is empty")):
    case(f"resume-{flags[0]}={flags[1]}", ["resume", "tiny", *R, *flags], needle)
case("resume-empty-results", ["resume", "tiny", "--results", ""], "--results is empty")
for name, needle in {"ghost": "no sweep 'ghost'", "trunc": "is not valid JSON", "notjson": "is not valid JSON",
                     "listjson": "list of cell ids under 'cells'", "nospecs": "one spec under 'specs'",
                     "misaligned": "one spec under 'specs'", "specnotdict": "every spec needs a domain",
                     "badspec": "specs cannot be read", "stale": "no longer resolve", "plain": "no sweep 'plain'",
                     "afile": "is not a sweep directory", "../tiny": "invalid sweep name"}.items():
    case(f"resume-{name}", ["resume", name, *R], needle)
case("resume-vae-mnist", ["resume", "vaesweep", *R], "could not be read", {"ASP_DIST_MNIST": "{mnist}/garbage.npz"})

# status
for name, needle in {"ghost": "no sweep 'ghost'", "trunc": "is not valid JSON", "notjson": "is not valid JSON",
                     "listjson": "list of cell ids under 'cells'", "nospecs": "one spec under 'specs'",
                     "nospace": "'space' is missing", "misaligned": "one spec under 'specs'",
                     "specnotdict": "every spec needs a domain", "plain": "no sweep 'plain'",
                     "afile": "is not a sweep directory", "../tiny": "invalid sweep name", "": "invalid sweep name",
                     "a/b": "invalid sweep name"}.items():
    case(f"status-{name or 'empty'}", ["status", name, *R], needle)
case("status-empty-results", ["status", "tiny", "--results", ""], "--results is empty")

# query
Q = ["query", "tiny", *R]
for sql, needle in {"COPY (SELECT * FROM cells) TO '{scratch}/leak.csv'": "COPY statement",
                    "ATTACH '{scratch}/x.db' AS x": "ATTACH statement", "INSTALL httpfs": "LOAD statement",
                    "LOAD parquet": "LOAD statement", "PRAGMA show_tables": "PRAGMA statement",
                    "SET threads = 2": "SET statement", "CREATE TABLE t AS SELECT 1": "CREATE statement",
                    "DELETE FROM cells": "DELETE statement", "SELECT 1; SELECT 2": "got 2",
                    "SELECT 1; COPY cells TO '{scratch}/leak.csv'": "got 2", "": "got none",
                    "SELECT * FROM read_csv('/etc/passwd')": "Permission Error", "SELEC 1": "SQL query failed",
                    "SELECT nope FROM cells": "SQL query failed"}.items():
    case(f"query-sql-{sql[:24]}", [*Q, "--sql", sql], needle)
for where, needle in {"1=1; COPY (SELECT 1) TO '{scratch}/leak.csv'": "is not one SQL condition",
                      "1=1) UNION SELECT * FROM cells --": "is not one SQL condition",
                      "paired = 1 ORDER BY trial": "is not one SQL condition", "": "--where is empty",
                      "methd = 'asp'": "failed: Binder Error",
                      "EXISTS (SELECT * FROM read_text('/etc/passwd'))": "Permission Error"}.items():
    case(f"query-where-{where[:20]}", [*Q, "--where", where], needle)
case("query-columns-unknown", [*Q, "--columns", "eval_mixd"], "did you mean eval_mixed")
case("query-columns-empty", [*Q, "--columns", ","], "--columns is empty")
case("query-limit-neg", [*Q, "--limit", "-1"], "--limit must be >= 0")
case("query-limit-text", [*Q, "--limit", "ten"], "invalid int value")
case("query-sql-and-where", [*Q, "--sql", "SELECT 1", "--where", "paired = 1"], "--sql is a whole query")
case("query-sql-and-limit", [*Q, "--sql", "SELECT 1", "--limit", "3"], "--sql is a whole query")
case("query-parquet-stdout", [*Q, "--format", "parquet"], "--format parquet needs --out")
case("query-format", [*Q, "--format", "xml"], "invalid choice: 'xml'")
case("query-force-alone", [*Q, "--force"], "--force only applies to --out")
case("query-out-exists", [*Q, "--out", "{scratch}/existing.csv"], "pass --force")
case("query-out-in-sweep", [*Q, "--out", "{sweep}/rows.csv", "--force"], "inside the sweep")
case("query-out-over-manifest", [*Q, "--out", "{sweep}/manifest.json", "--force"], "inside the sweep")
case("query-out-deep-in-sweep", [*Q, "--out", "{sweep}/curves/new/rows.csv"], "inside the sweep")
case("query-out-dir", [*Q, "--out", "{scratch}"], "is a directory")
case("query-out-no-dir", [*Q, "--out", "{root}/no/such/rows.csv"], "does not exist")
case("query-out-empty", [*Q, "--out", ""], "--out is empty")
case("query-limit-huge", [*Q, "--limit", "99999999999999999999"], "--limit must be <= 9223372036854775807")
case("query-empty-sweep", ["query", "", *R], "argument SWEEP: is empty")
case("query-ghost", ["query", "ghost", *R], "does not exist")
case("query-not-parquet", ["query", "{scratch}/existing.csv"], "is not a .parquet file")
case("query-garbage-parquet", ["query", "{scratch}/existing.parquet"], "cannot read")
case("query-empty-dir", ["query", "{mnist}/empty-dir"], "no finished cells")
case("query-curves-column", [*Q, "--curves", "--columns", "nope"], "unknown column 'nope'")
case("query-curves-where", [*Q, "--curves", "--where", "nope = 1"], "failed")

# stats (validated before the stats job, which is a stand-in here)
ST = ["stats", "tiny", *R, "--no-figures", "--quiet"]
for flags, needle in ((["--alpha", "0"], "--alpha must be between 0 and 1"),
                      (["--alpha", "1"], "--alpha must be between 0 and 1"),
                      (["--alpha", "nan"], "--alpha must be between 0 and 1"),
                      (["--alpha", "-0.1"], "--alpha must be between 0 and 1"),
                      (["--bootstrap", "10"], "--bootstrap must be >= 100, got 10"),
                      (["--bootstrap", "1000000000"], "--bootstrap must be <= 100000, got 1000000000"),
                      (["--seed", str(2**31)], "--seed must be <= 2147483647"),
                      (["--out", ""], "--out is empty"),  # was: the stats written into the sweep directory
                      (["--out", "  "], "--out is empty"),
                      (["--seed", "-1"], "--seed must be >= 0"),
                      (["--metric", "eval_nope"], "--metric: unknown column 'eval_nope'"),
                      (["--metric", " "], "--metric is empty"),
                      (["--threshold", "signaling=abc"], "--threshold 'signaling=abc'"),
                      (["--threshold", "signaling=nan"], "--threshold 'signaling=nan'"),
                      (["--threshold", "signaling=inf"], "--threshold 'signaling=inf'"),
                      (["--threshold", "=0.5"], "--threshold '=0.5'"),
                      (["--threshold", "chess=0.5"], "unknown domain 'chess'"),
                      (["--paired-range", "signaling=4-2"], "--paired-range 'signaling=4-2'"),
                      (["--paired-range", "signaling=x"], "--paired-range 'signaling=x'"),
                      (["--paired-range", "chess=1-2"], "unknown domain 'chess'"),
                      (["--bootstrap", "many"], "invalid int value")):
    case(f"stats-{flags[0]}={flags[1]}", [*ST, *flags], needle)
case("stats-sweep-empty", ["stats", "", *R, "--no-figures"], "argument SWEEP: is empty")
case("stats-ghost", ["stats", "ghost", *R, "--no-figures"], "does not exist")
case("stats-out-inside-cells", [*ST, "--out", "{results}/tiny/cells/stats"], "lies inside the sweep")
case("stats-out-is-a-file", [*ST, "--out", "{scratch}/existing.csv"], "cannot create the output directory")
case("stats-not-parquet", ["stats", "{scratch}/existing.csv", "--out", "{root}/out"], "is not a .parquet file")
case("stats-formats-unknown", [*ST, "--formats", "md,pdf"], "unknown format 'pdf'; choose from md,html,latex")
case("stats-formats-empty", [*ST, "--formats", ","], "--formats ',' is empty")

# compare (reads only; a case let through would compare and exit 0 or 1, not 2)
case("compare-ghost", ["compare", "ghost", "tiny", *R], "ghost does not exist")
case("compare-not-parquet", ["compare", "{scratch}/existing.csv", "tiny", *R], "is not a .parquet file")
case("compare-garbage-parquet", ["compare", "tiny", "{scratch}/existing.parquet", *R], "cannot read")
case("compare-bootstrap-low", ["compare", "tiny", "tiny", *R, "--bootstrap", "10"], "--bootstrap must be >= 100")
case("compare-bootstrap-huge", ["compare", "tiny", "tiny", *R, "--bootstrap", "1000000000"],
     "--bootstrap must be <= 100000")
case("compare-seed-neg", ["compare", "tiny", "tiny", *R, "--seed=-1"], "--seed must be >= 0, got -1")
case("compare-empty-sweep", ["compare", "", "tiny", *R], "argument SWEEP_A: is empty")
case("compare-margin", ["compare", "tiny", "tiny", *R, "--margin", "abc"], "--margin 'abc'")

# select
case("select-domain", ["select", "tiny", *R, "--domain", "chess"], "unknown domain 'chess'")
case("select-resamples", ["select", "tiny", *R, "--domain", "signaling", "--resamples", "10"],
     "--resamples must be >= 100")
case("select-resamples-huge", ["select", "tiny", *R, "--domain", "signaling", "--resamples", "1000000000"],
     "--resamples must be <= 100000, got 1000000000")
case("select-no-rows", ["select", "tiny", *R, "--domain", "vae"], "no vae rows")
case("select-ghost", ["select", "ghost", *R, "--domain", "signaling"], "does not exist")
case("select-not-parquet", ["select", "{scratch}/existing.csv", "--domain", "signaling"], "is not a .parquet file")
case("select-no-domain", ["select", "tiny", *R], "required: --domain")

# check-domain
case("check-domain-unknown", ["check-domain", "chess"], "unknown domain 'chess'")
case("check-domain-bad-knob", ["check-domain", "signaling", "--set", "signaling_tokens=0"], "signaling_tokens")
case("check-domain-unknown-knob", ["check-domain", "signaling", "--set", "nope=1"], "unknown cell field 'nope'")
for flag, value, needle in (("domain", "vae", "the domain is check-domain's NAME"),
                            ("method", "pc", "check-domain runs every method itself"),
                            ("paired", "3", "check-domain chooses the paired counts itself")):
    case(f"check-domain-set-{flag}", ["check-domain", "signaling", "--set", f"{flag}={value}"],
         f"--set '{flag}={value}': {needle}")

# power (refused before the rows are read)
P = ["power", "tiny", *R, "--domain", "signaling", "--a", "asp", "--b", "pc"]
for flags, needle in ((["--seed=-1"], "--seed must be >= 0, got -1"),
                      (["--seed", str(2**40)], "--seed must be <= 2147483647"),
                      (["--fresh-from=-5"], "--fresh-from must be >= 0, got -5"),
                      (["--target", "0"], "--target must be between 0 and 1 (both excluded), got 0"),
                      (["--target", "1"], "--target must be between 0 and 1"),
                      (["--target", "nan"], "--target must be between 0 and 1"),
                      (["--target", "1.5"], "--target must be between 0 and 1"),
                      (["--alpha", "0"], "--alpha must be between 0 and 1"),
                      (["--alpha", "inf"], "--alpha must be between 0 and 1"),
                      (["--resamples", "10"], "--resamples must be >= 100, got 10"),
                      (["--resamples", "1000000000"], "--resamples must be <= 100000"),
                      (["--resamples", "many"], "invalid int value: 'many'"),
                      (["--treatments", ""], "--treatments is empty")):
    case(f"power-{'='.join(flags)}", [*P, *flags], needle)
case("power-empty-sweep", ["power", "", *R, "--domain", "signaling", "--a", "asp", "--b", "pc"],
     "argument SWEEP: is empty")

# replay (refused before the manifest is read)
case("replay-empty-sweep", ["replay", "", "some-cell", *R], "argument SWEEP: is empty")
case("replay-empty-cell", ["replay", "tiny", "", *R], "argument CELL_ID: is empty")
case("replay-empty-results", ["replay", "tiny", "some-cell", "--results", ""], "--results is empty")

# tune (its flags, before the space is read)
TU = ["tune", "tune-particles", *R]
for flags, needle in ((["--budget", "0"], "--budget must be >= 1, got 0"),
                      (["--budget", "1000000000"], "--budget must be <= 100000"),
                      (["--seed=-1"], "--seed must be >= 0"),
                      (["--seed", str(2**32)], "--seed must be <= 2147483647"),
                      (["--workers", "0"], "--workers must be >= 1"),
                      (["--max-failures=-1"], "--max-failures must be >= 0"),
                      (["--checkpoint-every", "0"], "--checkpoint-every must be > 0 seconds"),
                      (["--checkpoint-every", "1e300"], "--checkpoint-every must be <= 86400 seconds"),
                      (["--name", ""], "--name is empty"),  # was: the space's name, silently
                      (["--ray-temp-dir", ""], "--ray-temp-dir is empty"),
                      (["--results", ""], "--results is empty")):
    case(f"tune-{'='.join(flags)}", [*TU, *flags], needle)


def test_there_are_at_least_a_hundred_cases_over_every_subcommand():
    assert len(CASES) >= 100
    assert len({c[0] for c in CASES}) == len(CASES), "case ids must be unique"
    commands = {argv[0] for _, argv, _, _ in CASES}
    assert commands == {"cell", "theory", "fields", "sweep", "resume", "status", "stats", "query", "select",
                        "compare", "check-domain", "power", "replay", "tune"}


@pytest.mark.parametrize("argv, needle, env", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(world, capsys, monkeypatch, argv, needle, env):
    places = {k: str(v) for k, v in world.items()}
    for key, value in env.items():
        monkeypatch.setenv(key, value.format(**places))
    argv = [a.format(**places) for a in argv]
    monkeypatch.chdir(world["root"] / "scratch")  # a relative default (./results) would land here, and be seen
    before = fingerprint(world["root"])
    try:
        code = main(argv)
    except SystemExit as exit_info:  # argparse's own errors
        code = exit_info.code
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert code == 2, captured.err
    assert "Traceback" not in captured.err
    assert len(lines) == 1 and lines[0].startswith("asp-dist: error: "), captured.err
    assert lines[0].strip() != "asp-dist: error:"
    assert needle in lines[0], lines[0]
    assert fingerprint(world["root"]) == before, "a bad input changed the files"


# ---- a reader that stops reading --------------------------------------------------------------------------

def closed_pipe_run(*args: str) -> subprocess.CompletedProcess:
    """Run `python -m asp_dist ARGS` with its stdout a pipe whose reading end is already closed (as after
    `| head -1` has read its line): the command's first write gets EPIPE."""
    import os

    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = subprocess.run([sys.executable, "-m", "asp_dist", *args], stdout=write_end, stderr=subprocess.PIPE,
                              text=True, timeout=300, check=False)
    finally:
        os.close(write_end)
    return proc


@pytest.mark.parametrize("argv", [["fields"], ["status", "tiny", "--results", "{results}"]], ids=["fields", "status"])
def test_a_closed_pipe_ends_the_command_quietly(world, argv):
    proc = closed_pipe_run(*[a.format(results=world["results"]) for a in argv])
    assert proc.returncode == cli.EXIT_BROKEN_PIPE, proc.stderr
    assert proc.stderr == ""


def test_broken_pipe_in_process_is_141_and_silent(monkeypatch, capsys):
    class ClosedPipe:
        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(sys, "stdout", ClosedPipe())
    assert main(["fields"]) == cli.EXIT_BROKEN_PIPE
    assert capsys.readouterr().err == ""
