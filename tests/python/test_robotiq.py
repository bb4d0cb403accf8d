"""A Robotiq 2F-85 over Modbus RTU, end to end: `r2g up` with a robot config naming the gripper
starts r2g-robotiq, which talks to OUR gripper simulator (rig/py/robotiq_sim.py, written from
the published register map on pymodbus's RTU server) over a pseudo-terminal pair made by socat.
Synthetic: no real gripper. The agent side is the real `robo`; the arm is the simulated one, on
the Franka profile (a gripper fault there needs the operator's `r2g clear`; a gripper still
starting or with a minor fault must not). The manual's frames themselves are checked byte for
byte in gripper/src/robotiq.rs (our side) and tests/python/test_robotiq_sim.py (the simulator's
side).

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
from conftest import R2G, need_program, robo_instance
from robotiq_rig import Rig, gripper_move, wait_for

need_program("socat", "socat is missing (scripts/install-deps.sh installs it; make test does)")

# Where the simulated fingers are at power-up: neither open (0) nor closed (230), so that a
# target the runtime made up (open or closed) would move them.
START_COUNT = 100


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    name = f"py{os.getpid()}rq"
    r = Rig(tmp_path_factory.mktemp("robotiq"), name, extra_env={"R2G_ABORT_ON_TICK_ALLOC": "1"},
            position=START_COUNT, profile="franka")
    try:
        with robo_instance(name):
            yield r
    finally:
        r.close()


def fault() -> str | None:
    return robo.get_state([])["fault"]


def grasp() -> dict:
    return robo.get_state([])["control_feedback"]["grasp"]


def clear(rig: Rig) -> None:
    out = subprocess.run([str(R2G), "clear", "--instance", rig.name], capture_output=True, text=True, timeout=20)
    assert out.returncode == 0, out.stdout + out.stderr


def start(rig: Rig) -> None:
    """Each test after the first starts from a gripper that acts on commands and no latched
    fault, so that one test's failure does not fail the next ones too."""
    rig.control(object_at=None, fault=0, kflt=0, silent=False)
    clear(rig)
    wait_for("no fault", lambda: fault() is None)


def faults_during(seconds: float) -> list[str]:
    """Every gripper fault text get_state showed over `seconds` (`grasp.gripper_fault`)."""
    seen, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        f = grasp()["gripper_fault"]
        if f:
            seen.append(f)
        time.sleep(0.01)
    return seen


def test_the_fingers_stay_where_they_are_until_a_chunk_moves_them(rig: Rig) -> None:
    """First in this module: right after `r2g up`. The activation ends without a fault and without
    an operator (Franka profile), and nothing commands the fingers: they stay at their power-up
    count, and get_state reports that opening."""
    wait_for("the gripper's activation", lambda: fault() is None, timeout=15)
    t_end = time.monotonic() + 1.0
    while time.monotonic() < t_end:
        pos = rig.control()["position"]
        assert abs(pos - START_COUNT) <= 1, f"the fingers moved by themselves to count {pos}"
        time.sleep(0.05)
    # 100 of 230 counts closed: 57 % open, gripper -1 (open) ... +1 (closed).
    g = robo.get_state([])["gripper"][0]
    assert abs(g - (2 * START_COUNT / 230 - 1)) < 0.02, g
    assert rig.control()["activations"] == 1


def test_open_close_and_grasp_detected(rig: Rig) -> None:
    start(rig)
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
    start(rig)
    before = rig.stats().get("crc_errors", 0)
    rig.control(corrupt_crc=1)
    assert faults_during(0.5) == [], "one bad answer must not stop the arm"
    # It did happen, and was retried: the driver counted it.
    wait_for("the CRC error counted", lambda: rig.stats().get("crc_errors", 0) >= before + 1, timeout=5)
    ok, _, s = gripper_move(robo, 0.0)
    assert ok == 1, s["control_feedback"]


def test_three_crc_errors_in_a_row_lose_the_link(rig: Rig) -> None:
    start(rig)
    before = rig.stats()
    rig.control(corrupt_crc=3)
    wait_for("the link loss counted",
             lambda: rig.stats().get("link_losses", 0) >= before.get("link_losses", 0) + 1, timeout=5)
    assert rig.stats()["crc_errors"] >= before.get("crc_errors", 0) + 3
    said = [ln for ln in rig.log().splitlines() if "CRC does not match" in ln and "(3 times in a row)" in ln]
    assert said, rig.log()[-2000:]
    # The link comes back by itself at once; a lost link that the runtime saw is latched on the
    # Franka profile (it may have missed one so short), which the operator's clear ends.
    clear(rig)
    wait_for("the gripper back", lambda: fault() is None, timeout=10)
    ok, _, s = gripper_move(robo, -1.0)
    assert ok == 1, s["control_feedback"]


def test_a_silent_gripper_is_named_and_a_1_s_gap_does_not_reset_it(rig: Rig) -> None:
    """The gripper stops answering for 1.5 s while it holds an object: the runtime hears the
    driver's own reason (no answer), never "the driver published nothing", and holds the arm.
    Afterwards the gripper's 0x09 (no communication for 1 s, a minor fault) must not make the
    driver reset it: the object stays held."""
    start(rig)
    rig.control(object_at=120)
    ok, _, s = gripper_move(robo, 1.0)
    assert ok == 1 and s["control_feedback"]["grasp"]["status"] == "holding", s["control_feedback"]
    activations = rig.control()["activations"]
    rig.control(silent=True)
    seen = faults_during(1.5)
    rig.control(silent=False)
    assert seen and all("no answer from the gripper" in f for f in seen), sorted(set(seen))
    assert not any("published nothing" in f for f in seen)
    clear(rig)  # Franka profile: the lost link was latched
    wait_for("the gripper back", lambda: fault() is None, timeout=10)
    assert rig.control()["activations"] == activations, "the gripper was reset: it dropped what it held"
    assert grasp()["status"] == "holding", grasp()
    ok, _, s = gripper_move(robo, -1.0)
    assert ok == 1, s["control_feedback"]
    rig.control(object_at=None)


def test_a_minor_fault_holds_the_arm_and_ends_by_itself(rig: Rig) -> None:
    start(rig)
    activations = rig.control()["activations"]
    rig.control(fault=0x08)
    f = wait_for("the temperature fault", fault, timeout=5)
    assert "0x08" in f and "temperature" in f, f
    q = list(robo.get_state([])["joint"])
    assert robo.post_actions({"actions": [q + [-1.0]], "type": "joint", "freq": ""}) == 0
    fb = robo.get_state([])["control_feedback"]
    assert fb["status"] == "rejected" and "cannot act" in fb["reason"], fb
    rig.control(fault=0)
    # No operator (Franka profile) and no reset.
    wait_for("the fault gone by itself", lambda: fault() is None, timeout=5)
    assert rig.control()["activations"] == activations
    ok, _, s = gripper_move(robo, -1.0)
    assert ok == 1, s["control_feedback"]


def test_a_major_fault_waits_for_an_operators_clear_made_after_it(rig: Rig) -> None:
    """An `r2g clear` made earlier (here during a minor fault) must not count for a later major
    fault: that one waits for a clear of its own before the reset (which drops what is held)."""
    start(rig)
    rig.control(fault=0x08)
    wait_for("the minor fault", fault, timeout=5)
    clear(rig)
    rig.control(fault=0)
    wait_for("no fault", lambda: fault() is None, timeout=5)
    activations = rig.control()["activations"]
    rig.control(fault=0x0E)
    # Franka profile: `fault` says an operator is needed, `grasp` says why.
    f = wait_for("the fault reaching get_state", lambda: grasp()["gripper_fault"], timeout=5)
    assert "0x0E" in f and "overcurrent" in f, f
    assert "r2g clear" in fault(), fault()
    time.sleep(1.0)
    assert rig.control()["activations"] == activations, "reset without the operator's clear"
    assert "0x0E" in (grasp()["gripper_fault"] or ""), grasp()
    q = list(robo.get_state([])["joint"])
    assert robo.post_actions({"actions": [q + [-1.0]], "type": "joint", "freq": ""}) == 0
    fb = robo.get_state([])["control_feedback"]
    assert fb["status"] == "operator_required", fb
    # The operator's reset reaches r2g-robotiq, which resets and reactivates the gripper.
    clear(rig)
    wait_for("the gripper reactivated", lambda: fault() is None, timeout=10)
    assert rig.control()["activations"] == activations + 1
    ok, _, s = gripper_move(robo, -1.0)
    assert ok == 1, s["control_feedback"]


def test_a_controller_fault_alone_is_a_fault(rig: Rig) -> None:
    """kFLT set, gFLT clear: a fault with a code and words, never "no fault"."""
    start(rig)
    rig.control(kflt=3)
    f = wait_for("the controller fault", lambda: grasp()["gripper_fault"], timeout=5)
    assert "kFLT 0x3" in f and "no fault" not in f, f
    clear(rig)
    wait_for("the gripper reactivated", lambda: fault() is None, timeout=10)
    ok, _, s = gripper_move(robo, -1.0)
    assert ok == 1, s["control_feedback"]


def test_the_port_vanishing_mid_grasp_fails_the_chunk_and_holds_the_arm(rig: Rig) -> None:
    start(rig)
    ok, _, _ = gripper_move(robo, -1.0)
    assert ok == 1
    # Close slowly enough to unplug during the motion: move the arm a little at the same time,
    # so the chunk lasts a second.
    rig.control(object_at=200)
    q = list(robo.get_state([])["joint"])
    far = list(q)
    far[6] += 0.3
    # The line goes once the fingers have started closing: the chunk runs (a thread that talks
    # only to the simulator; robo stays on this thread).
    unplugged = {}

    def unplug() -> None:
        deadline = time.monotonic() + 10
        while rig.control()["position"] < 20 and time.monotonic() < deadline:
            time.sleep(0.005)
        unplugged["t"] = time.monotonic()
        rig.unplug()

    timer = threading.Thread(target=unplug)
    timer.start()
    ok = robo.post_actions({"actions": [far + [1.0]], "type": "joint", "freq": 1.0})
    timer.join()
    t_unplug = unplugged["t"]
    took = time.monotonic() - t_unplug
    s = robo.get_state([])
    fb = s["control_feedback"]
    assert ok == 0, fb
    assert fb["status"] == "operator_required" and "gripper reports a fault" in fb["reason"], fb
    assert "vanished" in fb["reason"] or "no answer" in fb["reason"], fb["reason"]
    assert s["fault"] and "gripper" in s["fault"], s["fault"]
    assert all(abs(v) < 0.05 for v in s["joint_velocity"]), f"the arm holds: {s['joint_velocity']}"
    print(f"port removed mid-grasp: chunk failed {took * 1e3:.0f} ms later: {fb['reason']}")
    # Nothing crashed: the instance and the driver still run, and the line coming back is taken.
    assert rig.up.poll() is None, rig.log()
    rig.replug()
    clear(rig)
    wait_for("the gripper back", lambda: fault() is None, timeout=15)
    ok, _, s = gripper_move(robo, -1.0)
    assert ok == 1, s["control_feedback"]
    assert "panicked" not in rig.log()
