"""`executed` means reached: a chunk reports executed (post_actions returns 1) only when the
measured state ends within the documented tolerance of its last waypoint; a chunk stopped short
by contact fails with the measured error, in both control types. Live lockstep instances, real
MuJoCo contact (the closed hand pressed onto the block)."""
from __future__ import annotations

import json
import math
import subprocess

import robo

from conftest import R2G

BLOCK_XY = [0.5, -0.12]      # pick_block_plate's block, 4 cm cube on the table (top at z = 0.04)
DOWN = [1.0, 0.0, 0.0, 0.0]  # TCP pointing down (x, y, z, w): the start orientation


def feedback() -> dict:
    return robo.get_state([])["control_feedback"]


def line(start: list[float], goal: list[float], g: float, step: float = 0.01) -> list[list[float]]:
    n = max(1, math.ceil(math.dist(start[:3], goal[:3]) / step))
    return [[s + (e - s) * k / n for s, e in zip(start[:3], goal[:3])] + list(goal[3:]) + [g] for k in range(1, n + 1)]


def above_block(z: float) -> list[float]:
    ee = robo.get_state([])["ee_pose"]
    target = BLOCK_XY + [z] + ee[3:]
    assert robo.post_actions({"actions": line(ee, target, 1.0), "type": "ee_pose", "freq": ""}) == 1, feedback()
    f = feedback()
    assert f["status"] == "executed" and f["reason"] == "executed", f
    return target


def test_an_ee_pose_chunk_pressed_into_the_block_fails_with_the_measured_error(lockstep) -> None:
    assert robo.reset() == 1
    target = above_block(0.12)  # reachable: executed
    # 1 cm below the block's top with closed fingers: the block stops the hand.
    into = target[:2] + [0.03] + target[3:]
    assert robo.post_actions({"actions": line(target, into, 1.0, 0.005), "type": "ee_pose", "freq": ""}) == 0
    f = feedback()
    assert f["status"] == "failed" and f["reason"].startswith("not reached: the TCP stopped"), f
    ee = robo.get_state([])["ee_pose"]
    assert ee[2] > 0.035, ee  # really short of the target: resting on the block's top


def ik(z: float, seed: list[float]) -> list[float]:
    req = json.dumps({"position": BLOCK_XY + [z], "quaternion": DOWN, "seed": seed})
    out = subprocess.run([str(R2G), "kin", "ik", "--robot", "panda"], input=req + "\n", capture_output=True,
                         text=True, timeout=60, check=True)
    sol = json.loads(out.stdout)
    assert sol["ok"], sol
    return sol["q"]


def joint_line(q0: list[float], q1: list[float], g: float, steps: int = 20) -> list[list[float]]:
    return [[a + (b - a) * k / steps for a, b in zip(q0, q1)] + [g] for k in range(1, steps + 1)]


def test_a_joint_chunk_pressed_into_the_block_fails_and_a_free_one_executes(lockstep) -> None:
    assert robo.reset() == 1  # joint control for this episode
    home = robo.get_state([])["joint"]
    above = ik(0.12, home)
    assert robo.post_actions({"actions": joint_line(home, above, 1.0, 40), "type": "joint", "freq": ""}) == 1, feedback()
    assert feedback()["final_joint_error_rad"] <= 0.005
    # 1 cm below the block's top with closed fingers: the block stops the hand.
    into = ik(0.03, above)
    assert robo.post_actions({"actions": joint_line(above, into, 1.0), "type": "joint", "freq": ""}) == 0
    f = feedback()
    assert f["status"] == "failed" and f["reason"].startswith("not reached: the arm stopped"), f
    assert f["final_joint_error_rad"] > 0.005, f
    # Back up to where it came from: free of contact, so executed and within tolerance.
    q = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": joint_line(q, above, 1.0), "type": "joint", "freq": ""}) == 1, feedback()
    assert feedback()["final_joint_error_rad"] <= 0.005


def test_the_reported_rotation_vector_never_flips(lockstep) -> None:
    """At the start pose the TCP is turned a half turn about x, where [pi, 0, 0] and [-pi, 0, 0]
    name the same rotation: every report keeps one of them; turning on past it stays continuous."""
    assert robo.reset() == 1
    first = robo.get_state([])["ee_pose"][3:]
    assert abs(math.hypot(*first) - math.pi) < 0.01, first
    for _ in range(20):
        now = robo.get_state([])["ee_pose"][3:]
        assert math.dist(now, first) < 1e-3, (now, first)
    # Turn the hand 0.3 rad about the TCP's own z: the report moves a little, it does not jump.
    ee = robo.get_state([])["ee_pose"]
    q = robo.get_state([])["joint"]
    turned = q[:6] + [q[6] + 0.3]
    chunk = [[a + (b - a) * k / 10 for a, b in zip(q, turned)] + [-1.0] for k in range(1, 11)]
    assert robo.post_actions({"actions": chunk, "type": "joint", "freq": ""}) == 1, feedback()
    after = robo.get_state([])["ee_pose"][3:]
    # (a half turn about an axis tilted by 0.15 rad: pi * 2 sin(0.075) = 0.47 away, not 2 pi)
    assert 0.35 < math.dist(after, ee[3:]) < 0.6, (after, ee[3:])


def test_turning_past_a_half_turn_keeps_the_report_continuous(lockstep) -> None:
    """Tilting the hand 0.1 rad further about x than the start's half turn: the report continues
    to a norm of pi + 0.1 instead of flipping to the principal vector -(pi - 0.1) about x."""
    import robo_perception as rp

    assert robo.reset() == 1
    ee = robo.get_state([])["ee_pose"]
    sign = 1.0 if ee[3] > 0 else -1.0
    goal = ee[:3] + [sign * (math.pi + 0.1), 0.0, 0.0]
    chunk = [p + [-1.0] for p in rp.interpolate_poses(ee, goal, 0.01, 0.02)]
    assert robo.post_actions({"actions": chunk, "type": "ee_pose", "freq": ""}) == 1, feedback()
    after = robo.get_state([])["ee_pose"][3:]
    assert math.dist(after, goal[3:]) < 0.03 and math.hypot(*after) > math.pi, (after, goal)


def test_a_chunk_interpolated_across_the_axis_angle_wrap_is_refused_with_the_fix(lockstep) -> None:
    """Component-wise interpolation from [pi, 0, 0] to a vector on the other side of the wrap
    spins the hand nearly a full turn: refused (nothing moves), and the reason names the helper
    that takes the short way, which then works."""
    import robo_perception as rp

    assert robo.reset() == 1
    ee = robo.get_state([])["ee_pose"]
    sign = 1.0 if ee[3] > 0 else -1.0
    goal = ee[:3] + [-sign * (math.pi - 0.2), 0.0, 0.0]  # 0.2 rad from the start, other side of pi
    naive = [[a + (b - a) * k / 4 for a, b in zip(ee, goal)] + [-1.0] for k in range(1, 5)]
    assert robo.post_actions({"actions": naive, "type": "ee_pose", "freq": ""}) == 0
    f = feedback()
    assert f["status"] == "rejected" and "interpolate_poses" in f["reason"] and "wrap" in f["reason"], f
    # finely stepped, every step far under the cap: still the long way round, still refused
    fine = [[a + (b - a) * k / 60 for a, b in zip(ee, goal)] + [-1.0] for k in range(1, 61)]
    joints = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": fine, "type": "ee_pose", "freq": ""}) == 0
    f = feedback()
    assert f["status"] == "rejected" and "long way round" in f["reason"] and "interpolate_poses" in f["reason"], f
    assert max(abs(a - b) for a, b in zip(joints, robo.get_state([])["joint"])) < 1e-6
    short = [p + [-1.0] for p in rp.interpolate_poses(ee, goal, 0.01, 0.05)]
    assert robo.post_actions({"actions": short, "type": "ee_pose", "freq": ""}) == 1, feedback()


def test_open_drawer_chunks_return_0_with_what_blocked_them(tmp_path) -> None:
    """Like the open_drawer run that came back `executed` short of its target: every chunk that
    cannot end at its last waypoint returns 0. Refused before motion when acceptance can tell
    (joints at their limits named; out of reach said so), failed with the measured error when
    something the checks do not model (the cabinet) stops the arm."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "agent-host" / "py" / "lib"))
    import render_truth as rt
    import robo_perception as rp

    g = rt.LiveGym(R2G, R2G.parents[2] / "gyms", "open_drawer", tag="reach")
    try:
        assert g.ready.wait(90), "r2g up did not print READY"
        g.use()

        def send(xyz, rot=None):
            robo.reset()
            s = robo.get_state([])
            goal = list(xyz) + list(rot if rot is not None else s["ee_pose"][3:])
            path = rp.interpolate_poses(s["ee_pose"], goal, max_step_m=0.03, max_step_rad=0.25)
            r = robo.post_actions({"type": "ee_pose", "freq": "", "actions": rp.waypoints(path, -1.0)})
            return r, feedback(), s["joint"], robo.get_state([])["joint"]

        # folded in close to the base: the elbow and shoulder would pass their limits
        r, f, before, after = send((0.15, 0.0, 0.25))
        assert r == 0 and f["status"] == "rejected", f
        assert "joints at their limits: 2, 4" in f["reason"], f["reason"]
        assert max(abs(a - b) for a, b in zip(before, after)) < 1e-6   # nothing moved
        # stretched beyond reach: no joint at a limit, and the reason says what that means
        r, f, before, after = send((0.95, 0.0, 0.25))
        assert r == 0 and f["status"] == "rejected" and "out of the arm's reach" in f["reason"], f
        # the hand turned level and pushed into the cabinet: accepted, stopped short, failed
        r, f, _, _ = send((0.6, 0.0, 0.2), (math.pi / 2, 0.0, 0.0))
        assert r == 0 and f["status"] == "failed" and f["reason"].startswith("not reached:"), f
        mm = float(f["reason"].split("stopped ")[1].split(" mm")[0])
        assert mm > 5.0, f["reason"]
    finally:
        g.stop()   # also points robo back at the lockstep fixture's instance


def test_a_joint_chunk_to_the_edge_of_the_limits_executes_and_one_past_is_rejected(lockstep) -> None:
    """Nothing that is reached is reported as failed: joint 7 sent to exactly its limit minus the
    margin ends `executed`; a target 1 mrad further is refused before anything moves, naming the
    joint."""
    assert robo.reset() == 1
    s = robo.get_state([])
    home, safety = s["joint"], s["effective_safety"]
    edge = safety["joint_position_max_rad"][6] - safety["joint_position_margin_rad"]
    target = home[:6] + [edge]
    assert robo.post_actions({"actions": joint_line(home, target, -1.0, 40), "type": "joint", "freq": ""}) == 1, \
        feedback()
    f = feedback()
    assert f["status"] == "executed" and f["final_joint_error_rad"] <= 0.005, f
    assert abs(robo.get_state([])["joint"][6] - edge) <= 0.005
    past = home[:6] + [edge + 0.001]
    here = robo.get_state([])["joint"]
    assert robo.post_actions({"actions": joint_line(here, past, -1.0, 2), "type": "joint", "freq": ""}) == 0
    f = feedback()
    assert f["status"] == "rejected" and "joint 7" in f["reason"], f
    assert max(abs(a - b) for a, b in zip(here, robo.get_state([])["joint"])) < 1e-6
