"""The robo contract against live instances: real processes, real shared memory, real MuJoCo."""
from __future__ import annotations

import math
import os

import pytest

import robo
from pngdecode import decode

HOME = [0.0, -0.7853982, 0.0, -2.3561945, 0.0, 1.5707963, 0.7853982]


def ramp(start: list[float], goal: list[float], gripper: float, steps: int = 15) -> list[list[float]]:
    return [[s + (g - s) * (k + 1) / steps for s, g in zip(start, goal)] + [gripper] for k in range(steps)]


def rotation_between(a: list[float], b: list[float]) -> float:
    """Angle (rad) between two rotations given as axis-angle vectors."""

    def quat(v: list[float]) -> list[float]:
        angle = math.sqrt(sum(x * x for x in v))
        if angle < 1e-12:
            return [0.0, 0.0, 0.0, 1.0]
        s = math.sin(angle / 2) / angle
        return [v[0] * s, v[1] * s, v[2] * s, math.cos(angle / 2)]

    dot = abs(sum(x * y for x, y in zip(quat(a), quat(b))))
    return 2 * math.acos(min(1.0, dot))


def feedback() -> dict:
    return robo.get_state([])["control_feedback"]


def test_arm_reaches_joint_targets(wall) -> None:
    assert robo.reset() == 1
    current = robo.get_state([])["joint"]
    for goal in ([0.4, -0.5, 0.1, -2.0, 0.0, 1.6, 0.6], [-0.2, -0.1, -0.1, -2.4, 0.2, 2.1, 1.0]):
        assert robo.post_actions({"actions": ramp(current, goal, -1.0), "type": "joint", "freq": ""}) == 1, feedback()
        state = robo.get_state([])
        assert max(abs(a - b) for a, b in zip(state["joint"], goal)) < 0.01
        assert state["control_feedback"]["status"] == "executed"
        assert state["control_feedback"]["executed"] == 15
        current = goal


def test_both_images_decode_at_640x480_and_show_the_scene(wall) -> None:
    state = robo.get_state()
    assert set(state["image"]) == {"agentview", "wrist"}
    for name, png in state["image"].items():
        w, h, ch, px = decode(png)
        assert (w, h, ch) == (640, 480, 3), name
        # Not a flat frame: many distinct colours, and a real spread of brightness.
        colours = {px[i : i + 3] for i in range(0, len(px), 3 * 97)}
        lum = [px[i] + px[i + 1] + px[i + 2] for i in range(0, len(px), 3 * 31)]
        mean = sum(lum) / len(lum)
        std = math.sqrt(sum((v - mean) ** 2 for v in lum) / len(lum))
        assert len(colours) > 200, (name, len(colours))
        assert std > 20, (name, std)
        # The red block is somewhere in both views.
        red = sum(1 for i in range(0, len(px), 3) if px[i] > 150 and px[i + 1] < 80 and px[i + 2] < 80)
        assert red > 30, (name, red)
    k = state["camera_intrinsics"]["agentview"]
    # principal point in pixel-index coordinates: the image centre lies between pixels 319 and 320
    assert (k["width"], k["height"], k["cx"], k["cy"]) == (640, 480, 319.5, 239.5)
    assert len(state["camera_extrinsics"]["wrist"]) == 4


def test_state_fields_follow_the_contract(wall) -> None:
    s = robo.get_state([])
    assert len(s["joint"]) == 7 and len(s["ee_pose"]) == 6 and len(s["gripper"]) == 1
    assert -1.0 <= s["gripper"][0] <= 1.0
    assert s["image"] == {}
    assert s["timestamp"] > 0
    safety = s["effective_safety"]
    assert safety["joint_position_max_rad"][3] == pytest.approx(-0.0698)
    assert safety["default_freq_hz"] == 20.0


def test_camera_selection_and_resizing(wall) -> None:
    only = robo.get_state("wrist")
    assert set(only["image"]) == {"wrist"}
    small = robo.get_state({"agentview": (320, 240)})
    w, h, _, _ = decode(small["image"]["agentview"])
    assert (w, h) == (320, 240)
    assert small["camera_intrinsics"]["agentview"]["fx"] == pytest.approx(only_fx_half(), rel=1e-6)
    with pytest.raises(ValueError, match="unknown camera 'front'"):
        robo.get_state("front")
    with pytest.raises(TypeError):
        robo.get_state(42)


def only_fx_half() -> float:
    return robo.get_state("agentview")["camera_intrinsics"]["agentview"]["fx"] / 2


@pytest.mark.parametrize(
    "cmd, reason",
    [
        ({"actions": [[0.0] * 7], "type": "joint", "freq": ""}, "has 7 values; a joint waypoint has 8"),
        ({"actions": [HOME[:3] + [float("nan")] + HOME[4:] + [0.0]], "type": "joint", "freq": ""}, "not a finite number"),
        ({"actions": [HOME[:3] + [0.3] + HOME[4:] + [0.0]], "type": "joint", "freq": ""}, "joint 4 = 0.3000 rad is outside"),
        ({"actions": [HOME + [2.0]], "type": "joint", "freq": ""}, "gripper = 2"),
        ({"actions": [HOME + [0.0]], "type": "cartesian", "freq": ""}, "type \"cartesian\" is unknown"),
        ({"actions": [HOME + [0.0]], "type": "joint", "freq": "fast"}, "is not a number"),
        ({"actions": [HOME + [0.0]], "type": "joint", "freq": "1e-9"}, "is not usable"),
        ({"actions": [HOME + [0.0]] * 100, "type": "joint", "freq": 0.5}, "at most 120"),
        ({"actions": [], "type": "joint", "freq": ""}, "actions is empty"),
        ({"actions": [HOME + [0.0]] * 300, "type": "joint", "freq": ""}, "at most 256"),
    ],
)
def test_bad_commands_are_rejected_with_a_reason_and_nothing_moves(wall, cmd, reason) -> None:
    if max(abs(a - b) for a, b in zip(robo.get_state([])["joint"], HOME)) > 1e-3:
        assert robo.reset() == 1  # the commands are written around HOME (step caps apply)
    before = robo.get_state([])["joint"]
    assert robo.post_actions(cmd) == 0
    fb = feedback()
    assert fb["status"] == "rejected"
    assert reason in fb["reason"], fb["reason"]
    after = robo.get_state([])["joint"]
    assert max(abs(a - b) for a, b in zip(before, after)) < 1e-3


def test_control_type_is_fixed_per_episode(wall) -> None:
    assert robo.reset() == 1
    ee = robo.get_state([])["ee_pose"]
    assert robo.post_actions({"actions": [ee + [-1.0]], "type": "ee_pose", "freq": ""}) == 1, feedback()
    here = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": [here + [-1.0]], "type": "joint", "freq": ""}) == 0
    assert "uses \"ee_pose\" control" in feedback()["reason"], feedback()
    assert robo.reset() == 1
    here = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": [here + [-1.0]], "type": "joint", "freq": ""}) == 1, feedback()


def test_ee_pose_moves_the_tcp_along_a_straight_line(lockstep) -> None:
    assert robo.reset() == 1
    start = robo.get_state([])["ee_pose"]
    goal = [start[0] + 0.12, start[1] - 0.1, start[2] - 0.08] + start[3:]
    steps = 10
    chunk = [[s + (g - s) * (k + 1) / steps for s, g in zip(start, goal)] + [-1.0] for k in range(steps)]
    assert robo.post_actions({"actions": chunk, "type": "ee_pose", "freq": ""}) == 1, feedback()
    end = robo.get_state([])["ee_pose"]
    assert max(abs(a - b) for a, b in zip(end[:3], goal[:3])) < 0.005, (end, goal)
    # The orientation was held within a degree (axis-angle near a half turn may flip sign).
    assert rotation_between(end[3:], goal[3:]) < math.radians(1.0), (end, goal)


def test_unreachable_and_unsafe_ee_poses_are_rejected_untouched(lockstep) -> None:
    assert robo.reset() == 1
    s = robo.get_state([])
    before, ee = s["joint"], s["ee_pose"]
    # Out of reach, in steps within the 5 cm cap.
    far = [[ee[0] + 0.04 * (k + 1), ee[1], ee[2]] + ee[3:] + [-1.0] for k in range(50)]
    assert robo.post_actions({"actions": far, "type": "ee_pose", "freq": ""}) == 0
    assert "not reachable" in feedback()["reason"], feedback()
    # Through the table top (z = 0 in the base frame).
    low = [[ee[0], ee[1], ee[2] + (-0.05 - ee[2]) * (k + 1) / 14] + ee[3:] + [-1.0] for k in range(14)]
    assert robo.post_actions({"actions": low, "type": "ee_pose", "freq": ""}) == 0
    assert "table" in feedback()["reason"] or "workspace" in feedback()["reason"], feedback()
    after = robo.get_state([])["joint"]
    assert max(abs(a - b) for a, b in zip(before, after)) < 1e-3


def test_reset_restores_the_initial_pose(wall) -> None:
    start = robo.get_state([])["joint"]
    goal = [0.5, -0.3, 0.0, -2.0, 0.0, 1.8, 0.785]
    assert robo.post_actions({"actions": ramp(start, goal, 1.0), "type": "joint", "freq": ""}) == 1
    assert robo.get_state([])["gripper"][0] > 0.9
    assert robo.reset() == 1
    s = robo.get_state([])
    assert max(abs(a - b) for a, b in zip(s["joint"], HOME)) < 0.01
    assert s["gripper"][0] < -0.9
    assert feedback()["reason"].startswith("reset")


def test_lockstep_is_deterministic(lockstep) -> None:
    def episode() -> list[float]:
        assert robo.reset() == 1
        goal = [0.3, -0.4, 0.2, -2.1, 0.1, 1.9, 0.5]
        assert robo.post_actions({"actions": ramp(HOME, goal, 1.0, 12), "type": "joint", "freq": ""}) == 1
        s = robo.get_state([])
        return s["joint"] + s["ee_pose"] + s["gripper"] + [s["timestamp"]]

    runs = [episode() for _ in range(3)]
    assert runs[0] == runs[1] == runs[2]  # bit-identical, not merely close
    assert runs[0][-1] > 0
    assert robo.get_state([])["mode"] == "lockstep"


def test_a_missing_instance_is_a_connection_error_with_the_fix() -> None:
    previous = os.environ.get("R2G_INSTANCE")
    os.environ["R2G_INSTANCE"] = "nobody-runs-this"
    try:
        with pytest.raises(ConnectionError, match="r2g up <gym> --instance nobody-runs-this"):
            robo.get_state()
    finally:
        if previous is not None:
            os.environ["R2G_INSTANCE"] = previous


def test_an_fr3_scene_uses_fr3_limits_and_its_own_workspace(fr3) -> None:
    assert robo.reset() == 1
    here = robo.get_state([])["joint"]
    # Joint 6 at 0.3 rad is inside the Panda's range but below the FR3's 0.4398 rad.
    low6 = here[:5] + [0.3] + here[6:]
    assert robo.post_actions({"actions": [low6 + [-1.0]], "type": "joint", "freq": ""}) == 0
    assert "joint 6" in feedback()["reason"], feedback()
    # 5 cm above the table is fine for the table, not for this scene's workspace.
    ee = robo.get_state([])["ee_pose"]
    low = [[ee[0], ee[1], ee[2] + (0.05 - ee[2]) * (k + 1) / 12] + ee[3:] + [-1.0] for k in range(12)]
    assert robo.post_actions({"actions": low, "type": "ee_pose", "freq": ""}) == 0
    assert "workspace" in feedback()["reason"], feedback()
    # Motion within the FR3 limits runs in the simulator.
    goal = here[:5] + [1.2] + here[6:]
    assert robo.post_actions({"actions": ramp(here, goal, -1.0, 4), "type": "joint", "freq": ""}) == 1, feedback()
    assert abs(robo.get_state([])["joint"][5] - 1.2) < 0.01
