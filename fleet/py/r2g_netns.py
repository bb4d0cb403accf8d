"""A Ray cluster of several "machines" on this one, made of namespaces: each node a network
namespace (an address of its own on a bridge that lives in a namespace of its own and reaches
nothing outside) and a mount namespace (its own /dev/shm, /tmp with Ray's session folders and
the fleet's job folder), one folder shared by all at the same path. Each node is started as
fleet/MULTINODE.md tells a user, with token authentication. Needs root, `ip`, `nsenter`,
`unshare`. Used by tests/python/test_fleet_multinode.py and `r2g bench batch`:

    python fleet/py/r2g_netns.py bench --r2g target/release/r2g --jobs 6

builds a head (no gym slot of its own) and two workers, runs the same replay jobs one at a time
through Ray from the head to the workers and on a local worker in the head's namespace, prints Ray's overhead per task as
one JSON line, and removes everything it made (processes by pid, namespaces, links; the mounts
go with their namespaces)."""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

RAY = ROOT / ".venv" / "bin" / "ray"
PY = ROOT / ".venv" / "bin" / "python"
OBJECT_STORE_BYTES = 80 * 1024 * 1024
"""Results are a few kB: Ray's smallest object store, so three nodes start quickly on 2 cores."""
SHM_MB = 700
"""Each node's /dev/shm: the object store and one gym at the fleet's 512 MiB each, so
`resources` offers one r2g_gym slot per node."""
TOKEN_PATH = "/tmp/ray-auth-token"
"""Where each node keeps the cluster's token (in its own /tmp)."""


def _sh(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(list(args), capture_output=True, text=True, check=check, timeout=60)


def _stat(pid: int) -> list[str] | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _ns(pid: int, kind: str) -> str | None:
    try:
        return os.readlink(f"/proc/{pid}/ns/{kind}")
    except OSError:
        return None


def _pids() -> list[int]:
    return [int(e) for e in os.listdir("/proc") if e.isdigit()]


def _start(pid: int) -> int | None:
    s = _stat(pid)
    return int(s[19]) if s and s[0] not in ("Z", "X") else None


def _kill(pid: int, start: int | None) -> bool:
    """SIGKILL to `pid` only while it is still the process that started at `start` (clock
    ticks since boot, read when it was chosen): held by a pidfd, checked, then signalled
    through the pidfd, so a pid given out again in between is never signalled."""
    if start is None:
        return False
    try:
        fd = os.pidfd_open(pid)
    except OSError:
        return False
    try:
        if _start(pid) != start:
            return False
        signal.pidfd_send_signal(fd, signal.SIGKILL)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


class Node:
    """One "machine": a holder process (it keeps the mount namespace while Ray comes and goes)
    in network namespace `netns`, with private /dev/shm and /tmp and the shared folder."""

    def __init__(self, name: str, netns: str, ip: str, shared: Path, log_dir: Path) -> None:
        self.name, self.netns, self.ip, self.log_dir = name, netns, ip, log_dir
        self.ray: subprocess.Popen[bytes] | None = None
        self.ray_sid = 0
        """The session of the node's latest `ray start` (its pid): kept after that process is
        reaped, but only ever used together with the node's own mount namespace."""
        self.logs: list[Path] = []
        # A private mount namespace entered in the node's network namespace: tmpfs on /dev/shm
        # and /tmp, then the shared folder bound back at its own path (through an fd opened
        # before /tmp was covered: the kernel follows /proc/self/fd/N to the real folder), and
        # the checkout too when it lies under /tmp (a clone in /tmp: every machine of a real
        # cluster has its own checkout at the same path; here they share the one).
        # Outer folders first, so binding one never covers another's bind.
        keep = sorted([str(shared)] + ([str(ROOT)] if Path("/tmp") in ROOT.parents else []), key=len)
        holder = f"""
import ctypes, os, signal, sys
libc = ctypes.CDLL(None, use_errno=True)
def mount(src, dst, fs, flags, data):
    if libc.mount(src.encode(), dst.encode(), fs.encode() if fs else None, flags, data.encode() if data else None):
        raise OSError(ctypes.get_errno(), f"mount {{dst}}")
keep = {keep!r}
fds = [os.open(k, os.O_RDONLY | os.O_DIRECTORY) for k in keep]
mount("r2gshm", "/dev/shm", "tmpfs", 0, "size={SHM_MB}m,mode=1777")
mount("r2gtmp", "/tmp", "tmpfs", 0, "mode=1777")
for k, fd in zip(keep, fds):
    os.makedirs(k, exist_ok=True)
    mount(f"/proc/self/fd/{{fd}}", k, None, 4096, None)  # MS_BIND
    os.close(fd)
print("up", flush=True)
signal.signal(signal.SIGTERM, lambda *a: sys.exit(0))
while True:
    signal.pause()
"""
        self.holder = subprocess.Popen(
            ["nsenter", f"--net=/run/netns/{netns}", "unshare", "--mount", "--propagation", "private",
             str(PY), "-c", holder],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
        )
        assert self.holder.stdout is not None
        line = self.holder.stdout.readline()
        if line != b"up\n":
            _, err = self.holder.communicate(timeout=10)
            raise RuntimeError(f"node {name}: namespaces not set up: {err.decode(errors='replace')[-2000:]}")
        self.mnt = _ns(self.holder.pid, "mnt")

    def cmd(self, script: str) -> list[str]:
        """`sh -c script` on this node (its network and mount namespaces), in the checkout."""
        return ["nsenter", "-t", str(self.holder.pid), "--mount", "--net", "sh", "-c", f"cd {ROOT} && {script}"]

    def start_ray(self, env: dict[str, str], head: str | None, resources: str | None = None) -> None:
        """`ray start` as MULTINODE.md shows it, plus what a test on 2 cores needs (--block so
        the test holds it, a small object store, no dashboard); `resources`: instead of what
        `r2g_fleet.py resources` prints on the node."""
        where = "--head --port=6379 --include-dashboard=false" if head is None else f"--address={head}:6379"
        res = f"'{resources}'" if resources else '"$(.venv/bin/python fleet/py/r2g_fleet.py resources)"'
        script = (f"exec .venv/bin/ray start {where} --resources={res}"
                  f" --num-cpus=0 --object-store-memory={OBJECT_STORE_BYTES} --block")
        log = self.log_dir / f"ray-{self.name}-{len(self.logs)}.log"
        self.logs.append(log)
        self.ray = subprocess.Popen(self.cmd(script), env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT,
                                    start_new_session=True)
        self.ray_sid = self.ray.pid

    def wait_up(self, timeout: float = 120) -> None:
        assert self.ray is not None
        log = self.logs[-1]
        deadline = time.monotonic() + timeout
        while "Ray runtime started" not in log.read_text(errors="replace"):
            if self.ray.poll() is not None:
                raise RuntimeError(f"{self.name}: ray start exited: {log.read_text(errors='replace')[-3000:]}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"{self.name}: not up in {timeout} s: {log.read_text(errors='replace')[-3000:]}")
            time.sleep(0.3)
        if f"Local node IP: {self.ip}" not in log.read_text(errors="replace"):
            raise RuntimeError(f"{self.name} advertises another address: {log.read_text(errors='replace')[-3000:]}")

    def ray_session(self) -> list[int]:
        """Every process of this node's `ray start` (its session: raylet, workers and all).
        A session number is a pid, which the machine may give out again once every process of
        the session is gone (and `ray start` reaped): only processes in this node's own mount
        namespace, which nothing but this node's processes ever enters, are counted."""
        if not self.ray_sid or not self.mnt:
            return []
        return [p for p in _pids() if (s := _stat(p)) and s[0] not in ("Z", "X") and int(s[3]) == self.ray_sid
                and _ns(p, "mnt") == self.mnt]

    def kill_ray(self) -> list[int]:
        """The node dies: SIGKILL to every process of its Ray session, by pid."""
        killed = []
        for _ in range(20):
            pids = self.ray_session()
            if not pids:
                break
            starts = {p: _start(p) for p in pids}
            # Still this node's (in its mount namespace) when its start time is read again.
            killed += [p for p in pids if _ns(p, "mnt") == self.mnt and _kill(p, starts[p])]
            time.sleep(0.1)
        if self.ray is not None:
            try:
                self.ray.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.ray.kill()  # our child, not reaped yet: its pid is still its own
                self.ray.wait(timeout=10)
            self.ray = None
        return sorted(set(killed))

    def path(self, p: str) -> Path:
        """`p` as this node sees it (its own /tmp, /dev/shm)."""
        return Path(f"/proc/{self.holder.pid}/root") / p.lstrip("/")

    def fleet_jobs(self) -> dict[str, dict[str, object]]:
        root = self.path(f"/tmp/r2g-fleet-{os.getuid()}")
        seen: dict[str, dict[str, object]] = {}
        for f in root.glob("*/job.json") if root.is_dir() else []:
            try:
                seen[f.parent.name.split(".")[0]] = json.loads(f.read_text())
            except (OSError, ValueError):
                continue
        return seen

    def shm(self, prefix: str = "r2gj") -> list[str]:
        return sorted(p.name for p in self.path("/dev/shm").glob(f"{prefix}*"))


class Cluster:
    def __init__(self, tmp: Path) -> None:
        tag = f"r2gmn{os.getpid() % 100000}"
        self.hub = f"{tag}x"
        self.subnet = f"10.213.{os.getpid() % 250}"
        self.netns: list[str] = []
        self.nodes: list[Node] = []
        self.shared = tmp / "shared"
        self.shared.mkdir()
        # A token of this test's, copied to every node as MULTINODE.md says (there at
        # TOKEN_PATH, named by RAY_AUTH_TOKEN_PATH: the machine's ~/.ray is left alone).
        self.token = os.urandom(16).hex()
        self.env = {k: v for k, v in os.environ.items() if k not in ("R2G_IPC_CONFIG", "RAY_ADDRESS")}
        self.env.pop("RAY_AUTH_MODE", None)
        self.env.pop("RAY_AUTH_TOKEN", None)
        # The driver: the token file alone (the fleet's driver then asks for token mode).
        self.env.update(RAY_USAGE_STATS_ENABLED="0", RAY_AUTH_TOKEN_PATH=TOKEN_PATH)
        # The nodes, as MULTINODE.md starts them: `ray start --address` (unlike `--head`) does
        # not turn token mode on by itself when it finds a token.
        self.node_env = dict(self.env, RAY_AUTH_MODE="token")
        self.tmp = tmp
        self.started: list[subprocess.Popen[bytes]] = []
        self.net_ids: set[str] = set()

    def build(self, names: list[str]) -> None:
        _sh("ip", "netns", "add", self.hub)
        self.netns.append(self.hub)
        self.net_ids.add(f"net:[{os.stat(f'/run/netns/{self.hub}').st_ino}]")
        _sh("ip", "-n", self.hub, "link", "add", "br0", "type", "bridge")
        _sh("ip", "-n", self.hub, "addr", "add", f"{self.subnet}.254/24", "dev", "br0")
        _sh("ip", "-n", self.hub, "link", "set", "br0", "up")
        for k, name in enumerate(names, start=1):
            ns = f"{self.hub[:-1]}{name[0]}"
            _sh("ip", "netns", "add", ns)
            self.netns.append(ns)
            self.net_ids.add(f"net:[{os.stat(f'/run/netns/{ns}').st_ino}]")
            # Both ends made inside the namespaces: nothing appears in the machine's own.
            _sh("ip", "-n", self.hub, "link", "add", f"p{k}", "type", "veth", "peer", "name", "eth0", "netns", ns)
            _sh("ip", "-n", self.hub, "link", "set", f"p{k}", "master", "br0", "up")
            ip = f"{self.subnet}.{k}"
            _sh("ip", "-n", ns, "addr", "add", f"{ip}/24", "dev", "eth0")
            _sh("ip", "-n", ns, "link", "set", "lo", "up")
            _sh("ip", "-n", ns, "link", "set", "eth0", "up")
            # A default route to the hub (which forwards nothing), as a machine has one: Ray
            # finds its own address by the route out.
            _sh("ip", "-n", ns, "route", "add", "default", "via", f"{self.subnet}.254")
            node = Node(name, ns, ip, self.shared, self.tmp)
            self.nodes.append(node)
            token = node.path(TOKEN_PATH)
            token.write_text(self.token)
            token.chmod(0o600)

    def ours(self) -> list[int]:
        """Every process in one of the test's namespaces (network or mount), or below one."""
        mnts = {n.mnt for n in self.nodes if n.mnt}
        # Our children not reaped yet (poll() reaps one that has exited): a pid is ours only
        # while it is not reaped, since the machine may give it out again after.
        roots = {p.pid for p in self.started if p.poll() is None}
        roots |= {n.holder.pid for n in self.nodes if n.holder.poll() is None}
        roots |= {n.ray.pid for n in self.nodes if n.ray is not None and n.ray.poll() is None}
        parent = {p: int(s[1]) for p in _pids() if (s := _stat(p)) and s[0] not in ("Z", "X")}
        ours = {p for p in parent if _ns(p, "net") in self.net_ids or _ns(p, "mnt") in mnts or p in roots}
        for p in parent:
            q = p
            while q > 1 and q not in ours:
                q = parent.get(q, 0)
            if q > 1:
                ours.add(p)
        return sorted(p for p in ours if p in parent and p != os.getpid())

    def teardown(self) -> dict[str, object]:
        """Removes everything this cluster made, whatever state it is in (each step goes on
        when one before it failed), and returns what is left (all empty when all went)."""
        for p in self.started:
            try:
                p.kill()
                p.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                pass
        for n in self.nodes:
            try:
                n.kill_ray()
            except (OSError, subprocess.TimeoutExpired):
                pass
        # Then whatever else lives in our namespaces or below our processes (episodes'
        # sessions, holders), by pid.
        for _ in range(50):
            left = self.ours()
            if not left:
                break
            starts = {p: _start(p) for p in left}
            # Still ours when its start time is read again (see `_kill`): one that changed
            # between the two reads is left to the next pass, which looks again.
            still = set(self.ours())
            for p in left:
                if p in still:
                    _kill(p, starts[p])
            time.sleep(0.1)
        for n in self.nodes:
            try:
                n.holder.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
        for ns in reversed(self.netns):
            _sh("ip", "netns", "delete", ns, check=False)
        mounts = Path("/proc/self/mountinfo").read_text()
        names = _sh("ip", "netns", "list").stdout
        return {
            "processes": self.ours(),
            "namespaces": [n for n in self.netns if n in names.split()],
            # The nodes' mounts lived in their own namespaces (none ever showed here); `ip netns
            # add` binds each namespace at /run/netns/NAME, which `ip netns delete` undoes.
            "mounts": [m for m in mounts.splitlines() if str(self.shared) in m or " r2gshm " in m or " r2gtmp " in m
                       or any(f"/run/netns/{n} " in m for n in self.netns)],
        }


def bench(r2g: str, jobs: int) -> dict[str, object]:
    """Ray's overhead per task across namespaced nodes: the same `r2g replay` jobs one at a
    time (`--max-concurrent 1`) through Ray from the head to the workers, and on one local worker in the
    head's namespace; (Ray - local) / jobs. The nodes share this machine's cores: an overhead,
    never a speed-up."""
    with tempfile.TemporaryDirectory(prefix="r2g-netns-bench-") as tmp:
        c = Cluster(Path(tmp))
        try:
            c.build(["head", "a", "b"])
            head = c.nodes[0]
            # No gym slot on the head: every task crosses to a worker's namespace.
            head.start_ray(c.node_env, None, '{"r2g_gym": 0}')
            head.wait_up()
            for n in c.nodes[1:]:
                n.start_ray(c.node_env, head.ip)
            for n in c.nodes[1:]:
                n.wait_up()
            gyms = [g.name for g in sorted((ROOT / "gyms").iterdir()) if (g / "scene.toml").is_file()]
            walls: dict[str, float] = {}
            nodes: dict[str, int] = {}
            for where in ("local", "ray"):
                out = c.shared / where
                out.mkdir()
                body = [{"id": i, "args": ["replay", gyms[i % len(gyms)], "--out", str(out)], "cwd": str(ROOT)}
                        for i in range(jobs)]
                (out / "jobs.json").write_text(json.dumps(body))
                how = "--local 1" if where == "local" else f"--ray {head.ip}:6379 --max-concurrent 1"
                t0 = time.monotonic()
                r = subprocess.run(head.cmd(f"exec .venv/bin/python fleet/py/r2g_fleet.py run --jobs {out}/jobs.json "
                                            f"--r2g {r2g} {how}"),
                                   env=c.env, capture_output=True, text=True, timeout=600)
                walls[where] = time.monotonic() - t0
                results = [json.loads(x) for x in r.stdout.splitlines() if x.startswith("{")]
                if r.returncode != 0 or len(results) != jobs or any(x.get("value") is None for x in results):
                    raise RuntimeError(f"{where}: {len(results)} of {jobs} results: {r.stderr[-2000:]}")
                if where == "ray":
                    for x in results:
                        ip = x["node"]["ip"]
                        nodes[ip] = nodes.get(ip, 0) + 1
            return {"nodes": len(c.nodes), "jobs": jobs, "cores": os.cpu_count(), "wall_s": walls,
                    "ray_overhead_per_task_ms": (walls["ray"] - walls["local"]) / jobs * 1e3, "jobs_per_node": nodes}
        finally:
            left = c.teardown()
            if any(left.values()):
                print(f"left behind: {left}", file=sys.stderr)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("bench", help="Ray's overhead per task across three namespaced nodes")
    b.add_argument("--r2g", required=True, help="the r2g binary")
    b.add_argument("--jobs", type=int, default=6, help="replay jobs per configuration")
    a = ap.parse_args(argv)
    if os.geteuid() != 0:
        raise SystemExit("r2g_netns.py needs root (network and mount namespaces)")
    print(json.dumps(bench(str(Path(a.r2g).resolve()), max(1, a.jobs))))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
