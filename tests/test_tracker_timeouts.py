"""A tracker's server that does not answer is given up on in bounded time, on real sockets and real clients:
a closed loopback port and a listening socket that never replies (the kernel completes the handshake, nothing
answers the request). Before anything runs, `sweep --logger mlflow|wandb` refuses such a server in one line
within --connect-timeout, writing nothing; during a sweep, a real MLflow server (MLflow's own tracking app)
that goes away holds the hub for one bounded call, and the tracker is switched off with one warning.

Every bound asserted is far above the expected time (the timeout is 2 s; the assertions allow 60 s), so a
check only proves "did not hang": MLflow's own defaults hold a call for minutes (7 retries with backoff, 120 s
per read), W&B's init for 90 s."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
from harness import cli, env, free_port, kill_group, wait_for

from asp_dist.spec import CellSpec
from asp_dist.tracking import TrackingSettings
from asp_dist.tracking.cells import describe_cells
from asp_dist.tracking.hub import Hub

TIMEOUT_S = 2  # --connect-timeout of these tests
BOUND_S = 60  # "did not hang": far above what each case takes (about TIMEOUT_S, plus starting Python)
MLFLOW_HTTP = ("MLFLOW_HTTP_REQUEST_TIMEOUT", "MLFLOW_HTTP_REQUEST_MAX_RETRIES", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR")


@pytest.fixture
def silent_port():
    """A loopback port that accepts TCP connections (into the listen backlog) and never answers."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen(64)
        yield sock.getsockname()[1]


def closed_port() -> int:
    return free_port()  # bound and released: nothing listens there


def refused(args: list[str], tmp_path: Path, **extra_env: str | None) -> tuple[list[str], float]:
    """Run `asp-dist sweep smoke` with `args`; (its stderr lines, seconds it took), asserting exit 2, one line,
    nothing written."""
    results = tmp_path / "results"
    started = time.monotonic()
    done = cli("sweep", "smoke", "--results", str(results), "--connect-timeout", str(TIMEOUT_S), *args,
               timeout=4 * BOUND_S, MLFLOW_TRACKING_URI=None, **extra_env)
    took = time.monotonic() - started
    err = done.stderr.strip().splitlines()
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    assert len(err) == 1 and err[0].startswith("asp-dist: error: "), err
    assert "Traceback" not in done.stderr
    assert not results.exists(), "nothing written: no sweep directory"
    assert took < BOUND_S, f"took {took:.1f} s with --connect-timeout {TIMEOUT_S}"
    return err, took


# ---- MLflow: refused before anything runs ----------------------------------------------------------------
@pytest.mark.parametrize("server, says", [
    ("closed", "cannot be used ([Errno 111] Connection refused)"),
    ("silent", f"did not answer within {TIMEOUT_S} s"),
])
def test_an_mlflow_server_that_does_not_answer_is_refused_within_the_connect_timeout(server, says, tmp_path,
                                                                                     request):
    port = closed_port() if server == "closed" else request.getfixturevalue("silent_port")
    uri = f"http://127.0.0.1:{port}"
    # MLflow's own defaults, as a user has them (an explicit setting would be the user's to keep)
    err, _ = refused(["--logger", "mlflow", "--mlflow-uri", uri], tmp_path, **{k: None for k in MLFLOW_HTTP})
    assert err[0].startswith(f"asp-dist: error: --logger mlflow: tracking URI {uri} ") and says in err[0], err


# ---- W&B online: refused before anything runs ------------------------------------------------------------
def wandb_env(tmp_path: Path, **extra: str | None) -> dict[str, str | None]:
    """W&B online against `WANDB_BASE_URL`, its files and credentials confined to tmp_path."""
    return {"WANDB_MODE": "online", "WANDB_API_KEY": "a" * 40, "NETRC": str(tmp_path / "no-netrc"),
            "WANDB_CONFIG_DIR": str(tmp_path / "wandb-config"), "WANDB_CACHE_DIR": str(tmp_path / "wandb-cache"),
            "WANDB_DIR": str(tmp_path / "wandb-dir"), "WANDB_SILENT": "true"} | extra


@pytest.mark.parametrize("server", ["closed", "silent"])
def test_a_w_and_b_server_that_does_not_answer_is_refused_within_the_connect_timeout(server, tmp_path, request):
    pytest.importorskip("wandb")
    port = closed_port() if server == "closed" else request.getfixturevalue("silent_port")
    base = f"http://127.0.0.1:{port}"
    err, _ = refused(["--logger", "wandb"], tmp_path, **wandb_env(tmp_path, WANDB_BASE_URL=base))
    # W&B's login check answers a dead server after its own 10 s: --connect-timeout gives up first
    assert err[0].startswith(f"asp-dist: error: --logger wandb: {base} did not answer within {TIMEOUT_S} s"), err


def test_w_and_b_online_without_credentials_is_refused_in_one_line(tmp_path):
    pytest.importorskip("wandb")
    err, _ = refused(["--logger", "wandb"], tmp_path,
                     **wandb_env(tmp_path, WANDB_API_KEY=None, WANDB_BASE_URL=f"http://127.0.0.1:{closed_port()}"))
    assert "W&B online mode needs credentials" in err[0], err


# ---- during the sweep: a tracker that goes away ----------------------------------------------------------
SPECS = [CellSpec(domain="signaling", method=m, paired=2, trial=0).resolved() for m in ("pc", "asp")]


def cells():
    return describe_cells(SPECS, "gone", "rev0", lambda d: ("mixed",))


def points(steps):
    return [{"step": float(s), "loss_paired": 1.0 / s, "loss_total": 2.0 / s} for s in steps]


@pytest.fixture
def mlflow_http_env(monkeypatch):
    """The tracker sets MLflow's HTTP bounds in the process that logs (here pytest's): MLflow's defaults first,
    and whatever it sets is removed after the test."""
    for name in MLFLOW_HTTP:
        monkeypatch.setenv(name, "0")
        monkeypatch.delenv(name)


SERVER = """
import os, sys
os.environ["_MLFLOW_SERVER_FILE_STORE"] = sys.argv[2]
os.environ["_MLFLOW_SERVER_ARTIFACT_ROOT"] = sys.argv[3]
from mlflow.server import app
app.run(host="127.0.0.1", port=int(sys.argv[1]), threaded=True)
"""


@pytest.fixture
def mlflow_server(tmp_path):
    """A real MLflow tracking server (MLflow's own app, on its SQLite store) on a loopback port; (uri, process)."""
    pytest.importorskip("flask")
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-c", SERVER, str(port), f"sqlite:///{tmp_path / 'server.db'}",
                             str(tmp_path / "artifacts")], env=env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    uri = f"http://127.0.0.1:{port}"

    def answers() -> bool:
        try:
            with urllib.request.urlopen(f"{uri}/api/2.0/mlflow/experiments/search?max_results=1", timeout=2):
                return True
        except OSError:
            return False

    try:
        wait_for(answers, 120, poll_s=0.2, while_alive=proc, what="the MLflow server answering")
        yield uri, proc
    finally:
        kill_group(proc)
        proc.wait(timeout=30)


@pytest.mark.slow
@pytest.mark.parametrize("then", ["closed", "silent"])
def test_an_mlflow_server_that_goes_away_mid_sweep_holds_the_hub_for_one_bounded_call(then, mlflow_server,
                                                                                       mlflow_http_env, tmp_path):
    from mlflow.tracking import MlflowClient

    uri, proc = mlflow_server
    settings = TrackingSettings(("mlflow", "json"), mlflow_uri=uri, timeout_s=TIMEOUT_S).resolved(tmp_path / "t")
    pc, asp = (c.cell_id for c in cells().values())
    hub = Hub(settings, "gone", cells())
    assert hub.ready() == []
    hub.points([(pc, points([1, 2, 3]))])
    run = MlflowClient(tracking_uri=uri).search_runs(
        [MlflowClient(tracking_uri=uri).get_experiment_by_name("gone").experiment_id],
        f"tags.`asp_dist.cell_id` = '{pc}'")[0]
    assert [m.step for m in MlflowClient(tracking_uri=uri).get_metric_history(run.info.run_id, "loss/paired")] == \
        [1, 2, 3]

    kill_group(proc)  # the server goes away ...
    proc.wait(timeout=30)
    silent = None
    if then == "silent":  # ... and something on its port accepts connections and never answers
        silent = socket.socket()
        silent.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        silent.bind(("127.0.0.1", int(uri.rsplit(":", 1)[1])))
        silent.listen(64)
    try:
        started = time.monotonic()
        hub.points([(pc, points([4, 5])), (asp, points([1]))])
        took = time.monotonic() - started
        assert took < BOUND_S, f"one hub call took {took:.1f} s with --connect-timeout {TIMEOUT_S}"
        warnings = hub.take_warnings()
        assert len(warnings) == 1 and warnings[0].startswith("asp-dist: warning: logger mlflow failed while logging"), \
            warnings
        started = time.monotonic()  # switched off: the rest of the run does not wait on it
        hub.points([(pc, points([6]))])
        hub.finish(pc, {"eval_mixed": 0.5}, 6)
        assert hub.close(interrupted=False) == []
        assert time.monotonic() - started < BOUND_S
        lines = (Path(settings.dir) / "json").rglob("*.jsonl")
        assert sum(1 for f in lines for line in f.read_text().splitlines() if '"final"' in line) >= 1, \
            "the other tracker went on"
    finally:
        if silent is not None:
            silent.close()


WANDB_HUB = """
import json, sys
from asp_dist.spec import CellSpec
from asp_dist.tracking import TrackingSettings
from asp_dist.tracking.cells import describe_cells
from asp_dist.tracking.hub import Hub

spec = CellSpec(domain="signaling", method="asp", paired=2, trial=0).resolved()
cells = describe_cells([spec], "gone", "rev0", lambda d: ("mixed",))
settings = TrackingSettings(("wandb",), timeout_s=float(sys.argv[2])).resolved(sys.argv[1])
hub = Hub(settings, "gone", cells)
hub.points([(spec.cell_id, [{"step": 1.0, "loss_paired": 1.0}])])
hub.finish(spec.cell_id, {"eval_mixed": 0.5}, 1)
print(json.dumps(hub.close(interrupted=False) + hub.take_warnings()))
"""


@pytest.mark.slow
def test_a_w_and_b_server_that_goes_away_holds_the_hub_for_one_bounded_init(tmp_path):
    """A cell's wandb.init on a server that does not answer (online; the check passed before it went away) gives
    up after --connect-timeout, not W&B's 90 s: one warning, the tracker is off. In its own process: W&B keeps
    process-wide state."""
    pytest.importorskip("wandb")
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-c", WANDB_HUB, str(tmp_path / "t"), str(TIMEOUT_S)], check=False,
                          capture_output=True, text=True, timeout=4 * BOUND_S,
                          env=env(**wandb_env(tmp_path, WANDB_BASE_URL=f"http://127.0.0.1:{closed_port()}")))
    took = time.monotonic() - started
    assert done.returncode == 0, done.stderr[-2000:]
    warnings = json.loads(done.stdout.strip().splitlines()[-1])
    assert len(warnings) == 1 and warnings[0].startswith("asp-dist: warning: logger wandb failed while logging"), \
        warnings
    assert took < BOUND_S, f"took {took:.1f} s with --connect-timeout {TIMEOUT_S}"
