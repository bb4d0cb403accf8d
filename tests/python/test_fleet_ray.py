"""`r2g batch --ray` on a real local Ray head this test starts and stops itself (by the process
group it created, never `ray stop`), on loopback only: eight scripted episodes (recorded
conversations, so synthetic model answers), one Ray worker SIGKILLed mid-episode, the episode
retried (a second attempt seen starting), and nothing of the killed job left (processes,
/dev/shm files, its iceoryx2 root under /tmp) within 15 s; every episode folder whole where it
stays. Then the same head serves `r2g_fleet.py serve` (one driver, jobs as lines): a line that is
not a job is a failed result of its own, not the end of the driver."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from conftest import R2G, ROOT

RAY = ROOT / ".venv" / "bin" / "ray"
OBJECT_STORE_BYTES = 200 * 1024 * 1024
LOOPBACK = {"RAY_USAGE_STATS_ENABLED": "0", "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
"""Ray on Linux turns --node-ip-address=127.0.0.1 into the machine's address unless multi-node
clusters are off: the head, the batch's driver and the workers stay on loopback."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ppid(pid: int) -> int:
    stat = Path(f"/proc/{pid}/stat").read_text()
    return int(stat.rsplit(")", 1)[1].split()[1])


def _descends_from(pid: int, ancestor: int) -> bool:
    while pid > 1:
        if pid == ancestor:
            return True
        try:
            pid = _ppid(pid)
        except (OSError, ValueError, IndexError):
            return False
    return False


def _group(pgid: int) -> list[str]:
    out = subprocess.run(["ps", "-o", "pid,pgid,args", "-g", str(pgid)], capture_output=True, text=True).stdout
    return [line for line in out.splitlines()[1:] if line.strip()]


def _session(sid: int) -> list[int]:
    out = subprocess.run(["ps", "-o", "pid=", "-s", str(sid)], capture_output=True, text=True).stdout
    return [int(p) for p in out.split() if int(p) != sid]


def _shm(prefix: str) -> list[str]:
    return sorted(p.name for p in Path("/dev/shm").glob(f"{prefix}*"))


@pytest.fixture
def ray_head(tmp_path: Path):
    if not RAY.is_file():
        pytest.fail(f"{RAY} missing: make venv installs requirements-ray.txt")
    port = _free_port()
    jobs = tmp_path / "jobs"
    env = dict(os.environ, R2G_FLEET_DIR=str(jobs), **LOOPBACK)
    log = tmp_path / "ray-head.log"
    head = subprocess.Popen(
        [str(RAY), "start", "--head", "--node-ip-address=127.0.0.1", f"--port={port}", "--num-cpus=2",
         # Results are a few kB: a small object store starts at once (Ray's default maps 30 % of
         # the machine's memory in /dev/shm, which on a loaded machine outlasted the start-up).
         f"--object-store-memory={OBJECT_STORE_BYTES}",
         '--resources={"r2g_gym": 2}', "--include-dashboard=false", "--block"],
        env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT, start_new_session=True,
    )
    try:
        # Up when `ray start` says so (its GCS port opens before the node has started).
        deadline = time.monotonic() + 120
        while "Ray runtime started" not in log.read_text(errors="replace"):
            assert head.poll() is None, f"ray start exited: {log.read_text(errors='replace')[-2000:]}"
            assert time.monotonic() < deadline, f"ray start: not up in 120 s: {log.read_text(errors='replace')[-2000:]}"
            time.sleep(0.5)
        # The node advertises loopback, not the machine's address.
        assert "Local node IP: 127.0.0.1" in log.read_text(errors="replace"), log.read_text(errors="replace")[-2000:]
        yield head, f"127.0.0.1:{port}", jobs
    finally:
        # The group this test created: `ray start --block` and what it started.
        for sig, wait_s in ((signal.SIGTERM, 20), (signal.SIGKILL, 10)):
            try:
                os.killpg(head.pid, sig)
            except ProcessLookupError:
                break
            deadline = time.monotonic() + wait_s
            while time.monotonic() < deadline and _group(head.pid):
                time.sleep(0.5)
        # Ray's workers run in process groups of their own, in the session this test created.
        for pid in _session(head.pid):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        head.wait(timeout=10)


def _jobs_seen(jobs: Path) -> dict[str, dict[str, object]]:
    seen: dict[str, dict[str, object]] = {}
    for f in jobs.glob("*/job.json") if jobs.is_dir() else []:
        try:
            seen[f.parent.name.split(".")[0]] = json.loads(f.read_text())
        except (OSError, ValueError):
            continue
    return seen


def test_a_ray_batch_survives_a_killed_worker_and_leaves_nothing_behind(ray_head, tmp_path: Path) -> None:
    head, address, jobs = ray_head
    out = tmp_path / "batch"
    batch = subprocess.Popen(
        [str(R2G), "batch", "pick_block_plate", "--episodes", "8", "--max-decisions", "3", "--ray", address,
         "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ, **LOOPBACK),
    )
    try:
        _survives_a_killed_worker(batch, head, jobs, out)
    finally:
        if batch.poll() is None:
            batch.kill()
            batch.communicate()
    # One driver for jobs sent one by one (what `r2g augment --ray` uses): a line that is not a
    # job comes back as a failed result naming it, the jobs around it run, and the end of input
    # still ends the driver.
    serve = subprocess.run(
        [str(ROOT / ".venv" / "bin" / "python"), str(ROOT / "fleet" / "py" / "r2g_fleet.py"), "serve", "--ray", address,
         "--r2g", str(R2G)],
        input="not a job\n" + json.dumps({"id": 7, "args": ["replay", "pick_block_plate", "--out",
                                                            str(tmp_path / "replays")]}) + "\n",
        capture_output=True, text=True, timeout=240, env=dict(os.environ, R2G_FLEET_DIR=str(jobs), **LOOPBACK),
    )
    assert serve.returncode == 0, serve.stderr[-3000:]
    results = {r["id"]: r for r in map(json.loads, serve.stdout.splitlines())}
    assert sorted(results, key=str) == [7, None], results
    assert "not JSON" in results[None]["error"] and "not a job" in results[None]["error"], results[None]
    assert isinstance(results[7]["value"], dict) and results[7]["node"]["ip"] == "127.0.0.1", results[7]


def _survives_a_killed_worker(batch: subprocess.Popen[str], head: subprocess.Popen[bytes], jobs: Path, out: Path) -> None:
    # A job that has started its episode: its folder names the worker, the session and the prefix.
    victim = None
    deadline = time.monotonic() + 180
    while victim is None and time.monotonic() < deadline and batch.poll() is None:
        for tag, facts in _jobs_seen(jobs).items():
            if facts.get("leader") and _shm(str(facts["prefix"])) and len(_group(int(str(facts["leader"])))) >= 3:
                victim = dict(facts, tag=tag)
                break
        time.sleep(0.2)
    if victim is None:
        batch.kill()
        pytest.fail(f"no episode was seen running: {batch.communicate()[1][-3000:]}")
    worker, pgid, prefix = int(victim["worker"]), int(victim["leader"]), str(victim["prefix"])
    ipc_root = Path("/tmp") / str(victim["tag"])
    assert _descends_from(worker, head.pid), "the worker must be a process of the Ray head this test started"
    assert ipc_root.is_dir()
    before = {"processes": _group(pgid), "shm": _shm(prefix), "ipc_root": ipc_root.is_dir()}
    print("before SIGKILL:", json.dumps(before, indent=1))
    os.kill(worker, signal.SIGKILL)
    killed_at = time.monotonic()
    left = before
    retried = False
    while time.monotonic() - killed_at < 15:
        left = {"processes": _group(pgid), "shm": _shm(prefix), "ipc_root": ipc_root.is_dir()}
        retried = retried or any(
            f.get("job") == victim["job"] and t != victim["tag"] for t, f in _jobs_seen(jobs).items()
        )
        if not left["processes"] and not left["shm"] and not left["ipc_root"]:
            break
        time.sleep(0.25)
    print(f"after SIGKILL ({time.monotonic() - killed_at:.1f} s):", json.dumps(left, indent=1))
    assert not left["processes"] and not left["shm"] and not left["ipc_root"], left
    deadline = time.monotonic() + 120
    while not retried and time.monotonic() < deadline and batch.poll() is None:
        retried = any(f.get("job") == victim["job"] and t != victim["tag"] for t, f in _jobs_seen(jobs).items())
        time.sleep(0.2)
    stdout, stderr = batch.communicate(timeout=600)
    assert batch.returncode == 0, stderr[-3000:]
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["episodes"] == 8 and summary["errors"] == 0, summary
    assert retried, f"no second attempt of job {victim['job']} was seen starting"
    # The killed episode ran again: every episode folder has its result.
    missing = {d.name: sorted(p.name for p in d.iterdir()) if d.is_dir() else None
               for d in (out / f"episode-{i:03}" for i in range(8)) if not (d / "result.json").is_file()}
    assert not missing, (missing, sorted(p.name for p in out.iterdir()), victim["job"])
    # Each folder written where it stays: every link leads somewhere (they are absolute), no
    # file names a try folder, nothing beside the episodes.
    for base, dirs, files in os.walk(out):
        for name in dirs + files:
            p = Path(base) / name
            assert not p.is_symlink() or p.exists(), f"{p} links to {os.readlink(p)}, which is not there"
            assert not (p.is_file() and not p.is_symlink() and b".removed-" in p.read_bytes()), p
    assert sorted(p.name for p in out.iterdir()) == ["batch.json"] + [f"episode-{i:03}" for i in range(8)]
    assert json.loads((out / "batch.json").read_text())["episodes"] == 8
    # Every job is gone: no folder, no shared memory, no iceoryx2 root of any job of this batch.
    assert not list(jobs.glob("*/job.json")), list(jobs.iterdir())
    tags = {t for t in os.listdir(jobs)} if jobs.is_dir() else set()
    assert not tags, tags
    assert not any(p.name.startswith(prefix) for p in Path("/dev/shm").glob("r2gj*"))
