"""Results on S3-compatible object storage (``--results s3://bucket/prefix``), against a real S3 HTTP
server on loopback: moto's standalone server (``python -m moto.server``), started here in its own
process on a free port and killed after the module.

Fast tests (no Ray): the server honours conditional PUTs; the store round-trips rows, curves,
failures and the manifest and its verified reader refuses a planted object; leases (the sweep's
lock on S3) admit exactly one holder among racing processes, free at once when their holder was
SIGKILLed on this machine, lapse when their holder went silent elsewhere, and tell a holder that
lost its lease; two sweeps of one name are refused; two processes racing for one base train it
once; an endpoint that does not answer, refused credentials and a missing bucket each end `sweep`,
`resume`, `status`, `query` and `stats` with one line and exit 2, with nothing written.

Slow tests (Ray): the smoke sweep with everything in the bucket (run twice: nothing rewritten),
`status`, `query --sql` and `stats` on it; the same sweep damaged, grown with `--extend`, its driver
SIGKILLed mid-extension and resumed, restoring Tune's experiment from the bucket; a two-node loopback Ray
cluster whose nodes share no results directory, and no cell file on the local disk.

moto quirks worked around here (both are moto's, not S3's): with authentication switched on
(INITIAL_NO_AUTH_ACTION_COUNT) moto miscomputes the signature of a listing whose prefix contains a
"/", so the main server runs without authentication and a second, authenticating server serves
only the wrong-credentials test, whose requests are refused before any listing.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pandas as pd
import pytest
from harness import (
    KILL_GRID,
    S3_REGION,
    assert_rows_match,
    comparable_rows,
    expected_rows,
    free_port,
    hold_a_running_cell_at_its_checkpoint,
    kill_all,
    kill_group,
    ray_cluster,
    read_log,
    s3_env,
    space,
    start_cli,
    start_moto,
    stop_now,
    wait_for,
)

boto3 = pytest.importorskip("boto3")
pytest.importorskip("moto")

BUCKET = "asp-test"
REGION = S3_REGION


def s3_client(endpoint: str, key: str = "asp-test", secret: str = "asp-test-secret"):
    return boto3.client("s3", endpoint_url=endpoint, region_name=REGION, aws_access_key_id=key,
                        aws_secret_access_key=secret)


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    """A moto S3 server on a free loopback port with one bucket; its env for subprocesses."""
    log = tmp_path_factory.mktemp("moto") / "moto.log"
    proc, endpoint = start_moto(log)
    try:
        client = s3_client(endpoint)
        client.create_bucket(Bucket=BUCKET)
        env = s3_env(AWS_ENDPOINT_URL=endpoint, AWS_ACCESS_KEY_ID="asp-test", AWS_SECRET_ACCESS_KEY="asp-test-secret")
        yield SimpleNamespace(endpoint=endpoint, env=env, client=client, proc=proc, log=log)
    finally:
        stop_now(proc)


def use_env(monkeypatch, env: dict[str, str]) -> None:
    """This process talks to `env`'s endpoint with its credentials (clients and bucket checks made afresh)."""
    from asp_dist.results import s3 as results_s3

    for key in [k for k in os.environ if k.startswith("AWS_")]:
        monkeypatch.delenv(key)
    for key, value in env.items():
        if key.startswith("AWS_"):
            monkeypatch.setenv(key, value)
    results_s3._CLIENTS.clear()
    results_s3._BUCKETS_CHECKED.clear()


@pytest.fixture
def on_s3(s3, monkeypatch, request):
    """In-process use of the server; a prefix of its own for the test."""
    use_env(monkeypatch, s3.env)
    yield f"s3://{BUCKET}/{request.node.name.replace('[', '-').replace(']', '')}"
    from asp_dist.results import s3 as results_s3

    results_s3._CLIENTS.clear()
    results_s3._BUCKETS_CHECKED.clear()


def keys(s3, prefix: str) -> dict[str, tuple[str, object]]:
    """key -> (ETag, LastModified) of every object under `prefix` (an s3:// URI or a key prefix)."""
    prefix = prefix.split(f"s3://{BUCKET}/", 1)[-1]
    out = {}
    for page in s3.client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix):
        out.update({o["Key"]: (o["ETag"], o["LastModified"]) for o in page.get("Contents", [])})
    return out


def tiny_rows(with_curves: bool = False):
    """Real rows (and their learning curves) of three tiny signaling cells."""
    from asp_dist.spec import CellSpec
    from asp_dist.training.cell import run_cell

    rows = []
    for method, paired in (("pc", 2), ("asp", 2), ("asp", 4)):
        spec = CellSpec(domain="signaling", method=method, paired=paired, train_steps=30, batch_size=16,
                        unpaired_size=64)
        curve: list = []
        row = dict(run_cell(spec, curve=curve), ray_node_id="node-a", ray_version="x")
        rows.append((row, curve) if with_curves else row)
    return rows


# ---- the server and the store ---------------------------------------------------------------------------
def test_the_server_honours_conditional_puts(s3, on_s3):
    """If-None-Match: * on PutObject: the second writer of a key gets 412 and the object stays the first one."""
    from asp_dist.results.location import as_path

    s3.client.put_object(Bucket=BUCKET, Key="raw/x", Body=b"first", IfNoneMatch="*")
    with pytest.raises(Exception) as err:
        s3.client.put_object(Bucket=BUCKET, Key="raw/x", Body=b"second", IfNoneMatch="*")
    assert err.value.response["ResponseMetadata"]["HTTPStatusCode"] == 412
    path = as_path(on_s3) / "obj"
    assert path.create(b"one") is True
    assert path.create(b"two") is False
    assert path.read_bytes() == b"one"


def test_tune_storage_on_s3_sends_each_unchanged_file_once_through_tunes_own_threaded_copy(s3, on_s3, tmp_path):
    """The filesystem a sweep hands Tune (asp_dist.sweep.tune_storage) under the copy Tune's sync runs
    (Ray's _pyarrow_fs_copy_files: threaded for any filesystem but a bare S3FileSystem): a second sync of
    60 files with one changed sends one PUT, and neither sync hangs (a write closed on one of Arrow's IO
    threads must not wait for that pool)."""
    import threading

    from ray.train._internal.storage import _pyarrow_fs_copy_files

    from asp_dist.results.location import as_path
    from asp_dist.sweep.tune_storage import tune_storage

    staging = tmp_path / "driver_artifacts"
    for i in range(60):
        (staging / f"trial-{i}").mkdir(parents=True)
        (staging / f"trial-{i}" / "result.json").write_text(f'{{"step": {i}}}')
    storage_path, fs = tune_storage(as_path(on_s3))

    def sync() -> list[str]:
        before = len(s3.log.read_text().splitlines())
        done = threading.Thread(target=_pyarrow_fs_copy_files, args=(str(staging), f"{storage_path}/run-1"),
                                kwargs=dict(destination_filesystem=fs), daemon=True)
        done.start()
        done.join(60)
        assert not done.is_alive(), "the sync hangs"
        return [line for line in s3.log.read_text().splitlines()[before:] if '"PUT ' in line and ".json " in line]

    assert len(sync()) == 60
    (staging / "trial-7" / "result.json").write_text('{"step": 70}')
    second = sync()
    assert len(second) == 1 and "/trial-7/result.json " in second[0], second
    assert (as_path(on_s3) / "tune" / "run-1" / "trial-7" / "result.json").read_text() == '{"step": 70}'


def test_store_round_trip_on_s3_equals_local(s3, on_s3, tmp_path, capsys):
    from asp_dist.errors import SchemaError
    from asp_dist.results import store
    from asp_dist.results.location import as_path
    from asp_dist.results.s3 import S3Path
    from asp_dist.sweep import ledger
    from asp_dist.sweep.spaces import expand

    with_curves = tiny_rows(with_curves=True)
    rows = [row for row, _ in with_curves]
    remote, local = as_path(on_s3), tmp_path / "local"
    assert isinstance(remote, S3Path) and str(remote) == on_s3
    store.write_manifest(remote, ledger.new_manifest("x", "smoke", expand("smoke")))
    for row, curve in with_curves:
        assert curve
        for where in (remote, local):
            assert store.write_curve(where, row, curve)
            assert store.write_row(where, row, "x")
    before = keys(s3, on_s3)
    assert not any(store.write_row(remote, row, "x") for row in rows), "a finished cell was written again"
    assert keys(s3, on_s3) == before, "a finished cell's object changed"
    pd.testing.assert_frame_equal(store.read_rows(remote), store.read_rows(local))
    pd.testing.assert_frame_equal(store.read_curves(remote), store.read_curves(local))
    assert store.done_cell_ids(remote) == {r["cell_id"] for r in rows}
    assert store.is_done(remote, "signaling", "asp", rows[1]["cell_id"])
    assert store.read_manifest(remote)["name"] == "x" and store.is_sweep_dir(remote)

    store.record_failure(remote, "c1", "signaling", "pc", "boom")
    store.record_failure(remote, "c1", "signaling", "pc", "Traceback\nValueError: again")
    assert store.failed_cells(remote)["c1"]["times_failed"] == 2
    assert store.last_error_line(store.failed_cells(remote)["c1"]) == "ValueError: again"
    store.clear_failure(remote, "c1")
    assert store.failed_cells(remote) == {}

    # The verified reader: a planted object is named and left out, or refused with strict=True.
    planted = remote / "cells" / "domain=signaling" / "method=osp" / "planted.parquet"
    planted.write_bytes(b"not parquet")
    capsys.readouterr()
    assert len(store.cell_files(remote)) == 3
    assert "planted.parquet is not counted" in capsys.readouterr().err
    with pytest.raises(SchemaError, match="planted"):
        store.cell_files(remote, strict=True)


def test_query_by_name_on_the_bucket(s3, on_s3, capsys, tmp_path, monkeypatch):
    from asp_dist.cli import main
    from asp_dist.results import store
    from asp_dist.results.location import as_path

    for row in tiny_rows():
        store.write_row(as_path(on_s3) / "q", row, "q")
    monkeypatch.chdir(tmp_path)
    assert main(["query", "q", "--results", on_s3, "--sql",
                 "SELECT method, count(*) AS n FROM cells GROUP BY method ORDER BY method", "--format", "csv"]) == 0
    assert capsys.readouterr().out.split() == ["method,n", "asp,2", "pc,1"]
    assert main(["query", f"{on_s3}/q", "--where", "paired = 4", "--columns", "method,paired",
                 "--format", "csv"]) == 0
    assert capsys.readouterr().out.split() == ["method,paired", "asp,4"]
    assert not list(tmp_path.iterdir()), "query wrote to the local disk"


# ---- leases ---------------------------------------------------------------------------------------------
RACE = """import sys, time
from asp_dist.results.location import as_path
from asp_dist.sweep.lease import Lease
lease = Lease(as_path(sys.argv[1]), ttl_s=30, renew_s=5)
time.sleep(max(0.0, float(sys.argv[2]) - time.time()))
busy = lease.try_acquire()
print("won" if busy is None else "lost", flush=True)
if busy is None:
    sys.stdin.readline()  # hold the lease until every racer has answered (a late one must still lose)
    lease.release()
"""


def test_exactly_one_of_racing_processes_gets_a_lease(s3, on_s3):
    start = time.time() + 4  # the processes import, then all ask at this moment
    procs = [subprocess.Popen([sys.executable, "-c", RACE, f"{on_s3}/lease", str(start)], env=s3.env,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(6)]
    try:
        answers = [p.stdout.readline().strip() for p in procs]
    finally:
        errors = [p.communicate("\n", timeout=120)[1] for p in procs]
    assert sorted(answers) == ["lost"] * 5 + ["won"], errors


HOLD = """import sys, time
from pathlib import Path
from asp_dist.results.location import as_path
from asp_dist.sweep.ledger import sweep_lock
with sweep_lock(as_path(sys.argv[1])):
    print("locked", flush=True)
    time.sleep(600)
"""


def test_sweep_lock_on_s3_refuses_a_second_run_and_frees_at_once_after_sigkill_here(s3, on_s3):
    from asp_dist.cli import main
    from asp_dist.results import store
    from asp_dist.results.location import as_path
    from asp_dist.sweep import ledger
    from asp_dist.sweep.spaces import expand

    results = f"{on_s3}/runs"
    sweep_dir = as_path(results) / "smoke"
    store.write_manifest(sweep_dir, ledger.new_manifest("smoke", "smoke", expand("smoke")))
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(sweep_dir)], env=s3.env, stdout=subprocess.PIPE,
                              text=True, start_new_session=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert ledger.lock_holder(sweep_dir).startswith(f"pid {holder.pid} on ")
        assert f"RUNNING (pid {holder.pid} on " in ledger.sweep_status("smoke", results).splitlines()[0]
        with pytest.raises(ledger.SweepError, match="already running"):
            with ledger.sweep_lock(sweep_dir, grace_s=0.5):
                pass
        before = keys(s3, str(sweep_dir))
        proc = subprocess.run([sys.executable, "-m", "asp_dist.cli", "sweep", "smoke", "--results", results],
                              env=s3.env, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and "is already running (pid" in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1
        assert keys(s3, str(sweep_dir)) == before
        holder.send_signal(signal.SIGKILL)
        holder.wait(30)
    finally:
        stop_now(holder)
    # Killed on this machine: its lease is seen to be dead at once, no waiting for it to lapse.
    assert ledger.lock_holder(sweep_dir) is None
    assert "not running" in ledger.sweep_status("smoke", results)
    with ledger.sweep_lock(sweep_dir, grace_s=0):  # taken at the first try: nothing to wait for
        assert ledger.lock_holder(sweep_dir).startswith(f"pid {os.getpid()} on ")
    assert ledger.lock_holder(sweep_dir) is None
    assert main(["status", "smoke", "--results", results]) == 0


def test_a_silent_lease_of_another_machine_is_waited_out_and_a_lost_lease_is_told(s3, on_s3):
    from asp_dist.results.location import as_path
    from asp_dist.sweep.lease import Lease

    prefix = as_path(on_s3) / "lease"
    # A holder elsewhere that stopped renewing: its record says it lapses 3 s after its last renewal.
    record = {"holder": "pid 1 on elsewhere since then", "host": "elsewhere", "pid": 1, "ttl_s": 3.0,
              "released": False}
    (prefix / "000000000001.json").write_bytes(json.dumps(record).encode())
    lease = Lease(prefix, ttl_s=30, renew_s=0.3)
    busy = lease.try_acquire()
    assert busy is not None and "pid 1 on elsewhere" in busy.describe()
    deadline = time.monotonic() + 20
    while (busy := lease.try_acquire()) is not None and time.monotonic() < deadline:
        time.sleep(0.5)
    assert busy is None and lease.generation == 2
    assert not (prefix / "000000000001.json").exists(), "the superseded generation was not removed"
    # Another process takes generation 3 (as it would after this one went silent): the holder is told.
    told = []
    lease.on_lost = told.append
    (prefix / "000000000003.json").write_bytes(json.dumps(dict(record, ttl_s=30.0)).encode())
    deadline = time.monotonic() + 10
    while not told and time.monotonic() < deadline:
        time.sleep(0.1)
    assert told and "taken over (generation 3)" in told[0] and lease.lost
    lease.release()
    assert json.loads((prefix / "000000000002.json").read_text())["released"] is False  # a lost lease is not written


def test_a_lease_that_would_block_for_ever_is_refused_at_once_saying_whose_and_until_when(s3, on_s3, monkeypatch):
    """A silent lease whose record says it lasts 10^9 s (planted, or another tool's) is not waited for: the
    run is refused in one line naming the holder and when the lease lapses (before: resume waited for ever)."""
    from asp_dist.results import store
    from asp_dist.results.location import as_path
    from asp_dist.sweep import ledger
    from asp_dist.sweep.lease import Lease
    from asp_dist.sweep.spaces import expand

    sweep_dir = as_path(f"{on_s3}/runs") / "smoke"
    store.write_manifest(sweep_dir, ledger.new_manifest("smoke", "smoke", expand("smoke")))
    record = {"holder": "pid 7 on far-away since then", "host": "far-away", "pid": 7, "ttl_s": 1e9, "released": False}
    (sweep_dir / ledger.LEASE_DIR / "000000000001.json").write_bytes(json.dumps(record).encode())
    # Renewed every 0.1 s, a lease is silent after 0.2 s (asp-dist's own: 5 s and 10 s): no test waits 10 s.
    monkeypatch.setattr(ledger, "_sweep_lease", lambda d: Lease(d / ledger.LEASE_DIR, renew_s=0.1))
    while ledger._sweep_lease(sweep_dir).current().age_s <= 0.3:
        time.sleep(0.1)
    before = keys(s3, str(sweep_dir))
    with pytest.raises(ledger.SweepError) as refused:
        with ledger.sweep_lock(sweep_dir, connect_timeout_s=5):
            pytest.fail("the lease was taken")
    message = str(refused.value)
    assert "held by pid 7 on far-away" in message and "lapses only in 99999" in message, message
    assert f"{ledger.lease_wait_bound_s(5):.0f} s this run waits" in message and "delete" in message
    assert keys(s3, str(sweep_dir)) == before, "the refused run wrote to the bucket"


def test_an_endpoint_that_accepts_but_never_answers_is_given_up_on(s3, tmp_path):
    """status, query and sweep against an S3 endpoint that takes the TCP connection and never answers end in
    one line within ASP_DIST_S3_TIMEOUT (sweep: --connect-timeout), not after the SDKs' 4 x 60 s of retries."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(64)
    endpoint = f"http://127.0.0.1:{server.getsockname()[1]}"
    running = []
    try:
        for command, extra in ((["status", "smoke"], {"ASP_DIST_S3_TIMEOUT": "2"}),
                               (["query", "smoke", "--sql", "SELECT 1"], {"ASP_DIST_S3_TIMEOUT": "2"}),
                               (["sweep", "smoke", "--connect-timeout", "2"], {})):  # the three wait at once
            running.append((command, subprocess.Popen(
                [sys.executable, "-m", "asp_dist.cli", *command, "--results", f"s3://{BUCKET}/x"],
                env=dict(s3.env, AWS_ENDPOINT_URL=endpoint, **extra), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                text=True, cwd=tmp_path)))
        for command, proc in running:
            _, stderr = proc.communicate(timeout=120)
            assert proc.returncode == 2, (command, stderr[-2000:])
            assert stderr.startswith(f"asp-dist: error: no answer from the S3 endpoint {endpoint}"), stderr
            assert "within 2 s" in stderr and len(stderr.strip().splitlines()) == 1, stderr
    finally:
        for _, proc in running:
            proc.kill()
        server.close()
    assert not list(tmp_path.iterdir())


BASE = """import hashlib, json, sys, time
import asp_dist.sweep.base_cache as cache
import asp_dist.training.bases as bases
from asp_dist.results.location import as_path
from asp_dist.spec import CellSpec
original = bases.train_accepted_base
def counting(spec, progress=None):
    print("trained", flush=True)
    time.sleep(1.0)  # widen the race window
    return original(spec, progress)
cache.train_accepted_base = counting
time.sleep(max(0.0, float(sys.argv[2]) - time.time()))
base, cached = cache.get_base(CellSpec(domain="signaling", method="asp", trial=5), as_path(sys.argv[1]))
print(json.dumps({"cached": cached, "sha": hashlib.sha256(bases.base_to_bytes(base)).hexdigest()}), flush=True)
"""


def test_two_workers_racing_for_one_base_train_it_once(s3, on_s3):
    from asp_dist.results.location import as_path
    from asp_dist.spec import CellSpec
    from asp_dist.sweep.base_cache import base_path

    bases_dir = as_path(on_s3) / "bases"
    start = time.time() + 5
    procs = [subprocess.Popen([sys.executable, "-c", BASE, str(bases_dir), str(start)], env=s3.env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1][-2000:] for o in outs]
    lines = [o[0].split() for o in outs]
    assert sum(line.count("trained") for line in lines) == 1, lines
    answers = [json.loads(o[0].strip().splitlines()[-1]) for o in outs]
    assert sorted(a["cached"] for a in answers) == [False, True]
    assert answers[0]["sha"] == answers[1]["sha"], "the two cells got different bases"
    key = CellSpec(domain="signaling", trial=5).resolved().base_key
    stored = [k for k in keys(s3, str(bases_dir)) if k.endswith(".pt")]
    assert stored == [base_path(bases_dir, key).key]


def test_a_base_planted_in_the_bucket_runs_nothing_and_is_set_aside_and_trained_again(s3, on_s3, tmp_path, capsys):
    """A shared bucket is where a planted base would be met: read as plain tensors, refused in one line, moved
    under damaged/ in the bucket, trained again and stored with a conditional PUT."""
    from planted import torch_pickle

    from asp_dist.results.location import as_path
    from asp_dist.spec import CellSpec
    from asp_dist.sweep.base_cache import base_path, get_base
    from asp_dist.training.bases import base_from_bytes

    spec = CellSpec(domain="signaling", method="asp", trial=5).resolved()
    bases_dir = as_path(on_s3) / "bases"
    planted = torch_pickle(tmp_path / "ran")
    base_path(bases_dir, spec.base_key).write_bytes(planted)
    base, cached = get_base(spec, bases_dir)
    assert not (tmp_path / "ran").exists(), "the planted base ran its code"
    assert not cached and base.key == spec.base_key
    assert base_from_bytes(base_path(bases_dir, spec.base_key).read_bytes(), spec).key == spec.base_key
    (kept,) = [k for k in keys(s3, on_s3 + "/damaged/") if k.endswith(f"/bases/{spec.base_key}.pt")]
    assert s3.client.get_object(Bucket=BUCKET, Key=kept)["Body"].read() == planted
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "refused unread" in lines[0] and "trained again" in lines[0], lines


# ---- bad input: one line, exit 2, nothing written -------------------------------------------------------
COMMANDS = (["sweep", "smoke", "--name", "exp"], ["resume", "exp"], ["status", "exp"],
            ["query", "exp", "--sql", "SELECT 1"], ["stats", "exp", "--no-figures", "--quiet"])


@pytest.fixture(scope="module")
def auth_s3(tmp_path_factory):
    """A second moto server that checks credentials, with one user, one key and one bucket holding a sweep."""
    log = tmp_path_factory.mktemp("moto-auth") / "moto.log"
    proc, endpoint = start_moto(log, authenticate=True)
    try:
        iam = boto3.client("iam", endpoint_url=endpoint, region_name=REGION, aws_access_key_id="x",
                           aws_secret_access_key="x")
        iam.create_user(UserName="asp")
        iam.put_user_policy(UserName="asp", PolicyName="all", PolicyDocument=json.dumps(
            {"Version": "2012-10-17", "Statement": [{"Effect": "Allow", "Action": "*", "Resource": "*"}]}))
        key = iam.create_access_key(UserName="asp")["AccessKey"]
        client = s3_client(endpoint, key["AccessKeyId"], key["SecretAccessKey"])
        client.create_bucket(Bucket=BUCKET)
        client.put_object(Bucket=BUCKET, Key="runs/exp/manifest.json", Body=b'{"cells": []}')
        yield SimpleNamespace(endpoint=endpoint, key=key["AccessKeyId"], client=client)
    finally:
        stop_now(proc)


def all_keys(client) -> set[str]:
    return {o["Key"] for o in client.list_objects_v2(Bucket=BUCKET).get("Contents", [])}


@pytest.mark.parametrize("case", ["unreachable-endpoint", "wrong-credentials", "missing-bucket"])
@pytest.mark.xdist_group("auth-s3")  # shares a module fixture: one worker
def test_bad_storage_is_one_line_and_exit_2_with_nothing_written(case, s3, auth_s3, monkeypatch, capsys, tmp_path):
    from asp_dist.cli import main

    monkeypatch.chdir(tmp_path)
    bucket, env = BUCKET, dict(s3.env)
    if case == "unreachable-endpoint":
        env["AWS_ENDPOINT_URL"] = f"http://127.0.0.1:{free_port()}"
        needle = "cannot reach the S3 endpoint"
    elif case == "wrong-credentials":
        env.update(AWS_ENDPOINT_URL=auth_s3.endpoint, AWS_ACCESS_KEY_ID=auth_s3.key, AWS_SECRET_ACCESS_KEY="wrong")
        needle = "refused by"
    else:
        bucket, needle = "asp-no-such-bucket", "bucket 'asp-no-such-bucket' does not exist"
    use_env(monkeypatch, env)
    before = (all_keys(s3.client), all_keys(auth_s3.client))
    for command in COMMANDS:
        assert main([*command, "--results", f"s3://{bucket}/runs"]) == 2, command
        err = capsys.readouterr().err
        assert err.startswith("asp-dist: error: ") and needle in err and len(err.strip().splitlines()) == 1, err
    assert (all_keys(s3.client), all_keys(auth_s3.client)) == before, "something was written"
    if case == "missing-bucket":
        assert bucket not in {b["Name"] for b in s3.client.list_buckets()["Buckets"]}, "a bucket was created"
    assert not list(tmp_path.iterdir()), "something was written to the local disk"


REFUSED_WITHOUT_RAY = """import sys
from asp_dist.cli import main
code = main(sys.argv[1:])
assert 'ray' not in sys.modules, 'ray was imported'
sys.exit(code)
"""


def test_an_unreachable_endpoint_is_refused_before_ray_starts(s3, tmp_path):
    env = dict(s3.env, AWS_ENDPOINT_URL=f"http://127.0.0.1:{free_port()}")
    proc = subprocess.run([sys.executable, "-c", REFUSED_WITHOUT_RAY, "sweep", "smoke", "--results",
                           f"s3://{BUCKET}/runs"], env=env, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.startswith("asp-dist: error: cannot reach the S3 endpoint http://127.0.0.1:")
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not list(tmp_path.iterdir())


# ---- sweeps on Ray ----------------------------------------------------------------------------------------
def cli(s3, *args, cwd, timeout=600, **extra):
    return subprocess.run([sys.executable, "-m", "asp_dist.cli", *args], env=dict(s3.env, **extra), cwd=cwd,
                          capture_output=True, text=True, timeout=timeout, start_new_session=True)


def local_results(*roots: Path) -> list[Path]:
    """Result files (cells, curves, bases, manifests) under the given local directories."""
    found = []
    for root in roots:
        if Path(root).exists():
            found += [p for p in Path(root).rglob("*") if p.is_file() and (
                p.suffix in (".parquet", ".pt") or p.name == "manifest.json" or p.parent.name == "failed")]
    return found


@pytest.fixture(scope="module")
def smoke_on_s3(s3, tmp_path_factory):
    """`asp-dist sweep smoke --results s3://…` run once, from an empty working directory."""
    cwd = tmp_path_factory.mktemp("smoke-cwd")
    ray_temp = f"/tmp/asp-s3s-{os.getpid()}"
    results = f"s3://{BUCKET}/smoke-runs"
    start = time.monotonic()
    proc = cli(s3, "sweep", "smoke", "--results", results, "--ray-temp-dir", ray_temp, cwd=cwd)
    seconds = time.monotonic() - start
    yield SimpleNamespace(proc=proc, results=results, cwd=cwd, ray_temp=ray_temp, seconds=seconds)
    subprocess.run(["rm", "-rf", ray_temp])


@pytest.mark.slow
@pytest.mark.xdist_group("smoke-s3")  # shares a module fixture: one worker
def test_smoke_sweep_on_s3(s3, smoke_on_s3):
    from asp_dist.results import s3 as results_s3
    from asp_dist.results import store
    from asp_dist.sweep.spaces import expand

    run = smoke_on_s3
    assert run.proc.returncode == 0, run.proc.stderr[-3000:]
    assert "18/18 cells done, 0 failed" in run.proc.stdout
    assert f"results in {run.results}/smoke" in run.proc.stderr
    objects = keys(s3, f"{run.results}/smoke/")
    prefix = "smoke-runs/smoke/"
    cells = [k for k in objects if k.startswith(prefix + "cells/") and k.endswith(".parquet")]
    assert len(cells) == 18
    assert len([k for k in objects if k.startswith(prefix + "curves/")]) == 18
    assert len([k for k in objects if k.startswith(prefix + "bases/") and k.endswith(".pt")]) == 2
    assert prefix + "manifest.json" in objects and prefix + "tune/current.json" in objects
    assert any(k.startswith(prefix + "tune/run-1/experiment_state-") for k in objects), "Tune's state is not in the bucket"
    assert not local_results(run.cwd, run.ray_temp), "result files on the local disk"
    # Each trial's params.json went up once, not again at every later sync of Tune's experiment directory
    # (asp_dist.sweep.tune_storage): 29 PUTs of them for 18 trials before.
    puts = re.findall(r'"PUT /[^/ ]+/smoke-runs/smoke/tune/run-1/([^/ ]+)/params\.json ', s3.log.read_text())
    assert len(puts) == 18 and len(set(puts)) == 18, sorted(puts)
    env_files = {"command.txt", "space.toml", "git.txt", "distributions.txt", "machine.json"}
    assert {k.rsplit("/", 1)[1] for k in objects if k.startswith(prefix + "env/1/")} >= env_files  # provenance

    with pytest.MonkeyPatch.context() as mp:
        use_env(mp, s3.env)
        df = store.read_rows(f"{run.results}/smoke")
        results_s3._CLIENTS.clear()
    assert set(df["cell_id"]) == {s.cell_id for s in expand("smoke")} and df["ray_node_id"].notna().all()

    again = cli(s3, "sweep", "smoke", "--results", run.results, "--ray-temp-dir", run.ray_temp, cwd=run.cwd)
    assert again.returncode == 0 and "18 already done" in again.stderr, again.stderr[-2000:]
    after = keys(s3, f"{run.results}/smoke/")
    assert {k: after[k] for k in cells} == {k: objects[k] for k in cells}, "a finished cell was rewritten"
    assert {k: after[k] for k in objects if "/env/1/" in k} == {k: v for k, v in objects.items() if "/env/1/" in k}
    # It took the sweep's lease (a new generation under .lease/) to check the grid, and wrote nothing else.
    unleased = {k for k in after if "/.lease/" not in k}
    assert unleased == {k for k in objects if "/.lease/" not in k}, f"a run that trained nothing wrote {sorted(unleased - set(objects))}"
    resumed = cli(s3, "resume", "smoke", "--results", run.results, "--ray-temp-dir", run.ray_temp, cwd=run.cwd)
    assert resumed.returncode == 0 and "nothing to resume" in resumed.stderr, resumed.stderr[-2000:]
    assert keys(s3, f"{run.results}/smoke/") == after, "resuming a finished sweep wrote to the bucket"
    status = cli(s3, "status", "smoke", "--results", run.results, cwd=run.cwd)
    assert status.stdout.splitlines()[-1].split() == ["total", "18", "0", "0"] and "not running" in status.stdout


@pytest.mark.slow
@pytest.mark.xdist_group("smoke-s3")  # shares a module fixture: one worker
def test_query_and_stats_of_a_sweep_on_s3(s3, smoke_on_s3):
    run = smoke_on_s3
    assert run.proc.returncode == 0, run.proc.stderr[-3000:]
    query = cli(s3, "query", "smoke", "--results", run.results, "--sql",
                "SELECT method, count(*) AS n FROM cells GROUP BY method ORDER BY method", "--format", "csv",
                cwd=run.cwd)
    assert query.returncode == 0 and query.stdout.split() == ["method,n", "asp,6", "osp,6", "pc,6"], query.stderr
    curves = cli(s3, "query", f"{run.results}/smoke", "--curves", "--sql", "SELECT count(DISTINCT cell_id) AS n "
                 "FROM curves", "--format", "csv", cwd=run.cwd)
    assert curves.stdout.split() == ["n", "18"], curves.stderr
    stats = cli(s3, "stats", "smoke", "--results", run.results, "--bootstrap", "200", cwd=run.cwd)
    assert stats.returncode == 0, stats.stderr[-3000:]
    assert f"report: {run.results}/smoke/report.md" in stats.stderr
    report = s3.client.get_object(Bucket=BUCKET, Key="smoke-runs/smoke/report.md")["Body"].read().decode()
    assert "18 rows" in report
    objects = keys(s3, f"{run.results}/smoke/")
    assert "smoke-runs/smoke/stats/summary.parquet" in objects
    assert any(k.startswith("smoke-runs/smoke/figures/") and k.endswith(".png") for k in objects)
    assert not local_results(run.cwd) and not [p for p in run.cwd.rglob("*") if p.suffix in (".md", ".png")]


@pytest.mark.slow
@pytest.mark.xdist_group("smoke-s3")  # shares a module fixture: one worker
def test_a_damaged_sweep_extended_then_killed_resumes_to_every_cell_once_on_s3(s3, smoke_on_s3, tmp_path):
    """The S3 twin of tests/test_sweep.py's test of the same name: three of the smoke sweep's cell objects
    damaged (cut short, empty, another cell's), the sweep grown by the kill grid with `--extend` and its driver
    SIGKILLed mid-extension, then `resume`:

    - the damaged objects are copied into damaged/ and deleted (one warning each), their cells train again
      and each row is written once; the other objects are not rewritten;
    - the extension's grid and history are in manifest.json before any new cell runs;
    - the dead driver's lease is seen at once (`status`: not running);
    - resume restores Tune's experiment from the bucket: every cell once, rows as uninterrupted, a cell running
      at the kill continued from its checkpoint, nothing on the local disk.
    Runs after the other smoke_on_s3 tests (it changes the sweep they read)."""
    from asp_dist.results import s3 as results_s3
    from asp_dist.results import store
    from asp_dist.sweep.spaces import expand

    run = smoke_on_s3
    assert run.proc.returncode == 0, run.proc.stderr[-3000:]
    prefix = "smoke-runs/smoke/"
    cells = sorted(k for k in keys(s3, f"{run.results}/smoke/cells/") if k.endswith(".parquet"))

    def read_rows():
        with pytest.MonkeyPatch.context() as mp:
            use_env(mp, s3.env)
            df = store.read_rows(f"{run.results}/smoke")
            results_s3._CLIENTS.clear()
        return df

    rows = comparable_rows(read_rows())
    body = {k: s3.client.get_object(Bucket=BUCKET, Key=k)["Body"].read() for k in cells[:4]}
    cut, empty, wrong = cells[:3]
    s3.client.put_object(Bucket=BUCKET, Key=cut, Body=body[cut][:200])
    s3.client.put_object(Bucket=BUCKET, Key=empty, Body=b"")
    s3.client.put_object(Bucket=BUCKET, Key=wrong, Body=body[cells[3]])
    intact = {k: v for k, v in keys(s3, f"{run.results}/smoke/cells/").items() if k not in (cut, empty, wrong)}

    grown = run.cwd / "smoke-grown.toml"
    grown.write_text('include = ["smoke"]\n' + KILL_GRID)
    specs = expand(str(grown))
    new_cells = {s.cell_id for s in expand(space(tmp_path, KILL_GRID))}
    assert len(specs) == 22 and len(new_cells) == 4

    def cells_done() -> set[str]:
        return {k.rsplit("/", 1)[1][:-8] for k in keys(s3, prefix + "cells/") if k.endswith(".parquet")}

    def newest_state() -> str:
        states = sorted(k for k in keys(s3, prefix + "tune/run-2/") if k.rsplit("/", 1)[1].startswith("experiment_state-"))
        return s3.client.get_object(Bucket=BUCKET, Key=states[-1])["Body"].read().decode() if states else ""

    def checkpoint_in_the_bucket(cell: str, index: int) -> bool:
        return bool(keys(s3, f"{prefix}tune/run-2/{cell}/checkpoint_{index:06d}/state.pt"))

    ray_temp = f"/tmp/asp-s3k-{os.getpid()}"
    driver = start_cli("sweep", str(grown), "--name", "smoke", "--extend", "--results", run.results,
                       "--checkpoint-every", "0.3", "--ray-temp-dir", ray_temp, log_dir=tmp_path / "log",
                       base_env=s3.env, cwd=run.cwd)
    try:
        # Killed once a new cell has its row and another, still running, has a checkpoint that the bucket holds
        # and the Tune state in the bucket names; that cell's worker is stopped first (harness).
        wait_for(lambda: cells_done() & new_cells, 300, poll_s=0.3, while_alive=driver, what="a new cell done")
        hold_a_running_cell_at_its_checkpoint(newest_state, checkpoint_in_the_bucket, cells_done, ray_temp, 300, driver)
        driver.send_signal(signal.SIGKILL)
        driver.wait(30)
    finally:
        kill_group(driver)
        kill_all(driver.pid, ray_temp)
    _, killed_err = read_log(tmp_path / "log")
    warnings = [line for line in killed_err.splitlines() if "the cell trains again" in line]
    assert len(warnings) == 3 and all(line.startswith("asp-dist: warning: s3://") for line in warnings), killed_err
    kept = [k for k in keys(s3, f"{run.results}/smoke/{store.DAMAGED_DIR}/") if "/cells/" in k]
    assert sorted(k.rsplit("/", 1)[1] for k in kept) == sorted(k.rsplit("/", 1)[1] for k in (cut, empty, wrong))
    assert all(k.startswith(prefix + store.DAMAGED_DIR + "/") for k in kept)
    manifest = json.loads(s3.client.get_object(Bucket=BUCKET, Key=prefix + "manifest.json")["Body"].read())
    assert [h["cells"] for h in manifest["history"]] == [18, 22] and manifest["cells"] == [s.cell_id for s in specs]
    done_at_kill = len(cells_done())
    assert 15 <= done_at_kill < len(specs)
    status = cli(s3, "status", "smoke", "--results", run.results, cwd=run.cwd)
    assert "not running" in status.stdout, status.stdout + status.stderr  # the dead driver's lease, seen at once

    resumed = cli(s3, "resume", "smoke", "--results", run.results, "--checkpoint-every", "0.3", "--ray-temp-dir",
                  ray_temp, cwd=run.cwd)
    subprocess.run(["rm", "-rf", ray_temp])
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"({done_at_kill} already done)" in resumed.stderr and "22/22 cells done, 0 failed" in resumed.stdout
    df = read_rows()
    assert {k: v for k, v in comparable_rows(df).items() if k not in new_cells} == rows, \
        "a redone cell's row differs from its first run's"
    assert_rows_match(df[df["cell_id"].isin(new_cells)], expected_rows([s for s in specs if s.cell_id in new_cells]))
    after = keys(s3, f"{run.results}/smoke/cells/")
    assert {k: after[k] for k in intact} == intact, "a valid cell's object was rewritten"
    assert df["resumed_from_step"].notna().any(), \
        "no cell continued from a checkpoint restored from the bucket: " + resumed.stderr[-3000:]
    assert not local_results(run.cwd, run.ray_temp), "result files on the local disk"


@pytest.fixture
def two_nodes_without_shared_disk(s3, tmp_path):
    """Two Ray nodes on loopback, each with its own temp dir and working directory, both with the S3 env and
    Ray's token authentication on (the driver joins with cluster.env)."""
    dirs = {name: tmp_path / name for name in ("head", "worker", "driver")}
    for d in dirs.values():
        d.mkdir()
    temps = [f"/tmp/asp-s3h-{os.getpid()}", f"/tmp/asp-s3w-{os.getpid()}"]
    with ray_cluster(temps, base_env=s3.env, cwds=[dirs["head"], dirs["worker"]]) as cluster:
        cluster.dirs = dirs
        yield cluster


@pytest.mark.slow
def test_two_node_cluster_with_results_on_s3_and_none_on_disk(s3, tmp_path, two_nodes_without_shared_disk):
    """A sweep joins a two-node Ray cluster with `--address` (refused in one line without the cluster's token),
    its cells run on both nodes, and with results on S3 nothing lands on any node's disk. (The suite's one
    multi-node sweep: a cluster costs it two Ray start-ups, and this one covers what a cluster on a shared
    local disk would, plus the nodes that share nothing.)"""
    from asp_dist.results import s3 as results_s3
    from asp_dist.results import store

    cluster = two_nodes_without_shared_disk
    grid = space(tmp_path, """
[[grid]]
fixed = { train_steps = 300, unpaired_size = 256 }
axes = { domain = ["signaling"], method = ["osp", "asp"], paired = [0, 2, 4] }
""")
    results = f"s3://{BUCKET}/cluster-runs"
    # Without the cluster's token: refused in one line, nothing written.
    refused = cli(s3, "sweep", grid, "--name", "c", "--results", results, "--address", cluster.address,
                  "--connect-timeout", "5", cwd=cluster.dirs["driver"])
    assert refused.returncode == 2, refused.stderr[-3000:]
    errors = [line for line in refused.stderr.splitlines() if line.startswith("asp-dist: error:")]
    assert len(errors) == 1 and "RAY_AUTH_TOKEN" in errors[0], refused.stderr[-3000:]
    assert not keys(s3, "cluster-runs/c/"), keys(s3, "cluster-runs/c/")
    proc = cli(s3, "sweep", grid, "--name", "c", "--results", results, "--address", cluster.address, "--workers", "2",
               cwd=cluster.dirs["driver"], RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=cluster.env["RAY_AUTH_TOKEN"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"cluster {cluster.address}" in proc.stderr
    with pytest.MonkeyPatch.context() as mp:
        use_env(mp, s3.env)
        df = store.read_rows(f"{results}/c")
        results_s3._CLIENTS.clear()
    assert len(df) == 6 and df["cell_id"].is_unique
    assert df["ray_node_id"].nunique() == 2, df[["cell_id", "ray_node_id"]]
    roots = [*cluster.dirs.values(), *cluster.temps]
    assert not local_results(*roots), local_results(*roots)
    named = [p for root in roots if root.exists() for p in root.rglob("*")
             if any(p.name.startswith(c) and p.suffix in (".parquet", ".json", ".pt") for c in df["cell_id"])]
    assert not named, named
