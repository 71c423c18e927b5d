"""The Ray a sweep runs on: the embedded one (loopback only, token auth, its temp dir and session dirs, a
reaper that outlives a killed driver) or a cluster joined with --address (with a deadline on its first
answer, and SIGINT/SIGTERM that reach a driver stuck inside Ray's client). sweep.tune runs Tune on it."""

from __future__ import annotations

import getpass
import inspect
import logging
import os
import secrets
import select
import shutil
import signal
import subprocess
import sys
import threading
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Iterator, TextIO

import ray
from ray.exceptions import AuthenticationError

from asp_dist.errors import SweepError
from asp_dist.sweep import ledger, worker_start
from asp_dist.sweep import reaper as reaper_program

OBJECT_STORE_BYTES = 100 * 1024**2  # cells exchange no large objects; Ray's minimum is ~75 MB
# No pool workers started with the first driver (one per CPU). While Tune gave every trainable a runtime env they
# could never run a cell: with 2 workers the tracker hub's actor took one and the other idled all sweep long
# (≈ 0.9 CPU-s of imports, and its memory; on a 64-CPU node 63 would). The embedded Ray's trainables now start
# without one (worker_start), so a prestarted worker could take a cell, but that only moves a start earlier, and
# a sweep with fewer cells pending than CPUs would still idle the rest: every worker starts on demand.
SYSTEM_CONFIG = {"prestart_worker_first_driver": False}
RAY_SESSIONS_KEPT = 3  # session_* dirs of the embedded Ray kept at start (logs of the last runs)
RAY_SESSION_MIN_AGE_S = 300.0  # a younger session may belong to a Ray that is starting: never pruned

log = logging.getLogger(__name__)


# ---- Ray ----------------------------------------------------------------------------------------
LOOPBACK = "127.0.0.1"


@contextmanager
def loopback_only() -> Iterator[None]:
    """The environment of an embedded Ray that nobody else can reach: every server of it (GCS, raylet,
    object manager, workers, the driver's own) binds 127.0.0.1, and it asks for a token anyway.

    Loopback: Ray binds a node's servers to the loopback address only when its node IP is 127.0.0.1, and
    it keeps that IP (instead of swapping in the machine's address) only in its single-machine mode,
    RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 -- read from the environment by the processes it starts, and
    at import by this one, hence the constant set too. Token: loopback is open to every local user of
    a shared machine, so with RAY_AUTH_MODE unset Ray's own default for a new local cluster (token
    authentication) stays on, with a random per-process RAY_AUTH_TOKEN where the user configured none
    (no RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token): it lives in the environment of this
    process and of the Ray processes it starts, and nothing is written to ~/.ray. RAY_AUTH_MODE set by
    the user is theirs. tests/test_sweep.py checks the listening sockets of a running sweep."""
    from ray._private import ray_constants

    keys = (ray_constants.ENABLE_RAY_CLUSTERS_ENV_VAR, "RAY_AUTH_MODE", "RAY_AUTH_TOKEN")
    saved_env = {k: os.environ.get(k) for k in keys}
    saved_flag = ray_constants.ENABLE_RAY_CLUSTER
    os.environ[ray_constants.ENABLE_RAY_CLUSTERS_ENV_VAR] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    configured = (os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
                  or (Path.home() / ".ray" / "auth_token").is_file())
    if "RAY_AUTH_MODE" not in os.environ and not configured:
        os.environ["RAY_AUTH_TOKEN"] = _session_token()
    # Ray says at every start that it turned token authentication on: that is the expected state here.
    auth_log = logging.getLogger("ray._private.authentication.authentication_token_setup")
    level = auth_log.level
    auth_log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        auth_log.setLevel(level)
        ray_constants.ENABLE_RAY_CLUSTER = saved_flag
        for key, value in saved_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


_TOKEN: list[str] = []


def _session_token() -> str:
    """One random token per process: Ray's token loader caches the first one it reads."""
    if not _TOKEN:
        _TOKEN.append(secrets.token_hex(32))
    return _TOKEN[0]


RAY_TEMP_ENV = "ASP_DIST_RAY_TEMP_DIR"  # the default of --ray-temp-dir (the test suite sets one per xdist worker)


def default_ray_temp_dir() -> str:
    """Short (Unix sockets live under it, ~107-char limit) and per user, never a bare /tmp/ray."""
    return os.environ.get(RAY_TEMP_ENV) or f"/tmp/asp-ray-{getpass.getuser()}"


@contextmanager
def ray_session(workers: int, address: str | None, temp_dir: str | None, *, dashboard: bool = False,
                connect_timeout_s: float = ledger.DEFAULT_CONNECT_TIMEOUT_S,
                stream: TextIO | None = None) -> Iterator[None]:
    """Ray for one run: joined at ``address`` within ``connect_timeout_s``, or embedded (its old
    session dirs pruned, no dashboard unless asked, and then on 127.0.0.1 only, a reaper that ends
    its processes when this process dies). Shut down on the way out, however the run ends."""
    if ray.is_initialized():
        raise SweepError("Ray is already initialised in this process; run the sweep in a fresh process")
    common = dict(log_to_driver=False, logging_level=logging.WARNING, configure_logging=True)
    main_thread = threading.current_thread() is threading.main_thread()
    sigterm = signal.getsignal(signal.SIGTERM) if main_thread else None
    reaper = None
    stack = ExitStack()  # the embedded Ray's environment, put back after its shutdown
    try:
        try:
            if address:
                with _connect_deadline(address, connect_timeout_s):
                    ray.init(address=address, **common)
            else:
                # Absolute: the reaper finds Ray's processes by this path in their command lines.
                temp_dir = os.path.abspath(os.path.expanduser(temp_dir or default_ray_temp_dir()))
                for pruned in prune_ray_sessions(temp_dir):
                    log.info("pruned old Ray session %s", pruned)
                prune_reaper_logs(temp_dir)
                reaper = _start_reaper(temp_dir)
                stack.enter_context(loopback_only())
                stack.enter_context(worker_start.inherited_tune_env())  # workers get Tune's variables by birth
                with _signals_held(sigterm), _head_without_unused_daemons(unless=dashboard):
                    context = ray.init(address="local", num_cpus=workers, _temp_dir=temp_dir, _node_ip_address=LOOPBACK,
                                       include_dashboard=dashboard, dashboard_host=LOOPBACK,
                                       object_store_memory=OBJECT_STORE_BYTES, _system_config=SYSTEM_CONFIG, **common)
                if dashboard and context.dashboard_url:
                    (stream or sys.stderr).write(f"Ray dashboard: http://{context.dashboard_url}\n")
        except ConnectionError as e:
            raise SweepError(f"cannot connect to the Ray cluster at {address}: {e}{_token_hint()}") from None
        except AuthenticationError as e:  # the cluster wants a token this process lacks, or another one
            first = str(e).strip().splitlines()[0] if str(e).strip() else "token refused"
            raise SweepError(f"the Ray cluster at {address} refused this process ({first}); give it the cluster's "
                             f"token: RAY_AUTH_MODE=token and RAY_AUTH_TOKEN (or RAY_AUTH_TOKEN_PATH), see "
                             f"docs/sweeps.md, Security") from None
        finally:
            # ray.init sets its own SIGTERM handler (sys.exit); put back the sweep's (signals.sigterm_as_interrupt).
            if sigterm is not None:
                signal.signal(signal.SIGTERM, sigterm)
        yield
    finally:
        try:
            ray.shutdown()
        finally:
            _stop_reaper(reaper)
            stack.close()


@contextmanager
def _signals_held(sigterm) -> Iterator[None]:
    """While the embedded Ray starts: a SIGTERM is held, not lost, and handled once ray.init returns.

    ray.init installs SIGTERM handlers of its own (a driver's sys.exit, a node's drain-then-exit) that a
    SIGTERM during start-up would run inside Ray's code, where it was seen to vanish (the sweep went on).
    Here Ray's installer does nothing for the duration, a SIGTERM is only noted, and the sweep's own
    handler (signals.sigterm_as_interrupt) gets it as soon as Ray is up: the sweep stops as it does later,
    with ray_session's cleanup. A no-op off the main thread or without a sweep handler."""
    if sigterm is None or not callable(sigterm):
        yield
        return
    from ray._private import utils as ray_utils

    held: list[int] = []
    installer = ray_utils.set_sigterm_handler
    ray_utils.set_sigterm_handler = lambda handler: None
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        ray_utils.set_sigterm_handler = installer
        signal.signal(signal.SIGTERM, previous)
    if held:
        sigterm(held[0], None)  # raises KeyboardInterrupt: the sweep stops, ray_session shuts Ray down


@contextmanager
def _head_without_unused_daemons(unless: bool) -> Iterator[None]:
    """While the embedded Ray starts (without a dashboard): no autoscaler monitor and no log monitor, two
    Python daemons of ≈ 1 CPU-s each that a sweep never uses -- the embedded Ray has a fixed size (nothing to
    autoscale, no `ray status` reaches it: loopback and a random token), and the log monitor only streams
    worker output to drivers, which log_to_driver=False turns off. ray.init passes neither switch, so they
    are defaults of the RayParams it builds here. With --dashboard both stay (its cluster view reads the
    monitor). If a Ray release renames them, both start as before."""
    from ray._private import parameter

    init = parameter.RayParams.__init__
    if unless or not {"include_log_monitor", "no_monitor"} <= set(inspect.signature(init).parameters):
        yield
        return

    def lean_init(self, *args, **kwargs):
        kwargs.setdefault("include_log_monitor", False)
        kwargs.setdefault("no_monitor", True)
        init(self, *args, **kwargs)

    parameter.RayParams.__init__ = lean_init
    try:
        yield
    finally:
        parameter.RayParams.__init__ = init


def _token_hint() -> str:
    """Ray retries a refused token until it gives up as if nobody answered: say what may be missing."""
    if os.environ.get("RAY_AUTH_MODE", "").lower() == "token" and (
            os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
            or (Path.home() / ".ray" / "auth_token").is_file()):
        return " (or the cluster's token differs from this process's)"
    return ("; a cluster with token authentication also needs RAY_AUTH_MODE=token and RAY_AUTH_TOKEN "
            "(docs/sweeps.md, Security)")


def _hard_exit(code: int, message: str) -> None:
    try:
        os.write(2, (message + "\n").encode())
    finally:
        os._exit(code)


@contextmanager
def _connect_deadline(address: str, timeout_s: float) -> Iterator[None]:
    """Bound ray.init(address=...). It waits for an unresponsive head for minutes inside Ray's C++ client,
    where neither exceptions nor signal handlers reach it; a watcher thread ends the process instead:
    exit 2 at the deadline, 128+N on SIGINT/SIGTERM. Nothing has been written by then (see _run)."""
    done = threading.Event()
    wake_r = wake_w = None
    if threading.current_thread() is threading.main_thread():
        # The C-level signal handler writes the signal number here even while the main thread is stuck.
        wake_r, wake_w = os.pipe()
        os.set_blocking(wake_w, False)
        previous_wakeup = signal.set_wakeup_fd(wake_w, warn_on_full_buffer=False)

    def watch() -> None:
        deadline = time.monotonic() + timeout_s
        while not done.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                _hard_exit(2, f"asp-dist: error: no answer from the Ray cluster at {address} within "
                              f"{timeout_s:g} s; check --address, or raise --connect-timeout{_token_hint()}")
            if wake_r is None:
                done.wait(min(remaining, 0.5))
                continue
            ready, _, _ = select.select([wake_r], [], [], min(remaining, 0.5))
            for signum in (os.read(wake_r, 64) if ready else b""):
                if signum in (signal.SIGINT, signal.SIGTERM) and not done.wait(1.0):
                    # The main thread did not get to its handler within a second: it is inside Ray's wait.
                    _hard_exit(128 + signum, f"asp-dist: interrupted while connecting to the Ray cluster at {address}")

    watcher = threading.Thread(target=watch, name="asp-connect-deadline", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join(5)
        if wake_r is not None:
            signal.set_wakeup_fd(previous_wakeup)
            os.close(wake_r)
            os.close(wake_w)


# ---- the embedded Ray's processes and session dirs --------------------------------------------------
# The reaper (asp_dist/sweep/reaper.py, run by path: standard library only) kills what is left of the
# embedded Ray when the driver ends, however it ends; it watches a pipe whose other end only the driver holds.
def _start_reaper(temp_dir: str) -> tuple[subprocess.Popen, int] | None:
    """The reaper of the embedded Ray about to start (Linux: it reads /proc), and the pipe it watches."""
    if not os.path.isdir("/proc/self"):
        return None
    read_end, write_end = os.pipe()  # not inheritable: only the reaper gets an end of it
    try:
        proc = subprocess.Popen([sys.executable, "-I", "-S", reaper_program.__file__, str(os.getpid()), temp_dir],
                                stdin=read_end, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError as e:
        os.close(write_end)
        log.warning("no reaper for the embedded Ray (%s): its processes may outlive a killed driver", e)
        return None
    finally:
        os.close(read_end)
    return proc, write_end


def _stop_reaper(reaper: tuple[subprocess.Popen, int] | None) -> None:
    """After ray.shutdown: the reaper kills any straggler and exits."""
    if reaper is None:
        return
    proc, write_end = reaper
    os.close(write_end)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _processes_using(root: Path) -> set[str]:
    """Names of the session dirs under ``root`` that a live process names in its command line, works in,
    or holds a file of (Linux /proc; unreadable processes are skipped)."""
    prefix = f"{root}/session_"
    used: set[str] = set()

    def note(text: str) -> None:
        start = text.find(prefix)
        while start >= 0:
            used.add(text[start + len(prefix) - len("session_"):].split("/", 1)[0].split()[0])
            start = text.find(prefix, start + 1)

    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            note((proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"))
            note(os.readlink(proc / "cwd"))
            for fd in (proc / "fd").iterdir():
                note(os.readlink(fd))
        except OSError:
            continue
    return used


def prune_ray_sessions(temp_dir: str | Path, keep: int = RAY_SESSIONS_KEPT,
                       min_age_s: float = RAY_SESSION_MIN_AGE_S) -> list[Path]:
    """Remove old ``session_*`` dirs of an embedded Ray's temp dir, keeping the newest ``keep``, and
    never one that ``session_latest`` points to, that changed in the last ``min_age_s`` seconds, whose
    driver is alive, or that a live process uses. Returns the removed dirs. Needs /proc: elsewhere,
    and when the dir cannot be read, nothing is removed."""
    root = Path(temp_dir).expanduser().absolute()
    if not root.is_dir() or not os.path.isdir("/proc/self"):
        return []
    try:
        sessions = sorted((p for p in root.iterdir() if p.name.startswith("session_") and p.name != "session_latest"
                           and not p.is_symlink() and p.is_dir()), key=lambda p: p.name, reverse=True)
    except OSError:
        return []
    candidates = sessions[keep:]  # the names sort by start time: session_<date>_<time>_<us>_<driver pid>
    if not candidates:
        return []
    latest = root / "session_latest"
    latest = latest.resolve() if latest.is_symlink() else None
    used = _processes_using(root)
    removed = []
    now = time.time()
    for session in candidates:
        try:
            changed = max(session.stat().st_mtime, *(p.stat().st_mtime for p in session.iterdir()))
        except (OSError, ValueError):
            continue
        driver = session.name.rsplit("_", 1)[-1]
        if (session.resolve() == latest or now - changed < min_age_s or session.name in used
                or (driver.isdigit() and Path(f"/proc/{driver}").exists())):
            continue
        shutil.rmtree(session, ignore_errors=True)
        if not session.exists():
            removed.append(session)
    return removed


def prune_reaper_logs(temp_dir: str | Path, keep: int = RAY_SESSIONS_KEPT) -> None:
    """Keep the reaper logs of the newest ``keep`` drivers (and of any driver still alive)."""
    logs = sorted(Path(temp_dir).glob("reaper-*.log"), key=lambda p: p.stat().st_mtime, reverse=True)
    for old in logs[keep:]:
        driver = old.stem.removeprefix("reaper-")
        if not (driver.isdigit() and Path(f"/proc/{driver}").exists()):
            old.unlink(missing_ok=True)
