"""The reaper's family tree (asp_dist/sweep/reaper.py), on made-up /proc snapshots: which processes are the
driver's Ray. (End to end, with real processes: tests/test_sweep_lifecycle.py's reaper test and the driver
SIGKILL test in tests/test_sweep.py.)"""

from __future__ import annotations

from asp_dist.sweep.reaper import Family

DRIVER, TEMP = 100, b"/tmp/ray-x"
CMDLINES = {201: [b"raylet", b"--temp-dir=/tmp/ray-x"], 202: [b"gcs_server", b"/tmp/ray-x/session"],
            203: [b"python", b"unrelated.py"]}


def family() -> Family:
    return Family(DRIVER, TEMP, lambda pid: CMDLINES.get(pid, []), None, 0.0)


def test_node_processes_and_all_their_descendants_are_tracked_and_nothing_else():
    f = family()
    f.scan({201: (b"raylet", DRIVER, 10), 202: (b"gcs_server", DRIVER, 11), 203: (b"python", DRIVER, 12),
            # a grandchild listed before its parent: found in the same scan
            302: (b"ray::worker", 301, 15), 301: (b"agent", 201, 14), 400: (b"bash", 1, 5)})
    assert f.tracked == {201: 10, 202: 11, 301: 14, 302: 15}
    assert f.raylet == (201, 10)


def test_a_reused_pid_is_never_ours():
    f = family()
    f.scan({201: (b"raylet", DRIVER, 10), 301: (b"agent", 201, 14)})
    f.scan({201: (b"raylet", DRIVER, 10), 301: (b"bash", 1, 99)})  # 301 died; its pid went to someone else
    assert 301 not in f.tracked
    assert not f.ours(301, 99, lambda pid: [])
    # a child of the raylet whose start time is older than its parent's cannot be its child (a reused ppid)
    f.scan({201: (b"raylet", DRIVER, 10), 302: (b"old", 201, 3)})
    assert 302 not in f.tracked


def test_a_worker_born_after_the_last_scan_is_ours_by_its_raylet_environment():
    f = family()
    f.scan({201: (b"raylet", DRIVER, 10)})
    assert f.ours(500, 20, lambda pid: [b"PATH=/bin", b"RAY_RAYLET_PID=201"])
    assert not f.ours(500, 5, lambda pid: [b"RAY_RAYLET_PID=201"]), "started before the raylet: not its worker"
    assert not f.ours(501, 20, lambda pid: [b"RAY_RAYLET_PID=999"])
