"""Runs r2g jobs (one episode each: `r2g episode ...`, `r2g replay ...`, any subcommand that ends
with one JSON line) on local worker threads or as Ray tasks, and streams each result back as one
JSON line on stdout, in the order they finish.

    python fleet/py/r2g_fleet.py run --jobs JOBS.json (--local N | --ray auto|ADDRESS) [--retries 2]
    python fleet/py/r2g_fleet.py resources        # this node's r2g_gym capacity, for `ray start`

Every job runs the same way wherever it runs (`run_job`): `r2g` in a session and process group
of its own, dying with the worker (PR_SET_PDEATHSIG), on an iceoryx2 configuration of its own
(its own root path and /dev/shm prefix). Cleanup never relies on `finally` alone: a worker that
is SIGKILLed takes its job's processes with it (PDEATHSIG), and the next job on that node sweeps
what any dead job left (`sweep`): it kills a group whose worker is gone and removes the
job's shared-memory files by their prefix. Ray retries the task of a dead worker.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
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
    ``$R2G_FLEET_DIR`` of the node it runs on (read there, not in the driver), else /tmp/r2g-fleet."""
    return Path(os.environ.get("R2G_FLEET_DIR", "/tmp/r2g-fleet"))
PR_SET_PDEATHSIG = 1


def node_capacity() -> int:
    """Gyms this node runs at once: one per core, and no more than /dev/shm holds."""
    cores = os.cpu_count() or 1
    st = os.statvfs("/dev/shm")
    free_mb = st.f_bavail * st.f_frsize / 2**20
    return max(1, min(cores, int(free_mb // SHM_PER_GYM_MB)))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _kill_group(pgid: int) -> None:
    """SIGTERM to the job's group (r2g stops its instance in order), SIGKILL after 10 s."""
    for sig, wait_s in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            if not _group_alive(pgid):
                return
            time.sleep(0.05)


def _remove_job(d: Path) -> None:
    facts = json.loads((d / "job.json").read_text()) if (d / "job.json").is_file() else {}
    prefix = facts.get("prefix")
    if prefix:
        for f in Path("/dev/shm").glob(f"{prefix}*"):
            f.unlink(missing_ok=True)
    if facts.get("ipc_root"):
        shutil.rmtree(facts["ipc_root"], ignore_errors=True)
    shutil.rmtree(d, ignore_errors=True)


def sweep() -> list[str]:
    """Cleans up after dead jobs of this node: a job whose worker is gone has its process group
    killed (if anything of it survived) and its shared memory and folder removed. Returns the
    jobs swept."""
    swept: list[str] = []
    root = jobs_root()
    if not root.is_dir():
        return swept
    for d in root.iterdir():
        try:
            facts = json.loads((d / "job.json").read_text())
        except (OSError, ValueError):
            continue
        if _alive(int(facts["worker"])):
            continue
        pgid = int(facts.get("pgid") or 0)
        if pgid and _group_alive(pgid):
            _kill_group(pgid)
        _remove_job(d)
        swept.append(d.name)
    return swept


def _die_with_worker() -> None:
    # In the child before exec: its own session (so Ray's cleanup of the worker does not reach
    # it and we kill it as one group), and SIGKILL when the worker dies, however it dies.
    os.setsid()
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def run_job(job: dict[str, Any], r2g: str) -> dict[str, Any]:
    """Runs one job here: `r2g <job["args"]>`, isolated as the module docstring says. Returns
    its result: the exit status, its last JSON line, the tail of its stderr, where it ran."""
    sweep()
    tag = f"r2gj{uuid.uuid4().hex[:10]}"
    d = jobs_root() / tag
    d.mkdir(parents=True)
    # A short root path: iceoryx2's event sockets live under it, and socket paths are short.
    ipc_root = Path("/tmp") / tag
    ipc_root.mkdir()
    prefix = f"{tag}_"
    config = d / "iceoryx2.toml"
    config.write_text(f'[global]\nroot-path = "{ipc_root}/"\nprefix = "{prefix}"\n')
    facts: dict[str, Any] = {"worker": os.getpid(), "prefix": prefix, "pgid": 0, "ipc_root": str(ipc_root)}
    (d / "job.json").write_text(json.dumps(facts))
    env = dict(os.environ, R2G_IPC_CONFIG=str(config))
    for var in ("RAY_ADDRESS",):
        env.pop(var, None)
    stderr_path = d / "stderr.txt"
    t0 = time.monotonic()
    with open(stderr_path, "wb") as err:
        proc = subprocess.Popen(
            [r2g, *job["args"]],
            stdout=subprocess.PIPE,
            stderr=err,
            stdin=subprocess.DEVNULL,
            env=env,
            preexec_fn=_die_with_worker,
        )
        facts["pgid"] = proc.pid
        (d / "job.json").write_text(json.dumps(facts))
        if job.get("pid_file"):
            # Who runs this job (tests kill it to check the retry and the cleanup).
            Path(job["pid_file"]).write_text(f"{os.getpid()} {proc.pid}\n")
        try:
            out, _ = proc.communicate()
        finally:
            # Whatever is left of the group (an instance's processes) goes with the job.
            _kill_group(proc.pid)
    result = {
        "id": job["id"],
        "rc": proc.returncode,
        "value": None,
        "stderr_tail": stderr_path.read_text(errors="replace")[-1500:],
        "node": socket.gethostname(),
        "worker": os.getpid(),
        "wall_s": time.monotonic() - t0,
    }
    for line in reversed(out.decode(errors="replace").splitlines()):
        if line.startswith("{"):
            try:
                result["value"] = json.loads(line)
                break
            except ValueError:
                continue
    _remove_job(d)
    return result


def _local(jobs: list[dict[str, Any]], r2g: str, workers: int) -> Iterator[dict[str, Any]]:
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        pending: set[Future[dict[str, Any]]] = {pool.submit(run_job, j, r2g) for j in jobs}
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                yield f.result()


def _ray(
    jobs: list[dict[str, Any]], r2g: str, address: str, retries: int, max_concurrent: int | None
) -> Iterator[dict[str, Any]]:
    if "RAY_AUTH_MODE" not in os.environ and (Path.home() / ".ray" / "auth_token").is_file():
        # Clusters started by `ray start` (2.5x and later) want a token by default; a driver on a
        # node that has one (copied there, see fleet/MULTINODE.md) presents it. Read at import.
        os.environ["RAY_AUTH_MODE"] = "token"
    import ray  # only here: a batch without --ray needs no Ray
    if address == "auto":
        try:
            ray.init(address="auto", log_to_driver=False)
        except ConnectionError:
            # No cluster running: a local one for this batch, sized like `resources` says.
            ray.init(resources={RESOURCE: node_capacity()}, include_dashboard=False, log_to_driver=False)
    else:
        ray.init(address=address, log_to_driver=False)
    total = ray.cluster_resources().get(RESOURCE, 0)
    if not total:
        raise SystemExit(
            f"the Ray cluster offers no '{RESOURCE}' resource: start each node with "
            f"--resources='{{\"{RESOURCE}\": N}}' (python fleet/py/r2g_fleet.py resources prints N)"
        )
    # At most `max_concurrent` at once: each task takes that share of the cluster's gym slots.
    share = 1.0 if not max_concurrent else max(1.0, total / max_concurrent)
    task = ray.remote(run_job).options(
        resources={RESOURCE: share}, num_cpus=0, max_retries=retries, retry_exceptions=True
    )
    started = time.monotonic()
    refs = {task.remote(j, r2g): j for j in jobs}
    try:
        while refs:
            done, _ = ray.wait(list(refs), num_returns=1)
            for ref in done:
                job = refs.pop(ref)
                try:
                    yield ray.get(ref)
                except Exception as e:  # the task failed on every try
                    yield {"id": job["id"], "rc": None, "value": None, "error": f"{type(e).__name__}: {e}"[-1500:]}
    finally:
        _ = started
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
    sub.add_parser("resources", help="this node's resources for `ray start --resources=...`")
    sub.add_parser("sweep", help="clean up after this node's dead jobs")
    a = ap.parse_args(argv)
    if a.cmd == "resources":
        print(json.dumps({RESOURCE: node_capacity()}))
        return 0
    if a.cmd == "sweep":
        print(json.dumps({"swept": sweep()}))
        return 0
    jobs = json.loads(Path(a.jobs).read_text())
    results: Callable[[], Iterator[dict[str, Any]]]
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
