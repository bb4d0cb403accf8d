"""The robo contract against a real-arm robot side: r2g-fci speaking the Franka network protocol
to franka-sim (PyPI, an independent implementation of that protocol, run on 127.0.0.1 in its own
environment with the arm our sim-host compiles). The contract tests written for sim-host run
here unchanged where they apply; those that cannot (cameras, resets of the scene, lockstep) are
skipped with the reason. Faults are provoked on the real peer: its communication-constraint
reflex (20 lost command cycles) fires when r2g-control is stopped for 100 ms mid-chunk.
"""
from __future__ import annotations

import inspect
import json
import os
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Iterator

import pytest

import robo
import test_robo_contract as contract
from conftest import R2G, ROOT, _instance

PEER_VENV = ROOT / ".venv-franka-sim" / "bin" / "python"
GYM = "pick_block_plate"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class FrankaSim:
    """franka-sim on 127.0.0.1 with its communication-constraint check switched on."""

    def __init__(self, tmp: Path, protocol_version: int = 10, gripper: bool = False) -> None:
        if not PEER_VENV.is_file():
            raise RuntimeError(f"{PEER_VENV} missing: run scripts/setup-venv.sh (make test does)")
        model = tmp / "arm.xml"
        subprocess.run(
            [str(R2G.parent / "r2g-sim"), str(ROOT / f"gyms/{GYM}/scene.toml"), "--instance", f"dump{os.getpid()}",
             "--dump-mjcf", str(model), "--exit-after-dump"],
            check=True, timeout=60,
        )
        self.port = free_port()
        # The communication check is on (it provokes the reflex below). The motion-limit check
        # (jerk from consecutive commands) stays off here: on these shared 2-core machines without
        # a real-time kernel an answer now and then misses its cycle, the peer extrapolates it, and
        # the next command reads as an acceleration jump. `r2g bench fci` measures how often.
        env = dict(os.environ, FRANKA_SIM_ENFORCE_COMM_CONSTRAINTS="1", FRANKA_SIM_ENFORCE_MOTION_LIMITS="0")
        self.log = open(tmp / "franka-sim.log", "w")
        self.proc = subprocess.Popen(
            [str(PEER_VENV), str(ROOT / "fci/franka-sim/serve.py"), "--model", str(model), "--port", str(self.port),
             "--protocol-version", str(protocol_version)] + (["--gripper"] if gripper else []),
            stdout=self.log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
        )
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"franka-sim exited: {(tmp / 'franka-sim.log').read_text()[-2000:]}")
            try:
                # the arm's port, and the hand's (1338, fixed by the protocol) when it serves one
                for port in [self.port] + ([1338] if gripper else []):
                    socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                return
            except OSError:
                time.sleep(0.2)
        self.stop()
        raise RuntimeError("franka-sim did not listen within 60 s")

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


CONFIG = {
    "profile": "franka",
    "control": {"max_chunk_waypoints": 16},
    "franka": {"reflex_force_n": 30, "operator_force_n": 80, "reflex_window_s": 60},
}


WRIST = {"width": 640, "height": 480, "fx": 416.0, "fy": 416.0, "cx": 320.0, "cy": 240.0,
         "flange_from_camera": [[0, -1, 0, 0.05], [1, 0, 0, 0], [0, 0, 1, 0.02], [0, 0, 0, 1]]}


@pytest.fixture(scope="module")
def peer(tmp_path_factory: pytest.TempPathFactory) -> Iterator[FrankaSim]:
    p = FrankaSim(tmp_path_factory.mktemp("franka-sim"))
    try:
        yield p
    finally:
        p.stop()


@pytest.fixture(scope="module")
def arm(peer: FrankaSim, tmp_path_factory: pytest.TempPathFactory):
    d = tmp_path_factory.mktemp("fci")
    # A hand-eye calibration for a wrist camera that sends no frames here: reported, not used.
    (d / "wrist.json").write_text(json.dumps(WRIST))
    cfg = contract.write_config(d, dict(CONFIG, calibration={"cameras": {"wrist": "wrist.json"}}))
    for inst in _instance("wall", "fci", GYM, ("--robot-config", cfg, "--fci", peer.address)):
        # The peer starts at its own home pose (elbow straight at joint 2 = 0): move to the gym's
        # start so the contract tests begin where they do on sim-host.
        home = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
        q = robo.get_state([])["joint"]
        steps = 40
        ramp = [[a + (b - a) * (k + 1) / steps for a, b in zip(q, home)] + [1.0] for k in range(steps)]
        for i in range(0, steps, 16):
            assert robo.post_actions({"actions": ramp[i : i + 16], "type": "joint", "freq": ""}) == 1, contract.fb()
        yield inst


# The contract suite of sim-host, run against this robot side. The fixtures it asks for (`sim`,
# `franka`, `franka_strict`) are the FCI instance here.
@pytest.fixture(scope="module")
def sim(arm):
    return arm


@pytest.fixture(scope="module")
def franka(arm):
    return arm


@pytest.fixture(scope="module")
def franka_strict(arm):
    return arm


NO_CAMERAS = "no camera host runs beside the real arm here (cameras are a separate issue)"
NO_SCENE_RESET = "reset() on a real arm only refreshes observations: nothing restores the scene"
SKIPS = {
    "test_raw_images_are_read_only_zero_copy_arrays_with_metric_depth": NO_CAMERAS,
    "test_many_held_raw_observations_fall_back_to_copies": NO_CAMERAS,
    "test_images_after_a_chunk_show_the_scene_after_it": NO_CAMERAS,
    "test_images_right_after_a_reset_show_the_new_episode": NO_CAMERAS,
    "test_reset_restores_the_objects_as_the_cameras_see_them": NO_SCENE_RESET + "; " + NO_CAMERAS,
    "test_freq_is_an_upper_bound_on_the_waypoint_rate": "it times chunks in simulated lockstep time",
    "test_effective_safety_reports_the_configured_limits": "it checks the simulation profile's figures",
    "test_step_caps_reject_with_the_amount_and_move_nothing": NO_SCENE_RESET + " (it resets between its parts)",
    "test_franka_reset_only_refreshes_observations": "it checks that the simulated objects stay put, through the cameras",
    "test_a_contact_reflex_stops_the_chunk_part_way_and_the_arm_can_back_off": (
        "it presses on the simulated block; franka-sim's contact force is not our emulated reflex "
        "(the robot's own reflexes are tested below)"
    ),
    "test_operator_required_blocks_everything_until_r2g_clear": (
        "it escalates through the emulated contact force; the operator path of the robot's own reflexes is tested below"
    ),
    "test_live_states_have_exactly_the_keys_the_stubs_promise": NO_CAMERAS + " (it asks for images)",
}
for _name, _fn in inspect.getmembers(contract, inspect.isfunction):
    _uses = set(inspect.signature(_fn).parameters) & {"sim", "franka", "franka_strict"}
    if _name.startswith("test_") and _uses:
        globals()[f"{_name}__fci"] = pytest.mark.skip(reason=SKIPS[_name])(_fn) if _name in SKIPS else _fn
for _name in SKIPS:
    assert hasattr(contract, _name), f"SKIPS names {_name}, which test_robo_contract no longer has"


# ---------------------------------------------------------------- this robot side's own tests


def test_a_5_s_joint_move_is_executed_and_the_state_says_real_arm(arm) -> None:
    s = robo.get_state([])
    assert s["backend"] == "franka" and s["mode"] == "wall" and s["camera_intrinsics"] == {}
    # The wrist camera's calibration file is reported though the camera sends nothing; no
    # intrinsics or extrinsics are made up for it.
    wrist = robo.get_state()["calibration"]["cameras"]["wrist"]
    assert wrist["source"].startswith("file: ") and wrist["source"].endswith("wrist.json"), wrist
    assert wrist["flange_from_camera"] == WRIST["flange_from_camera"] and wrist["fx"] == 416.0
    assert robo.get_state()["camera_intrinsics"] == {} and robo.get_state()["calibration"]["tcp"]["source"] == "description"
    q = s["joint"]
    goal = [q[0] + 0.3] + q[1:3] + [q[3] + 0.2] + q[4:]
    steps = 100  # 5 s at the default 20 Hz, in chunks of 16
    ramp = [[a + (b - a) * (k + 1) / steps for a, b in zip(q, goal)] + [1.0] for k in range(steps)]
    for i in range(0, steps, 16):
        assert robo.post_actions({"actions": ramp[i : i + 16], "type": "joint", "freq": ""}) == 1, contract.fb()
    err = max(abs(a - b) for a, b in zip(robo.get_state([])["joint"], goal))
    assert err < 5e-3, err
    # The Franka profile reports the force felt over a chunk too (the robot's own estimate):
    # franka-sim's arm moves in free space, so it is small, and it is a number in newtons.
    c = contract.fb()["contact"]
    assert set(c) == {"start_n", "peak_n", "mean_n", "peak_waypoint"}, c
    assert 0.0 <= c["start_n"] <= c["peak_n"] and 0.0 <= c["mean_n"] <= c["peak_n"] < 50.0, c


def control_pid(inst) -> int:
    """r2g-control of this instance: a child of the `r2g up` this test started."""
    kids = Path(f"/proc/{inst.proc.pid}/task/{inst.proc.pid}/children").read_text().split()
    for pid in kids:
        if Path(f"/proc/{pid}/comm").read_text().strip() == "r2g-control":
            return int(pid)
    raise AssertionError(f"no r2g-control among {kids}")


def chunk_with_a_pause(pid: int, at_s: float, pause_s: float | None, joint_by: float) -> dict:
    """Posts a 3 s chunk (16 waypoints at 5 Hz turning joint 1 by ``joint_by``) and, ``at_s``
    into it, stops process ``pid`` (one this test started) for ``pause_s`` (None: until the
    chunk ends, then it is continued). Returns post_actions' value and the control feedback."""
    q = robo.get_state([])["joint"]
    ramp = [[q[0] + joint_by * (k + 1) / 16] + q[1:] + [1.0] for k in range(16)]
    result: dict = {}

    def post() -> None:
        result["ret"] = robo.post_actions({"actions": ramp, "type": "joint", "freq": 5})
        result["fb"] = contract.fb()

    t = threading.Thread(target=post)
    t.start()
    time.sleep(at_s)
    os.kill(pid, signal.SIGSTOP)
    try:
        if pause_s is not None:
            time.sleep(pause_s)
            os.kill(pid, signal.SIGCONT)
        t.join(timeout=30)
        assert not t.is_alive()
    finally:
        os.kill(pid, signal.SIGCONT)
    return result


def chunk_with_a_stall(inst) -> dict:
    """Stops r2g-control for 100 ms in the middle of a 3 s chunk: the robot gets no command for
    100 cycles and its communication reflex (20 lost cycles) stops the motion."""
    sign = 1.0 if robo.get_state([])["joint"][0] < 0 else -1.0
    return chunk_with_a_pause(control_pid(inst), 1.2, 0.1, sign * 0.25)


def wait_until_accepting(timeout: float = 10.0) -> None:
    """No operator fault is latched (a recovered reflex latches none; its reply came only after
    the robot reported the recovery's end)."""
    deadline = time.monotonic() + timeout
    while robo.get_state([])["fault"]:
        assert time.monotonic() < deadline, f"still faulted after {timeout} s: {robo.get_state([])['fault']}"
        time.sleep(0.1)


def test_robot_reflexes_recover_then_need_the_operator(arm) -> None:
    first = chunk_with_a_stall(arm)
    assert first["ret"] == 0 and first["fb"]["status"] == "recovered_replan_required", first
    assert "communication_constraints_violation" in first["fb"]["reason"], first
    assert 0 < first["fb"]["executed"] < 16, first
    wait_until_accepting()
    # The arm takes chunks again after the recovery...
    q = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": [q[:6] + [q[6] + 0.05, 1.0]], "type": "joint", "freq": ""}) == 1, contract.fb()
    # ...but a second reflex within the window needs the operator.
    second = chunk_with_a_stall(arm)
    assert second["ret"] == 0 and second["fb"]["status"] == "operator_required", second
    q = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": [q + [1.0]], "type": "joint", "freq": ""}) == 0
    assert contract.fb()["status"] == "operator_required"
    out = subprocess.run([str(R2G), "clear", "--instance", arm.name], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    q = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": [q[:6] + [q[6] - 0.05, 1.0]], "type": "joint", "freq": ""}) == 1, contract.fb()


def test_a_real_arm_refuses_lockstep_and_the_simulation_profile(tmp_path: Path) -> None:
    sim_cfg = contract.write_config(tmp_path, {"profile": "simulation"})
    for extra in (("--mode", "lockstep", "--robot-config", sim_cfg), ("--robot-config", sim_cfg)):
        out = subprocess.run([str(R2G), "up", GYM, "--instance", f"py{os.getpid()}ref", "--fci", "127.0.0.1:1", *extra],
                             capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
        assert out.returncode != 0 and "wall mode with the franka profile" in out.stderr, out.stderr


def test_a_vanishing_peer_is_a_clear_error_and_the_runtime_holds(tmp_path: Path) -> None:
    peer = FrankaSim(tmp_path)
    cfg = contract.write_config(tmp_path, CONFIG)
    up = subprocess.Popen([str(R2G), "up", GYM, "--instance", f"py{os.getpid()}gone", "--robot-config", cfg, "--fci", peer.address],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL)
    try:
        assert up.stdout is not None and up.stdout.readline().strip().startswith("READY")
        peer.proc.kill()
        peer.proc.wait()
        _, err = up.communicate(timeout=30)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
        peer.stop()
    assert up.returncode == 1 and "panicked" not in err, err[-2000:]
    assert "robot" in err and "r2g-fci" in err, err[-2000:]


def test_a_protocol_version_mismatch_is_a_clear_error(tmp_path: Path) -> None:
    """franka-sim announces FCI version 10 (an FR3); r2g-fci told to expect a Panda's version 5
    refuses to drive it, naming both versions, before anything moves or any port opens."""
    peer = FrankaSim(tmp_path)
    try:
        out = subprocess.run(
            [str(R2G.parent / "r2g-fci"), str(ROOT / f"gyms/{GYM}/scene.toml"), "--instance", f"py{os.getpid()}ver",
             "--robot", peer.address, "--fci-version", "5"],
            capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
        )
    finally:
        peer.stop()
    assert out.returncode == 1 and "panicked" not in out.stderr, out.stderr[-2000:]
    assert "speaks FCI version 10" in out.stderr and "5" in out.stderr, out.stderr[-2000:]


def test_the_franka_hand_follows_the_gripper_value(tmp_path: Path) -> None:
    """With --fci-gripper, the waypoints' gripper value drives the Franka Hand (franka-sim's
    emulated hand on port 1338, libfranka's gripper protocol) from r2g-fci's hand thread, and the
    measured opening comes back in `gripper` (-1 open ... +1 closed)."""
    peer = FrankaSim(tmp_path, gripper=True)
    cfg = contract.write_config(tmp_path, CONFIG)
    try:
        for _inst in _instance("wall", "hand", GYM, ("--robot-config", cfg, "--fci", peer.address, "--fci-gripper")):
            def settle(want: float) -> float:
                q = robo.get_state([])["joint"]
                assert robo.post_actions({"actions": [q + [want]] * 4, "type": "joint", "freq": ""}) == 1, contract.fb()
                deadline = time.monotonic() + 10
                g = robo.get_state([])["gripper"][0]
                while abs(g - want) > 0.1 and time.monotonic() < deadline:
                    time.sleep(0.1)
                    g = robo.get_state([])["gripper"][0]
                return g

            assert settle(-1.0) < -0.9
            assert settle(1.0) > 0.9
            assert settle(-1.0) < -0.9
    finally:
        peer.stop()


def test_a_missing_state_stream_fails_the_chunk_and_the_arm_holds(tmp_path: Path) -> None:
    """franka-sim stopped (SIGSTOP: its connection stays open, its states stop) while a chunk
    runs: the runtime notices the silence, fails the chunk with the reason and holds; nothing
    panics. The peer is continued afterwards and stopped by this test."""
    peer = FrankaSim(tmp_path)
    cfg = contract.write_config(tmp_path, CONFIG)
    try:
        for _inst in _instance("wall", "mute", GYM, ("--robot-config", cfg, "--fci", peer.address)):
            result = chunk_with_a_pause(peer.proc.pid, 1.0, None, 0.2)
            assert result["ret"] == 0 and result["fb"]["status"] == "failed", result
            assert "published no state" in result["fb"]["reason"], result
            assert 0 < result["fb"]["executed"] < 16, result
    finally:
        peer.stop()


def test_a_franka_hand_is_refused_when_the_config_names_a_robotiq(tmp_path: Path) -> None:
    """--gripper (the Franka Hand) with a robot config whose gripper is a Robotiq 2F-85: two
    drivers for one gripper; refused before any connection."""
    cfg = contract.write_config(tmp_path, dict(CONFIG, gripper={"driver": "robotiq_2f85", "port": "/dev/ttyUSB9"}))
    out = subprocess.run(
        [str(R2G.parent / "r2g-fci"), str(ROOT / f"gyms/{GYM}/scene.toml"), "--instance", f"py{os.getpid()}rq",
         "--robot", "127.0.0.1:1", "--robot-config", cfg, "--gripper"],
        capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
    )
    assert out.returncode == 1 and "panicked" not in out.stderr, out.stderr[-2000:]
    assert "Robotiq 2F-85 on /dev/ttyUSB9" in out.stderr and "--gripper" in out.stderr, out.stderr[-2000:]
