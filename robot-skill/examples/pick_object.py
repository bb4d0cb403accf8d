"""Worked example stage program: pick up an object named by a text prompt and lift it 10 cm.
The prompt is the first argument (default "red block", for gym `pick_block_plate`), e.g.
`... pick_object.py "orange bowl"` in `stack_bowls`.

Uses only `robo` and `robo_perception` (numpy + stdlib). Every motion is an ee_pose chunk of
small steps (at most 4 cm and 0.3 rad apart, under the runtime's 5 cm / 0.35 rad caps), the
first step measured from the *measured* TCP pose. Prints one line per stage and ends with
``RESULT lifted=<bool> rise=<m>``; the exit status is 0 only when the object was seen to rise.

Run against a live gym (lockstep is repeatable):
    r2g up pick_block_plate --instance demo --mode lockstep &
    R2G_INSTANCE=demo .venv/bin/python robot-skill/examples/pick_object.py
"""

import os
import sys

# robo_perception imports as is in the sandbox and in the project's .venv; this line serves other interpreters.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "agent-host", "py", "lib"))

import numpy as np  # noqa: E402
from robo import get_state, post_actions  # noqa: E402

import robo_perception as rp  # noqa: E402

PROMPT = sys.argv[1] if len(sys.argv) > 1 else "red block"
STEP_M, STEP_RAD = 0.04, 0.30          # below max_tcp_step_m / max_tcp_step_rad
LIFT_M = 0.10


def move(poses, gripper, label, stop=True):
    """Send ee_pose waypoints (in chunks of <= 200). On a refusal or failure: stop the program
    (``stop``) or return False."""
    for k in range(0, len(poses), 200):
        chunk = rp.waypoints(poses[k:k + 200], gripper)
        if not post_actions({"actions": chunk, "type": "ee_pose", "freq": ""}):
            fb = get_state([])["control_feedback"]
            print(f"{label}: {fb['status']} after {fb['executed']} waypoints: {fb['reason']}")
            if stop:
                sys.exit(2)
            return False
    print(f"{label}: ok ({len(poses)} waypoints)")
    return True


def path_to(goal, max_m=STEP_M):
    """Straight path from the measured pose to `goal`."""
    here = get_state([])["ee_pose"]
    return rp.interpolate_poses(here, goal, max_step_m=max_m, max_step_rad=STEP_RAD)


def find_target(state, near=None):
    scene = rp.segment_scene(state)
    target = rp.select(scene, PROMPT)
    if near is not None:
        reds = [o for o, _ in rp.rank_objects(scene, PROMPT)]
        if reds:
            target = min(reds, key=lambda o: float(np.linalg.norm(o.center - near)))
    return scene, target


def main():
    info = pick(PROMPT)
    print(f"RESULT lifted={info['lifted']} rise={info['rise']:.3f}")
    sys.exit(0 if info["lifted"] else 1)


def pick(prompt):
    """Pick the object `prompt` names and lift it LIFT_M. Returns {"lifted", "rise", "grasp",
    "start_center", "object_height"}; exits the program when nothing can be tried."""
    global PROMPT
    PROMPT = prompt
    state = get_state(["agentview", "wrist"], raw=True)
    scene, target = find_target(state)
    print(f"segmentation: {scene.timings_ms['total']:.0f} ms, plane z0={scene.plane.height_at_origin:.4f}")
    print("\n".join("  " + o.describe() for o in scene.objects))
    if target is None:
        print(f"no object matches {PROMPT!r}")
        sys.exit(1)
    start_center = target.center.copy()
    grasps = rp.propose_grasps(target, scene, reference_pose=state["ee_pose"])
    if not grasps:
        print("no feasible grasp")
        sys.exit(1)
    g = grasps[0]
    print(f"grasp: {g.kind} at {np.round(g.pose, 3).tolist()} width {g.width:.3f} score {g.score:.2f}")

    # 1. to the pre-grasp, gripper open
    move(path_to(g.pregrasp), -1.0, "to pre-grasp")

    # 2. look again from close by and refine the grasp if the object is still there
    state = get_state(["agentview", "wrist"], raw=True)
    scene2, target2 = find_target(state, near=start_center)
    if target2 is not None and np.linalg.norm(target2.center - start_center) < 0.03:
        better = rp.propose_grasps(target2, scene2, reference_pose=state["ee_pose"])
        # same kind of grasp, same place, same closing axis: only a correction, not a new plan
        better = [b for b in better if b.kind == g.kind and np.linalg.norm(b.position - g.position) < 0.02
                  and abs(float(np.dot(b.closing, g.closing))) > 0.95]
        if better:
            g = better[0]
            print(f"refined grasp: {np.round(g.pose, 3).tolist()} width {g.width:.3f}")
            move(path_to(g.pregrasp), -1.0, "adjust pre-grasp")

    # 3. descend along the approach in 1 cm steps, close in place, lift straight up
    move(path_to(g.pose, max_m=0.01), -1.0, "descend")
    move([g.pose] * 12, 1.0, "close")
    here = get_state([])["ee_pose"]
    goal = list(here)
    goal[2] += LIFT_M
    move(path_to(goal, max_m=0.01), 1.0, "lift")

    # 4. verify: the gripper is blocked by something and the object's cluster rose
    state = get_state(["agentview", "wrist"], raw=True)
    grip = state["gripper"][0]
    _, target3 = find_target(state, near=start_center + np.array([0.0, 0.0, LIFT_M]))
    rise = float(target3.center[2] - start_center[2]) if target3 is not None else float("nan")
    lifted = bool(target3 is not None and rise > 0.05 and grip < 0.95)
    print(f"gripper {grip:.2f} (1 = closed on nothing); object centre z {start_center[2]:.3f} -> "
          f"{target3.center[2] if target3 is not None else float('nan'):.3f}")
    return {"lifted": lifted, "rise": rise, "grasp": g, "start_center": start_center,
            "object_height": float(target.height)}


if __name__ == "__main__":
    main()
