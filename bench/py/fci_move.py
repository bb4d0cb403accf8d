"""The move of `r2g bench fci`, through `robo` against the instance R2G_INSTANCE names: first to
the gyms' start pose (a real arm starts wherever it stands), then 5 s of joint motion (joint 1 by
+0.3 rad and joint 4 by +0.2 rad together, one 20 Hz waypoint at a time in chunks of 16). A chunk
that a robot reflex stops (`recovered_replan_required`) is continued from the measured joints, so
the move ends where it should even on a peer that enforces its motion limits; each such stop is
counted. Prints one JSON object: the final joint error (rad), the move's wall time, and the stops.
"""
from __future__ import annotations

import json
import sys
import time

import robo

START = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
CHUNK = 16


def ramp(q: list[float], goal: list[float], steps: int) -> list[list[float]]:
    return [[a + (b - a) * (k + 1) / steps for a, b in zip(q, goal)] + [1.0] for k in range(steps)]


def run(waypoints: list[list[float]], stops: list[str]) -> None:
    i = 0
    while i < len(waypoints):
        part = waypoints[i : i + CHUNK]
        if robo.post_actions({"actions": part, "type": "joint", "freq": ""}) == 1:
            i += len(part)
            continue
        fb = robo.get_state([])["control_feedback"]
        if fb.get("status") != "recovered_replan_required" or len(stops) >= 20:
            raise SystemExit(f"fci_move.py: chunk at waypoint {i} failed: {json.dumps(fb)}")
        stops.append(str(fb.get("reason", "")))
        i += int(fb.get("executed", 0))


def main() -> None:
    stops: list[str] = []
    q = robo.get_state([])["joint"]
    far = max(abs(a - b) for a, b in zip(q, START))
    run(ramp(q, START, max(1, int(far / 0.02) + 1)), stops)  # 0.4 rad/s at most
    q = robo.get_state([])["joint"]
    goal = [q[0] + 0.3] + q[1:3] + [q[3] + 0.2] + q[4:]
    t = time.monotonic()
    run(ramp(q, goal, 100), stops)
    wall = time.monotonic() - t
    time.sleep(0.5)  # settle
    err = max(abs(a - b) for a, b in zip(robo.get_state([])["joint"], goal))
    print(json.dumps({"final_error_rad": err, "move_wall_s": wall, "reflex_stops": len(stops), "stop_reasons": stops}))


if __name__ == "__main__":
    sys.exit(main())
