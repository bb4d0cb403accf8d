"""Worked example stage program: push an object along the table until the whole of it is past a
coloured line, with the closed fingers (gym `push_to_line`: "green block" past the "yellow" tape).

    push_past_line.py                          # "green block" past the yellow mark
    push_past_line.py "red block" blue         # another object, another colour of mark

What "past" means here is what the judge of push_to_line measures (api/SIMULATION.md, "past"):
the **whole** object beyond the mark's far edge, i.e. its centre at least half its own size past
that edge. This program aims a further 2 cm beyond that.

Stages: find the object (`select`) and the line (`find_markings`) -> the push direction: across
the line (its short side), from the object towards it -> close the fingers -> over a start point
behind the object, down to pushing height (fingertips about 1.6 cm above the table, the closed
finger pair square to the push) -> push in 4 mm steps until the object's centre should be at the
goal -> back off, look again; push again from where it now is if it is short (at most 3 pushes)
-> back off, up, let the scene settle. Ends with ``RESULT past=<bool> beyond_m=<m>`` (how far the
object's centre is beyond the mark's far edge, measured from a fresh observation) from fresh
observations only; only the simulator's evaluator knows whether the task succeeded.

Run it against a live gym (lockstep is repeatable), or in the sandbox with `r2g exec`:
    r2g up push_to_line --instance demo --mode lockstep &
    R2G_INSTANCE=demo .venv/bin/python robot-skill/examples/push_past_line.py
    r2g exec robot-skill/examples/push_past_line.py --instance demo
Importable: `push_past_line(prompt, color)` does all of it and returns a dict (see its docstring).
"""

import math
import os
import sys

# robo_perception imports as is in the sandbox and in the project's .venv; this line serves other interpreters.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "agent-host", "py", "lib"))

import numpy as np  # noqa: E402
from robo import get_state, post_actions  # noqa: E402

import robo_perception as rp  # noqa: E402

CAMERAS = ["agentview", "wrist"]
PUSH_Z = 0.025              # TCP height: fingertips 1.6 cm above the table (about 2 cm is the floor)
FINGER_HALF_M = 0.012       # half the closed finger pair along the push (two 12 mm pads)
MARGIN_M = 0.02             # aim this far beyond the judge's threshold
STEP_M = 0.004              # push step per waypoint (8 cm/s at 20 Hz)


def move(poses, gripper, label):
    """ee_pose waypoints in chunks of <= 200; False (and the reason printed) on a refusal or failure."""
    for k in range(0, len(poses), 200):
        if not post_actions({"type": "ee_pose", "freq": "", "actions": rp.waypoints(poses[k:k + 200], gripper)}):
            fb = get_state([])["control_feedback"]
            print(f"{label}: {fb['status']} after {fb['executed']} waypoints: {fb['reason']}")
            return False
    print(f"{label}: ok ({len(poses)} waypoints, felt {felt_n():.2f} N)")
    return True


def felt_n():
    """What the last chunk added to the force on the robot, N (its contact peak over its start):
    0 for a push that never touched anything."""
    c = get_state([])["control_feedback"].get("contact")
    return 0.0 if not c else max(0.0, c["peak_n"] - c["start_n"])


def path_to(goal, max_m=0.03):
    return rp.interpolate_poses(get_state([])["ee_pose"], goal, max_step_m=max_m, max_step_rad=0.3)


def hand_down(direction):
    """Hand pointing down, turned so that the fingers close along the push: the closed pair then
    meets the object square, one pad behind the other."""
    yaw = math.atan2(direction[1], direction[0]) - math.pi / 2   # TCP y (the closing axis) along the push
    R = rp.axis_angle_to_matrix([0.0, 0.0, yaw]) @ rp.axis_angle_to_matrix([math.pi, 0.0, 0.0])
    return [float(v) for v in rp.matrix_to_axis_angle(R)]


def look(prompt, color):
    """(object, mark, scene) from a fresh observation of both cameras; either may be None."""
    scene = rp.segment_scene(get_state(CAMERAS, raw=True))
    obj = rp.select(scene, prompt)
    marks = rp.find_markings(scene, color)
    return obj, (marks[0] if marks else None), scene


def far_edge_of(mark, across):
    """The mark's far edge along the push direction `across` (a coordinate along it, m)."""
    return float(np.percentile(mark.points @ across, 99))


def geometry(obj, mark):
    """The push direction (unit, horizontal, across the mark, from the object towards it), the
    mark's far edge along it, and the object's half size along it (m)."""
    axes = np.asarray(mark.obb.axes, dtype=float)
    across = axes[:, 1].copy()                     # the mark's short side
    across[2] = 0.0
    across /= np.linalg.norm(across)
    if np.dot(mark.center[:2] - obj.center[:2], across[:2]) < 0:
        across = -across
    far_edge = far_edge_of(mark, across)
    pts = obj.points @ across
    half = 0.5 * float(np.percentile(pts, 99) - np.percentile(pts, 1))
    return across, far_edge, half


def push_past_line(prompt="green block", color="yellow", tries=3):
    """Push the object `prompt` names past the `color` mark. Returns {"past", "beyond_m",
    "needed_m", "pushes"}: beyond_m is how far the object's centre ended beyond the mark's far
    edge (fresh observation), needed_m half the object's size along the push."""
    obj, mark, scene = look(prompt, color)
    if obj is None or mark is None:
        print(f"not found: object {prompt!r}: {obj is not None}, {color} mark: {mark is not None}")
        return {"past": False, "beyond_m": float("nan"), "needed_m": float("nan"), "pushes": 0}
    print(f"object: {obj.describe()}\nmark: {mark.describe()}")
    across, far_edge, half = geometry(obj, mark)
    rot = hand_down(across)
    closed = 1.0
    pushes = 0
    beyond = float(np.dot(obj.center, across)) - far_edge
    here = get_state([])["ee_pose"]
    move([list(here[:3]) + list(here[3:])] * 10, closed, "close the fingers")
    for pushes in range(1, tries + 1):
        c = np.array([obj.center[0], obj.center[1], 0.0])
        goal_center = far_edge + half + MARGIN_M                 # along `across`
        travel = goal_center - float(np.dot(c, across))
        if travel <= 0:
            break
        contact = c - across * (half + FINGER_HALF_M)           # TCP touching the object's near side
        start = contact - across * 0.03
        end = contact + across * travel
        print(f"push {pushes}: {travel:.3f} m along ({across[0]:.2f}, {across[1]:.2f})")
        here = get_state([])["ee_pose"]
        hop = max(0.12, here[2])
        ok = (move(path_to([*here[:2], hop, *rot]), closed, "up and turn")
              and move(path_to([start[0], start[1], hop, *rot]), closed, "over the start point")
              and move(path_to([start[0], start[1], PUSH_Z + 0.03, *rot], max_m=0.02), closed, "down behind the object")
              and move(path_to([start[0], start[1], PUSH_Z, *rot], max_m=0.005), closed, "to pushing height")
              and move(path_to([end[0], end[1], PUSH_Z, *rot], max_m=STEP_M), closed, "push"))
        if ok and felt_n() < 0.2:
            print("the push felt nothing: the fingers passed beside or above the object")
        # straight up off the table first (also after a stop), then back along the push, then look
        here = get_state([])["ee_pose"]
        move(path_to([here[0], here[1], PUSH_Z + 0.035, *rot], max_m=0.005), closed, "up off the table")
        back = np.asarray(here[:3]) - across * 0.05
        move(path_to([back[0], back[1], 0.15, *rot], max_m=0.03), closed, "back and up")
        seen, mark2, _ = look(prompt, color)
        if seen is not None:
            obj = seen
        if mark2 is not None:
            far_edge = far_edge_of(mark2, across)
        beyond = float(np.dot(obj.center, across)) - far_edge
        print(f"after push {pushes}: {obj.describe()}; centre {beyond:.3f} m beyond the far edge (needs {half:.3f})")
        if not ok or beyond >= half + 0.005:
            break
    here = get_state([])["ee_pose"]
    move([here] * 10, closed, "settle")
    return {"past": bool(beyond >= half), "beyond_m": beyond, "needed_m": half, "pushes": pushes}


def main():
    prompt = sys.argv[1] if len(sys.argv) > 1 else "green block"
    color = sys.argv[2] if len(sys.argv) > 2 else "yellow"
    out = push_past_line(prompt, color)
    print(f"RESULT past={out['past']} beyond_m={out['beyond_m']:.3f} needed_m={out['needed_m']:.3f} "
          f"pushes={out['pushes']}")
    sys.exit(0 if out["past"] else 1)


if __name__ == "__main__":
    main()
