"""The operator channel: only root, the runtime's own user or the operator group clears a fault.

A real fault (a Franka-profile contact past the operator limit) on a live instance, then
`r2g clear` from three other users the kernel vouches for on the operator socket (SO_PEERCRED):
a plain user, a stand-in for the agent host's user (outside the sandbox, in the instance's
shared group but not the operator group), and an operator. Needs root to start processes as
those users; the uids are unused numbers, so nothing on the machine is changed.
"""
from __future__ import annotations

import grp
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

import robo
from conftest import R2G
from test_robo_contract import fb, press_on_block, tcp_line, write_config

PLAIN_UID = 65534  # nobody
AGENT_UID = 64998
OPERATOR_UID = 64999


@pytest.fixture()
def faulted(tmp_path: Path):
    if os.geteuid() != 0:
        pytest.fail("this test starts processes as other users and must run as root (CI does)")
    # Reachable by the other users (pytest's own temp folder is not).
    run_dir = Path(tempfile.mkdtemp(prefix="r2g-op-"))
    run_dir.chmod(0o755)
    log = tmp_path / "up.log"
    cfg = write_config(tmp_path, {"profile": "franka", "franka": {"reflex_force_n": 500, "operator_force_n": 25}})
    name = f"py{os.getpid()}op"
    env = {**os.environ, "R2G_RUN_DIR": str(run_dir)}
    with open(log, "w") as err:
        proc = subprocess.Popen(
            [str(R2G), "up", "pick_block_plate", "--instance", name, "--mode", "lockstep", "--render-hz", "0",
             "--robot-config", cfg, "--operator-group", "operator"],
            stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL, text=True, env=env)
    previous = os.environ.get("R2G_INSTANCE")
    os.environ["R2G_INSTANCE"] = name
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == f"READY {name}", log.read_text()
        assert press_on_block() == 0
        assert robo.get_state([])["fault"], fb()
        yield name, env, log
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(run_dir, ignore_errors=True)
        if previous is None:
            os.environ.pop("R2G_INSTANCE", None)
        else:
            os.environ["R2G_INSTANCE"] = previous


def clear_as(name: str, env: dict, uid: int, groups: list[int]) -> subprocess.CompletedProcess:
    return subprocess.run([str(R2G), "clear", "--instance", name], capture_output=True, text=True, timeout=30,
                          env=env, user=uid, group=uid, extra_groups=groups)


def test_only_an_operator_clears_a_fault(faulted) -> None:
    name, env, log = faulted
    operator = grp.getgrnam("operator").gr_gid
    shared = grp.getgrnam("users").gr_gid  # stands in for the instance's shared group
    plain = clear_as(name, env, PLAIN_UID, [])
    assert plain.returncode != 0 and "refused" in plain.stderr, plain
    agent = clear_as(name, env, AGENT_UID, [shared])
    assert agent.returncode != 0 and "refused" in agent.stderr, agent
    assert "not in the operator group operator" in agent.stderr
    assert robo.get_state([])["fault"], "still faulted after the refused attempts"
    rot = robo.get_state([])["ee_pose"][3:]
    away = {"actions": tcp_line([0.5, -0.12, 0.12], rot, 1.0, 2), "type": "ee_pose", "freq": ""}
    assert robo.post_actions(away) == 0 and fb()["status"] == "operator_required"

    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and f"uid {AGENT_UID} pid" not in log.read_text():
        time.sleep(0.05)
    text = log.read_text()
    for uid in (PLAIN_UID, AGENT_UID):
        assert f"refused operator request 'clear' from uid {uid} pid " in text, text

    ok = clear_as(name, env, OPERATOR_UID, [operator])
    assert ok.returncode == 0 and "fault cleared" in ok.stdout, ok
    assert robo.get_state([])["fault"] is None
    assert robo.post_actions(away) == 1, fb()
