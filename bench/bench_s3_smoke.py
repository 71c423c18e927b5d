"""Results on local disk vs on a loopback S3 server: the same `asp-dist sweep smoke` (18 signaling
cells, embedded Ray, 2 workers), then `status`, `query --sql` and `stats --no-figures` of it, with
`--results` a local directory and `--results s3://bucket/prefix` on moto's S3 server (started here
on a free loopback port, stopped at the end), in one run of this script.

    python bench/bench_s3_smoke.py [--rounds 1] [--out bench/results/s3_smoke.json]

Rounds alternate local, S3, local, S3 … so that a change in the machine's load hits both alike.
Reported per command: the whole command's wall time (Ray start-up included for the sweep) and, for
the sweep, the span the sweep's own counter reports (cells only), plus the number of HTTP requests
the S3 server answered during the sweep. The load average is printed before and after: timings
taken while other jobs run are noisy. Every process runs with one torch thread.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

BUCKET = "asp-bench"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_moto(log: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=open(log, "w"), stderr=subprocess.STDOUT, start_new_session=True)
    for _ in range(600):
        try:
            socket.create_connection(("127.0.0.1", port), 0.2).close()
            return proc, f"http://127.0.0.1:{port}"
        except OSError:
            time.sleep(0.1)
    raise RuntimeError("moto server did not start")


def timed(args: list[str], env: dict[str, str], cwd: Path) -> tuple[float, subprocess.CompletedProcess]:
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "asp_dist.cli", *args], env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=1800)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return seconds, proc


def sweep_span(stderr: str) -> float | None:
    """The last `elapsed M:SS` of the sweep's counter line."""
    found = re.findall(r"elapsed (\d+):(\d+)", stderr)
    return int(found[-1][0]) * 60 + int(found[-1][1]) if found else None


def requests(log: Path | None) -> int:
    """HTTP requests the moto server has answered so far (one access-log line each)."""
    return len(re.findall(r'"(?:GET|PUT|POST|HEAD|DELETE) ', log.read_text())) if log else 0


def one_round(kind: str, results: str, env: dict[str, str], work: Path, log: Path | None) -> dict:
    cwd = work / f"cwd-{kind}"
    cwd.mkdir(exist_ok=True)
    ray_temp = f"/tmp/asp-bench-{kind}-{os.getpid()}"
    name = f"smoke-{kind}-{int(time.time())}"
    requests_before = requests(log)
    out: dict = {"kind": kind, "results": results}
    out["sweep_s"], proc = timed(["sweep", "smoke", "--name", name, "--results", results, "--ray-temp-dir", ray_temp],
                                 env, cwd)
    out["sweep_cells_span_s"] = sweep_span(proc.stderr)
    if log:
        out["s3_requests_during_sweep"] = requests(log) - requests_before
    out["status_s"], _ = timed(["status", name, "--results", results], env, cwd)
    out["query_s"], _ = timed(["query", name, "--results", results, "--sql",
                               "SELECT method, paired, median(eval_mixed) FROM cells GROUP BY ALL"], env, cwd)
    out["stats_s"], _ = timed(["stats", name, "--results", results, "--no-figures", "--bootstrap", "200", "--quiet"],
                              env, cwd)
    subprocess.run(["rm", "-rf", ray_temp])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=1, help="local+S3 pairs (default 1)")
    ap.add_argument("--out", default=None, help="also write the results as JSON here")
    args = ap.parse_args()

    import boto3

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="asp-bench-s3-") as tmp:
        work = Path(tmp)
        log = work / "moto.log"
        moto, endpoint = start_moto(log)
        try:
            env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
            env.update(OMP_NUM_THREADS="1", RAY_USAGE_STATS_ENABLED="0", AWS_ENDPOINT_URL=endpoint,
                       AWS_ACCESS_KEY_ID="bench", AWS_SECRET_ACCESS_KEY="bench-secret", AWS_DEFAULT_REGION="us-east-1",
                       AWS_EC2_METADATA_DISABLED="true")
            boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1", aws_access_key_id="bench",
                         aws_secret_access_key="bench-secret").create_bucket(Bucket=BUCKET)
            runs = []
            for _ in range(args.rounds):
                runs.append(one_round("local", str(work / "results"), env, work, None))
                print(json.dumps(runs[-1]), flush=True)
                runs.append(one_round("s3", f"s3://{BUCKET}/bench", env, work, log))
                print(json.dumps(runs[-1]), flush=True)
        finally:
            os.killpg(moto.pid, signal.SIGKILL)
            moto.wait(10)
    load_after = os.getloadavg()

    report = {"when": datetime.now(timezone.utc).isoformat(timespec="seconds"), "host": platform.node(),
              "cpus": os.cpu_count(), "load_before": load_before, "load_after": load_after, "runs": runs}
    keys = ("sweep_s", "sweep_cells_span_s", "status_s", "query_s", "stats_s")
    print(f"\nload average before {load_before[0]:.2f} / after {load_after[0]:.2f} on {os.cpu_count()} CPUs")
    print("| results | " + " | ".join(keys) + " | S3 requests |")
    print("|---|" + "---|" * (len(keys) + 1))
    for run in runs:
        cells = [f"{run[k]:.1f}" if run.get(k) is not None else "-" for k in keys]
        print(f"| {run['kind']} | " + " | ".join(cells) + f" | {run.get('s3_requests_during_sweep', '-')} |")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
