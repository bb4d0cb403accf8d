"""The fleet's sweep (fleet/py/r2g_fleet.py) on job folders this test writes: it ends the session
of a dead job only when a process of that session proves it is the job's, never a process a
stale job.json merely names (one the test started outside any job, or a pid reused by a younger
process), and sweeps running side by side in threads never trip over each other. A job's own
episode folder is kept only from a try that ended with its result. Every process here is one
this test started, signalled only by its pid (the killed episode's through a pidfd, after
checking it is still the job's)."""
from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Iterator

import pytest

from conftest import R2G, ROOT

_spec = importlib.util.spec_from_file_location("r2g_fleet", ROOT / "fleet" / "py" / "r2g_fleet.py")
assert _spec is not None and _spec.loader is not None
fleet = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fleet)


def _start_time(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def _dead_pid() -> tuple[int, int]:
    """A pid and start time of a process that has exited (a worker that is gone)."""
    p = subprocess.Popen(["sleep", "0.01"])
    start = _start_time(p.pid)
    p.wait()
    return p.pid, start


@pytest.fixture
def root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    r = tmp_path / "jobs"
    monkeypatch.setenv("R2G_FLEET_DIR", str(r))
    return r


@pytest.fixture
def started() -> Iterator[list[subprocess.Popen[bytes]]]:
    procs: list[subprocess.Popen[bytes]] = []
    yield procs
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.wait()


def _job(root: Path, facts: dict[str, object]) -> tuple[str, Path]:
    tag = f"r2gj{uuid.uuid4().hex[:10]}"
    d = root / tag
    d.mkdir(parents=True)
    (d / "job.json").write_text(json.dumps({"boot_id": fleet._boot_id(), "prefix": f"{tag}_", **facts}))
    return tag, d


def _session_leader(started: list[subprocess.Popen[bytes]], env: dict[str, str] | None, child: bool = False) -> int:
    # With `child`, it starts a second process in a process group of its own (as the sandbox
    # does), in the same session.
    code = "import subprocess, time\n"
    if child:
        code += "subprocess.Popen(['sleep', '60'], process_group=0)\n"
    code += "print('up', flush=True)\ntime.sleep(60)\n"
    p = subprocess.Popen([sys.executable, "-c", code], env=env, start_new_session=True, stdout=subprocess.PIPE)
    started.append(p)
    assert p.stdout is not None and p.stdout.readline() == b"up\n"
    return p.pid


def test_a_stale_job_never_signals_a_process_that_is_not_the_jobs(root: Path, started: list[subprocess.Popen[bytes]]) -> None:
    worker, worker_start = _dead_pid()
    # A session leader the test started outside any job, named by a stale job.json with its
    # true start time: nothing of the job's in its environment.
    stranger = _session_leader(started, dict(os.environ))
    tag_a, dir_a = _job(root, {"worker": worker, "worker_start": worker_start, "leader": stranger,
                               "leader_start": _start_time(stranger)})
    shm = Path("/dev/shm") / f"{tag_a}_leftover"
    shm.write_bytes(b"x")
    # A pid reused by a younger process: it even carries the job's tag, but it started after the
    # leader the job recorded, so it is not that leader.
    tag_b = f"r2gj{uuid.uuid4().hex[:10]}"
    reused = _session_leader(started, dict(os.environ, R2G_IPC_CONFIG=f"{root}/{tag_b}/iceoryx2.toml"))
    d_b = root / tag_b
    d_b.mkdir()
    (d_b / "job.json").write_text(json.dumps({"boot_id": fleet._boot_id(), "worker": worker,
                                              "worker_start": worker_start, "leader": reused,
                                              "leader_start": _start_time(reused) - 100}))
    try:
        swept = fleet.sweep()
    finally:
        shm.unlink(missing_ok=True)
    assert sorted(swept) == sorted([tag_a, tag_b])
    assert _running(stranger) and _running(reused), "a process outside the job was signalled"
    assert not dir_a.exists() and not d_b.exists() and not shm.exists()


def test_a_dead_jobs_session_ends_and_a_live_job_stays(root: Path, started: list[subprocess.Popen[bytes]]) -> None:
    worker, worker_start = _dead_pid()
    tag = f"r2gj{uuid.uuid4().hex[:10]}"
    env = dict(os.environ, R2G_IPC_CONFIG=f"{root}/{tag}/iceoryx2.toml")
    leader = _session_leader(started, env, child=True)
    sid_members = fleet._members(leader, _start_time(leader))
    assert len(sid_members) == 2, sid_members
    d = root / tag
    d.mkdir(parents=True)
    (d / "job.json").write_text(json.dumps({"boot_id": fleet._boot_id(), "worker": worker, "worker_start": worker_start,
                                            "leader": leader, "leader_start": _start_time(leader)}))
    # A job whose worker lives (this process) stays; one whose worker pid now names a younger
    # process (this one, with an older start time recorded) is dead.
    me = _start_time(os.getpid())
    live, live_dir = _job(root, {"worker": os.getpid(), "worker_start": me, "leader": 0})
    reused, _ = _job(root, {"worker": os.getpid(), "worker_start": me - 100, "leader": 0})
    torn, _ = _job(root, {})
    (root / torn / "job.json").write_text('{"worker": 12')
    t0 = time.monotonic()
    swept = fleet.sweep()
    assert sorted(swept) == sorted([tag, reused, torn])
    assert live_dir.is_dir()
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and any(_running(p) for p in sid_members):
        time.sleep(0.05)
    assert not any(_running(p) for p in sid_members), "the dead job's session (both groups) must end"
    assert time.monotonic() - t0 < 8, "SIGTERM was enough: no wait for SIGKILL"


def test_sweeps_in_threads_side_by_side_each_job_once(root: Path) -> None:
    worker, worker_start = _dead_pid()
    tags = {_job(root, {"worker": worker, "worker_start": worker_start, "leader": 0})[0] for _ in range(24)}
    results: list[list[str]] = []
    errors: list[BaseException] = []

    def one() -> None:
        try:
            results.append(fleet.sweep())
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=one) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    every = [t for r in results for t in r]
    assert sorted(every) == sorted(tags), "each job swept exactly once"
    assert not list(root.iterdir())


def test_the_jobs_root_must_be_this_users_own_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real = tmp_path / "real"
    real.mkdir()
    link = tmp_path / "link"
    link.symlink_to(real)
    monkeypatch.setenv("R2G_FLEET_DIR", str(link))
    with pytest.raises(SystemExit, match="not a folder of this user"):
        fleet.jobs_root()
    monkeypatch.delenv("R2G_FLEET_DIR")
    assert fleet.jobs_root() == Path(f"/tmp/r2g-fleet-{os.getuid()}")


def _fleet_run(out: Path, tmp: Path, env: dict[str, str]) -> subprocess.Popen[str]:
    """One `r2g episode` (a scripted one: synthetic model answers) into `out`, as a fleet job on
    one local worker: what `r2g batch --workers 1` runs for each episode."""
    jobs = tmp / f"jobs-{uuid.uuid4().hex[:6]}.json"
    args = ["episode", "pick_block_plate", "--max-decisions", "2", "--out", str(out)]
    jobs.write_text(json.dumps([{"id": 0, "args": args, "cwd": str(ROOT), "out": str(out)}]))
    return subprocess.Popen([sys.executable, str(ROOT / "fleet" / "py" / "r2g_fleet.py"), "run", "--jobs", str(jobs),
                             "--r2g", str(R2G), "--local", "1"], env=env, stdout=subprocess.PIPE, text=True)


def _result(p: subprocess.Popen[str]) -> dict[str, object]:
    stdout, _ = p.communicate(timeout=240)
    assert p.returncode == 0
    return json.loads(stdout.strip().splitlines()[-1])


def test_an_episode_folder_is_kept_only_from_a_try_that_ended_with_its_result(root: Path, tmp_path: Path) -> None:
    """A folder an earlier try left is gone before the next try writes; a try killed by a
    signal while its worker lives (as the OOM killer would) leaves no folder; a try that ends
    leaves a whole one, written where it stays (its links lead somewhere)."""
    out = tmp_path / "b" / "episode-000"
    env = dict(os.environ, R2G_FLEET_DIR=str(root))
    env.pop("R2G_IPC_CONFIG", None)
    # 1. A leftover of a dead try; this try is SIGKILLed once its episode has begun writing.
    out.mkdir(parents=True)
    (out / "stale.txt").write_text("an earlier try's")
    p = _fleet_run(out, tmp_path, env)
    try:
        killed = None
        deadline = time.monotonic() + 120
        while killed is None and time.monotonic() < deadline and p.poll() is None:
            for f in root.glob("r2gj*/job.json"):
                try:
                    facts = json.loads(f.read_text())
                except ValueError:
                    continue
                leader = int(facts.get("leader") or 0)
                if leader and out.is_dir() and not (out / "stale.txt").exists() and (out / "scratch").exists():
                    # The job's own r2g (a child of this test's driver), checked by its start time
                    # through a pidfd before the signal.
                    fd = os.pidfd_open(leader)
                    try:
                        assert _start_time(leader) == facts["leader_start"]
                        assert int(Path(f"/proc/{leader}/stat").read_text().rsplit(")", 1)[1].split()[1]) == p.pid
                        signal.pidfd_send_signal(fd, signal.SIGKILL)
                        killed = leader
                    finally:
                        os.close(fd)
                    break
            time.sleep(0.05)
        assert killed, "the episode was not seen writing its folder"
        first = _result(p)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    print("a killed try:", json.dumps({k: first[k] for k in ("rc", "value")}))
    assert first["rc"] == -signal.SIGKILL and first["value"] is None, first
    assert sorted(x.name for x in out.parent.iterdir()) == [], list(out.parent.iterdir())
    # 2. Another leftover; this try ends (the scripted episode may or may not achieve its task
    # in 2 decisions: exit 0 or 1, both whole episodes).
    out.mkdir()
    (out / "stale.txt").write_text("an earlier try's")
    second = _result(_fleet_run(out, tmp_path, env))
    assert second["rc"] in (0, 1) and isinstance(second["value"], dict), second
    assert (out / "result.json").is_file() and not (out / "stale.txt").exists()
    assert sorted(x.name for x in out.parent.iterdir()) == ["episode-000"]
    links = [x for x in out.rglob("*") if x.is_symlink()]
    assert links and all(x.exists() for x in links), [x for x in links if not x.exists()]
