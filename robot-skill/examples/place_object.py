"""Worked example stage program: pick up one object and put it on or into another, or on the
table past a coloured mark, with `robo_perception.place_poses`.

    place_object.py "red block" "blue plate"          # on a support (pick_block_plate)
    place_object.py "orange bowl" "blue bowl"         # into a container (stack_bowls)
    place_object.py "green block" --past yellow       # on the table past a yellow mark (push_to_line)

Stages: pick and lift (examples/pick_object.py's `pick`), look again, find the held object (its
tracked identity, or the held flag) and the target, compute the placement, go to the pre-place
pose, descend, open, retreat straight up, and let the scene settle. Ends with
``RESULT placed=<bool> ...`` from fresh observations only: the object is no longer held, it is
not touching the hand (the gripper is open and the TCP is more than 5 cm from it), and it rests
where it was put. Only the simulator's evaluator knows whether the task succeeded.

Run against a live gym (lockstep is repeatable):
    r2g up pick_block_plate --instance demo --mode lockstep &
    R2G_INSTANCE=demo .venv/bin/python robot-skill/examples/place_object.py "red block" "blue plate"
"""

import argparse
import os
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
# robo_perception imports as is in the sandbox and in the project's .venv; this line serves other interpreters.
sys.path[:0] = [HERE, os.path.join(HERE, "..", "..", "agent-host", "py", "lib")]

import numpy as np  # noqa: E402
from robo import get_state, post_actions  # noqa: E402

import robo_perception as rp  # noqa: E402
from pick_object import move, path_to, pick  # noqa: E402

CAMERAS = ["agentview", "wrist"]
# Identity across observations: the sandbox names a tracker file for the whole episode; elsewhere
# this program keeps its own, so the held object is the one it picked.
os.environ.setdefault("R2G_PERCEPTION_TRACKS", os.path.join(tempfile.mkdtemp(prefix="place-tracks-"), "tracks.json"))


def settle(gripper, steps=10):
    """Hold the measured pose for `steps` waypoints (0.5 s at 20 Hz) so the scene comes to rest,
    commanding `gripper` (the last value sent, never the measured one)."""
    here = get_state([])["ee_pose"]
    post_actions({"type": "ee_pose", "freq": "", "actions": rp.waypoints([here] * steps, gripper)})


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("object", help="what to pick, e.g. 'red block'")
    ap.add_argument("target", nargs="?", help="what to put it on or in, e.g. 'blue plate'")
    ap.add_argument("--past", metavar="COLOUR", help="put it on the table past the mark of this colour")
    a = ap.parse_args()
    if (a.target is None) == (a.past is None):
        ap.error("give a target object or --past COLOUR")

    # 1. the target and the object's own height, seen before the pick
    state = get_state(CAMERAS, raw=True)
    scene = rp.segment_scene(state)
    obj0 = rp.select(scene, a.object)
    if obj0 is None:
        print(f"no object matches {a.object!r}")
        sys.exit(1)
    goal = None
    if a.past:
        marks = rp.find_markings(scene, a.past)
        if not marks:
            print(f"no {a.past} mark on the table")
            sys.exit(1)
        mark = marks[0]
        # away from the robot base, past the mark's far edge by half the object plus 3 cm
        away = mark.center[:2] / np.linalg.norm(mark.center[:2])
        reach = float(np.max(np.abs((mark.points[:, :2] - mark.center[:2]) @ away)))
        goal = mark.center[:2] + away * (reach + 0.5 * float(obj0.obb.extents[0]) + 0.03)
        print(f"{mark.describe()}; placing at ({goal[0]:.3f}, {goal[1]:.3f})")

    # 2. pick and lift
    info = pick(a.object)
    if not info["lifted"]:
        print("RESULT placed=False (the pick failed)")
        sys.exit(1)
    closed = 1.0

    # 3. look again: the held object (by track, else the held flag) and the target
    state = get_state(CAMERAS, raw=True)
    scene = rp.segment_scene(state)
    held = next((o for o in scene.objects if obj0.track_id is not None and o.track_id == obj0.track_id), None)
    if held is None:
        held = next((o for o in scene.objects if o.held), None)
    if held is None:
        print("RESULT placed=False (the held object is not in view)")
        sys.exit(1)
    support = None
    if a.target:
        ranked = [o for o, _ in rp.rank_objects(scene, a.target) if o is not held]
        if not ranked:
            print(f"RESULT placed=False (no {a.target!r} in view)")
            sys.exit(1)
        support = ranked[0]
    # the object's centre relative to the fingers, from the pick (more of it was visible then)
    offset = info["start_center"] - info["grasp"].position
    pl = rp.place_poses(held, support, scene, state["ee_pose"], at=goal, object_height=info["object_height"],
                        center_offset=offset)
    print(f"held: {held.describe()}")
    if support is not None:
        print(f"target: {support.describe()}")
    print(f"place at {np.round(pl.pose[:3], 3).tolist()}, surface {pl.surface:.3f} m ({pl.details['surface']})")

    # 4. over the target, down, open, up
    move(path_to(pl.preplace), closed, "to pre-place")
    if not move(path_to(pl.pose, max_m=0.01), closed, "descend", stop=False):
        print("descent stopped early (contact?); releasing where the hand is")
    here = get_state([])["ee_pose"]
    move([here] * 10, -1.0, "open")
    move(path_to([*here[:2], pl.retreat[2], *here[3:]], max_m=0.02), -1.0, "retreat")
    settle(-1.0)

    # 5. verify from fresh observations
    state = get_state(CAMERAS, raw=True)
    scene = rp.segment_scene(state)
    now = next((o for o in scene.objects if held.track_id is not None and o.track_id == held.track_id), None)
    if now is None:
        ranked = [o for o, _ in rp.rank_objects(scene, a.object)]
        now = min(ranked, key=lambda o: float(np.linalg.norm(o.center[:2] - pl.target[:2]))) if ranked else None
    if now is None:
        print("RESULT placed=False (the object is not in view)")
        sys.exit(1)
    tcp = np.asarray(state["ee_pose"][:3])
    off = float(np.linalg.norm(now.center[:2] - pl.target[:2]))
    gap = float(np.min(np.linalg.norm(now.points - tcp, axis=1)))
    placed = bool(not now.held and state["gripper"][0] < -0.5 and gap > 0.05 and off < 0.03)
    print(f"object now: {now.describe()}; {off * 100:.1f} cm from the target, hand {gap * 100:.1f} cm away")
    print(f"RESULT placed={placed} offset_m={off:.3f} hand_gap_m={gap:.3f}")
    sys.exit(0 if placed else 1)


if __name__ == "__main__":
    main()
