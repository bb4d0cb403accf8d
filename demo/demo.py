"""Moves the simulated Panda through a few joint targets through `robo`, then plays the gym's
demonstration (pick the block, put it on the plate) as joint chunks, saves both camera images,
and prints the native evaluator's verdict on that episode.

Run by `make demo` against an instance started with
`r2g up pick_block_plate --trace-dir <out>/episodes`.
"""
from __future__ import annotations

import csv
import json
import math
import os
import sys
import time
from pathlib import Path

from robo import get_state, post_actions, reset

OUT = sys.argv[1] if len(sys.argv) > 1 else "demo-out"


def chunk(start: list[float], goal: list[float], gripper: float, steps: int) -> list[list[float]]:
    """Evenly spaced joint waypoints from start to goal (the agent picks nearby targets)."""
    return [[s + (g - s) * (k + 1) / steps for s, g in zip(start, goal)] + [gripper] for k in range(steps)]


def main() -> int:
    os.makedirs(OUT, exist_ok=True)
    t0 = time.monotonic()
    state = get_state()
    print(f"connected in {time.monotonic() - t0:.2f} s; joints {[round(q, 3) for q in state['joint']]}")
    print(f"TCP {[round(v, 3) for v in state['ee_pose']]} gripper {state['gripper'][0]:+.2f}")
    if reset() != 1:
        print("reset failed:", get_state([])["control_feedback"])
        return 1
    home = get_state([])["joint"]
    targets = [
        ([0.3, -0.4, 0.0, -2.2, 0.0, 1.9, 0.785], -1.0),
        ([-0.3, -0.2, 0.2, -2.0, 0.1, 1.8, 0.5], 1.0),
        ([0.0, -0.3, 0.0, -2.5, 0.0, 2.2, 0.785], -1.0),
    ]
    worst = 0.0
    current = home
    for goal, grip in targets:
        t = time.monotonic()
        ok = post_actions({"actions": chunk(current, goal, grip, 20), "type": "joint", "freq": ""})
        state = get_state([])
        err = max(abs(a - b) for a, b in zip(state["joint"], goal))
        worst = max(worst, err)
        fb = state["control_feedback"]
        print(
            f"chunk -> {goal}: returned {ok} in {time.monotonic() - t:.2f} s, {fb['status']}, max joint error {err:.5f} rad,"
            f" first motion {fb['submit_to_first_motion_us'] or 0:.0f} us after submission"
        )
        if ok != 1:
            print("  reason:", fb["reason"])
            return 1
        current = goal
    # The demonstration, as an agent would post it: joint chunks of at most 200 waypoints.
    if reset() != 1:
        return 1
    demo = Path(__file__).resolve().parents[1] / "gyms" / "pick_block_plate" / "demo.csv"
    with demo.open() as f:
        rows = [[float(x) for x in r] for r in csv.reader(f) if r and not r[0].startswith("q")]
    t = time.monotonic()
    for start in range(0, len(rows), 200):
        if post_actions({"actions": rows[start : start + 200], "type": "joint", "freq": ""}) != 1:
            print("demonstration chunk failed:", get_state([])["control_feedback"])
            return 1
    print(f"played the demonstration ({len(rows)} waypoints) in {time.monotonic() - t:.1f} s")
    # A target past a joint limit is rejected with a reason, never clipped.
    bad = post_actions({"actions": [[0, 0, 0, 0.5, 0, 1.5, 0.7, -1]], "type": "joint", "freq": ""})
    print(f"out-of-range target returned {bad}: {get_state([])['control_feedback']['reason']}")
    t = time.monotonic()
    state = get_state()
    print(f"get_state with both images took {time.monotonic() - t:.3f} s")
    for name, png in state["image"].items():
        path = os.path.join(OUT, f"{name}.png")
        with open(path, "wb") as f:
            f.write(png)
        print(f"saved {path} ({len(png)} bytes)")
    get_state("wrist", raw=True)  # the first raw call imports numpy
    t = time.monotonic()
    raw = get_state("agentview", raw=True)
    rgb, depth = raw["image"]["agentview"], raw["depth"]["agentview"]
    print(
        f"raw agentview in {(time.monotonic() - t) * 1e6:.0f} us: RGB {rgb.shape} {rgb.dtype}, depth {depth.shape}"
        f" {depth.dtype}, centre pixel {float(depth[depth.shape[0] // 2, depth.shape[1] // 2]):.3f} m (views into shared memory)"
    )
    print(f"final joint error: {worst:.5f} rad (worst over {len(targets)} targets)")
    # Ending the episode makes sim-host judge it from its native trace.
    episodes = Path(OUT) / "episodes"
    before = set(episodes.glob("episode-*.eval.json"))
    reset()
    for _ in range(100):
        new = set(episodes.glob("episode-*.eval.json")) - before
        if new:
            break
        time.sleep(0.05)
    if not new:
        print("no verdict was written for the demonstration episode")
        return 1
    verdict = new.pop()
    ev = json.loads(verdict.read_text())
    for name, check in ev["checks"].items():
        print(f"  {'pass' if check['pass'] else 'FAIL'} {name}: {check['value']}")
    print(f"episode judged from the native trace: success = {ev['success']} ({verdict})")
    return 0 if worst < 0.01 and not math.isnan(worst) and ev["success"] else 1


if __name__ == "__main__":
    sys.exit(main())
