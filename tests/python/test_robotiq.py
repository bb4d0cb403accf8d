"""A Robotiq 2F-85 over Modbus RTU, end to end: `r2g up` with a robot config naming the gripper
starts r2g-robotiq, which talks to OUR gripper simulator (rig/py/robotiq_sim.py, written from
the published register map on pymodbus's RTU server) over a pseudo-terminal pair made by socat.
Synthetic: no real gripper. The agent side is the real `robo`; the arm is the simulated one.
The manual's frames themselves are checked byte for byte in gripper/src/robotiq.rs (our side)
and tests/python/test_robotiq_sim.py (the simulator's side).

r2g-control runs with R2G_ABORT_ON_TICK_ALLOC=1: an allocation inside the tick (where the
gripper's state is taken) would abort it, and every test here would fail.
"""
from __future__ import annotations

import os
import subprocess
import threading
import time
from typing import Iterator

import pytest

import robo
from conftest import R2G, robo_instance
from robotiq_rig import Rig, gripper_move, wait_for

pytestmark = pytest.mark.skipif(
    subprocess.run(["which", "socat"], capture_output=True).returncode != 0,
    reason="socat is missing (scripts/install-deps.sh installs it; make test does)",
)


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    name = f"py{os.getpid()}rq"
    r = Rig(tmp_path_factory.mktemp("robotiq"), name, extra_env={"R2G_ABORT_ON_TICK_ALLOC": "1"})
    try:
        with robo_instance(name):
            yield r
    finally:
        r.close()


def fault() -> str | None:
    return robo.get_state([])["fault"]


def grasp() -> dict:
    return robo.get_state([])["control_feedback"]["grasp"]


def test_open_close_and_grasp_detected(rig: Rig) -> None:
    # Activation finishes, then the gripper holds no fault.
    wait_for("the gripper's activation", lambda: fault() is None)
    rig.control(object_at=None)
    ok, dt, s = gripper_move(robo, -1.0)
    assert ok == 1, s["control_feedback"]
    assert s["gripper"][0] < -0.95, s["gripper"]
    assert s["control_feedback"]["grasp"]["status"] == "at_target"
    # Closing on an object at count 120 of 230: the fingers stop there, and the gripper says so.
    rig.control(object_at=120)
    ok, dt, s = gripper_move(robo, 1.0)
    assert ok == 1, s["control_feedback"]
    g = s["control_feedback"]["grasp"]
    assert g == {"status": "holding", "object_detected": True, "gripper_fault": None}, g
    # Stopped part-way: 120 of 230 counts closed is about 48 % open.
    assert -0.1 < s["gripper"][0] < 0.1, s["gripper"]
    # Open again: nothing held.
    ok, dt, s = gripper_move(robo, -1.0)
    assert ok == 1 and s["control_feedback"]["grasp"]["status"] == "at_target", s["control_feedback"]
    rig.control(object_at=None)


def test_one_crc_error_is_retried_without_a_fault(rig: Rig) -> None:
    wait_for("no fault", lambda: fault() is None)
    rig.control(corrupt_crc=1)
    t_end = time.monotonic() + 0.5
    while time.monotonic() < t_end:
        assert fault() is None, "one bad answer must not stop the arm"
        time.sleep(0.02)
    ok, _, s = gripper_move(robo, 0.0)
    assert ok == 1, s["control_feedback"]


def test_a_gripper_fault_holds_the_arm_until_the_operator_clears_it(rig: Rig) -> None:
    wait_for("no fault", lambda: fault() is None)
    rig.control(fault=0x0E)
    f = wait_for("the fault reaching get_state", fault, timeout=5)
    assert "0x0E" in f and "overcurrent" in f, f
    assert grasp()["gripper_fault"] and "overcurrent" in grasp()["gripper_fault"]
    q = list(robo.get_state([])["joint"])
    assert robo.post_actions({"actions": [q + [-1.0]], "type": "joint", "freq": ""}) == 0
    fb = robo.get_state([])["control_feedback"]
    assert fb["status"] == "rejected" and "gripper reports a fault" in fb["reason"], fb
    # The operator's reset reaches r2g-robotiq, which resets and reactivates the gripper.
    out = subprocess.run([str(R2G), "clear", "--instance", rig.name], capture_output=True, text=True, timeout=20)
    assert out.returncode == 0, out.stdout + out.stderr
    wait_for("the gripper reactivated", lambda: fault() is None, timeout=10)
    ok, _, s = gripper_move(robo, -1.0)
    assert ok == 1, s["control_feedback"]


def test_the_port_vanishing_mid_grasp_fails_the_chunk_and_holds_the_arm(rig: Rig) -> None:
    wait_for("no fault", lambda: fault() is None)
    ok, _, _ = gripper_move(robo, -1.0)
    assert ok == 1
    # Close slowly enough to unplug during the motion: move the arm a little at the same time,
    # so the chunk lasts a second.
    rig.control(object_at=200)
    q = list(robo.get_state([])["joint"])
    far = list(q)
    far[6] += 0.3
    # The line goes 0.25 s into the chunk (a timer thread; robo stays on this thread).
    unplugged = {}

    def unplug() -> None:
        unplugged["t"] = time.monotonic()
        rig.unplug()

    timer = threading.Timer(0.25, unplug)
    timer.start()
    ok = robo.post_actions({"actions": [far + [1.0]], "type": "joint", "freq": 1.0})
    timer.join()
    t_unplug = unplugged["t"]
    took = time.monotonic() - t_unplug
    s = robo.get_state([])
    fb = s["control_feedback"]
    assert ok == 0, fb
    assert fb["status"] == "failed" and "gripper reports a fault" in fb["reason"], fb
    assert "vanished" in fb["reason"] or "no answer" in fb["reason"], fb["reason"]
    assert s["fault"] and "gripper" in s["fault"], s["fault"]
    assert all(abs(v) < 0.05 for v in s["joint_velocity"]), f"the arm holds: {s['joint_velocity']}"
    print(f"port removed mid-grasp: chunk failed {took * 1e3:.0f} ms later: {fb['reason']}")
    # Nothing crashed: the instance and the driver still run, and the line coming back is taken.
    assert rig.up.poll() is None, rig.log()
    rig.replug()
    wait_for("the gripper back", lambda: fault() is None, timeout=15)
    ok, _, s = gripper_move(robo, -1.0)
    assert ok == 1, s["control_feedback"]
    assert "panicked" not in rig.log()
