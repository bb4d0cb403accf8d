"""robot-skill/examples/close_door.py closing close_cabinet's door from several initial angles.

Seeds do not move fixtures, so each angle is a copy of close_cabinet's scene whose door joint
starts there (tests/python/articulation_truth.py `scene_with_joint`). For each angle a gym is
started (`r2g up`, lockstep, with a trace folder), the example runs as a stage program through
`r2g exec` (sandboxed, as a model's program would), and the simulator's evaluator judges the
episode. The door angle at the start and at the end come from the native trace.

Usage: close_door_from.py [--angles 30,60,100]   (R2G_BIN: the r2g binary)
Prints a table, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "python"))
import articulation_truth as at  # noqa: E402

EXAMPLE = ROOT / "robot-skill" / "examples" / "close_door.py"


def one(angle: float, work: Path) -> dict:
    scene = at.scene_with_joint("close_cabinet", angle, work)
    g = at.SceneGym(scene, work / "trace", tag="cdf")
    t0 = time.monotonic()
    try:
        r = subprocess.run([str(at.R2G), "exec", str(EXAMPLE), "--instance", g.instance,
                            "--scratch", str(work / "scratch")],
                           capture_output=True, text=True, timeout=600)
    finally:
        g.stop()
    wall = time.monotonic() - t0
    verdict = g.last("eval")
    samples = g.last("trace")["samples"]
    result = json.loads(r.stdout) if r.returncode == 0 and r.stdout.strip() else {}
    return {
        "initial_deg": angle,
        "start_deg": samples[0]["joints"][0],
        "end_deg": samples[-1]["joints"][0],
        "success": bool(verdict.get("success")),
        "violation": result.get("violation"),
        "control_steps": result.get("control_steps"),
        "wall_s": round(wall, 1),
    }


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--angles", default="30,60,100")
    args = ap.parse_args()
    rows = []
    for a in (float(x) for x in args.angles.split(",")):
        with tempfile.TemporaryDirectory(prefix="r2g-cdf-") as d:
            rows.append(one(a, Path(d)))
    print(f"{'initial':>8} {'start':>8} {'end':>8} {'success':>8} {'wall s':>7}")
    for r in rows:
        print(f"{r['initial_deg']:8.1f} {r['start_deg']:8.2f} {r['end_deg']:8.2f} {str(r['success']):>8} {r['wall_s']:7.1f}")
    print(json.dumps({"bench": "close_door_from", "runs": rows,
                      "closed": sum(r["success"] for r in rows), "of": len(rows)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
