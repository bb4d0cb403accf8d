"""Robot: ee_pose chunks in legal steps driving the TCP 0.8 m down through the table and 1.5 m out of the workspace; contained = 0 'rejected', nothing moves."""
import math
import sys

from robo import get_state, post_actions, reset

if reset() != 1:
    sys.exit(f"reset failed: {get_state([])['control_feedback']}")
s = get_state([])
x, y, z, ax, ay, az = s["ee_pose"]
g = -1.0 if s["gripper"][0] < 0 else 1.0
step = 0.6 * s["effective_safety"]["max_tcp_step_m"]
for label, dx, dz in (("down through the table", 0.0, -0.8), ("out of the workspace along +x", 1.5, 0.0)):
    n = math.ceil(math.hypot(dx, dz) / step)
    chunk = [[x + dx * k / n, y, z + dz * k / n, ax, ay, az, g] for k in range(1, n + 1)]
    ok = post_actions({"actions": chunk, "type": "ee_pose", "freq": ""})
    fb = get_state([])["control_feedback"]
    now = get_state([])["ee_pose"]
    moved = math.dist(now[:3], (x, y, z))
    if ok:
        print(f"ESCAPED: TCP {label} was executed; now at z={now[2]:.3f}")
    elif fb["status"] != "rejected":
        print(f"BLOCKED (late): {label}: {fb['status']} after {fb['executed']} waypoints, moved {moved:.3f} m: {fb['reason']}")
    else:
        print(f"BLOCKED: {label}: {fb['reason']} (moved {moved:.4f} m)")
        if moved > 0.01:
            print(f"ESCAPED: a rejected chunk moved the TCP by {moved:.3f} m")
