"""A Ray cluster of three nodes on this one machine, each node a separate "machine" made of
namespaces this test creates: its own network namespace (a private 10.x address on a bridge
that lives in a namespace of its own, reaching nothing outside), and its own mount namespace
with its own /dev/shm, /tmp (Ray's session folders) and fleet job folder, so no node can see
or sweep another's leftovers. The batch's output folder is the one thing every node shares,
bind-mounted at the same path on each, as fleet/MULTINODE.md asks of a real cluster.

Each node is started as MULTINODE.md tells a user (`ray start --head --port=6379` /
`ray start --address=HEAD:6379`, both with `--resources="$(python fleet/py/r2g_fleet.py
resources)"`), with token authentication on (a token file of this test's, RAY_AUTH_TOKEN_PATH).
The episodes are scripted (recorded conversations: synthetic model answers).

1. `r2g batch --ray HEAD:6379`, driven from the head: every row of batch.json names the Ray
   node id and address that ran it, and every node ran some.
2. In the same batch, one worker node is killed (every process of its `ray start`, by pid)
   while an episode runs there, after it has finished one: the batch still ends with each
   episode exactly once, every episode folder whole (its result.json, no link that leads
   nowhere, no trace of another try's name), nothing else beside them; the node, brought
   back, sweeps the dead job's shared memory and processes (`r2g_fleet.py sweep`, as
   MULTINODE.md says).
   Replays (`r2g replay --seeds 3 --ray`) name their nodes in their summary too, and
   `r2g augment --ray` joins the cluster once for all its validations and counts them per node.
3. A second batch loses its head: the driver exits non-zero naming the head (Ray's wait for a
   lost head shortened with RAY_gcs_rpc_server_reconnect_timeout_s, as MULTINODE.md says),
   with no batch.json; once the workers are gone too, every episode folder left is whole.

The namespaces and nodes are fleet/py/r2g_netns.py's (`r2g bench batch` uses them too).
Everything the test made (processes, by pid; namespaces; links; mounts, which go with their
namespaces) is removed however it ends, and checked gone at the end."""
from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import time
from pathlib import Path
from typing import Iterator

import pytest

from conftest import R2G, ROOT, STRICT

_spec = importlib.util.spec_from_file_location("r2g_netns", ROOT / "fleet" / "py" / "r2g_netns.py")
assert _spec is not None and _spec.loader is not None
netns = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(netns)
Cluster, Node, RAY, _sh, _stat, _pids = netns.Cluster, netns.Node, netns.RAY, netns._sh, netns._stat, netns._pids
CI = os.environ.get("CI") == "true" or STRICT
GYM = "pick_block_plate"


def _fail_or_skip(why: str) -> None:
    if CI:
        pytest.fail(why, pytrace=False)
    pytest.skip(why)


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    if os.geteuid() != 0 or not all(shutil.which(t) for t in ("ip", "nsenter", "unshare")):
        _fail_or_skip("needs root and ip, nsenter, unshare (network and mount namespaces)")
    if not RAY.is_file():
        pytest.fail(f"{RAY} missing: make venv installs requirements-ray.txt")
    c = Cluster(tmp_path)
    try:
        try:
            c.build(["head", "a", "b"])
        except (subprocess.CalledProcessError, RuntimeError) as e:
            _fail_or_skip(f"namespaces could not be made here: {e}")
        yield c
    finally:
        left = c.teardown()
        print("cleanup check:", json.dumps(left))
        assert left == {"processes": [], "namespaces": [], "mounts": []}, left


def _batch(c: Cluster, head: Node, out: Path, episodes: int, **env: str) -> subprocess.Popen[str]:
    """`r2g batch` on the head node, as a user there would run it."""
    p = subprocess.Popen(
        head.cmd(f"exec {R2G} batch {GYM} --episodes {episodes} --max-decisions 2 --ray {head.ip}:6379 --out {out}"),
        env=dict(c.env, **env), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    c.started.append(p)  # type: ignore[arg-type]
    return p


def _not_whole(out: Path) -> list[str]:
    """What is wrong with the episode folders under `out`: one without result.json, a link
    that leads nowhere (the episode's links are absolute: a folder written under another name
    and renamed would break them), a file naming a hidden try folder, or a leftover beside
    the folders."""
    bad = [f"{d.name}: no result.json" for d in out.glob("episode-*") if not (d / "result.json").is_file()]
    for d in out.glob("episode-*"):
        for base, dirs, files in os.walk(d):
            for name in dirs + files:
                p = Path(base) / name
                if p.is_symlink() and not p.exists():
                    bad.append(f"{p.relative_to(out)}: a link to {os.readlink(p)}, which is not there")
                elif p.is_file() and not p.is_symlink() and any(t in p.read_bytes() for t in (b".part-", b".removed-")):
                    bad.append(f"{p.relative_to(out)}: names a try folder")
    return bad + [f"{d.name}: left beside the episodes" for d in out.glob(".episode-*")]


def test_a_batch_across_three_namespaced_nodes_survives_a_lost_worker_and_names_a_lost_head(cluster: Cluster) -> None:
    t0 = time.monotonic()
    c = cluster
    head, a, b = c.nodes
    head.start_ray(c.node_env, None)
    head.wait_up()
    for n in (a, b):
        n.start_ray(c.node_env, head.ip)
    for n in (a, b):
        n.wait_up()
    print("nodes:", {n.name: n.ip for n in c.nodes}, f"up in {time.monotonic() - t0:.1f} s")
    # The cluster wants its token: a driver presenting another one is turned away.
    wrong = dict(c.env, RAY_AUTH_MODE="token", RAY_AUTH_TOKEN="0" * 32)
    wrong.pop("RAY_AUTH_TOKEN_PATH")
    refused = subprocess.run(head.cmd(f".venv/bin/python -c 'import ray; ray.init(address=\"{head.ip}:6379\")'"),
                             env=wrong, capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0 and "uthenticat" in refused.stderr, refused.stderr[-2000:]
    print("a driver with a wrong token:", refused.stderr.strip().splitlines()[-1][:200])
    # Each node offers what `resources` prints there: one slot, by its own /dev/shm.
    for n in c.nodes:
        assert json.loads(_sh(*n.cmd(".venv/bin/python fleet/py/r2g_fleet.py resources")).stdout) == {"r2g_gym": 1}

    # 1 + 2. A batch across the nodes; a worker node is killed while an episode runs there,
    # one it started after finishing another (so it has a row of its own in the summary):
    # whichever worker gets there first.
    out = c.shared / "b1"
    episodes = 8
    batch = _batch(c, head, out, episodes)
    victim, dead = None, None
    first: dict[str, object] = {}
    deadline = time.monotonic() + 200
    while victim is None and time.monotonic() < deadline and batch.poll() is None:
        for n in (a, b):
            jobs = n.fleet_jobs()
            for tag, facts in jobs.items():
                first.setdefault(n.name, facts["job"])
                # Running there (its gym's shared memory made), after the node's first one ended.
                if (facts["job"] != first[n.name] and facts.get("leader") and n.shm(str(facts["prefix"]))
                        and all(f["job"] != first[n.name] for f in jobs.values())):
                    victim, dead = dict(facts, tag=tag), n
                    break
            if victim is not None:
                break
        time.sleep(0.2)
    if victim is None or dead is None:
        batch.kill()
        pytest.fail(f"no worker node was seen running a second episode: {batch.communicate()[1][-3000:]}")
    prefix = str(victim["prefix"])
    print(f"killing node {dead.name} ({dead.ip}) while job {victim['job']} ({victim['tag']}) runs there")
    killed = dead.kill_ray()
    assert killed, f"node {dead.name} had no Ray processes"
    left_shm = dead.shm(prefix)
    stdout, stderr = batch.communicate(timeout=300)
    assert batch.returncode == 0, stderr[-4000:]
    summary = json.loads(stdout.strip().splitlines()[-1])
    rows = summary["per_episode"]
    assert summary["episodes"] == episodes and summary["errors"] == 0, summary
    saved = json.loads((out / "batch.json").read_text())
    assert [r["node"]["id"] for r in saved["per_episode"]] == [r["node"]["id"] for r in rows]
    ips = {n.ip: n.name for n in c.nodes}
    per_node: dict[str, list[int]] = {}
    for i, r in enumerate(rows):
        node = r["node"]
        assert len(node["id"] or "") == 56 and node["ip"] in ips, node
        per_node.setdefault(ips[node["ip"]], []).append(i)
    print("episodes per node:", json.dumps(per_node))
    print("node ids:", json.dumps({ips[r["node"]["ip"]]: r["node"]["id"] for r in rows}))
    assert sorted(per_node) == ["a", "b", "head"], per_node
    assert not _not_whole(out), _not_whole(out)
    # Each episode exactly once: one folder each, one row each, nothing else.
    assert sorted(p.name for p in out.iterdir()) == ["batch.json"] + [f"episode-{i:03}" for i in range(episodes)]
    retried = int(str(victim["job"]))
    assert ips[rows[retried]["node"]["ip"]] != dead.name, f"episode {retried} should have run again elsewhere"
    print(f"episode {retried} was retried on node {ips[rows[retried]['node']['ip']]}")

    # The node comes back: sweeps what the dead job left, then joins again.
    leader_sid = int(str(victim["leader"]))
    session = [p for p in _pids() if (s := _stat(p)) and int(s[3]) == leader_sid and s[0] not in ("Z", "X")]
    print(f"left on node {dead.name} after the kill:", json.dumps({"shm files": len(left_shm), "job folder":
                                                               victim["tag"] in dead.fleet_jobs(),
                                                               "job processes": len(session)}))
    swept = json.loads(_sh(*dead.cmd(".venv/bin/python fleet/py/r2g_fleet.py sweep")).stdout)
    print(f"node {dead.name}'s sweep:", swept)
    assert victim["tag"] in swept["swept"], swept
    assert not dead.shm(prefix) and not dead.path(f"/tmp/{victim['tag']}").exists() and not dead.fleet_jobs()
    assert not [p for p in _pids() if (s := _stat(p)) and int(s[3]) == leader_sid and s[0] not in ("Z", "X")]
    dead.start_ray(c.node_env, head.ip)
    dead.wait_up()

    # Replays name their nodes too (in their own summary).
    r = subprocess.run(head.cmd(f"exec {R2G} replay {GYM} --seeds 3 --ray {head.ip}:6379 --out {c.shared / 'r'}"),
                       env=c.env, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-3000:]
    replays = json.loads(r.stdout.strip().splitlines()[-1])["per_episode"]
    assert len(replays) == 3 and all(len(x["node"]["id"]) == 56 and x["node"]["ip"] in ips for x in replays), replays
    print("replays per node:", json.dumps({ips[x["node"]["ip"]]: x["seed"] for x in replays}))

    # One driver for a whole augmentation, its validations counted per node.
    r = subprocess.run(head.cmd(f"exec {R2G} augment {GYM} --candidates 3 --factors object_size --levels 1 --no-sheet "
                                f"--ray {head.ip}:6379 --out {c.shared / 'aug'}"),
                       env=c.env, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-3000:]
    aug = json.loads(r.stdout.strip().splitlines()[-1])
    print("augment --ray:", json.dumps({k: aug[k] for k in ("kept", "gate_runs", "fleet_drivers_started",
                                                            "fleet_nodes")}))
    assert aug["kept"] >= 1 and aug["fleet_drivers_started"] == 1, aug
    assert aug["fleet_nodes"] and 1 <= sum(aug["fleet_nodes"].values()) <= aug["gate_runs"], aug
    for key in aug["fleet_nodes"]:
        node_id, _, ip = key.partition("@")
        assert len(node_id) == 56 and ip in ips, key

    # 3. The head is lost mid-batch: the driver says so and leaves nothing half-written.
    out2 = c.shared / "b2"
    # Ray's wait for a lost head, shortened for the driver alone (MULTINODE.md).
    batch = _batch(c, head, out2, 4, RAY_gcs_rpc_server_reconnect_timeout_s="10")
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and batch.poll() is None:
        if any(n.fleet_jobs() for n in c.nodes) and any(n.shm() for n in c.nodes):
            break
        time.sleep(0.2)
    running = {n.name: [f["job"] for f in n.fleet_jobs().values()] for n in c.nodes}
    head.kill_ray()
    lost_at = time.monotonic()
    stdout, stderr = batch.communicate(timeout=180)
    print(f"head lost while running {running}: exit {batch.returncode} after {time.monotonic() - lost_at:.1f} s:",
          stderr.strip().splitlines()[-1] if stderr.strip() else "")
    assert batch.returncode != 0
    assert f"Ray head at {head.ip}:6379" in stderr, stderr[-3000:]
    assert not (out2 / "batch.json").exists()
    # Tries still running on the workers go on until their nodes give up on the head (or, as
    # here, die): a folder they leave is whole once it has its result.json. The workers die
    # now; what is left must be whole folders and folders that say they are not (no result).
    for n in (a, b):
        n.kill_ray()
    print("batch folder after:", sorted(p.name for p in out2.iterdir()))
    bad = _not_whole(out2)
    assert all(x.endswith(": no result.json") for x in bad), bad
    print(f"test wall {time.monotonic() - t0:.1f} s")
