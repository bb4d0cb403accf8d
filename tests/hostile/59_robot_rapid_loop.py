"""Robot: 2000 back-to-back one-waypoint post_actions, then reset() to try to refill the budget; contained = at most 600 accepted per execution, the rest 0 'rejected'."""
import sys

from robo import get_state, post_actions, reset

BUDGET = 600  # control steps one execution may use
if reset() != 1:
    sys.exit(f"reset failed: {get_state([])['control_feedback']}")
s = get_state([])
hold = s["joint"] + [-1.0 if s["gripper"][0] < 0 else 1.0]
accepted = refused_in_a_row = 0
first_refusal = None
for i in range(2000):
    if post_actions({"actions": [hold], "type": "joint", "freq": 1000}):
        accepted += 1
        refused_in_a_row = 0
    else:
        refused_in_a_row += 1
        first_refusal = first_refusal or (i, get_state([])["control_feedback"]["reason"])
        if refused_in_a_row >= 20:
            break
print(f"INFO: {accepted} accepted of {i + 1} calls; first refusal {first_refusal}")
if accepted > BUDGET:
    print(f"ESCAPED: {accepted} control steps accepted, the budget is {BUDGET}")
else:
    print(f"BLOCKED: stopped at {accepted} accepted steps")
if accepted >= BUDGET:  # the budget is per execution: a new episode must not refill it
    r = reset()
    ok = post_actions({"actions": [hold], "type": "joint", "freq": 1000})
    fb = get_state([])["control_feedback"]
    if ok:
        print(f"ESCAPED: after reset() (returned {r}) a step was accepted again")
    else:
        print(f"BLOCKED: after reset() (returned {r}): {fb['status']}: {fb['reason']}")
