"""Agent-side load for `r2g bench jitter`: polls get_state (both cameras as PNG, then the numeric
state alone) and posts joint chunks back and forth, for the given seconds, as an LLM-written
stage program would. Prints one JSON line of what it did."""
from __future__ import annotations

import json
import sys
import time

from robo import get_state, post_actions


def main() -> int:
    seconds = float(sys.argv[1])
    home = get_state([])["joint"]
    away = [home[0] + 0.3, home[1] + 0.2, home[2], home[3] + 0.2, home[4], home[5], home[6]]
    counts = {"get_state_images": 0, "get_state_numeric": 0, "chunks": 0, "chunks_ok": 0}
    deadline = time.monotonic() + seconds
    try:
        run(deadline, home, away, counts)
    except ConnectionError:
        pass  # the runtime finished its measured run
    print(json.dumps(counts))
    return 0


def run(deadline: float, home: list[float], away: list[float], counts: dict[str, int]) -> None:
    flip = False
    while time.monotonic() < deadline:
        get_state()
        counts["get_state_images"] += 1
        for _ in range(20):
            get_state([])
            counts["get_state_numeric"] += 1
        a, b = (home, away) if flip else (away, home)
        flip = not flip
        chunk = [[x + (y - x) * (k + 1) / 10 for x, y in zip(a, b)] + [-1.0] for k in range(10)]
        counts["chunks"] += 1
        counts["chunks_ok"] += post_actions({"actions": chunk, "type": "joint", "freq": ""})


if __name__ == "__main__":
    sys.exit(main())
