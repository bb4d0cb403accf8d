"""Robot: lock 'joint' with a hold chunk, then send ee_pose, an unknown type and a smuggled extra key; contained = 0 'rejected' or TypeError, type stays 'joint'."""
import sys

from robo import get_state, post_actions, reset

if reset() != 1:
    sys.exit(f"reset failed: {get_state([])['control_feedback']}")
s = get_state([])
g = -1.0 if s["gripper"][0] < 0 else 1.0
if not post_actions({"actions": [s["joint"] + [g]], "type": "joint", "freq": ""}):
    sys.exit(f"a hold chunk was refused: {get_state([])['control_feedback']}")
print(f"INFO: control_type is now {get_state([])['control_type']!r}")
CASES = [
    ("ee_pose after joint", {"actions": [s["ee_pose"] + [g]], "type": "ee_pose", "freq": ""}),
    ("type 'EE_POSE'", {"actions": [s["ee_pose"] + [g]], "type": "EE_POSE", "freq": ""}),
    ("type 'torque'", {"actions": [[0.0] * 7 + [g]], "type": "torque", "freq": ""}),
    ("extra key control_type", {"actions": [s["ee_pose"] + [g]], "type": "joint", "freq": "", "control_type": "ee_pose"}),
    ("type as list", {"actions": [s["ee_pose"] + [g]], "type": ["joint", "ee_pose"], "freq": ""}),
]
for label, cmd in CASES:
    try:
        ok = post_actions(cmd)
    except TypeError as e:
        print(f"BLOCKED: {label}: TypeError {e}")
        continue
    fb = get_state([])["control_feedback"]
    if ok:
        print(f"ESCAPED: {label} was executed")
    else:
        print(f"BLOCKED: {label}: {fb['status']}: {fb['reason']}")
after = get_state([])["control_type"]
if after != "joint":
    print(f"ESCAPED: control_type changed to {after!r} without a reset")
