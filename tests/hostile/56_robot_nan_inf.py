"""Robot: NaN/inf/out-of-range/overflowing values in waypoints, gripper and freq; contained = every command returns 0 'rejected' (or a TypeError/ValueError for non-numbers)."""
import sys

from robo import get_state, post_actions, reset

if reset() != 1:
    sys.exit(f"reset failed: {get_state([])['control_feedback']}")
s = get_state([])
q, pose = s["joint"], s["ee_pose"]
nan, inf = float("nan"), float("inf")


def wp(i, v, base):
    w = list(base)
    w[i] = v
    return w


CASES = [
    ("joint 3 NaN", {"actions": [wp(2, nan, q + [-1.0])], "type": "joint", "freq": ""}),
    ("joint 1 +inf", {"actions": [wp(0, inf, q + [-1.0])], "type": "joint", "freq": ""}),
    ("gripper -inf", {"actions": [q + [-inf]], "type": "joint", "freq": ""}),
    ("gripper 5.0", {"actions": [q + [5.0]], "type": "joint", "freq": ""}),
    ("gripper NaN", {"actions": [q + [nan]], "type": "joint", "freq": ""}),
    ("ee_pose z NaN", {"actions": [wp(2, nan, pose + [-1.0])], "type": "ee_pose", "freq": ""}),
    ("ee_pose axis inf", {"actions": [wp(3, inf, pose + [-1.0])], "type": "ee_pose", "freq": ""}),
    ("freq NaN", {"actions": [q + [-1.0]], "type": "joint", "freq": nan}),
    ("freq 'inf'", {"actions": [q + [-1.0]], "type": "joint", "freq": "inf"}),
    ("freq -5", {"actions": [q + [-1.0]], "type": "joint", "freq": -5}),
    ("freq 1e9", {"actions": [q + [-1.0]], "type": "joint", "freq": 1e9}),
    ("9-value joint waypoint", {"actions": [q + [-1.0, 0.0]], "type": "joint", "freq": ""}),
    ("1e308 joint", {"actions": [wp(1, 1e308, q + [-1.0])], "type": "joint", "freq": ""}),
    ("10**400 joint", {"actions": [wp(1, 10**400, q + [-1.0])], "type": "joint", "freq": ""}),
]
for label, cmd in CASES:
    try:
        ok = post_actions(cmd)
    except (TypeError, ValueError, OverflowError) as e:
        print(f"BLOCKED: {label}: raised {e!r}")
        continue
    fb = get_state([])["control_feedback"]
    if ok:
        print(f"ESCAPED: {label} was executed")
    else:
        print(f"BLOCKED: {label}: {fb['status']}: {fb['reason']}")
