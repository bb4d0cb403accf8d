"""Robot: joint chunks in legal steps that end past a joint limit (and inside the margin); contained = each returns 0 'rejected' and nothing moves."""
import math
import sys

from robo import get_state, post_actions, reset

if reset() != 1:
    sys.exit(f"reset failed: {get_state([])['control_feedback']}")
s = get_state([])
es = s["effective_safety"]
q0, g = s["joint"], (-1.0 if s["gripper"][0] < 0 else 1.0)
lo, hi, margin = es["joint_position_min_rad"], es["joint_position_max_rad"], es["joint_position_margin_rad"]
step = 0.8 * es["max_joint_step_rad"]
targets = [(3, hi[3] + 0.3, "joint 4 past its max"), (0, lo[0] - 0.3, "joint 1 past its min")]
if margin > 0:
    targets.append((6, hi[6] - margin / 2, "joint 7 inside the margin"))
for j, target, label in targets:
    n = max(1, math.ceil(abs(target - q0[j]) / step))
    path = []
    for k in range(1, n + 1):
        q = list(q0)
        q[j] = q0[j] + (target - q0[j]) * k / n
        path.append(q + [g])
    ok = post_actions({"actions": path, "type": "joint", "freq": ""})
    fb = get_state([])["control_feedback"]
    moved = max(abs(a - b) for a, b in zip(get_state([])["joint"], q0))
    if ok:
        print(f"ESCAPED: {label} ({target:.3f} rad) was executed")
    elif fb["status"] != "rejected" or moved > 0.02:
        print(f"ESCAPED: {label}: status {fb['status']}, arm moved {moved:.4f} rad before stopping")
    else:
        print(f"BLOCKED: {label}: {fb['status']}: {fb['reason']}")
