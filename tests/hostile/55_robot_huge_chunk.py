"""Robot: chunks of max_chunk_len+1 and 10000 waypoints (all at the current pose); contained = each returns 0 'rejected'."""
import sys

from robo import get_state, post_actions, reset

if reset() != 1:
    sys.exit(f"reset failed: {get_state([])['control_feedback']}")
s = get_state([])
hold = s["joint"] + [-1.0 if s["gripper"][0] < 0 else 1.0]
cap = s["effective_safety"]["max_chunk_len"]
for n in (cap + 1, 10000):
    ok = post_actions({"actions": [list(hold) for _ in range(n)], "type": "joint", "freq": 1000})
    fb = get_state([])["control_feedback"]
    if ok:
        print(f"ESCAPED: a {n}-waypoint chunk was executed (cap {cap})")
    else:
        print(f"BLOCKED: {n} waypoints: {fb['status']}: {fb['reason']}")
