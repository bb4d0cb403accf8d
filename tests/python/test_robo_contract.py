"""The full robo contract, in both profiles, against live `r2g up` instances (real processes,
real shared memory, real MuJoCo). Object positions are checked only through what the cameras
see (raw RGB + depth back-projected with the reported calibration), never simulator internals.
"""
from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

import robo
import conftest
from conftest import R2G, ROOT, Instance, _instance

BLOCK = np.array([0.5, -0.12, 0.04])  # top centre of the red block in pick_block_plate (base frame)
PLATE_XY = np.array([0.5, 0.15])


def fb() -> dict:
    return robo.get_state([])["control_feedback"]


def joint_ramp(goal: list[float], gripper: float, steps: int) -> list[list[float]]:
    start = robo.get_state([])["joint"]
    return [[s + (g - s) * (k + 1) / steps for s, g in zip(start, goal)] + [gripper] for k in range(steps)]


def tcp_line(goal_xyz: list[float], rot: list[float], gripper: float, steps: int) -> list[list[float]]:
    start = robo.get_state([])["ee_pose"][:3]
    return [[s + (g - s) * (k + 1) / steps for s, g in zip(start, goal_xyz)] + rot + [gripper] for k in range(steps)]


def red_centroid(name: str = "agentview") -> np.ndarray:
    """Base-frame centroid of the red pixels' surface points, from raw RGB + depth."""
    s = robo.get_state([name], raw=True)
    rgb, depth = s["image"][name], s["depth"][name]
    k, base_from_cam = s["camera_intrinsics"][name], np.array(s["camera_extrinsics"][name])
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    v, u = np.nonzero((r > 120) & (g < 70) & (b < 70))
    assert len(u) > 20, "no red block in view"
    d = depth[v, u].astype(float)
    cam = np.stack([(u - k["cx"]) * d / k["fx"], (v - k["cy"]) * d / k["fy"], d, np.ones_like(d)])
    return (base_from_cam @ cam)[:3].mean(axis=1)


def write_config(tmp: Path, body: dict) -> str:
    p = tmp / "robot.json"
    p.write_text(json.dumps(body))
    return str(p)


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Instance]:
    """Simulation profile with a 16-waypoint chunk cap (the shipped file allows 256)."""
    cfg = write_config(tmp_path_factory.mktemp("sim"), {"profile": "simulation", "control": {"max_chunk_waypoints": 16}})
    yield from _instance("lockstep", "cs", extra=("--robot-config", cfg))


# ---------------------------------------------------------------- simulation profile


def test_effective_safety_reports_the_configured_limits(sim) -> None:
    s = robo.get_state([])
    assert s["backend"] == "simulation"
    e = s["effective_safety"]
    assert e["profile"] == "simulation"
    assert e["max_chunk_len"] == 16
    assert (e["max_joint_step_rad"], e["max_tcp_step_m"], e["max_tcp_step_rad"]) == (0.35, 0.05, 0.35)
    assert e["reflex_force_n"] is None and e["operator_force_n"] is None
    assert len(e["workspace_min_m"]) == 3 and e["workspace_min_m"][2] <= 0.0 < e["workspace_max_m"][2]
    assert e["collision_margin_m"] > 0
    assert s["fault"] is None and len(s["external_force_n"]) == 3


def test_raw_images_are_read_only_zero_copy_arrays_with_metric_depth(sim) -> None:
    s = robo.get_state(raw=True)
    for name in ("agentview", "wrist"):
        rgb, depth = s["image"][name], s["depth"][name]
        assert rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8
        assert depth.shape == (480, 640) and depth.dtype == np.float32
        assert not rgb.flags.writeable and not depth.flags.writeable
        assert not rgb.flags.owndata  # a view over the frame in shared memory
        assert np.isfinite(depth).all() and 0.05 < float(np.median(depth)) < 5.0
        with pytest.raises(ValueError):
            rgb[0, 0, 0] = 1
    # Depth, intrinsics and extrinsics agree: the red block's surface back-projects onto it.
    c = red_centroid("agentview")
    assert np.linalg.norm(c[:2] - BLOCK[:2]) < 0.015, c
    assert 0.0 < c[2] < 0.05, c
    # A resized raw request scales the intrinsics and resamples both planes.
    small = robo.get_state({"agentview": (320, 240)}, raw=True)
    assert small["image"]["agentview"].shape == (240, 320, 3)
    assert small["depth"]["agentview"].shape == (240, 320)
    assert small["camera_intrinsics"]["agentview"]["fx"] == pytest.approx(s["camera_intrinsics"]["agentview"]["fx"] / 2)
    # PNG is the default and carries no depth key.
    assert "depth" not in robo.get_state("wrist") and isinstance(robo.get_state("wrist")["image"]["wrist"], bytes)


def test_many_held_raw_observations_fall_back_to_copies(sim) -> None:
    held = [robo.get_state(raw=True) for _ in range(12)]
    views = sum(not h["image"]["agentview"].flags.owndata for h in held)
    assert all(h["image"]["agentview"].shape == (480, 640, 3) for h in held)
    # Nothing failed, and the views in flight never exceed what shared memory lends a reader.
    assert 1 <= views <= 12
    first = held[0]["image"]["agentview"].copy()
    assert robo.post_actions({"actions": joint_ramp(robo.get_state([])["joint"], -1.0, 2), "type": "joint", "freq": ""}) == 1
    # Held arrays still read the frame they were taken from.
    assert np.array_equal(held[0]["image"]["agentview"], first)
    del held
    assert robo.get_state(raw=True)["image"]["wrist"].shape == (480, 640, 3)


def test_images_after_a_chunk_show_the_scene_after_it(sim) -> None:
    assert robo.reset() == 1
    before = robo.get_state([])["timestamp"]
    q = robo.get_state([])["joint"]
    goal = q[:5] + [q[5] + 0.3] + q[6:]
    assert robo.post_actions({"actions": joint_ramp(goal, -1.0, 10), "type": "joint", "freq": ""}) == 1, fb()
    s = robo.get_state()
    # Ten waypoints at 20 Hz take at least 0.5 s: both images are from after that.
    for name, t in s["image_timestamp"].items():
        assert t >= before + 0.5, (name, t, before)


def test_images_right_after_a_reset_show_the_new_episode(sim) -> None:
    """Simulated time starts again at a reset, so frames of the old episode (queued or in flight,
    with larger times) must not pass for fresh ones."""
    for _ in range(3):
        q = robo.get_state([])["joint"]
        goal = q[:5] + [q[5] + 0.4] + q[6:]
        assert robo.post_actions({"actions": joint_ramp(goal, -1.0, 16), "type": "joint", "freq": ""}) == 1, fb()
        assert robo.reset() == 1
        s = robo.get_state(["agentview", "wrist"], raw=True)
        for name, t in s["image_timestamp"].items():
            assert t <= s["timestamp"] + 1e-9, (name, t, s["timestamp"])
        home = np.array(s["image"]["wrist"], dtype=int)
        later = robo.get_state(["wrist"], raw=True)["image"]["wrist"]
        assert np.abs(home - later).mean() < 1.0  # the same (home) view, not the moved one


def test_freq_is_an_upper_bound_on_the_waypoint_rate(sim) -> None:
    assert robo.reset() == 1

    def duration(freq: object, goal_offset: float) -> float:
        q = robo.get_state([])["joint"]
        t0 = robo.get_state([])["timestamp"]
        goal = q[:6] + [q[6] + goal_offset]
        assert robo.post_actions({"actions": joint_ramp(goal, -1.0, 10), "type": "joint", "freq": freq}) == 1, fb()
        return robo.get_state([])["timestamp"] - t0

    assert duration("", 0.1) >= 0.5  # default 20 Hz
    assert duration(5, -0.1) >= 2.0  # 5 Hz: 10 waypoints take at least 2 s
    assert duration("5", 0.1) >= 2.0  # a numeric string is the same
    # 1000 Hz does not lift the velocity limit: joint 7 at 2.61 rad/s x speed_scale 0.5.
    assert duration(1000, -0.1) >= 0.1 / (2.61 * 0.5)


def test_feedback_reports_acceptance_and_first_motion_latency(sim) -> None:
    q = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": joint_ramp(q[:6] + [q[6] + 0.05], -1.0, 3), "type": "joint", "freq": ""}) == 1
    f = fb()
    assert f["status"] == "executed" and f["executed"] == 3
    assert 0 < f["submit_to_accept_us"] < 1e6
    assert f["submit_to_accept_us"] < f["submit_to_first_motion_us"] < 5e6


def test_step_caps_reject_with_the_amount_and_move_nothing(sim) -> None:
    s = robo.get_state([])
    q, ee = s["joint"], s["ee_pose"]
    jump = q[:1] + [q[1] + 0.5] + q[2:] + [-1.0]
    assert robo.post_actions({"actions": [jump], "type": "joint", "freq": ""}) == 0
    assert "joint 2 changes by 0.5000 rad from the measured position; the cap is 0.3500 rad" in fb()["reason"], fb()
    assert "0.1500 rad over" in fb()["reason"]
    # The same move in two waypoints is fine (the cap is per waypoint, not per chunk)...
    ok = [q[:1] + [q[1] + 0.25] + q[2:] + [-1.0], jump]
    assert robo.post_actions({"actions": ok, "type": "joint", "freq": ""}) == 1, fb()
    assert robo.reset() == 1
    s = robo.get_state([])
    ee = s["ee_pose"]
    far = [[ee[0], ee[1], ee[2] - 0.02] + ee[3:] + [-1.0], [ee[0], ee[1], ee[2] - 0.09] + ee[3:] + [-1.0]]
    assert robo.post_actions({"actions": far, "type": "ee_pose", "freq": ""}) == 0
    reason = fb()["reason"]
    assert reason.startswith("actions[1]: the TCP moves by 0.0700 m from the previous waypoint"), reason
    assert np.allclose(robo.get_state([])["joint"], s["joint"], atol=1e-3)


def test_the_configured_chunk_length_cap_holds(sim) -> None:
    q = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": [q + [-1.0]] * 17, "type": "joint", "freq": ""}) == 0
    assert "actions has 17 waypoints, at most 16" in fb()["reason"]
    assert robo.post_actions({"actions": [q + [-1.0]] * 16, "type": "joint", "freq": ""}) == 1, fb()


@pytest.mark.parametrize(
    "cmd, message",
    [
        ("move please", "expects a dict"),
        ([1, 2, 3], "expects a dict"),
        ({"actions": [], "type": "joint", "speed": 2}, "unknown key 'speed'"),
        ({"type": "joint"}, "missing key 'actions'"),
        ({"actions": [[0.0] * 8]}, "missing key 'type'"),
        ({"actions": [[0.0] * 8], "type": 1}, "type must be the string"),
        ({"actions": "fast", "type": "joint"}, "actions must be a list"),
        ({"actions": [["a"] * 8], "type": "joint"}, "actions[0] must be a list of numbers"),
        ({"actions": [[0.0] * 8], "type": "joint", "freq": [20]}, "freq must be"),
    ],
)
def test_malformed_structure_raises_a_clear_type_error(sim, cmd, message) -> None:
    with pytest.raises(TypeError) as e:
        robo.post_actions(cmd)
    assert message in str(e.value)
    assert fb()["status"] == "rejected" and message in fb()["reason"]


def test_well_formed_but_unacceptable_commands_return_zero_without_raising(sim) -> None:
    q = robo.get_state([])["joint"]
    for cmd in (
        {"actions": [q + [-1.0]], "type": "cartesian"},
        {"actions": [q], "type": "joint"},
        {"actions": [q[:6] + [float("inf"), -1.0]], "type": "joint"},
        {"actions": [q + [-1.0]], "type": "joint", "freq": 0},
        {"actions": [q + [-1.0]], "type": "joint", "freq": "-3"},
    ):
        assert robo.post_actions(cmd) == 0, cmd
        assert fb()["status"] == "rejected" and fb()["reason"], cmd


def test_reset_restores_the_objects_as_the_cameras_see_them(sim) -> None:
    assert robo.reset() == 1
    assert np.linalg.norm(red_centroid()[:2] - BLOCK[:2]) < 0.015
    # Play the demonstration: the block ends on the plate...
    rows = [[float(x) for x in line.split(",")] for line in (ROOT / "gyms/pick_block_plate/demo.csv").read_text().splitlines() if line and line[0] in "-0123456789"]
    for i in range(0, len(rows), 16):
        assert robo.post_actions({"actions": rows[i : i + 16], "type": "joint", "freq": ""}) == 1, fb()
    assert np.linalg.norm(red_centroid()[:2] - PLATE_XY) < 0.03
    # ...and reset() puts it back where it started.
    assert robo.reset() == 1
    assert np.linalg.norm(red_centroid()[:2] - BLOCK[:2]) < 0.015


def test_a_new_process_starts_with_no_feedback(sim) -> None:
    code = "import robo, json; print(json.dumps(robo.get_state([])['control_feedback']))"
    out = subprocess.run([__import__("sys").executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    f = json.loads(out.stdout)
    assert f["status"] == "none" and f["submit_to_accept_us"] is None


def test_without_files_the_description_tcp_and_the_scene_cameras_are_reported(sim) -> None:
    c = robo.get_state([])["calibration"]
    assert c["tcp"]["source"] == "description"
    assert np.allclose(c["tcp"]["flange_from_tcp"], described_tcp(), atol=1e-9)
    # Every camera that sends frames (none beside a real arm) without a file is the scene's.
    scene = {name for name, v in c["cameras"].items() if v == {"source": "scene"}}
    assert scene == set(robo.get_state()["camera_intrinsics"])


# ---------------------------------------------------------------- Franka profile


@pytest.fixture(scope="module")
def franka(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Instance]:
    cfg = write_config(tmp_path_factory.mktemp("franka"), {"profile": "franka", "franka": {"reflex_force_n": 30, "operator_force_n": 80}})
    yield from _instance("lockstep", "cf", extra=("--robot-config", cfg))


@pytest.fixture(scope="module")
def franka_strict(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Instance]:
    """Franka profile whose operator limit sits below its reflex threshold: any hard contact faults."""
    cfg = write_config(tmp_path_factory.mktemp("strict"), {"profile": "franka", "franka": {"reflex_force_n": 500, "operator_force_n": 25}})
    yield from _instance("lockstep", "cx", extra=("--robot-config", cfg))


def press_on_block() -> int:
    """Closed gripper above the block, then down into it (the block's top is at z = 0.04)."""
    rot = robo.get_state([])["ee_pose"][3:]
    assert robo.post_actions({"actions": tcp_line([0.5, -0.12, 0.10], rot, 1.0, 10), "type": "ee_pose", "freq": ""}) == 1, fb()
    return robo.post_actions({"actions": tcp_line([0.5, -0.12, 0.02], rot, 1.0, 4), "type": "ee_pose", "freq": ""})


def test_franka_reports_its_profile_and_thresholds(franka) -> None:
    s = robo.get_state([])
    assert s["backend"] == "franka"
    assert s["effective_safety"]["reflex_force_n"] == 30.0
    assert s["effective_safety"]["operator_force_n"] == 80.0


def test_franka_reset_only_refreshes_observations(franka) -> None:
    q = robo.get_state([])["joint"]
    goal = q[:5] + [q[5] + 0.3] + q[6:]
    assert robo.post_actions({"actions": joint_ramp(goal, -1.0, 2), "type": "joint", "freq": ""}) == 1
    moved = robo.get_state([])["joint"]
    assert robo.reset() == 1
    assert "only refreshes observations" in fb()["reason"]
    assert np.allclose(robo.get_state([])["joint"], moved, atol=1e-3)
    # No control-type lock on the arm: ee_pose then joint in the same session.
    ee = robo.get_state([])["ee_pose"]
    assert robo.post_actions({"actions": [ee + [-1.0]], "type": "ee_pose", "freq": ""}) == 1, fb()
    assert robo.post_actions({"actions": [robo.get_state([])["joint"] + [-1.0]], "type": "joint", "freq": ""}) == 1, fb()


def test_franka_ee_pose_targets_are_tcp_poses_in_the_base_frame(franka) -> None:
    rot = robo.get_state([])["ee_pose"][3:]
    goal = [0.45, 0.05, 0.3]
    assert robo.post_actions({"actions": tcp_line(goal, rot, -1.0, 10), "type": "ee_pose", "freq": ""}) == 1, fb()
    assert np.allclose(robo.get_state([])["ee_pose"][:3], goal, atol=0.003)


def test_a_contact_reflex_stops_the_chunk_part_way_and_the_arm_can_back_off(franka) -> None:
    assert press_on_block() == 0
    s = robo.get_state([])
    f = s["control_feedback"]
    assert f["status"] == "recovered_replan_required", f
    assert "exceeded the 30 N threshold" in f["reason"]
    assert 0 < f["executed"] < 4
    assert s["ee_pose"][2] > 0.03  # stopped on the block, not through it
    assert s["fault"] is None
    # Backing away works at once: the force may still be high, but it is not growing.
    rot = s["ee_pose"][3:]
    assert robo.post_actions({"actions": tcp_line([0.5, -0.12, 0.12], rot, 1.0, 2), "type": "ee_pose", "freq": ""}) == 1, fb()
    assert np.linalg.norm(robo.get_state([])["external_force_n"]) < 5.0


def test_operator_required_blocks_everything_until_r2g_clear(franka_strict) -> None:
    assert press_on_block() == 0
    s = robo.get_state([])
    assert s["control_feedback"]["status"] == "operator_required", s["control_feedback"]
    assert f"r2g clear --instance {franka_strict.name}" in s["control_feedback"]["reason"]
    assert s["fault"] and "25 N" in s["fault"]
    rot = s["ee_pose"][3:]
    away = {"actions": tcp_line([0.5, -0.12, 0.12], rot, 1.0, 2), "type": "ee_pose", "freq": ""}
    assert robo.post_actions(away) == 0
    assert fb()["status"] == "operator_required"
    assert robo.reset() == 1 and robo.get_state([])["fault"]  # reset does not clear it
    out = subprocess.run([str(R2G), "clear", "--instance", franka_strict.name], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    assert "fault cleared" in out.stdout
    assert robo.get_state([])["fault"] is None
    assert robo.post_actions(away) == 1, fb()
    again = subprocess.run([str(R2G), "clear", "--instance", franka_strict.name], capture_output=True, text=True, timeout=30)
    assert again.returncode == 0 and "no fault" in again.stdout


def test_a_bad_robot_config_stops_r2g_up_with_the_reason(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, {"profile": "real-arm"})
    out = subprocess.run(
        [str(R2G), "up", "pick_block_plate", "--instance", "badcfg", "--robot-config", cfg],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode != 0
    assert '"profile": "real-arm" is unknown' in out.stderr and "robot.json" in out.stderr


# ---------------------------------------------------------------- calibration files


def kin_fk(q: list[float], frame: str | None = None) -> np.ndarray:
    """4x4 base-frame pose of the description's TCP (or `frame`) at q, from `r2g kin fk`."""
    return conftest.kin_fk([q], *(["--frame", frame] if frame else []))[0]


def rotvec_matrix(r: list[float]) -> np.ndarray:
    v = np.asarray(r, dtype=float)
    a = np.linalg.norm(v)
    if a < 1e-12:
        return np.eye(3)
    k = v / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def described_tcp() -> np.ndarray:
    """The description's flange-to-TCP transform."""
    home = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
    return np.linalg.inv(kin_fk(home, "flange")) @ kin_fk(home)


def measured_tcp() -> np.ndarray:
    """The description's, moved 2 mm along tool x and 4 mm along tool z: what a measurement a few
    millimetres off the nominal hand would give."""
    return described_tcp() @ np.array([[1, 0, 0, 0.002], [0, 1, 0, 0], [0, 0, 1, 0.004], [0, 0, 0, 1.0]])

CEILING = {"width": 1280, "height": 720, "fx": 910.5, "fy": 911.25, "cx": 640.5, "cy": 360.25,
           "distortion": [0.1, -0.25, 0.001, -0.002, 0.08],
           "base_from_camera": [[0, -1, 0, 0.5], [-1, 0, 0, 0], [0, 0, -1, 1.8], [0, 0, 0, 1]],
           "note": "a camera that sends no frames here"}


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Instance]:
    """Franka profile with a measured TCP, a valid file for a camera that sends no frames, and a
    missing and an invalid camera file (relative paths: resolved against robot.json's folder)."""
    d = tmp_path_factory.mktemp("calibrated")
    (d / "cal").mkdir()
    (d / "cal" / "tcp.json").write_text(json.dumps({"flange_from_tcp": measured_tcp().tolist()}))
    (d / "cal" / "ceiling.json").write_text(json.dumps(CEILING))
    skewed = dict(CEILING, base_from_camera=[[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]])
    (d / "cal" / "skewed.json").write_text(json.dumps(skewed))
    cfg = write_config(d, {"profile": "franka", "calibration": {
        "tcp": "cal/tcp.json",
        "cameras": {"ceiling": "cal/ceiling.json", "side": "cal/absent.json", "skewed": str(d / "cal" / "skewed.json")},
    }})
    for inst in _instance("lockstep", "cc", extra=("--robot-config", cfg)):
        inst.cal_dir = d / "cal"  # type: ignore[attr-defined]
        yield inst


def test_a_measured_tcp_file_is_the_tcp_of_ee_pose_and_its_targets(calibrated) -> None:
    s = robo.get_state([])
    tcp = s["calibration"]["tcp"]
    measured = measured_tcp()
    assert tcp["source"] == f"file: {calibrated.cal_dir / 'tcp.json'}", tcp
    assert np.allclose(tcp["flange_from_tcp"], measured, atol=1e-9), tcp

    def check(state: dict) -> np.ndarray:
        """FK: the reported ee_pose is flange(q) x the measured transform, 4.5 mm from the
        description's TCP."""
        want = kin_fk(state["joint"], "flange") @ measured
        ee = np.array(state["ee_pose"])
        assert np.allclose(ee[:3], want[:3, 3], atol=1e-6), (ee, want)
        assert np.allclose(rotvec_matrix(ee[3:]), want[:3, :3], atol=1e-6)
        described = kin_fk(state["joint"])[:3, 3]
        assert abs(np.linalg.norm(ee[:3] - described) - np.hypot(0.002, 0.004)) < 1e-6
        return ee
    ee = check(s)
    # An ee_pose target puts the measured TCP there, not the description's.
    goal = [0.45, 0.05, 0.3]
    assert robo.post_actions({"actions": tcp_line(goal, list(ee[3:]), -1.0, 10), "type": "ee_pose", "freq": ""}) == 1, fb()
    after = check(robo.get_state([]))
    assert np.linalg.norm(after[:3] - goal) < 0.002, after


def test_camera_calibration_files_are_reported_and_missing_ones_say_why(calibrated) -> None:
    s = robo.get_state()
    cams = s["calibration"]["cameras"]
    ceiling = cams["ceiling"]
    assert ceiling["source"] == f"file: {calibrated.cal_dir / 'ceiling.json'}"
    assert {k: ceiling[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "distortion", "base_from_camera")} == {
        k: CEILING[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "distortion", "base_from_camera")}
    # Reported, but nothing invented: it sends no frames, so it has no image or intrinsics.
    assert "ceiling" not in s["image"] and "ceiling" not in s["camera_intrinsics"]
    with pytest.raises(ValueError, match="unknown camera 'ceiling'"):
        robo.get_state("ceiling")
    assert cams["side"]["source"] == "missing"
    assert f"{calibrated.cal_dir / 'absent.json'}: cannot be read" in cams["side"]["reason"], cams["side"]
    assert cams["skewed"]["source"] == "missing"
    assert "skewed.json: base_from_camera: the rotation (upper-left 3x3) is not orthonormal" in cams["skewed"]["reason"]
    # The scene's cameras send frames without a file: their calibration is the scene's.
    assert cams["agentview"] == {"source": "scene"} and cams["wrist"] == {"source": "scene"}
    assert set(s["camera_intrinsics"]) == {"agentview", "wrist"}


def test_an_unusable_tcp_file_stops_r2g_up_with_the_file_and_field(tmp_path: Path) -> None:
    bad = {"flange_from_tcp": [[1, 0.05, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.1034], [0, 0, 0, 1]]}
    (tmp_path / "tcp.json").write_text(json.dumps(bad))
    for name, want in (("tcp.json", "flange_from_tcp: the rotation (upper-left 3x3) is not orthonormal"),
                       ("absent.json", "cannot be read")):
        cfg = write_config(tmp_path, {"profile": "franka", "calibration": {"tcp": name}})
        out = subprocess.run(
            [str(R2G), "up", "pick_block_plate", "--instance", "badtcp", "--robot-config", cfg],
            capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
        )
        assert out.returncode != 0
        assert f"calibration file {tmp_path / name} (calibration.tcp in the robot config): {want}" in out.stderr, out.stderr
        assert "motion with a wrong TCP is unsafe" in out.stderr, out.stderr


def test_the_type_stubs_describe_the_module_as_built() -> None:
    import ast
    import inspect

    tree = ast.parse((ROOT / "robo" / "robo.pyi").read_text())
    funcs: dict[str, list[ast.FunctionDef]] = {}
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            funcs.setdefault(node.name, []).append(node)
    public = {n for n in dir(robo) if not n.startswith("_") and callable(getattr(robo, n)) and n != "Plane"}
    assert set(funcs) == public, (set(funcs), public)
    for name, defs in funcs.items():
        built = list(inspect.signature(getattr(robo, name)).parameters)
        for d in defs:
            stub = [a.arg for a in d.args.args + d.args.kwonlyargs]
            assert stub == built, (name, stub, built)
    # Every key the stubs promise is in a live state (checked against the module's own output
    # in the sim fixture's tests); here: the TypedDicts name the contract's keys.
    classes = {n.name: n for n in tree.body if isinstance(n, ast.ClassDef)}
    state_keys = {t.target.id for t in classes["_StateBase"].body if isinstance(t, ast.AnnAssign)}
    assert {"joint", "ee_pose", "gripper", "timestamp", "control_feedback", "effective_safety", "fault"} <= state_keys


def stub_keys(name: str) -> set[str]:
    import ast

    classes = {n.name: n for n in ast.parse((ROOT / "robo" / "robo.pyi").read_text()).body if isinstance(n, ast.ClassDef)}
    keys: set[str] = set()
    todo = [name]
    while todo:
        c = classes[todo.pop()]
        keys |= {t.target.id for t in c.body if isinstance(t, ast.AnnAssign) and isinstance(t.target, ast.Name)}
        todo += [b.id for b in c.bases if isinstance(b, ast.Name) and b.id in classes]
    return keys


def test_live_states_have_exactly_the_keys_the_stubs_promise(sim) -> None:
    plain, raw = robo.get_state(), robo.get_state(raw=True)
    assert set(plain) == stub_keys("State")
    assert set(raw) == stub_keys("RawState")
    assert set(plain["control_feedback"]) == stub_keys("ControlFeedback")
    assert set(plain["effective_safety"]) == stub_keys("EffectiveSafety")
    assert set(plain["camera_intrinsics"]["wrist"]) == stub_keys("Intrinsics")
    assert set(plain["calibration"]) == stub_keys("Calibration")
    assert set(plain["calibration"]["tcp"]) == stub_keys("TcpCalibration")
