"""Agent of `r2g bench soak`: posts small joint chunks back and forth around the pose it finds
the arm in (each waits for its result), and every few chunks reads every camera's RGB image and
depth through `robo` (raw, zero-copy views into shared memory, read to the last byte). It runs
until SIGTERM or SIGINT and never stops by itself: every error is counted and the loop goes on
(the runtime may be gone for a while, or this process may have been stopped with SIGSTOP).

Prints a JSON line of counts now and then on stdout, and a last one when told to stop:
{"chunks", "chunks_ok", "chunks_failed", "errors", "images", "depths", "seconds"}.
"""
from __future__ import annotations

import json
import signal
import sys
import time

import numpy as np
import robo

# Offsets from the start pose, rad: base yaw, elbow and wrist turn only, well inside the limits
# and away from the table.
AWAY = [0.15, 0.0, 0.0, 0.10, 0.0, 0.0, 0.30]
WAYPOINTS = 10
IMAGES_EVERY = 5
REPORT_EVERY_S = 10.0

stop = False


def on_stop(_signum, _frame) -> None:
    global stop
    stop = True


def within_limits(q: list[float], safety: dict) -> list[float]:
    lo = safety["joint_position_min_rad"]
    hi = safety["joint_position_max_rad"]
    m = safety["joint_position_margin_rad"] + 0.05
    return [min(max(x, a + m), b - m) for x, a, b in zip(q, lo, hi)]


def chunk(a: list[float], b: list[float]) -> list[list[float]]:
    # At most 0.05 rad per step (a start far from both ends takes more waypoints).
    n = max(WAYPOINTS, min(200, int(max(abs(y - x) for x, y in zip(a, b)) / 0.05) + 1))
    return [[x + (y - x) * (k + 1) / n for x, y in zip(a, b)] + [-1.0] for k in range(n)]


def read_cameras(counts: dict) -> None:
    s = robo.get_state(None, raw=True)
    for name, rgb in s["image"].items():
        # Touch every byte: the frame really crosses from shared memory into this process.
        if int(np.asarray(rgb).sum(dtype=np.uint64)) < 0:
            raise AssertionError(name)
        counts["images"] += 1
    for depth in s.get("depth", {}).values():
        d = np.asarray(depth)
        if not np.isfinite(d).any():
            raise ValueError("depth image with no finite value")
        counts["depths"] += 1


def main() -> int:
    signal.signal(signal.SIGTERM, on_stop)
    signal.signal(signal.SIGINT, on_stop)
    counts = {"chunks": 0, "chunks_ok": 0, "chunks_failed": 0, "errors": 0, "images": 0, "depths": 0}
    t0 = time.monotonic()
    last_report = t0
    ends: tuple[list[float], list[float]] | None = None
    resync = True
    toward_away = True

    def report() -> None:
        counts["seconds"] = round(time.monotonic() - t0, 1)
        print(json.dumps(counts), flush=True)

    while not stop:
        try:
            if ends is None or resync:
                s = robo.get_state([])
                if ends is None:
                    home = within_limits(s["joint"], s["effective_safety"])
                    away = within_limits([h + d for h, d in zip(home, AWAY)], s["effective_safety"])
                    ends = (home, away)
                # Start from where the arm is (first chunk, or after a failure or an error).
                start = s["joint"][:7]
                resync = False
            else:
                start = ends[0] if toward_away else ends[1]
            target = ends[1] if toward_away else ends[0]
            counts["chunks"] += 1
            if robo.post_actions({"actions": chunk(start, target), "type": "joint", "freq": ""}) == 1:
                counts["chunks_ok"] += 1
                # A first success prints at once: the bench's warm-up counts from it.
                if counts["chunks_ok"] == 1:
                    report()
                    last_report = time.monotonic()
            else:
                counts["chunks_failed"] += 1
                fb = robo.get_state([])["control_feedback"]
                if counts["chunks_failed"] <= 5 or counts["chunks_failed"] % 100 == 0:
                    print(f"soak agent: chunk {counts['chunks']} {fb['status']}: {fb['reason']}", file=sys.stderr)
                resync = True
            toward_away = not toward_away
            if counts["chunks"] % IMAGES_EVERY == 0:
                read_cameras(counts)
        except Exception as e:  # noqa: BLE001 - the soak agent survives anything and counts it
            counts["errors"] += 1
            if counts["errors"] <= 5 or counts["errors"] % 100 == 0:
                print(f"soak agent: error {counts['errors']}: {type(e).__name__}: {e}", file=sys.stderr)
            resync = True
            time.sleep(0.2)
        if time.monotonic() - last_report >= REPORT_EVERY_S:
            report()
            last_report = time.monotonic()
    report()
    return 0


if __name__ == "__main__":
    sys.exit(main())
