"""Runs r2g jobs (one episode each: `r2g episode ...`, `r2g replay ...`, any subcommand that ends
with one JSON line) on local worker threads or as Ray tasks, and streams each result back as one
JSON line on stdout, in the order they finish.

    python fleet/py/r2g_fleet.py run --jobs JOBS.json (--local N | --ray auto|ADDRESS) [--retries 2]
    python fleet/py/r2g_fleet.py serve --ray auto|ADDRESS   # one driver, jobs as JSON lines on stdin
    python fleet/py/r2g_fleet.py resources        # this node's r2g_gym capacity, for `ray start`
    python fleet/py/r2g_fleet.py sweep            # by hand: clean up after this node's dead jobs

Every job runs the same way wherever it runs (`run_job`): `r2g` in a session of its own, dying
with the worker (PR_SET_PDEATHSIG), on an iceoryx2 configuration of its own (its own root path
and /dev/shm prefix, both named by the job's tag). Cleanup never relies on `finally` alone: a
worker that is SIGKILLed takes its job's processes with it (PDEATHSIG), and the next job on that
node sweeps what any dead job left (`sweep`): it ends the session of a job whose worker is gone,
once a process of that session proves it is the job's (its environment names the job's tag),
and removes the job's shared-memory files and folders. Ray retries the task of a dead worker.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import re
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any, Callable, Iterator

RESOURCE = "r2g_gym"
"""The custom Ray resource every job takes one of: a node offers as many as it runs gyms at once."""
SHM_PER_GYM_MB = float(os.environ.get("R2G_SHM_PER_GYM_MB", "512"))
"""/dev/shm one gym instance may use (its camera and request services, with headroom)."""


def jobs_root() -> Path:
    """Where each running job keeps its iceoryx2 configuration and the facts its sweep needs:
    ``$R2G_FLEET_DIR`` of the node it runs on (read there, not in the driver), else
    /tmp/r2g-fleet-<uid>: one folder per user, only ever read by that user's sweeps."""
    root = Path(os.environ.get("R2G_FLEET_DIR") or f"/tmp/r2g-fleet-{os.getuid()}")
    try:
        root.mkdir(mode=0o700, parents=True)
    except FileExistsError:
        pass
    st = root.lstat()
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid():
        raise SystemExit(f"{root} is not a folder of this user (uid {os.getuid()}): set R2G_FLEET_DIR to one")
    return root


PR_SET_PDEATHSIG = 1
_TAG = re.compile(r"^r2gj[0-9a-f]{10}$")
"""A job's tag (its folder, iceoryx2 root and /dev/shm prefix); nothing else is ever swept."""


def node_capacity() -> int:
    """Gyms this node runs at once: one per core, and no more than /dev/shm holds."""
    cores = os.cpu_count() or 1
    st = os.statvfs("/dev/shm")
    free_mb = st.f_bavail * st.f_frsize / 2**20
    return max(1, min(cores, int(free_mb // SHM_PER_GYM_MB)))


def _boot_id() -> str:
    return Path("/proc/sys/kernel/random/boot_id").read_text().strip()


def _stat(pid: int) -> tuple[int, int] | None:
    """(session id, start time in clock ticks since boot) of a process, None when it is gone
    (or a zombie: nothing left to end)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    if fields[0] in ("Z", "X"):
        return None
    return int(fields[3]), int(fields[19])


def _same_process(pid: int, start: int) -> bool:
    """Whether `pid` is still the process that had start time `start` (not a reused pid)."""
    s = _stat(pid)
    return s is not None and s[1] == start


def _environ_has(pid: int, marker: bytes) -> bool | None:
    """Whether the process's environment holds `marker`; None when it cannot be read (another
    user's process, or one that made itself undumpable, as the sandbox does)."""
    try:
        return marker in Path(f"/proc/{pid}/environ").read_bytes()
    except PermissionError:
        return None
    except OSError:
        return False


def _members(sid: int, since: int) -> list[int]:
    """The processes of session `sid` started at or after `since` (clock ticks since boot)."""
    out = []
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            s = _stat(int(entry.name))
            if s is not None and s[0] == sid and s[1] >= since:
                out.append(int(entry.name))
    return out


def _kill_session(sid: int, since: int, tag: str) -> list[int]:
    """Ends what is left of a job: the processes of session `sid` (its leader's, started at
    `since`), SIGTERM first (r2g stops its instance in order), SIGKILL after 10 s. Only when a
    member proves the session is the job's: its environment names the job's tag (every process
    of a job inherits R2G_IPC_CONFIG, the sandbox R2G_IPC_ROOT, both under the tag). A session
    number is not given out again while any member lives, so members that cannot be read (the
    sandbox) go with the proven ones. Returns the pids signalled."""
    marker = tag.encode()
    signalled: list[int] = []
    for sig, wait_s in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        members = _members(sid, since)
        marks = [_environ_has(p, marker) for p in members]
        if not any(marks):
            return signalled
        for pid, mark in zip(members, marks):
            if mark is False:
                continue
            try:
                os.kill(pid, sig)
                signalled.append(pid)
            except (ProcessLookupError, PermissionError):
                pass
        targets = {p for p, m in zip(members, marks) if m is not False}
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline and targets & set(_members(sid, since)):
            time.sleep(0.05)
    return signalled


def _write_facts(d: Path, facts: dict[str, Any]) -> None:
    tmp = d / f".job.json.{os.getpid()}.{threading.get_ident()}"
    tmp.write_text(json.dumps(facts))
    os.replace(tmp, d / "job.json")


def _remove_files(d: Path, tag: str) -> None:
    """A job's shared memory (its /dev/shm prefix), iceoryx2 root and folder `d`."""
    for f in Path("/dev/shm").glob(f"{tag}_*"):
        f.unlink(missing_ok=True)
    shutil.rmtree(Path("/tmp") / tag, ignore_errors=True)
    shutil.rmtree(d, ignore_errors=True)


def _worker_alive(facts: dict[str, Any], boot: str) -> bool:
    return facts.get("boot_id") == boot and _same_process(int(facts["worker"]), int(facts["worker_start"]))


def sweep() -> list[str]:
    """Cleans up after dead jobs of this node: a job whose worker is gone (gone from /proc, or
    its pid now names a younger process) has what is left of its session ended (see
    `_kill_session`) and its shared memory and folders removed. A folder is claimed by renaming
    it before anything else, so sweeps running side by side never handle the same job twice.
    Returns the jobs swept."""
    swept: list[str] = []
    root = jobs_root()
    boot = _boot_id()
    for d in sorted(root.iterdir()):
        tag, _, claimer = d.name.partition(".claimed-")
        if not _TAG.match(tag):
            continue
        if claimer:
            # Claimed by a sweep that died before it finished: claimed again below.
            pid, _, start = claimer.partition("-")
            start = start.partition("-")[0]  # the claimer: pid-start-thread
            if pid.isdigit() and start.isdigit() and _same_process(int(pid), int(start)):
                continue
        try:
            facts = json.loads((d / "job.json").read_text())
            alive = _worker_alive(facts, boot)
        except FileNotFoundError:
            # A job still writing its first facts, or a folder another sweep just claimed;
            # one without facts for a minute lost its worker before it wrote them.
            try:
                if time.time() - d.stat().st_mtime < 60:
                    continue
            except OSError:
                continue
            facts, alive = {}, False
        except (OSError, ValueError, KeyError, TypeError):
            facts, alive = {}, False
        if alive:
            continue
        me = _stat(os.getpid())
        mine = root / f"{tag}.claimed-{os.getpid()}-{me[1] if me else 0}-{threading.get_ident()}"
        try:
            d.rename(mine)
        except OSError:
            continue
        leader = int(facts.get("leader") or 0)
        if leader and facts.get("boot_id") == boot:
            s = _stat(leader)
            if s is None or s[1] == int(facts.get("leader_start", -1)):
                # The leader is gone or still the job's own (not a reused pid): its session.
                _kill_session(leader, int(facts.get("leader_start", 0)), tag)
        # (Its output folder, if any, is not touched here: a retry elsewhere may already be
        # writing it. The retry removes what the dead try left before it starts; see run_job.)
        _remove_files(mine, tag)
        swept.append(tag)
    return swept


def _die_with_worker() -> Callable[[], None]:
    """What the child runs before exec (its session is new: start_new_session): SIGKILL when
    the worker dies, however it dies. libc is loaded here, in the worker (a module-level handle
    would travel with the pickled function to Ray, and cannot), so the child loads nothing."""
    libc = ctypes.CDLL(None, use_errno=True)
    return lambda: libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def discard(out: str, why: str) -> None:
    """Removes the output folder `out` of a try that did not end well (or that an earlier,
    dead try left): first renamed aside in one step (`.NAME.removed-<why>`), so no reader ever
    sees a folder under its own name half-removed, then deleted. Nothing at `out`: nothing."""
    out = out.rstrip("/")
    parent, name = os.path.split(out)
    aside = os.path.join(parent, f".{name}.removed-{why}")
    try:
        os.rename(out, aside)
    except FileNotFoundError:
        return
    if os.path.isdir(aside) and not os.path.islink(aside):
        shutil.rmtree(aside, ignore_errors=True)
    else:
        os.unlink(aside)


def ended(result: dict[str, Any]) -> bool:
    """Whether a try ended by itself with its result: it exited (not killed by a signal) after
    printing its JSON line, which `r2g episode` prints once its folder is whole (its exit
    status says whether the task was achieved, 0 or 1, not whether the episode ran)."""
    return isinstance(result.get("rc"), int) and result["rc"] >= 0 and isinstance(result.get("value"), dict)


def _node() -> dict[str, Any]:
    """Where this job runs: the host name (the same in every container or namespace of a
    machine), and under Ray the node id (the driver adds the node's address)."""
    node: dict[str, Any] = {"host": socket.gethostname(), "id": None, "ip": None}
    if "ray" in sys.modules:
        import ray

        if ray.is_initialized():
            node["id"] = ray.get_runtime_context().get_node_id()
    return node


def run_job(job: dict[str, Any], r2g: str) -> dict[str, Any]:
    """Runs one job here: `r2g <job["args"]>`, isolated as the module docstring says, in the
    driver's working directory when this node has it. A job that names its output folder
    (`job["out"]`, one of its arguments: an episode's, whose `result.json` is written when the
    episode has ended) writes it in place, under its own name, and owns it alone: whatever is
    there when the try starts (left by an earlier try that died with its worker or node, or by
    an earlier run into the same folder) is removed first, and a try that did not end with its
    result (`ended`) removes its folder (`discard`). So a folder of that name is either being written by the one
    live try, or whole, or left by a try cut short with its node (no `result.json`: the job's
    retry, or the driver when no try is left, removes it). Returns its result: the exit status,
    its last JSON line, the tail of its stderr, where it ran."""
    sweep()
    tag = f"r2gj{uuid.uuid4().hex[:10]}"
    d = jobs_root() / tag
    d.mkdir(mode=0o700)
    me = _stat(os.getpid())
    out = job.get("out")
    facts: dict[str, Any] = {
        "job": job["id"],
        "boot_id": _boot_id(),
        "worker": os.getpid(),
        "worker_start": me[1] if me else 0,
        "leader": 0,
        "leader_start": 0,
        "prefix": f"{tag}_",
        "out": out,
    }
    # The facts first: from here on a sweep can tell whether this job's worker lives.
    _write_facts(d, facts)
    # A short root path: iceoryx2's event sockets live under it, and socket paths are short.
    ipc_root = Path("/tmp") / tag
    ipc_root.mkdir(mode=0o700)
    config = d / "iceoryx2.toml"
    config.write_text(f'[global]\nroot-path = "{ipc_root}/"\nprefix = "{tag}_"\n')
    env = dict(os.environ, R2G_IPC_CONFIG=str(config))
    env.pop("RAY_ADDRESS", None)
    cwd = job.get("cwd")
    stderr_path = d / "stderr.txt"
    t0 = time.monotonic()
    if out:
        # What an earlier try left (it died with its worker, and the job's processes with it).
        discard(out, tag)
    with open(stderr_path, "wb") as err:
        proc = subprocess.Popen(
            [r2g, *job["args"]],
            stdout=subprocess.PIPE,
            stderr=err,
            stdin=subprocess.DEVNULL,
            env=env,
            cwd=cwd if cwd and os.path.isdir(cwd) else None,
            # Its own session: Ray's cleanup of the worker does not reach it, we end it as one.
            start_new_session=True,
            preexec_fn=_die_with_worker(),
        )
        leader = _stat(proc.pid)
        facts["leader"], facts["leader_start"] = proc.pid, leader[1] if leader else 0
        _write_facts(d, facts)
        try:
            stdout, _ = proc.communicate()
        finally:
            # Whatever is left of the session (an instance's processes) goes with the job.
            _kill_session(proc.pid, int(facts["leader_start"]), tag)
    result = {
        "id": job["id"],
        "rc": proc.returncode,
        "value": None,
        "stderr_tail": stderr_path.read_text(errors="replace")[-1500:],
        "node": _node(),
        "worker": os.getpid(),
        "wall_s": time.monotonic() - t0,
    }
    for line in reversed(stdout.decode(errors="replace").splitlines()):
        if line.startswith("{"):
            try:
                result["value"] = json.loads(line)
                break
            except ValueError:
                continue
    if out and not ended(result):
        # Killed (a signal, the OOM killer) or failed before its result: not an episode
        # anyone should count.
        discard(out, tag)
    _remove_files(d, tag)
    return result


def _failed(job: dict[str, Any], e: BaseException) -> dict[str, Any]:
    return {"id": job["id"], "rc": None, "value": None, "error": f"{type(e).__name__}: {e}"[-1500:]}


def _local(jobs: list[dict[str, Any]], r2g: str, workers: int) -> Iterator[dict[str, Any]]:
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        pending: dict[Future[dict[str, Any]], dict[str, Any]] = {pool.submit(run_job, j, r2g): j for j in jobs}
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                job = pending.pop(f)
                try:
                    yield f.result()
                except Exception as e:  # the job could not run here: a row, as on Ray
                    yield _failed(job, e)


def _recorded_cluster() -> str | None:
    """The cluster `ray.init(address="auto")` would join, if one answers: $RAY_ADDRESS, else the
    one `ray start` recorded on this node. (Ray's own last resort, any GCS process `ps` shows,
    is never used: on a shared machine that may be somebody else's cluster.)"""
    address = os.environ.get("RAY_ADDRESS") or None
    if address is None:
        tmp = os.environ.get("RAY_TMPDIR") or tempfile.gettempdir()
        try:
            address = (Path(tmp) / "ray" / "ray_current_cluster").read_text().strip() or None
        except OSError:
            return None
    if address is None:
        return None
    host, _, port = address.rpartition(":")
    try:
        with socket.create_connection((host, int(port)), timeout=2.0):
            return address
    except (OSError, ValueError):
        return None


def _connect(address: str) -> Any:
    """Joins the Ray cluster at `address` (`auto`: the running one, else one of our own on
    loopback for this run alone) and checks that it offers gym slots. Returns the module."""
    has_token = (
        os.environ.get("RAY_AUTH_TOKEN")
        or os.environ.get("RAY_AUTH_TOKEN_PATH")
        or (Path.home() / ".ray" / "auth_token").is_file()
    )
    if "RAY_AUTH_MODE" not in os.environ and has_token:
        # Clusters started by `ray start` on nodes with a token want it; a driver on a node
        # that has one (see fleet/MULTINODE.md) presents it. `ray.init` with an address does
        # not look for one by itself. Read when Ray is imported.
        os.environ["RAY_AUTH_MODE"] = "token"
    if address == "auto":
        # The cluster `auto` means, resolved once here (none answering: one of our own).
        address = _recorded_cluster() or "local"
    local = address == "local"
    if local or address.rpartition(":")[0] in ("127.0.0.1", "localhost", "[::1]"):
        # A cluster of this batch alone, or one on loopback: Ray on Linux advertises the
        # machine's address even when asked for 127.0.0.1, unless multi-node clusters are off
        # (read when Ray is imported, and by the processes it starts).
        os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    import ray  # only here: a batch without --ray needs no Ray

    if local:
        # Sized like `resources` says; "local": never a cluster some file still names.
        ray.init(
            address="local",
            _node_ip_address="127.0.0.1",
            resources={RESOURCE: node_capacity()},
            # Results are a few kB: a small object store (Ray's default maps 30 % of memory
            # in /dev/shm, slow to start on a loaded machine and taken from the gyms' budget).
            object_store_memory=200 * 1024 * 1024,
            include_dashboard=False,
            log_to_driver=False,
        )
    else:
        ray.init(address=address, log_to_driver=False)
    if not ray.cluster_resources().get(RESOURCE, 0):
        ray.shutdown()
        raise SystemExit(
            f"the Ray cluster offers no '{RESOURCE}' resource: start each node with "
            f"--resources='{{\"{RESOURCE}\": N}}' (python fleet/py/r2g_fleet.py resources prints N)"
        )
    return ray


class _Nodes:
    """Each Ray node's address by its id, from the cluster's node table (read again when a
    result names a node not seen yet: one that joined after the last read)."""

    def __init__(self, ray: Any) -> None:
        self.ray, self.ips = ray, {}

    def name(self, result: dict[str, Any]) -> dict[str, Any]:
        node = result.get("node")
        if isinstance(node, dict) and node.get("id"):
            if node["id"] not in self.ips:
                self.ips = {n["NodeID"]: n["NodeManagerAddress"] for n in self.ray.nodes()}
            node["ip"] = self.ips.get(node["id"])
        return result


def _task(ray: Any, retries: int) -> Any:
    # Each task takes one gym slot; a task whose worker or node died runs again elsewhere.
    return ray.remote(run_job).options(resources={RESOURCE: 1}, num_cpus=0, max_retries=retries, retry_exceptions=True)


def _ray(
    jobs: list[dict[str, Any]], r2g: str, address: str, retries: int, max_concurrent: int | None
) -> Iterator[dict[str, Any]]:
    ray = _connect(address)
    try:
        task, nodes = _task(ray, retries), _Nodes(ray)
        # At most `max_concurrent` in flight, the next one submitted as one finishes (a task
        # never waits for more slots than a node has).
        cap = max(1, max_concurrent) if max_concurrent else len(jobs)
        queue = list(reversed(jobs))
        refs: dict[Any, dict[str, Any]] = {}
        while queue or refs:
            while queue and len(refs) < cap:
                j = queue.pop()
                refs[task.remote(j, r2g)] = j
            done, _ = ray.wait(list(refs), num_returns=1)
            for ref in done:
                job = refs.pop(ref)
                try:
                    yield nodes.name(ray.get(ref))
                except Exception as e:  # the task failed on every try
                    yield _failed(job, e)
    finally:
        ray.shutdown()


def _parse_job(line: str) -> tuple[str, dict[str, Any]]:
    """One line of `serve`'s stdin: ("job", the job), or ("bad", a failed result saying what
    is wrong with the line, under its id when it has one)."""
    try:
        job = json.loads(line)
    except ValueError as e:
        return "bad", {"id": None, "rc": None, "value": None, "error": f"a job line that is not JSON ({e}): {line[:200]!r}"}
    if not isinstance(job, dict):
        return "bad", {"id": None, "rc": None, "value": None, "error": f"a job line that is not an object: {line[:200]!r}"}
    if not isinstance(job.get("id"), int) or not isinstance(job.get("args"), list) or not all(
        isinstance(a, str) for a in job["args"]
    ):
        return "bad", {
            "id": job.get("id") if isinstance(job.get("id"), int) else None,
            "rc": None,
            "value": None,
            "error": f'a job needs "id" (an integer) and "args" (a list of strings): {line[:200]!r}',
        }
    return "job", job


def _serve(r2g: str, address: str, retries: int) -> Iterator[dict[str, Any]]:
    """One driver for a stream of jobs: each JSON line on stdin is a job, submitted as a Ray
    task at once (as many in flight as the caller sends); results come back as they finish.
    Ends when stdin ends and every job has its result."""
    import queue as q

    ray = _connect(address)
    # ("job", job), ("bad", its failed result), or None at the end of stdin.
    incoming: q.Queue[tuple[str, dict[str, Any]] | None] = q.Queue()

    def read() -> None:
        try:
            for line in sys.stdin:
                if line.strip():
                    incoming.put(_parse_job(line))
        finally:
            # However reading ends, the end comes: the loop below must not wait for ever.
            incoming.put(None)

    threading.Thread(target=read, daemon=True).start()
    try:
        task, nodes = _task(ray, retries), _Nodes(ray)
        refs: dict[Any, dict[str, Any]] = {}
        open_ = True
        while open_ or refs:
            try:
                # Block for the next job only when nothing runs.
                while True:
                    item = incoming.get(timeout=None if not refs else 0.0) if open_ else None
                    if item is None:
                        open_ = False
                        break
                    kind, job = item
                    if kind == "bad":
                        yield job
                    else:
                        refs[task.remote(job, r2g)] = job
            except q.Empty:
                pass
            if not refs:
                continue
            done, _ = ray.wait(list(refs), num_returns=1, timeout=0.05)
            for ref in done:
                job = refs.pop(ref)
                try:
                    yield nodes.name(ray.get(ref))
                except Exception as e:  # the task failed on every try
                    yield _failed(job, e)
    finally:
        ray.shutdown()


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run the jobs of a JSON file, print one JSON line per result")
    r.add_argument("--jobs", required=True, help='JSON list of {"id": N, "args": [r2g arguments...]}')
    r.add_argument("--r2g", required=True, help="the r2g binary (the same path on every node)")
    where = r.add_mutually_exclusive_group(required=True)
    where.add_argument("--local", type=int, metavar="N", help="N worker threads on this machine")
    where.add_argument("--ray", metavar="ADDRESS", help="'auto' or a Ray cluster's address")
    r.add_argument("--retries", type=int, default=2, help="tries after a failed one (Ray only)")
    r.add_argument("--max-concurrent", type=int, help="at most this many jobs at once (Ray only)")
    v = sub.add_parser("serve", help="one Ray driver for jobs sent as JSON lines on stdin, results on stdout")
    v.add_argument("--r2g", required=True, help="the r2g binary (the same path on every node)")
    v.add_argument("--ray", required=True, metavar="ADDRESS", help="'auto' or a Ray cluster's address")
    v.add_argument("--retries", type=int, default=2, help="tries after a failed one")
    sub.add_parser("resources", help="this node's resources for `ray start --resources=...`")
    sub.add_parser("sweep", help="clean up after this node's dead jobs")
    a = ap.parse_args(argv)
    if a.cmd == "resources":
        print(json.dumps({RESOURCE: node_capacity()}))
        return 0
    if a.cmd == "sweep":
        print(json.dumps({"swept": sweep()}))
        return 0
    results: Callable[[], Iterator[dict[str, Any]]]
    if a.cmd == "serve":
        results = lambda: _serve(a.r2g, a.ray, a.retries)  # noqa: E731
        for res in results():
            sys.stdout.write(json.dumps(res) + "\n")
            sys.stdout.flush()
        return 0
    jobs = json.loads(Path(a.jobs).read_text())
    if a.local is not None:
        results = lambda: _local(jobs, a.r2g, a.local)  # noqa: E731
    else:
        results = lambda: _ray(jobs, a.r2g, a.ray, a.retries, a.max_concurrent)  # noqa: E731
    for res in results():
        sys.stdout.write(json.dumps(res) + "\n")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
